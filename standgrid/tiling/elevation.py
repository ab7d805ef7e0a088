"""Payloads' derived maps into the catalog: elevation maps placed and mosaicked per epoch,
volumetric maps placed (their bounds in the catalog CRS).

Each payload's elevation map is placed with the payload's pose and the mission's placement,
the very transform its points take (:meth:`ToCatalog.base_points`), then resampled onto the
catalog's raster lattice (the DTM's: corners on the lattice origin plus whole pixels of
:data:`PIXEL_M`): the mean of the map cells whose centres fall in a pixel, else (a map
coarser than the pixel) linear between cell centres. A mission's maps are averaged where
they overlap into ``maps/<epoch>/<mission>.elevation.tif``; the epoch's mosaic
``rasters/<epoch>/elevation_map.tif`` is the mean of its missions' (a mission kept from an
earlier run keeps its own), so it is rebuilt whenever the epoch is tiled; where the epoch's
DTM still holds (its points did not move) the mosaic minus the DTM is reported then, else
by the next ``enrich``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.catalog import paths
from standgrid.rastergrid import RasterGrid

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, Transaction
    from standgrid.crs import CRS, CRSLike
    from standgrid.georeference.placement import ToCatalog
    from standgrid.mission.derived_maps import ElevationMap
    from standgrid.mission.model import Mission
    from standgrid.mission.payload import Payload

#: Pixel of the elevation-map rasters (m): the DTM's default (``EnrichOptions.pixel_size``).
PIXEL_M = 1.0


@dataclass
class PlacedMaps:
    """One mission's derived maps in the catalog CRS."""

    #: the mean of its payloads' elevation maps on the lattice (None: no elevation map)
    grid: RasterGrid | None = None
    heights: NDArray[np.float64] | None = None
    elevation_maps: int = 0
    #: per volumetric map: its payload stamp, kind, voxel size and bounds in the CRS
    volumetric: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def record(self) -> dict[str, Any]:
        """What the mission record and the tile report say of the maps."""
        out: dict[str, Any] = {"elevation_maps": self.elevation_maps}
        if self.heights is not None:
            out["elevation_pixels"] = int(np.isfinite(self.heights).sum())
        out["volumetric_maps"] = self.volumetric
        if self.notes:
            out["notes"] = self.notes
        return out


def has_maps(mission: Mission) -> bool:
    return any(p.elevation_map or p.volumetric_map for p in mission.payloads)


def place_mission_maps(
    mission: Mission,
    to_catalog: ToCatalog,
    crs: CRSLike,
    origin: tuple[float, float],
) -> PlacedMaps:
    """Place every derived map of ``mission``'s payloads into ``crs`` (its elevation maps
    resampled and averaged on the raster lattice through ``origin``)."""
    from standgrid.crs import CRS

    crs = CRS.of(crs)
    placed = PlacedMaps()
    pieces: list[tuple[RasterGrid, NDArray[np.float64]]] = []
    for payload in mission.payloads:
        if payload.elevation_map is None and payload.volumetric_map is None:
            continue
        pose = _pose(mission, payload, to_catalog, placed)
        if payload.elevation_map is not None:
            emap = mission.load_elevation_map(payload)
            xyz = _placed_cells(emap, pose, to_catalog, crs, payload, placed)
            if xyz is not None and len(xyz):
                pieces.append(resample(xyz, emap.resolution, origin, crs))
                placed.elevation_maps += 1
        if payload.volumetric_map is not None:
            _place_volume(mission, payload, pose, to_catalog, placed)
    if pieces:
        placed.grid, placed.heights = mean_mosaic(pieces, origin, crs)
    return placed


def _pose(
    mission: Mission, payload: Payload, to_catalog: ToCatalog, placed: PlacedMaps
) -> NDArray[np.float64] | None:
    from standgrid.errors import OrphanPayloadError

    if to_catalog.fit is None:
        return None  # a projected mission: its maps must carry their CRS
    try:
        return mission.pose_of(payload)
    except OrphanPayloadError:
        placed.notes.append(f"{payload.stamp}: no pose-graph node, its maps left out")
        return None


def _placed_cells(
    emap: ElevationMap,
    pose: NDArray[np.float64] | None,
    to_catalog: ToCatalog,
    crs: CRS,
    payload: Payload,
    placed: PlacedMaps,
) -> NDArray[np.float64] | None:
    """The map's cells in the catalog CRS (None: it cannot be placed, said in ``notes``)."""
    pts = emap.cell_points()
    if emap.crs is not None:
        if emap.crs == crs:
            return pts
        x, y = emap.crs.transformer_to(crs).transform(pts[:, 0], pts[:, 1], errcheck=True)
        return np.column_stack([np.asarray(x), np.asarray(y), pts[:, 2]])
    if pose is None:
        if to_catalog.fit is None:
            placed.notes.append(
                f"{payload.elevation_map}: in the payload frame, but the mission's clouds are "
                "in a projected CRS (no pose): left out"
            )
        return None
    return to_catalog.base_points(np.array(pts), pose=pose)


