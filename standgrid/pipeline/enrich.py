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

from standgrid.catalog import paths
from standgrid.enrich.rasters import NODATA, chm, density
from standgrid.enrich.stands import CoverageRule, StandSample, stem_xy
from standgrid.errors import EnrichError, EpochNotFoundError, StandgridError
from standgrid.pointcloud import PointCloud

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog, Transaction
    from standgrid.enrich.allometry import HeightDiameterModel
    from standgrid.enrich.coverage import Coverage
    from standgrid.enrich.rasters import RasterGrid

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
    min_observed_fraction: float = 0.25
    min_density_pts_m2: float = 2.0
    coverage_closing_m: float = 2.0
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
    from standgrid.catalog import Catalog

    with Catalog.writing(catalog_path, lock_timeout=lock_timeout) as catalog:
        return _enrich(catalog, options, wrap, status)


def _enrich(
    catalog: Catalog, options: EnrichOptions, wrap: Wrap, status: Callable[[str], None]
) -> EnrichReport:
    from standgrid.catalog.invalidate import clear_invalidation, invalidate_comparisons
    from standgrid.enrich.allometry import impute_dbh

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
    rule = CoverageRule(options.min_observed_fraction, options.min_density_pts_m2)
    report = EnrichReport(catalog.root)
    metric_tables: dict[str, pd.DataFrame] = {}
    tree_tables: dict[str, pd.DataFrame] = {}
    with catalog.transaction() as txn:
        results = {}
        for epoch in epochs:
            note = clear_invalidation(txn.state["epochs"][epoch])  # says if it was stale
            status(f"enriching epoch {epoch}: {note}")
            results[epoch] = _enrich_epoch(catalog, txn, epoch, options, wrap)
        lost = invalidate_comparisons(catalog, txn, set(epochs), "re-enriched")
        if lost:
            status(f"comparisons {', '.join(lost)} removed (their inputs change): compare again")
        models = _height_diameter_models(catalog, {e: r.trees for e, r in results.items()})
        for epoch, result in results.items():
            trees = impute_dbh(result.trees, models[epoch])
            metric_tables[epoch] = _metrics_table(
                _stand_rows(catalog, result, trees, rule, options), epoch
            )
            tree_tables[epoch] = trees
            summary = result.summary | _tree_summary(trees, models[epoch])
            summary["coverage_rule"] = {
                "min_observed_fraction": rule.min_observed_fraction,
                "min_density_pts_m2": rule.min_density_pts_m2,
            }
            report.epochs[epoch] = summary
            txn.state["epochs"][epoch]["enriched"] = True
            txn.state["epochs"][epoch]["enrichment"] = summary
        _write_tables(catalog, txn, metric_tables, tree_tables)
        _write_layers(catalog, txn, metric_tables, tree_tables)
    return report


# --- one epoch ---------------------------------------------------------------------------


@dataclass
class _EpochResult:
    """An epoch after segmentation: per-cell samples (trees not yet attached), trees."""

    cells: list[_Cell]
    samples: dict[str, StandSample]
    trees: pd.DataFrame
    summary: dict[str, Any]


