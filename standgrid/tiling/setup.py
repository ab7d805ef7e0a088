"""Where a tiling run writes: checking the output folder, creating a catalog, its settings."""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from standgrid._atomic import check_replaceable
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.state import is_standgrid_catalog
from standgrid.errors import (
    CRSError,
    GridMismatchError,
    MissionFolderConflictError,
    OutputExistsError,
    OutputNotWritableError,
    OutputOverlapsInputError,
    TilingError,
)
from standgrid.storage.objects import is_url, source_of

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, FileLock, Transaction
    from standgrid.catalog.records import TilingSettings
    from standgrid.georeference.placement import Placement


@dataclass(frozen=True)
class GridRequest:
    """The partition a run asks for (``None``/``"auto"``: the catalog's own)."""

    scheme: Literal["grid", "voronoi"] | None = None
    cell_size: float | None = None
    levels: tuple[float, ...] = ()
    origin: tuple[float, float] = (0.0, 0.0)
    crs: str = "auto"

    def definition(self, crs: str) -> dict[str, Any]:
        """The catalog.json ``grid`` of this request in the CRS ``crs``."""
        from standgrid.partition import StandGrid
        from standgrid.partition.grid import grid_crs

        if self.scheme == "voronoi":
            return {"scheme": "voronoi", "crs": crs}  # cells come from the payloads
        size = self.cell_size or 20.0
        grid = StandGrid(grid_crs(crs), size, origin=self.origin, levels=self.levels)
        return grid.to_dict()


def absolute_output(catalog_path: str | Path, overwrite: bool) -> Path:
    """The catalog path made absolute ("." included); replacing the folder the process
    works in is refused."""
    path = Path(os.path.abspath(catalog_path))
    if not path.name:
        raise OutputNotWritableError("a catalog cannot be the file-system root", path=path)
    cwd = Path.cwd().resolve()
    if overwrite and path.is_dir() and any(path.iterdir()):
        real = path.resolve()
        if cwd == real or cwd.is_relative_to(real):
            raise OutputNotWritableError(
                "is (or holds) the current folder; --overwrite cannot replace it (run from "
                "another folder)",
                path=catalog_path,
            )
    return path


def refuse_overlap(output: Path, inputs: Iterable[str | Path]) -> None:
    """Refuse an output that is, holds or lies inside an input folder (symlinks resolved)."""
    out = Path(os.path.realpath(output))
    for given in inputs:
        source = Path(os.path.realpath(given))
        if out == source:
            how = "is"
        elif out.is_relative_to(source):
            how = "lies inside"
        elif source.is_relative_to(out):
            how = "holds"
        else:
            continue
        raise OutputOverlapsInputError(
            f"the output {how} the input {given}; outputs never overlap inputs (choose another -o)",
            path=output,
        )


def is_catalog(path: Path) -> bool:
    """True when ``path`` holds a standgrid catalog (its ``catalog.json`` says so; another
    tool's catalog.json, a STAC catalog, is not one)."""
    return is_standgrid_catalog(path)


def refuse_foreign_folder(path: Path) -> None:
    """A folder with other files is never turned into, nor replaced by, a catalog: overwriting
    replaces a catalog only."""
    if path.exists() and not path.is_dir():
        raise OutputExistsError("exists and is not a folder", path=path)
    if path.is_dir() and any(path.iterdir()) and not is_catalog(path):
        check_replaceable(path, overwrite=True, what="a catalog")


def check_existing(catalog: Catalog, request: GridRequest) -> None:
    """Refuse adding missions in another CRS, scheme or grid than the catalog's."""
    from dataclasses import replace

    from standgrid.georeference import resolve_crs

    path = catalog.root
    if request.crs not in ("auto", "", None):
        wanted = resolve_crs(request.crs).text
        if wanted != catalog.crs:
            raise CRSError(
                f"the catalog is in {catalog.crs}; cannot add missions in {wanted}",
                path=path / CATALOG_FILE,
            )
    if request.scheme is not None and request.scheme != catalog.scheme:
        raise GridMismatchError(
            f"the catalog uses the {catalog.scheme} scheme, not {request.scheme}",
            path=path / CATALOG_FILE,
        )
    if catalog.scheme == "grid" and request.cell_size is not None:
        stored = catalog.grid_definition
        if not request.levels and float(request.cell_size) == float(stored["cell_size"]):
            # an unspecified --levels means "the catalog's", not the default levels
            request = replace(request, levels=tuple(float(v) for v in stored["levels"]))
        catalog.check_grid(request.definition(catalog.crs))


#: Degrees a mission may lie outside its catalog CRS's area of use (UTM: a zone's edge plus
#: 1 degree keeps the scale error under ~0.25 %; beyond, a projection's numbers drift).
AREA_OF_USE_MARGIN_DEG = 1.0


def existing_crs(path: Path, overwrite: bool, lock_timeout: float | None = 30.0) -> str | None:
    """The CRS of the catalog at ``path`` that missions are added to (None: a new one)."""
    if overwrite or not is_catalog(path):
        return None
    from standgrid.catalog.store import Catalog

    return Catalog.open(path, lock_timeout=lock_timeout).crs


