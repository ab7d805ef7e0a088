"""Enrich a catalog: ground, terrain rasters, height above ground, trees, stand metrics.

Per epoch, cell by cell, each cell is processed as a *block*: its tile plus the points of
neighbouring tiles within ``halo`` metres, so that ground filtering, the terrain model and
tree crowns see across cell edges. A tree belongs to the cell that holds its top, and its
id derives from the top's position, so a tree crossing a cell edge is one tree.

Outputs (one catalog transaction; the previous state stays intact on any error):

- tiles rewritten with ``classification`` (2 = ground, 1 = other), ``height_above_ground``
  and ``tree_id`` (0 = no tree);
- ``rasters/<epoch>/{dtm,chm,density}.tif``: Cloud-Optimized GeoTIFFs pixel-aligned to the
  stand grid, so rasters of different epochs overlay exactly;
- ``tables/stand_metrics.{csv,parquet}`` (keyed by ``cell_id``, ``epoch``) and
  ``tables/tree_list_<epoch>.{csv,parquet}``;
- GeoPackage layers ``stand_metrics`` (cell polygons) and ``trees`` (crown polygons), styled.
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.enrich.rasters import NODATA
from standgrid.errors import EnrichError, EpochNotFoundError, StandgridError
from standgrid.pointcloud import PointCloud

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.enrich.rasters import RasterGrid
    from standgrid.export.catalog import Catalog, Transaction

Wrap = Callable[[Iterable[Any], int, str], Iterable[Any]]

GROUND = 2
OTHER = 1


def _no_wrap(items: Iterable[Any], total: int, desc: str) -> Iterable[Any]:
    return items


@dataclass(frozen=True)
class EnrichOptions:
    """Parameters of enrichment (documented in docs/METRICS.md)."""

    pixel_size: float = 1.0
    halo: float = 10.0
    height_break: float = 2.0
    cloth_resolution: float = 0.5
    rigidness: int = 1
    tree_pixel_size: float = 0.5
    tree_min_height: float = 2.0
    epochs: tuple[str, ...] = ()


@dataclass
class EnrichReport:
    catalog: Path
    epochs: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"catalog": str(self.catalog), "epochs": self.epochs}


@dataclass
class _Cell:
    cell_id: str
    rel: str
    polygon: Any
    #: The id of the 1 ha (next level) stand holding the cell (grid scheme), else None.
    stand_id: str | None = None


class _TileCache:
    """Reads tiles (withheld points included) into an LRU bounded by a point count: each tile
    is read for itself and as a neighbour of up to 8 others, in two passes."""

    def __init__(
        self, catalog: Catalog, origin: tuple[float, float], max_points: int = 8_000_000
    ) -> None:
        self.catalog = catalog
        self.origin = origin
        self.max_points = max_points
        self._points = 0
        self._items: OrderedDict[str, PointCloud] = OrderedDict()

    def get(self, rel: str) -> PointCloud:
        from standgrid.export.las import read_tile, snap_to_storage

        cloud = self._items.get(rel)
        if cloud is None:
            cloud = read_tile(self.catalog.path(rel), include_withheld=True)
            cloud = PointCloud(snap_to_storage(cloud.xyz, self.origin), cloud.fields)
            self._items[rel] = cloud
            self._points += len(cloud)
            while self._points > self.max_points and len(self._items) > 1:
                _, dropped = self._items.popitem(last=False)
                self._points -= len(dropped)
        else:
            self._items.move_to_end(rel)
        return cloud


def enrich_catalog(
    catalog_path: str | Path,
    options: EnrichOptions = EnrichOptions(),
    *,
    wrap: Wrap = _no_wrap,
    status: Callable[[str], None] = lambda message: None,
    lock_timeout: float | None = 30.0,
) -> EnrichReport:
    """Enrich every epoch of the catalog (or ``options.epochs``); returns what was done.

    Everything is read and written under the catalog's writer lock (waiting up to
    ``lock_timeout`` seconds for another writer).
    """
    from standgrid.export.catalog import Catalog

    with Catalog.writing(catalog_path, lock_timeout=lock_timeout) as catalog:
        return _enrich(catalog, options, wrap, status)


def _enrich(
    catalog: Catalog, options: EnrichOptions, wrap: Wrap, status: Callable[[str], None]
) -> EnrichReport:
    if not catalog.crs:
        raise EnrichError("the catalog has no CRS (not georeferenced)", path=catalog.root)
    epochs = list(options.epochs) or sorted(catalog.epochs)
    for epoch in epochs:
        if epoch not in catalog.epochs:
            raise EpochNotFoundError(
                f"no epoch {epoch!r} (epochs: {sorted(catalog.epochs)})", path=catalog.root
            )
    if not epochs:
        raise EnrichError(
            "the catalog has no epochs: tile missions into it first", path=catalog.root
        )
    report = EnrichReport(catalog.root)
    metric_tables: dict[str, pd.DataFrame] = {}
    tree_tables: dict[str, pd.DataFrame] = {}
    with catalog.transaction() as txn:
        for epoch in epochs:
            status(f"enriching epoch {epoch}")
            metrics, trees, summary = _enrich_epoch(catalog, txn, epoch, options, wrap)
            metric_tables[epoch], tree_tables[epoch] = metrics, trees
            report.epochs[epoch] = summary
            txn.state["epochs"][epoch]["enriched"] = True
            txn.state["epochs"][epoch]["enrichment"] = summary
        _write_tables(catalog, txn, metric_tables, tree_tables)
        _write_layers(catalog, txn, metric_tables, tree_tables)
    return report


# --- one epoch ---------------------------------------------------------------------------


def _epoch_cells(catalog: Catalog, epoch: str) -> list[_Cell]:
    from standgrid.export.gpkg import read_index_layer

    grid = _stand_grid(catalog)
    cells = read_index_layer(catalog.path("index.gpkg"), "cells")
    cells = cells[cells["epoch"].astype(str) == epoch].sort_values("cell_id")
    return [
        _Cell(str(r.cell_id), str(r.tile_path), r.geometry, _stand_of(grid, str(r.cell_id)))
        for r in cells.itertuples()
    ]


def _stand_grid(catalog: Catalog) -> Any:
    """The catalog's StandGrid when it has a coarser (stand) level, else None."""
    from standgrid.partition import StandGrid

    if catalog.scheme != "grid":
        return None
    grid = StandGrid.from_dict(catalog.grid_definition)
    return grid if len(grid.levels) > 1 else None


