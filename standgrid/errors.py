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

    #: The library name of the option that would change the outcome (a field of an options
    #: class or of :class:`~standgrid.engine.execution.Execution`, e.g.
    #: ``"accept_poor_georeference"``); the message names it as ``option <name>``, which the
    #: CLI alone turns into its flag (``--accept-poor-georeference``).
    option: str | None = None

    def __init__(
        self,
        message: str,
        *,
        path: str | PathLike[str] | None = None,
        line: int | None = None,
        option: str | None = None,
    ) -> None:
        self.message = message
        self.path = Path(path) if path is not None else None
        self.line = line
        if option is not None:
            self.option = option
        if self.path is not None and line is not None:
            text = f"{self.path}:{line}: {message}"
        elif self.path is not None:
            text = f"{self.path}: {message}"
        else:
            text = message
        super().__init__(text)

    def __str__(self) -> str:  # OSError subclasses would otherwise format their own way
        return str(self.args[0]) if self.args else self.message


class OptionError(StandgridError, ValueError):
    """An option (of an options class, or of an execution) out of its range, or options that
    cannot go together; :attr:`option` names the first at fault by its library name."""

    def __init__(self, option: str, message: str) -> None:
        super().__init__(f"option {option}: {message}", option=option)


def option_hint(name: str) -> str:
    """``option <name>``: how an error message names the option ``name``."""
    return f"option {name}"


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


class DerivedMapFormatError(FormatError):
    """A malformed elevation map or volumetric map attached to a payload (docs/FORMATS.md)."""


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
        option: str | None = None,
    ) -> None:
        super().__init__(message, path=path, line=line, option=option)
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


class PayloadTooFarError(PayloadNotFoundError):
    """The payload nearest a GNSS coordinate is beyond the distance allowed (often latitude
    and longitude given in the wrong order)."""


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


class EpochDateError(CatalogError, ValueError):
    """An epoch has no date (tiled with ``--epoch`` from missions without one) where an
    operation needs it."""


class NotEnrichedError(CatalogError, FileNotFoundError):
    """A table an export needs (tree list, stand metrics) is missing: run ``enrich`` first."""


#: How a refusal to replace an output says what would: the CLI renders it as its flag.
OVERWRITE_HINT = f"{option_hint('overwrite')} replaces it"


class OutputExistsError(StandgridError, FileExistsError):
    """An output exists and ``overwrite`` was not asked for (the message says
    :data:`OVERWRITE_HINT` when asking for it would replace it)."""

    option = "overwrite"


class OutputNotWritableError(StandgridError, PermissionError):
    """An output location cannot be written."""


class OutputOverlapsInputError(StandgridError, ValueError):
    """An output folder is, holds, or lies inside an input (writing it would destroy data)."""


class OutOfSpaceError(StandgridError, OSError):
    """The disk (or a quota, or the file-size limit) is full; the previous state is kept."""


class CatalogBusyError(CatalogError, TimeoutError):
    """Another process holds the catalog's writer lock (and did not finish within the wait)."""


class MissionFolderConflictError(CatalogError, FileExistsError):
    """The catalog holds a mission of this name tiled from another folder (replacing it
    needs ``replace_missions`` / ``--replace``)."""


class StorageError(StandgridError, OSError):
    """Object storage (``s3://`` and the other URLs :mod:`standgrid.storage` reaches) refused
    or failed a request; the message names the URL."""


class CatalogConflictError(CatalogError):
    """The catalog changed after it was opened; a transaction on the stale view is refused."""


class PayloadNotTiledError(CatalogError, LookupError):
    """A payload whose layers were asked for is not in the catalog (its mission was not
    tiled into it, from that folder, or the payload is no cloud)."""


class StaleLayersError(CatalogError):
    """A payload's layers cannot be the catalog's: its epoch is not enriched, was re-tiled
    since, or the payload's points no longer match its tiles (changed since tiled)."""


class PoorGeoreferenceError(GeoreferenceError):
    """A georeference fit whose residuals are far beyond the fixes' stated accuracy."""


class MisplacedMissionError(GeoreferenceError):
    """A georeference that puts the mission far from where its own metadata says it was
    (often latitude and longitude swapped in the GNSS log)."""


#: errno values that mean "no room left to write".
_FULL_ERRNOS = {28, 27, 122}  # ENOSPC, EFBIG, EDQUOT
_FULL_TEXTS = ("no space left on device", "file too large", "disk quota exceeded")
#: SQLite's SQLITE_FULL, as SQLite, GDAL and pyogrio say it.
_SQLITE_FULL_TEXT = "database or disk is full"


def out_of_space_error(exc: BaseException, path: str | PathLike[str]) -> OutOfSpaceError | None:
    """An :class:`OutOfSpaceError` naming ``path`` when ``exc`` (or its cause) means the disk
    is full (ENOSPC/EFBIG/EDQUOT, also as the text of lazrs/GDAL errors), else None."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OutOfSpaceError):
            return current
        code = getattr(current, "errno", None)
        text = str(current).lower()
        if (
            (isinstance(current, OSError) and code in _FULL_ERRNOS)
            or any(t in text for t in _FULL_TEXTS)
            or _SQLITE_FULL_TEXT in text
        ):
            where = getattr(current, "filename", None) or path
            reason = (
                "file-size limit reached"
                if code == 27 or "too large" in text
                else ("out of disk space")
            )
            return OutOfSpaceError(
                f"{reason} while writing ({type(current).__name__}: {current}); "
                "the previous state is kept",
                path=where,
            )
        current = current.__cause__ or current.__context__
    return None


#: Bytes of free space below which a write that failed without an errno (SQLite's "disk
#: I/O error", GDAL's "failed to commit", copclib's streams) is taken for a full disk.
FULL_DISK_SLACK = 1 << 20


def short_of_room_error(
    exc: BaseException | None, written: str | PathLike[str], path: str | PathLike[str]
) -> OutOfSpaceError | None:
    """:func:`out_of_space_error`, else an :class:`OutOfSpaceError` naming ``path`` when the
    writer of ``written`` (a file, maybe partly written) failed without saying why, and the
    file system had less than its size + :data:`FULL_DISK_SLACK` bytes free, or the file
    reached the process's file-size limit (``RLIMIT_FSIZE``); else None."""
    import os
    import resource

    if exc is not None:
        full = out_of_space_error(exc, path)
        if full is not None:
            return full
    target = Path(written)
    size = 0
    for candidate in (
        target,
        target.with_name(target.name + "-journal"),
        target.with_name(target.name + "-wal"),
    ):
        try:
            size = max(size, candidate.stat().st_size)
        except OSError:
            continue
    why = f" ({type(exc).__name__}: {exc})" if exc is not None else ""
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and size + FULL_DISK_SLACK // 16 >= limit:
        return OutOfSpaceError(
            f"file-size limit ({limit} bytes) reached while writing{why}; the previous state "
            "is kept",
            path=path,
        )
    try:
        stat = os.statvfs(target.parent)
    except OSError:
        return None
    free = stat.f_bavail * stat.f_frsize
    if free < size + FULL_DISK_SLACK:
        return OutOfSpaceError(
            f"out of disk space while writing ({free // 1024} KiB free){why}; the previous "
            "state is kept",
            path=path,
        )
    return None


# --- enrichment --------------------------------------------------------------------------


class TilingError(StandgridError, ValueError):
    """Tiling options that cannot work together (e.g. COPC tiles uncompressed)."""


class EnrichError(StandgridError, RuntimeError):
    """Terrain, tree or metric computation cannot proceed."""


__all__ = [name for name in dir() if name.endswith("Error")]