def _place_volume(
    mission: Mission,
    payload: Payload,
    pose: NDArray[np.float64] | None,
    to_catalog: ToCatalog,
    placed: PlacedMaps,
) -> None:
    import importlib.util

    from standgrid.mission.derived_maps import VoxelGrid

    path = payload.volumetric_map
    entry: dict[str, Any] = {"stamp": str(payload.stamp), "file": str(path)}
    octomap = path is not None and path.suffix.lower() in (".bt", ".ot")
    if octomap and importlib.util.find_spec("octomap") is None:
        entry.update(kind="octomap", bounds=None)  # kept: no OctoMap reader installed
        placed.notes.append(f"{path}: kept, not placed (octomap-python is not installed)")
        placed.volumetric.append(entry)
        return
    grid = mission.load_volumetric_map(payload)
    entry.update(kind=grid.kind, voxel_size=grid.voxel_size)
    if isinstance(grid, VoxelGrid):
        entry["shape"] = list(grid.values.shape)
    else:
        entry["occupied"] = len(grid.occupied)
    if pose is None:
        entry["bounds"] = None
    else:
        corners = to_catalog.base_points(grid.corners(), pose=pose)
        entry["bounds"] = [
            *corners.min(axis=0).round(3).tolist(),
            *corners.max(axis=0).round(3).tolist(),
        ]
    placed.volumetric.append(entry)


def lattice_grid(
    bounds: tuple[float, float, float, float],
    origin: tuple[float, float],
    crs: CRS,
    *,
    closed: bool = False,
) -> RasterGrid:
    """The raster of :data:`PIXEL_M` pixels through ``origin`` covering ``bounds``."""
    return RasterGrid.covering(
        bounds,
        origin=origin,
        cell_size=PIXEL_M,
        pixel_size=PIXEL_M,
        snap_to_cells=False,
        closed=closed,
        crs=crs,
    )


def resample(
    xyz: NDArray[np.float64],
    resolution: float,
    origin: tuple[float, float],
    crs: CRS,
) -> tuple[RasterGrid, NDArray[np.float64]]:
    """Placed map cells ``xyz`` (``resolution`` m apart) onto the lattice: each pixel the mean
    of the cells inside it; a pixel holding none but within one cell of the map's cells, and
    inside their hull, linear between them."""
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import QhullError, cKDTree

    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    grid = lattice_grid((lo[0], lo[1], hi[0], hi[1]), origin, crs)
    index = grid.flat_index(xyz[:, 0], xyz[:, 1])
    total = np.bincount(index, weights=xyz[:, 2], minlength=grid.ncols * grid.nrows)
    count = np.bincount(index, minlength=grid.ncols * grid.nrows)
    with np.errstate(invalid="ignore", divide="ignore"):
        values = total / count
    empty = count == 0
    if empty.any() and len(xyz) >= 3:
        cx, cy = grid.centers()
        query = np.column_stack([cx.ravel()[empty] - grid.x0, cy.ravel()[empty] - grid.y0])
        local = xyz[:, :2] - (grid.x0, grid.y0)
        near, _ = cKDTree(local).query(query, distance_upper_bound=resolution)
        try:
            filled = LinearNDInterpolator(local, xyz[:, 2])(query)
        except QhullError:  # collinear cells: nothing between them
            filled = np.full(len(query), np.nan)
        filled[~np.isfinite(near)] = np.nan
        values[empty] = filled
    return grid, values.reshape(grid.shape)


def paste_offset(outer: RasterGrid, inner: RasterGrid) -> tuple[int, int] | None:
    """(row, col) of ``inner``'s north-west pixel in ``outer`` when both lie on one pixel
    lattice (same pixel size, corners whole pixels apart); else None."""
    if not math.isclose(outer.pixel_size, inner.pixel_size, rel_tol=1e-9):
        return None
    col = (inner.x0 - outer.x0) / outer.pixel_size
    row = (outer.bounds[3] - inner.bounds[3]) / outer.pixel_size
    if abs(col - round(col)) > 1e-6 or abs(row - round(row)) > 1e-6:
        return None
    return round(row), round(col)


def mean_mosaic(
    pieces: list[tuple[RasterGrid, NDArray[np.float64]]],
    origin: tuple[float, float],
    crs: CRS,
) -> tuple[RasterGrid, NDArray[np.float64]]:
    """Rasters on one lattice into one: their mean where they overlap (NaN: none)."""
    bounds = np.array([g.bounds for g, _ in pieces])
    union = (bounds[:, 0].min(), bounds[:, 1].min(), bounds[:, 2].max(), bounds[:, 3].max())
    grid = lattice_grid(union, origin, crs, closed=True)
    total = np.zeros(grid.shape)
    count = np.zeros(grid.shape, dtype=np.int64)
    for piece, values in pieces:
        at = paste_offset(grid, piece)
        assert at is not None, "rasters off the lattice"
        window = (slice(at[0], at[0] + piece.nrows), slice(at[1], at[1] + piece.ncols))
        seen = np.isfinite(values)
        total[window] += np.where(seen, values, 0.0)
        count[window] += seen
    with np.errstate(invalid="ignore", divide="ignore"):
        return grid, np.where(count > 0, total / np.maximum(count, 1), np.nan)


