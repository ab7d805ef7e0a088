"""The one error hierarchy of standgrid.

Every error standgrid raises derives from :class:`StandgridError`; most also derive from
the matching builtin (a missing mission is a ``FileNotFoundError``, a malformed file a
``ValueError``) so callers can catch either. Errors about a file name the file and, where
there is one, the line: ``str(err)`` reads ``path:line: message``.
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path


class StandgridError(Exception):
    """Root of every error standgrid raises."""

    def __init__(
        self,
        message: str,
        *,
        path: str | PathLike[str] | None = None,
        line: int | None = None,
    ) -> None:
        self.message = message
        self.path = Path(path) if path is not None else None
        self.line = line
        if self.path is not None and line is not None:
            text = f"{self.path}:{line}: {message}"
        elif self.path is not None:
            text = f"{self.path}: {message}"
        else:
            text = message
        super().__init__(text)

    def __str__(self) -> str:  # OSError subclasses would otherwise format their own way
        return str(self.args[0]) if self.args else self.message


# --- reading missions -------------------------------------------------------------------


class MissionNotFoundError(StandgridError, FileNotFoundError):
    """A mission folder (or a file a mission needs) does not exist."""


class FormatError(StandgridError, ValueError):
    """A file's content does not follow its format. Names the file and line."""


class PoseGraphFormatError(FormatError):
    """A malformed ``.g2o`` / ``.slam`` pose graph or pose CSV."""


class PointCloudFormatError(FormatError):
    """A malformed point cloud (PCD, PLY, LAS/LAZ): truncated, count mismatch, NaN, ..."""


class SensorLogFormatError(FormatError):
    """A malformed GNSS or IMU text log."""


class BagFormatError(FormatError):
    """A ROS bag cannot be read, or a message in it cannot be decoded or used."""


class MetadataError(FormatError):
    """An unreadable or invalid ``metadata.yaml``; ``key`` names the metadata key at fault."""

    def __init__(
        self,
        message: str,
        *,
        path: str | PathLike[str] | None = None,
        line: int | None = None,
        key: str | None = None,
    ) -> None:
        super().__init__(message, path=path, line=line)
        self.key = key


class MissionNameError(FormatError):
    """A folder name that does not follow ``YYYY-MM-DD-<place>-<robot>[-<unit>]``."""


class MissionConsistencyError(StandgridError, ValueError):
    """Files that parse, but do not fit together."""


class DuplicateStampError(MissionConsistencyError):
    """Two vertices (or two payloads of one type) share a ``(sec, nsec)`` stamp."""


class OrphanPayloadError(MissionConsistencyError):
    """A payload whose stamp matches no pose-graph node."""


class PayloadNotFoundError(StandgridError, LookupError):
    """No payload matches a retrieval query."""


# --- georeferencing ----------------------------------------------------------------------


class GeoreferenceError(StandgridError, RuntimeError):
    """The map frame cannot be tied to the Earth."""


class NotGeoreferencedError(GeoreferenceError):
    """An operation needs a georeference that the mission does not have (yet)."""


class InsufficientGnssError(GeoreferenceError):
    """Too few good GNSS fixes to fit a georeference."""


class CRSError(StandgridError, ValueError):
    """An unknown or unusable coordinate reference system."""


# --- partitioning ------------------------------------------------------------------------


class GridError(StandgridError, ValueError):
    """An invalid stand-grid definition."""


class CellIdError(GridError):
    """A cell id text that does not parse."""


class GridMismatchError(GridError):
    """Two grids (catalog vs. mission, epoch vs. epoch) differ where they must agree."""


class ConservationError(StandgridError, RuntimeError):
    """Points were lost or duplicated on the way through the partition engine."""


# --- catalogs and outputs ----------------------------------------------------------------


class CatalogError(StandgridError):
    """A problem with a catalog folder."""


class CatalogNotFoundError(CatalogError, FileNotFoundError):
    """The catalog folder does not exist or is not a standgrid catalog."""


class EpochNotFoundError(CatalogError, LookupError):
    """The catalog has no such epoch."""


class NotEnrichedError(CatalogError, FileNotFoundError):
    """A table an export needs (tree list, stand metrics) is missing: run ``enrich`` first."""


class OutputExistsError(StandgridError, FileExistsError):
    """An output exists and ``overwrite`` was not asked for."""


class OutputNotWritableError(StandgridError, PermissionError):
    """An output location cannot be written."""


# --- enrichment --------------------------------------------------------------------------


class EnrichError(StandgridError, RuntimeError):
    """Terrain, tree or metric computation cannot proceed."""


__all__ = [name for name in dir() if name.endswith("Error")]