def _epoch_cells(catalog: Catalog, epoch: str) -> list[_Cell]:
    from standgrid.export.gpkg import read_index_layer

    grid = _stand_grid(catalog)
    cells = read_index_layer(catalog.path(paths.INDEX), "cells")
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
) -> _EpochResult:
    import shapely

    from standgrid.enrich.coverage import cells_mask, coverage_from_hits, ground_hits
    from standgrid.enrich.rasters import RasterGrid

    cells = _epoch_cells(catalog, epoch)
    if not cells:
        raise EnrichError(f"epoch {epoch} has no tiles", path=catalog.root)
    origin, cell_size = _grid_alignment(catalog)
    polygons = [c.polygon for c in cells]
    grid = RasterGrid.covering(
        tuple(shapely.bounds(shapely.union_all(polygons))),
        origin=origin,
        cell_size=cell_size,
        pixel_size=options.pixel_size,
        closed=True,
    )
    tree = shapely.STRtree(polygons)
    tiles = _TileCache(catalog, origin)
    # the block must reach every buffer copy a tile holds, so those get heights and ids too
    halo = max(options.halo, float(txn.state.get("tiling", {}).get("buffer", 0.0)))

    def block(cell: _Cell) -> tuple[NDArray[np.float64], int]:
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
        return np.concatenate(parts), len(parts[0])

    # pass 1: ground, the terrain model and where the ground was seen
    dtm = np.full(grid.shape, np.nan, dtype=np.float32)
    hits = np.zeros(grid.shape, dtype=np.int64)
    ground_of: dict[str, NDArray[np.bool_]] = {}
    no_ground: set[str] = set()
    for cell in wrap(cells, len(cells), f"{epoch}: ground"):
        xyz, n_core = block(cell)
        mask = _classify(xyz, options, catalog.path(cell.rel))
        ground_of[cell.rel] = mask
        if not mask.any():
            no_ground.add(cell.cell_id)
            continue
        hits += ground_hits(grid, xyz[:n_core][mask[:n_core], :2])
        ground = xyz[mask]
        _paste(dtm, grid, cell.polygon, functools.partial(_dtm, ground))
    if np.isnan(dtm).all():
        raise EnrichError(
            f"epoch {epoch}: no ground points anywhere, so no terrain model", path=catalog.root
        )
    coverage = coverage_from_hits(
        hits, grid, cells_mask(grid, polygons), closing_radius=options.coverage_closing_m
    )
    dtm_filled = _nearest_fill(dtm)

    # pass 2: heights, rasters, trees, tiles
    chm_raster = np.full(grid.shape, np.nan, dtype=np.float32)
    density_raster = np.zeros(grid.shape, dtype=np.float32)
    samples: dict[str, StandSample] = {}
    tree_frames: list[pd.DataFrame] = []
    size = _cell_size(catalog)
    for cell in wrap(cells, len(cells), f"{epoch}: trees and tiles"):
        xyz, _ = block(cell)
        core_xyz, core_hag, owned = _enrich_cell(
            catalog, txn, cell, tiles, xyz, ground_of.pop(cell.rel), dtm_filled, grid,
            options, cell.cell_id in no_ground,
        )  # fmt: skip
        tree_frames.append(owned)
        if cell.cell_id not in no_ground:
            _paste(chm_raster, grid, cell.polygon, functools.partial(chm, core_xyz, core_hag))
        _paste(density_raster, grid, cell.polygon, functools.partial(density, core_xyz))
        on_observed = coverage.observed_at(core_xyz[:, 0], core_xyz[:, 1])
        samples[cell.cell_id] = StandSample(
            stand_id=cell.cell_id,
            level=0,
            cell_size=size,
            area_m2=float(cell.polygon.area),
            observed_m2=coverage.observed_m2(cell.polygon),
            n_points=len(core_xyz),
            heights=core_hag[on_observed],
            trees=owned.iloc[0:0],
            no_ground=cell.cell_id in no_ground,
        )
    trees = _tree_table(tree_frames, epoch)
    trees["observed"] = coverage.observed_at(*stem_xy(trees))

    unseen = ~coverage.near_ground
    for name, array, description in (
        ("dtm", dtm, "digital terrain model: ellipsoidal height of the ground (m)"),
        ("chm", chm_raster, "canopy height model: height above ground (m)"),
    ):
        array[unseen] = np.nan  # terrain (and heights over it) extrapolated there
        _write_raster(txn, paths.raster(epoch, name), array, grid, catalog.crs, description)
    _write_raster(
        txn, paths.raster(epoch, "density"), density_raster, grid, catalog.crs,
        "points per square metre",
    )  # fmt: skip
    _write_coverage(txn, paths.raster(epoch, "observed"), coverage, catalog.crs)
    observed_m2 = float(coverage.observed.sum()) * grid.pixel_size**2
    summary = {
        "cells": len(cells),
        "cells_without_ground": len(no_ground),
        "raster_pixel_size_m": options.pixel_size,
        "observed_m2": observed_m2,
        "observed_fraction": observed_m2 / float(sum(p.area for p in polygons)),
    }
    return _EpochResult(cells, samples, trees, summary)


def _height_diameter_models(
    catalog: Catalog, trees: dict[str, pd.DataFrame]
) -> dict[str, HeightDiameterModel | None]:
    """Per epoch: its own height-diameter model, or one pooled over the catalog's epochs."""
    import pandas as pd

    from standgrid.enrich.allometry import fit_height_diameter

    measured = {e: t[np.isfinite(t["dbh_m"].to_numpy(np.float64))] for e, t in trees.items()}
    for epoch in catalog.epochs:  # measured trees of epochs enriched before
        path = catalog.path(paths.tree_list(epoch, "parquet"))
        if epoch not in measured and path.exists():
            old = pd.read_parquet(path)
            if "dbh_source" in old.columns:
                measured[epoch] = old[old["dbh_source"] == "measured"]
    frames = [m[["height_m", "dbh_m"]] for m in measured.values() if len(m)]
    pooled_trees = pd.concat(frames, ignore_index=True) if frames else None
    pooled = None
    if pooled_trees is not None:
        pooled = fit_height_diameter(
            pooled_trees["height_m"], pooled_trees["dbh_m"], source="catalog (all epochs)"
        )
    models: dict[str, HeightDiameterModel | None] = {}
    for epoch in trees:
        own = measured[epoch]
        model = fit_height_diameter(own["height_m"], own["dbh_m"], source=f"epoch {epoch}")
        models[epoch] = model or pooled
    return models