def _stand_of(grid: Any, cell_id: str) -> str | None:
    from standgrid.partition import CellId

    return None if grid is None else str(CellId.parse(cell_id).parent(grid))


def _grid_alignment(catalog: Catalog) -> tuple[tuple[float, float], float]:
    """Origin and cell size the rasters align to (the stand grid's; 10 m for Voronoi)."""
    definition = catalog.grid_definition
    if catalog.scheme == "grid":
        x0, y0 = definition["origin"]
        return (float(x0), float(y0)), float(definition["cell_size"])
    return (0.0, 0.0), 10.0


def _enrich_epoch(
    catalog: Catalog, txn: Transaction, epoch: str, options: EnrichOptions, wrap: Wrap
) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]:
    import shapely

    from standgrid.enrich.rasters import RasterGrid

    cells = _epoch_cells(catalog, epoch)
    if not cells:
        raise EnrichError(f"epoch {epoch} has no tiles", path=catalog.root)
    origin, cell_size = _grid_alignment(catalog)
    bounds = shapely.bounds(shapely.union_all([c.polygon for c in cells]))
    grid = RasterGrid.covering(
        tuple(bounds), origin=origin, cell_size=cell_size, pixel_size=options.pixel_size
    )
    tree = shapely.STRtree([c.polygon for c in cells])
    tiles = _TileCache(catalog, origin)
    # the block must reach every buffer copy a tile holds, so those get heights and ids too
    halo = max(options.halo, float(txn.state.get("tiling", {}).get("buffer", 0.0)))

    def block(cell: _Cell) -> NDArray[np.float64]:
        """The cell's core points first, then every neighbour core point within the halo."""
        xmin, ymin, xmax, ymax = cell.polygon.bounds
        h = halo
        parts = [_core_xyz(tiles.get(cell.rel))]
        for j in sorted(int(j) for j in tree.query(cell.polygon.buffer(h))):
            if cells[j].rel == cell.rel:
                continue
            xyz = _core_xyz(tiles.get(cells[j].rel))
            x, y = xyz[:, 0], xyz[:, 1]
            parts.append(xyz[(x >= xmin - h) & (x < xmax + h) & (y >= ymin - h) & (y < ymax + h)])
        return np.concatenate(parts)

    # pass 1: ground and the terrain model
    dtm = np.full(grid.shape, np.nan, dtype=np.float32)
    ground_of: dict[str, NDArray[np.bool_]] = {}
    no_ground: set[str] = set()
    for cell in wrap(cells, len(cells), f"{epoch}: ground"):
        xyz = block(cell)
        mask = _classify(xyz, options, catalog.path(cell.rel))
        ground_of[cell.rel] = mask
        if not mask.any():
            no_ground.add(cell.cell_id)
            continue
        ground = xyz[mask]
        _paste(dtm, grid, cell.polygon, functools.partial(_dtm, ground))
    if np.isnan(dtm).all():
        raise EnrichError(
            f"epoch {epoch}: no ground points anywhere, so no terrain model", path=catalog.root
        )
    dtm_filled = _nearest_fill(dtm)

    # pass 2: heights, rasters, trees, metrics, tiles
    chm_raster = np.full(grid.shape, np.nan, dtype=np.float32)
    density_raster = np.zeros(grid.shape, dtype=np.float32)
    metric_rows = []
    tree_frames: list[pd.DataFrame] = []
    heights: dict[str, NDArray[np.float32]] = {}
    for cell in wrap(cells, len(cells), f"{epoch}: trees and metrics"):
        metric_rows.append(
            _enrich_cell(
                catalog,
                txn,
                cell,
                tiles,
                block(cell),
                ground_of.pop(cell.rel),
                dtm_filled,
                grid,
                chm_raster,
                density_raster,
                tree_frames,
                heights,
                options,
                cell.cell_id in no_ground,
            )
        )
    metric_rows.extend(_stand_rows(catalog, cells, heights, tree_frames, no_ground, options))
    for name, array, description in (
        ("dtm", dtm, "digital terrain model: ellipsoidal height of the ground (m)"),
        ("chm", chm_raster, "canopy height model: height above ground (m)"),
        ("density", density_raster, "points per square metre"),
    ):
        _write_raster(txn, f"rasters/{epoch}/{name}.tif", array, grid, catalog.crs, description)
    metrics = _metrics_table(metric_rows, epoch)
    trees = _tree_table(tree_frames, epoch)
    summary = {
        "cells": len(cells),
        "cells_without_ground": len(no_ground),
        "trees": len(trees),
        "trees_with_dbh": int(np.isfinite(trees["dbh_m"]).sum()) if len(trees) else 0,
        "raster_pixel_size_m": options.pixel_size,
    }
    return metrics, trees, summary