def difference(
    values: NDArray[np.float64],
    grid: RasterGrid,
    reference: NDArray[np.floating],
    reference_grid: RasterGrid,
) -> dict[str, Any]:
    """``values - reference`` where both hold a value: median, MAD (scaled to a normal
    sigma: 1.4826 x median absolute deviation), mean, RMSE (m) and pixels compared."""
    at = paste_offset(reference_grid, grid)
    if at is None:
        return {"pixels": 0, "note": "the rasters do not share a pixel lattice"}
    rows = np.arange(grid.nrows) + at[0]
    cols = np.arange(grid.ncols) + at[1]
    keep_r = (rows >= 0) & (rows < reference_grid.nrows)
    keep_c = (cols >= 0) & (cols < reference_grid.ncols)
    mine = values[np.ix_(keep_r, keep_c)]
    theirs = np.asarray(reference, np.float64)[np.ix_(rows[keep_r], cols[keep_c])]
    diff = (mine - theirs)[np.isfinite(mine) & np.isfinite(theirs)]
    if diff.size == 0:
        return {"pixels": 0, "note": "no pixel holds both"}
    median = float(np.median(diff))
    return {
        "pixels": int(diff.size),
        "median_m": round(median, 4),
        "mad_m": round(1.4826 * float(np.median(np.abs(diff - median))), 4),
        "mean_m": round(float(diff.mean()), 4),
        "rmse_m": round(float(np.sqrt(np.mean(diff**2))), 4),
    }


# --- the catalog's files ----------------------------------------------------------------


def stage_mission_maps(
    catalog: Catalog, txn: Transaction, epoch: str, name: str, placed: PlacedMaps | None
) -> None:
    """The mission's placed elevation map into ``maps/<epoch>/``; its earlier ones (this epoch
    without maps now, or another epoch it left) deleted."""
    from standgrid.geotiff import NODATA, write_cog

    rel = paths.mission_elevation_map(epoch, name)
    for old in sorted(catalog.root.glob(paths.mission_elevation_map("*", name))):
        old_rel = old.relative_to(catalog.root).as_posix()
        if old_rel != rel or placed is None or placed.heights is None:
            txn.delete(old_rel)
    if placed is not None and placed.heights is not None:
        assert placed.grid is not None
        write_cog(
            txn.stage(rel),
            placed.heights.astype(np.float32),
            placed.grid,
            nodata=NODATA,
            description=f"{name}: payload elevation maps, mean (m)",
        )


def stage_epoch_mosaic(
    catalog: Catalog, txn: Transaction, epoch: str, staged: set[str]
) -> dict[str, Any] | None:
    """``rasters/<epoch>/elevation_map.tif`` (and its style): the mean of the epoch's
    missions' placed elevation maps (those on disk not deleted, and ``staged``); removed
    when there are none. Returns its summary (None: no map)."""
    from standgrid.crs import CRS
    from standgrid.export.styles import raster_style_path, write_raster_style
    from standgrid.geotiff import NODATA, read_raster, write_cog

    rels = {
        p.relative_to(catalog.root).as_posix()
        for p in catalog.root.glob(paths.mission_elevation_map(epoch, "*"))
    }
    rels |= {r for r in staged if r.startswith(paths.maps_folder(epoch) + "/")}
    pieces = []
    for rel in sorted(rels):
        current = txn.current(rel)
        if current is not None:
            raster = read_raster(current)
            pieces.append((raster.grid, raster.array))
    target = paths.raster(epoch, paths.ELEVATION_MAP)
    if not pieces:
        if txn.current(target) is not None:
            txn.delete(target)
            txn.delete(paths.raster_style(epoch, paths.ELEVATION_MAP))
        return None
    crs = CRS.of(catalog.crs)
    grid0 = pieces[0][0]
    origin = (grid0.x0, grid0.y0)  # every piece lies on the one lattice
    grid, heights = mean_mosaic(pieces, origin, crs)
    tif = txn.stage(target)
    write_cog(
        tif,
        heights.astype(np.float32),
        grid,
        nodata=NODATA,
        description="payloads' elevation maps, placed and averaged (m)",
    )
    write_raster_style(tif, "dtm", qml=txn.stage(raster_style_path(target)))
    summary: dict[str, Any] = {
        "raster": target,
        "missions": len(pieces),
        "pixels": int(np.isfinite(heights).sum()),
        "pixel_size_m": PIXEL_M,
    }
    dtm = txn.current(paths.raster(epoch, "dtm"))
    if dtm is not None:  # the epoch's points did not move: its DTM still holds
        terrain = read_raster(dtm)
        summary["minus_dtm"] = difference(heights, grid, terrain.array, terrain.grid)
    return summary