def check_area_of_use(catalog: Catalog, placed: Iterable[tuple[str, Placement]]) -> None:
    """:class:`CRSError` when a fitted mission (its georeference's origin) lies more than
    :data:`AREA_OF_USE_MARGIN_DEG` outside the area of use of the catalog's CRS (pyproj
    ``CRS.area_of_use``; a CRS without one is not checked)."""
    from standgrid.crs import CRS

    crs = CRS.of(catalog.crs)
    area = crs.pyproj_crs.area_of_use
    if area is None:
        return
    m = AREA_OF_USE_MARGIN_DEG
    for name, placement in placed:
        if placement.fit is None:
            continue
        lat, lon = float(placement.fit.lla_ref[0]), float(placement.fit.lla_ref[1])
        if area.west <= area.east:
            inside_lon = area.west - m <= lon <= area.east + m
        else:  # the area crosses the antimeridian
            inside_lon = lon >= area.west - m or lon <= area.east + m
        if inside_lon and area.south - m <= lat <= area.north + m:
            continue
        code = crs.authority
        label = f"{code[0]}:{code[1]} ({crs.name})" if code else crs.name
        hint = _swapped_near_catalog(catalog, lat, lon)
        raise CRSError(
            f"mission {name!r} lies at lat {lat:.5f}, lon {lon:.5f}, outside the area of use "
            f"of the catalog's CRS {label}: {area.name} (lon {area.west:.2f} to "
            f"{area.east:.2f}, lat {area.south:.2f} to {area.north:.2f}); "
            + (hint or "tile it into another catalog (--crs auto: its UTM zone)"),
            path=catalog.root / CATALOG_FILE,
        )


#: Metres: how near the catalog's missions a mission read with latitude and longitude
#: swapped must lie for the swap hint.
SWAP_HINT_NEAR_M = 50_000.0


def _swapped_near_catalog(catalog: Catalog, lat: float, lon: float) -> str | None:
    """The swap hint (:func:`~standgrid.georeference.location.swap_hint`) when ``lat, lon``
    read the other way round lies near a mission of the catalog."""
    import numpy as np

    from standgrid.georeference.location import geodesic_m, swap_hint

    refs = [
        (float(r.georeference["lla_ref"][0]), float(r.georeference["lla_ref"][1]))
        for r in catalog.mission_records.values()
        if r.georeference and r.georeference.get("lla_ref")
    ]
    if not refs:
        return None
    lats, lons = np.array(refs).T

    def nearest_mission_m(la: float, lo: float) -> float:
        return float(geodesic_m(la, lo, lats, lons).min())

    return swap_hint(
        round(lat, 6),
        round(lon, 6),
        nearest_mission_m,
        SWAP_HINT_NEAR_M,
        what="the catalog's nearest mission is",
        advice="the mission's GNSS log has latitude and longitude swapped",
    )


def create_catalog(
    path: Path,
    final: Path,
    lock: FileLock,
    placements: list[Placement],
    request: GridRequest,
    lock_timeout: float | None,
) -> Catalog:
    """A new, empty catalog at ``path`` (to be published at ``final``) in the requested (or
    the missions' UTM, or their clouds' own projected) CRS."""
    from standgrid.catalog.store import Catalog
    from standgrid.georeference import resolve_crs

    first = placements[0]
    if first.fit is None and request.crs in ("auto", "", None):
        assert first.source_crs is not None
        crs = first.source_crs.text  # projected clouds: their own CRS
    else:
        fit = next((p.fit for p in placements if p.fit is not None), None)
        lat, lon = (fit.lla_ref[0], fit.lla_ref[1]) if fit is not None else (None, None)
        crs = resolve_crs(request.crs, lon=lon, lat=lat).text
    scheme = request.scheme or "grid"
    catalog = Catalog.build(path, request.definition(crs), crs, scheme, final=final, held=lock)
    catalog.lock_timeout = lock_timeout
    return catalog


def settle_tiling(
    txn: Transaction, buffer: float | None, laz: bool | None, copc: bool | None = None
) -> TilingSettings:
    """Unset buffer/format settings take the catalog's (the last ones given; 0 m and LAZ for
    a new catalog), which are updated to what this run uses. COPC is always compressed: LAS
    given alone leaves COPC; given with COPC, :class:`TilingError`."""
    from standgrid.catalog.records import TilingSettings

    stored = txn.tiling_settings()
    if copc and laz is False:
        raise TilingError("COPC tiles are compressed LAZ: give either COPC or LAS")
    use_copc = (stored.copc and laz is not False) if copc is None else bool(copc)
    use_laz = True if use_copc else stored.laz if laz is None else bool(laz)
    settings = TilingSettings(
        buffer=stored.buffer if buffer is None else float(buffer), laz=use_laz, copc=use_copc
    )
    txn.set_tiling_settings(settings)
    return settings


def refuse_other_folders(catalog: Catalog, missions: Iterable[tuple[str, Path]]) -> None:
    """:class:`MissionFolderConflictError` when a mission's name (of ``(name, folder)``) is in
    the catalog, tiled from another folder: the same name is not the same mission (tiling it
    would replace that mission's points)."""
    known = catalog.mission_records
    for name, folder in missions:
        record = known.get(name)
        if record is None or not record.path:
            continue
        here = source_of(folder)  # a URL for a mission fetched from object storage
        there = record.path if is_url(record.path) else os.path.realpath(record.path)
        if here != there:
            raise MissionFolderConflictError(
                f"the catalog holds a mission {name!r} tiled from another folder, "
                f"{record.path} (now given: {here}); tiling it would replace that mission's "
                "points. Replace it with --replace (TileOptions.replace_missions), or tile "
                "into another catalog",
                path=catalog.root,
            )