# --- one cell ----------------------------------------------------------------------------


def _core_xyz(cloud: PointCloud) -> NDArray[np.float64]:
    return cloud.xyz[~cloud.fields["withheld"].astype(bool)]


def _classify(xyz: NDArray[np.float64], options: EnrichOptions, source: Path) -> NDArray[np.bool_]:
    from standgrid.enrich.ground import classify_ground

    if len(xyz) < 3:
        return np.zeros(len(xyz), dtype=bool)
    try:
        return classify_ground(
            xyz, cloth_resolution=options.cloth_resolution, rigidness=options.rigidness
        )
    except StandgridError:
        raise
    except Exception as exc:  # CSF is a C++ extension: name the tile it failed on
        raise EnrichError(f"ground classification failed: {exc}", path=source) from exc


#: Ground points this far outside a DTM window still shape its triangulation.
DTM_MARGIN_M = 3.0


def _dtm(ground: NDArray[np.float64], window: RasterGrid) -> NDArray[np.float32]:
    """The window's DTM from the block's ground points near it (all of them if none are)."""
    from standgrid.enrich.rasters import dtm_from_ground

    xmin, ymin, xmax, ymax = window.bounds
    m = DTM_MARGIN_M
    x, y = ground[:, 0], ground[:, 1]
    near = (x >= xmin - m) & (x <= xmax + m) & (y >= ymin - m) & (y <= ymax + m)
    points = ground[near] if near.sum() >= 3 else ground
    return dtm_from_ground(_thin(points, window.pixel_size / 4), window)


