"""The parameters of tiling (what ``standgrid tile`` and :func:`standgrid.tile` take)."""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from standgrid.errors import OptionError

SCHEMES = ("grid", "voronoi")
METHODS = ("yaw2d", "rigid3d")
#: An epoch label: it names folders and files of the catalog.
EPOCH_LABEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


def _metres(name: str, value: float | None, *, positive: bool) -> None:
    if value is None:
        return
    if (
        not isinstance(value, int | float)
        or not math.isfinite(value)
        or value < 0
        or (positive and value == 0)
    ):
        raise OptionError(name, f"{value!r}: give metres {'> 0' if positive else '>= 0'}")


@dataclass(frozen=True)
class TileOptions:
    """How to tile; validated when made (:class:`~standgrid.errors.OptionError` naming the
    field at fault). ``cell_size``/``crs`` of ``None``/``"auto"`` take the catalog's own.

    ``crs="auto"``: a new catalog takes the first fitted mission's UTM zone (or the projected
    clouds' own CRS); missions added to a catalog take its CRS, also as the CRS of projected
    clouds that name none, and a mission outside that CRS's area of use is refused
    (:class:`~standgrid.errors.CRSError`)."""

    #: ``None``: the catalog's scheme ("grid" for a new catalog).
    scheme: Literal["grid", "voronoi"] | None = None
    cell_size: float | None = None
    levels: tuple[float, ...] = ()
    origin: tuple[float, float] = (0.0, 0.0)
    crs: str = "auto"
    #: ``None``: the catalog's setting (0 for a new catalog).
    buffer: float | None = None
    #: ``None``: the catalog's setting (LAZ for a new catalog).
    laz: bool | None = None
    #: COPC tiles (streamable LAZ; tiling to COPC costs 1.1-1.4x the CPU of tiling to LAZ:
    #: ``benchmarks/bench_copc.py --tiling``). ``None``: the catalog's setting (not COPC for
    #: a new catalog).
    copc: bool | None = None
    method: Literal["yaw2d", "rigid3d"] = "yaw2d"
    #: ``(lat, lon, alt, yaw_deg)``: place the map frame by hand, no GNSS fit
    #: (:func:`standgrid.georeference.fit_from_anchor`); one mission per run.
    anchor: tuple[float, float, float, float] | None = None
    epoch: str | None = None
    overwrite: bool = False
    #: Tile even when a georeference's residuals are far beyond the fixes' stated accuracy.
    accept_poor_georeference: bool = False
    #: Metres: a mission already in its epoch keeps the placement the catalog used while its
    #: fresh georeference moves none of its points this far from it (the epoch re-tiles in
    #: place; the offset is reported). None: always the fresh fit (exact, the default).
    #: See :mod:`standgrid.tiling.placement_policy`.
    placement_tolerance: float | None = None
    #: A mission of a name the catalog holds, tiled from another folder, replaces it (else
    #: :class:`~standgrid.errors.MissionFolderConflictError`). Re-ingesting from the same
    #: folder is always allowed.
    replace_missions: bool = False
    #: Register the missions given together to each other on their stems and ground, and
    #: place them by one graph with their GNSS (:mod:`standgrid.alignment`), when two or more
    #: overlap. False: each mission by its own GNSS fit alone.
    align: bool = True
    #: Epoch by mission name (over ``epoch`` and the mission's year): a catalog's own
    #: labels when its missions are re-tiled (``standgrid align``).
    epochs: tuple[tuple[str, str], ...] = ()
    #: Plain scans (LAS/LAZ/COPC files, folders of tiles, VPCs): their date when the header
    #: gives none (or to override it), and a scanner trajectory file
    #: (:mod:`standgrid.mission.scan`).
    scan_date: dt.date | None = None
    trajectory: Path | None = None

    def __post_init__(self) -> None:
        if self.scheme not in (None, *SCHEMES):
            raise OptionError("scheme", f"{self.scheme!r}: give one of {', '.join(SCHEMES)}")
        if self.method not in METHODS:
            raise OptionError("method", f"{self.method!r}: give one of {', '.join(METHODS)}")
        _metres("cell_size", self.cell_size, positive=True)
        for size in self.levels:
            _metres("levels", size, positive=True)
        _metres("buffer", self.buffer, positive=False)
        _metres("placement_tolerance", self.placement_tolerance, positive=False)
        if self.anchor is not None:
            if len(self.anchor) != 4 or not all(math.isfinite(v) for v in self.anchor):
                raise OptionError("anchor", f"{self.anchor!r}: give (lat, lon, alt, yaw_deg)")
            lat, lon = self.anchor[:2]
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise OptionError(
                    "anchor", f"latitude {lat:g}, longitude {lon:g}: not on the Earth"
                )
        if self.epoch is not None and not EPOCH_LABEL.fullmatch(self.epoch):
            raise OptionError("epoch", f"{self.epoch!r}: letters, digits, '.', '_' and '-' only")
        if self.scan_date is not None and not isinstance(self.scan_date, dt.date):
            raise OptionError("scan_date", f"{self.scan_date!r}: give a datetime.date")