def _tree_summary(trees: pd.DataFrame, model: HeightDiameterModel | None) -> dict[str, Any]:
    source = trees["dbh_source"] if len(trees) else None
    return {
        "trees": len(trees),
        "trees_on_observed_ground": int(trees["observed"].sum()) if len(trees) else 0,
        "trees_dbh_measured": int((source == "measured").sum()) if source is not None else 0,
        "trees_dbh_imputed": int((source == "imputed").sum()) if source is not None else 0,
        "height_diameter_model": model.to_dict() if model is not None else None,
    }


def _stand_rows(
    catalog: Catalog,
    result: _EpochResult,
    trees: pd.DataFrame,
    rule: CoverageRule,
    options: EnrichOptions,
) -> list[dict[str, Any]]:
    """Every cell's row, then every 1 ha stand's (the grid's next level) over its measured
    cells: a stand aggregates the observed ground, points and trees of its cells that pass
    the coverage rule; its area is the whole stand's."""
    from standgrid.enrich.stands import aggregate, passes, stand_row

    on_ground = trees[trees["observed"]] if len(trees) else trees
    by_cell = dict(tuple(on_ground.groupby("cell_id"))) if len(on_ground) else {}
    rows, measured = [], []
    for cell in result.cells:
        sample = result.samples[cell.cell_id]
        sample.trees = by_cell.get(cell.cell_id, trees.iloc[0:0])
        row = stand_row(sample, rule, height_break=options.height_break)
        rows.append(row)
        if passes(row):
            measured.append(cell)
    grid = _stand_grid(catalog)
    if grid is None:
        return rows
    size = float(grid.levels[1])
    for stand_id in sorted({c.stand_id for c in result.cells if c.stand_id is not None}):
        members = [result.samples[c.cell_id] for c in measured if c.stand_id == stand_id]
        sample = aggregate(stand_id, size, size * size, members)
        rows.append(stand_row(sample, rule, height_break=options.height_break))
    return rows


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


def _paste(
    target: NDArray[np.float32],
    grid: RasterGrid,
    polygon: Any,
    compute: Callable[[RasterGrid], NDArray[np.floating]],
) -> None:
    """Compute a raster window over ``polygon`` and keep the pixels whose centre is inside."""
    from standgrid.enrich.coverage import polygon_pixels, window

    sub, _ = window(grid, polygon)
    index, inside = polygon_pixels(grid, polygon)
    values = compute(sub)
    target[index][inside] = np.asarray(values, dtype=np.float32)[inside]


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
    options: EnrichOptions,
    no_ground: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float32], pd.DataFrame]:
    """Heights, trees and the rewritten tile of one cell: (core xyz, core heights, the
    trees whose top is in the cell)."""
    import shapely
    from scipy.spatial import cKDTree

    from standgrid.enrich.rasters import height_above_ground
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
    return full.xyz[core], hag[core], owned


def _cell_size(catalog: Catalog) -> float:
    return float(catalog.grid_definition["cell_size"]) if catalog.scheme == "grid" else math.nan


# --- outputs -----------------------------------------------------------------------------


def _write_raster(
    txn: Transaction, rel: str, array: NDArray[np.float32], grid: RasterGrid, crs: str, text: str
) -> None:
    from standgrid.enrich.rasters import write_cog
    from standgrid.export.styles import raster_style_path, write_raster_style

    data = np.where(np.isfinite(array), array, NODATA).astype(np.float32)
    tif = txn.stage(rel)
    write_cog(tif, data, grid, crs=crs, nodata=NODATA, description=text)
    write_raster_style(tif, qml=txn.stage(raster_style_path(rel)))  # QGIS default style


def _write_coverage(txn: Transaction, rel: str, coverage: Coverage, crs: str) -> None:
    from standgrid.enrich.coverage import MASK_NODATA
    from standgrid.enrich.rasters import write_cog
    from standgrid.export.styles import raster_style_path, write_raster_style

    tif = txn.stage(rel)
    write_cog(
        tif,
        coverage.as_mask_raster(),
        coverage.grid,
        crs=crs,
        nodata=MASK_NODATA,
        description="observed ground: 1 observed, 0 not observed (docs/METRICS.md)",
    )
    write_raster_style(tif, "observed", qml=txn.stage(raster_style_path(rel)))


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

    existing = catalog.path(paths.stand_metrics("parquet"))
    frames = []
    if existing.exists():
        old = pd.read_parquet(existing)
        frames.append(old[~old["epoch"].astype(str).isin(metric_tables)])
    frames.extend(metric_tables.values())
    metrics = pd.concat(frames, ignore_index=True).sort_values(["epoch", "cell_id"])
    _write_table(txn, paths.METRICS_TABLE, metrics)
    for epoch, trees in tree_tables.items():
        _write_table(
            txn, paths.tree_list_stem(epoch), trees.drop(columns=["crown"], errors="ignore")
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

    index = catalog.path(paths.INDEX)
    staged = txn.stage(paths.INDEX)
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