def _thin(points: NDArray[np.float64], spacing: float) -> NDArray[np.float64]:
    """At most one point per ``spacing`` square (the first in file order, so unbiased in z):
    a terrain model at pixel size p needs no more than ~16 ground points per p^2."""
    if len(points) < 1000:
        return points
    bins = np.floor((points[:, :2] - points[:, :2].min(axis=0)) / spacing).astype(np.int64)
    keys = bins[:, 0] * (int(bins[:, 1].max()) + 1) + bins[:, 1]
    _, first = np.unique(keys, return_index=True)
    return points[np.sort(first)]


def _window(grid: RasterGrid, polygon: Any) -> tuple[RasterGrid, tuple[slice, slice]]:
    """The pixels of ``grid`` covering ``polygon``'s bounds, and their slice of the array."""
    from standgrid.enrich.rasters import RasterGrid

    xmin, ymin, xmax, ymax = polygon.bounds
    ps = grid.pixel_size
    tol = 1e-9
    i0 = max(0, math.floor((xmin - grid.x0) / ps + tol))
    i1 = min(grid.ncols, math.ceil((xmax - grid.x0) / ps - tol))
    j0 = max(0, math.floor((ymin - grid.y0) / ps + tol))
    j1 = min(grid.nrows, math.ceil((ymax - grid.y0) / ps - tol))
    i1, j1 = max(i1, i0 + 1), max(j1, j0 + 1)
    sub = RasterGrid(grid.x0 + i0 * ps, grid.y0 + j0 * ps, ps, i1 - i0, j1 - j0)
    rows = slice(grid.nrows - j1, grid.nrows - j0)  # row 0 is the northern edge
    return sub, (rows, slice(i0, i1))


def _paste(
    target: NDArray[np.float32],
    grid: RasterGrid,
    polygon: Any,
    compute: Callable[[RasterGrid], NDArray[np.floating]],
) -> None:
    """Compute a raster window over ``polygon`` and keep the pixels whose centre is inside."""
    import shapely

    sub, index = _window(grid, polygon)
    values = compute(sub)
    cx, cy = sub.centers()
    inside = shapely.contains_xy(polygon, cx, cy)
    window = target[index]
    window[inside] = np.asarray(values, dtype=np.float32)[inside]


def _nearest_fill(raster: NDArray[np.float32]) -> NDArray[np.float32]:
    """Empty pixels take the value of the nearest filled pixel."""
    from scipy import ndimage

    empty = np.isnan(raster)
    if not empty.any():
        return raster
    _, (ri, ci) = ndimage.distance_transform_edt(empty, return_indices=True)
    return raster[ri, ci]


def _enrich_cell(
    catalog: Catalog,
    txn: Transaction,
    cell: _Cell,
    tiles: _TileCache,
    block_xyz: NDArray[np.float64],
    block_ground: NDArray[np.bool_],
    dtm: NDArray[np.float32],
    grid: RasterGrid,
    chm_raster: NDArray[np.float32],
    density_raster: NDArray[np.float32],
    tree_frames: list[pd.DataFrame],
    heights: dict[str, NDArray[np.float32]],
    options: EnrichOptions,
    no_ground: bool,
) -> dict[str, Any]:
    import shapely
    from scipy.spatial import cKDTree

    from standgrid.enrich.rasters import chm, density, height_above_ground
    from standgrid.enrich.trees import segment_trees
    from standgrid.export.las import write_tile

    full = tiles.get(cell.rel)
    withheld = full.fields["withheld"].astype(bool)
    core = ~withheld
    n_core = int(core.sum())
    block_hag = height_above_ground(block_xyz, dtm, grid).astype(np.float64)

    # tile points -> their row in the block (core points are the block's first rows; buffer
    # points are exact copies of neighbours' core points, found in the halo)
    rows = np.empty(len(full), dtype=np.int64)
    rows[core] = np.arange(n_core)
    if withheld.any():
        dist, nearest = cKDTree(block_xyz).query(full.xyz[withheld])
        rows[withheld] = np.where(dist < 1e-6, nearest, -1)
    hag = np.where(rows >= 0, block_hag[rows], np.nan).astype(np.float32)
    if no_ground:
        hag[:] = np.nan

    segmentation = segment_trees(
        block_xyz,
        block_hag,
        pixel_size=options.tree_pixel_size,
        min_height=options.tree_min_height,
        keep_bounds=cell.polygon.bounds if catalog.scheme == "grid" else None,
    )
    point_ids = segmentation.point_tree_ids()
    if no_ground:  # heights there come from a distant terrain: no tree is claimed
        point_ids = np.zeros_like(point_ids)
    owned = segmentation.table
    if catalog.scheme == "grid":  # half-open cell bounds: a top on an edge has one owner
        top_inside = owned["owned"].to_numpy(dtype=bool)
    else:  # Voronoi polygons, edges included; a top on a shared edge is kept once later
        top_inside = shapely.intersects_xy(cell.polygon, owned["x"], owned["y"])
    owned = owned[top_inside].reset_index(drop=True)
    if no_ground:
        owned = owned.iloc[0:0]
    owned.insert(0, "cell_id", cell.cell_id)
    if cell.stand_id is not None:
        owned.insert(1, "stand_id", cell.stand_id)
    tree_frames.append(owned)

    core_xyz = full.xyz[core]
    core_hag = hag[core]
    if not no_ground:
        _paste(chm_raster, grid, cell.polygon, lambda g: chm(core_xyz, core_hag, g))
    _paste(density_raster, grid, cell.polygon, lambda g: density(core_xyz, g))

    classification = np.where(rows >= 0, block_ground[np.maximum(rows, 0)], False)
    fields = dict(full.fields)
    previous = fields.get("classification")
    other = np.full(len(full), OTHER, dtype=np.uint8)
    if previous is not None:  # keep classes the source had, except a stale ground class
        other = np.where(previous.astype(np.uint8) == GROUND, OTHER, previous).astype(np.uint8)
    fields["classification"] = np.where(classification, GROUND, other).astype(np.uint8)
    fields["height_above_ground"] = hag
    fields["tree_id"] = np.where(rows >= 0, point_ids[np.maximum(rows, 0)], 0).astype(np.int64)
    out = PointCloud(full.xyz, fields)
    rewritten = {k: v for k, v in out.fields.items() if k != "withheld"}
    write_tile(
        txn.stage(cell.rel),
        PointCloud(full.xyz[core], {k: v[core] for k, v in rewritten.items()}),
        crs=catalog.crs,
        buffer=PointCloud(full.xyz[withheld], {k: v[withheld] for k, v in rewritten.items()}),
        core_bounds=cell.polygon,
        lattice_origin=tiles.origin,
    )

    heights[cell.cell_id] = core_hag
    size = _cell_size(catalog)
    return _metrics_row(
        cell.cell_id, 0, size, float(cell.polygon.area), core_hag, owned, options, no_ground
    )


def _cell_size(catalog: Catalog) -> float:
    return float(catalog.grid_definition["cell_size"]) if catalog.scheme == "grid" else math.nan


NO_TERRAIN = "no ground points in or near the stand: no terrain model"


def _metrics_row(
    stand_id: str,
    level: int,
    size: float,
    area: float,
    heights: NDArray[np.floating],
    trees: pd.DataFrame,
    options: EnrichOptions,
    no_ground: bool,
) -> dict[str, Any]:
    """One stand_metrics row: the area-based and the tree-based set, nulls with reasons."""
    from standgrid.enrich.metrics import area_metrics, tree_metrics

    area_row = area_metrics(
        np.zeros(len(heights), dtype=np.int64),
        heights,
        cell_area_m2=area,
        cells=[0],
        height_break=options.height_break,
    ).iloc[0]
    tree_row = tree_metrics(
        np.zeros(len(trees), dtype=np.int64),
        trees["height_m"].to_numpy(dtype=np.float64),
        trees["dbh_m"].to_numpy(dtype=np.float64),
        cell_area_m2=max(area, 1e-9),
        cells=[0],
    ).iloc[0]
    reasons = [area_row.get("null_reason")]
    if no_ground:  # the tree set was not looked for: its own reason does not apply
        reasons.insert(0, NO_TERRAIN)
    else:
        reasons.append(tree_row.get("null_reason"))
    reasons = [r for r in reasons if _text(r)]
    row: dict[str, Any] = {"cell_id": stand_id, "level": level, "cell_size": size, "area_m2": area}
    row.update({k: v for k, v in area_row.items() if k != "null_reason"})
    row.update({k: v for k, v in tree_row.items() if k != "null_reason"})
    if no_ground:  # no tree could be looked for: unknown, not zero
        for name in tree_row.index:
            if name != "null_reason":
                row[name] = None if name == "dominant_by" else math.nan
    row["null_reason"] = "; ".join(dict.fromkeys(str(r) for r in reasons)) or None
    return row


def _stand_rows(
    catalog: Catalog,
    cells: list[_Cell],
    heights: dict[str, NDArray[np.float32]],
    tree_frames: list[pd.DataFrame],
    no_ground: set[str],
    options: EnrichOptions,
) -> list[dict[str, Any]]:
    """Metrics of each 1 ha stand (the grid's next level) over its measured cells.

    The stand's area is that of its cells that have points and ground (a stand at the edge
    of the survey is measured over what was surveyed); its trees are the trees of those cells.
    """
    import pandas as pd

    grid = _stand_grid(catalog)
    if grid is None:
        return []
    frames = [t for t in tree_frames if len(t)]
    trees = pd.concat(frames, ignore_index=True) if frames else None
    rows = []
    for stand_id in sorted({c.stand_id for c in cells if c.stand_id is not None}):
        members = [c for c in cells if c.stand_id == stand_id]
        measured = [c for c in members if c.cell_id not in no_ground]
        # every member's points count (heights are NaN where a cell has no terrain)
        h = np.concatenate([heights[c.cell_id] for c in members])
        stand_trees = (
            trees[trees["stand_id"] == stand_id]
            if trees is not None and "stand_id" in trees.columns
            else pd.DataFrame({"height_m": [], "dbh_m": []})
        )
        area = float(sum(c.polygon.area for c in measured))
        row = _metrics_row(stand_id, 1, grid.levels[1], area, h, stand_trees, options, not measured)
        measured_points = row["n_points"] - row["n_no_height"]
        row["density_pts_m2"] = measured_points / area if area > 0 else math.nan
        rows.append(row)
    return rows


def _text(value: Any) -> bool:
    """True for a real reason text (not None, NaN or pandas NA)."""
    import pandas as pd

    return isinstance(value, str) and value != "" and value is not pd.NA


# --- outputs -----------------------------------------------------------------------------


def _write_raster(
    txn: Transaction, rel: str, array: NDArray[np.float32], grid: RasterGrid, crs: str, text: str
) -> None:
    from standgrid.enrich.rasters import write_cog

    data = np.where(np.isfinite(array), array, NODATA).astype(np.float32)
    write_cog(txn.stage(rel), data, grid, crs=crs, nodata=NODATA, description=text)


def _metrics_table(rows: list[dict[str, Any]], epoch: str) -> pd.DataFrame:
    import pandas as pd

    table = pd.DataFrame(rows)
    table.insert(1, "epoch", epoch)
    table["null_reason"] = table["null_reason"].astype("string")
    return table


def _tree_table(frames: list[pd.DataFrame], epoch: str) -> pd.DataFrame:
    import pandas as pd

    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if "tree_id" in table.columns:  # a top on a shared Voronoi edge: the first cell keeps it
        table = table.drop_duplicates("tree_id").reset_index(drop=True)
    table.insert(2 if "stand_id" in table.columns else 1, "epoch", epoch)
    return table


def _write_tables(
    catalog: Catalog,
    txn: Transaction,
    metric_tables: dict[str, pd.DataFrame],
    tree_tables: dict[str, pd.DataFrame],
) -> None:
    """``tables/stand_metrics`` (all epochs; replaced rows of re-enriched epochs) and tree lists."""
    import pandas as pd

    existing = catalog.path("tables/stand_metrics.parquet")
    frames = []
    if existing.exists():
        old = pd.read_parquet(existing)
        frames.append(old[~old["epoch"].astype(str).isin(metric_tables)])
    frames.extend(metric_tables.values())
    metrics = pd.concat(frames, ignore_index=True).sort_values(["epoch", "cell_id"])
    _write_table(txn, "tables/stand_metrics", metrics)
    for epoch, trees in tree_tables.items():
        _write_table(
            txn, f"tables/tree_list_{epoch}", trees.drop(columns=["crown"], errors="ignore")
        )


def _write_table(txn: Transaction, stem: str, frame: pd.DataFrame) -> None:
    frame = frame.reset_index(drop=True)
    frame.to_parquet(txn.stage(f"{stem}.parquet"), index=False)
    frame.to_csv(txn.stage(f"{stem}.csv"), index=False)


def _write_layers(
    catalog: Catalog,
    txn: Transaction,
    metric_tables: dict[str, pd.DataFrame],
    tree_tables: dict[str, pd.DataFrame],
) -> None:
    """GeoPackage layers ``stand_metrics`` and ``trees`` with default QGIS styles."""
    import shutil

    import geopandas as gpd
    import pandas as pd

    from standgrid.export.gpkg import IndexWriter, index_layer_names, read_index_layer
    from standgrid.export.styles import stand_metric_style

    index = catalog.path("index.gpkg")
    staged = txn.stage("index.gpkg")
    if not staged.exists():
        shutil.copyfile(index, staged)
    present = index_layer_names(staged)
    cells = read_index_layer(staged, "cells")[["cell_id", "epoch", "geometry"]]
    cells["epoch"] = cells["epoch"].astype(str)
    old_metrics = read_index_layer(staged, "stand_metrics") if "stand_metrics" in present else None
    old_trees = read_index_layer(staged, "trees") if "trees" in present else None

    new_metrics = pd.concat(metric_tables.values(), ignore_index=True)
    stands = gpd.GeoDataFrame(
        new_metrics,
        geometry=stand_polygons(catalog, new_metrics["cell_id"], cells),
        crs=catalog.crs,
    )
    if old_metrics is not None:
        keep = old_metrics[~old_metrics["epoch"].astype(str).isin(metric_tables)]
        stands = gpd.GeoDataFrame(pd.concat([keep, stands], ignore_index=True), geometry="geometry")
    tree_rows = [t for t in tree_tables.values() if len(t)]
    trees = None
    if tree_rows:
        table = pd.concat(tree_rows, ignore_index=True)
        trees = gpd.GeoDataFrame(
            table.drop(columns=["crown"]), geometry=list(table["crown"]), crs=catalog.crs
        )
        trees["tree_id"] = trees["tree_id"].astype(np.int64)
    if old_trees is not None:
        keep = old_trees[~old_trees["epoch"].astype(str).isin(tree_tables)]
        trees = gpd.GeoDataFrame(
            pd.concat([keep, trees] if trees is not None else [keep], ignore_index=True),
            geometry="geometry",
        )
    with IndexWriter(staged, catalog.crs) as writer:
        height = stands["zq95"] if "zq95" in stands.columns else stands.get("zmax")
        lo, hi = _range(height)
        writer.write_layer("stand_metrics", stands, style=stand_metric_style("zq95", lo, hi))
        if trees is not None and len(trees):
            lo, hi = _range(trees["height_m"])
            writer.write_layer("trees", trees, style=stand_metric_style("height_m", lo, hi))


def stand_polygons(catalog: Catalog, ids: Iterable[str], cells: Any) -> list[Any]:
    """Polygons of stand ids: a tile cell's own polygon, or a coarser stand's grid square."""
    from standgrid.partition import CellId, StandGrid

    known = dict(zip(cells["cell_id"].astype(str), cells.geometry, strict=True))
    grid = StandGrid.from_dict(catalog.grid_definition) if catalog.scheme == "grid" else None
    polygons = []
    for stand in ids:
        polygon = known.get(str(stand))
        if polygon is None and grid is not None:
            polygon = grid.polygon(CellId.parse(str(stand)))
        polygons.append(polygon)
    return polygons


def _range(values: Any) -> tuple[float, float]:
    import pandas as pd

    if values is None:
        return 0.0, 1.0
    finite = pd.to_numeric(values, errors="coerce").dropna()
    if len(finite) == 0:
        return 0.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    return (lo, hi) if hi > lo else (lo, lo + 1.0)
