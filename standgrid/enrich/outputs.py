"""What enrichment writes: COG rasters with QGIS styles, the stand-metric and tree tables,
and the GeoPackage layers ``stand_metrics`` and ``trees`` (all staged in one transaction)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.catalog import paths
from standgrid.enrich.rasters import NODATA

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog, Transaction
    from standgrid.enrich.coverage import Coverage
    from standgrid.enrich.rasters import RasterGrid


def write_raster(
    txn: Transaction, rel: str, array: NDArray[np.float32], grid: RasterGrid, crs: str, text: str
) -> None:
    from standgrid.enrich.rasters import write_cog
    from standgrid.export.styles import raster_style_path, write_raster_style

    data = np.where(np.isfinite(array), array, NODATA).astype(np.float32)
    tif = txn.stage(rel)
    write_cog(tif, data, grid, crs=crs, nodata=NODATA, description=text)
    write_raster_style(tif, qml=txn.stage(raster_style_path(rel)))  # QGIS default style


def write_coverage(txn: Transaction, rel: str, coverage: Coverage, crs: str) -> None:
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


def metrics_table(rows: list[dict[str, Any]], epoch: str) -> pd.DataFrame:
    import pandas as pd

    table = pd.DataFrame(rows)
    table.insert(1, "epoch", epoch)
    table["null_reason"] = table["null_reason"].astype("string")
    return table


def tree_table(frames: list[pd.DataFrame], epoch: str) -> pd.DataFrame:
    import pandas as pd

    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if "tree_id" in table.columns:  # a top on a shared Voronoi edge: the first cell keeps it
        table = table.drop_duplicates("tree_id").reset_index(drop=True)
    table.insert(2 if "stand_id" in table.columns else 1, "epoch", epoch)
    return table


def write_tables(
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


def write_layers(
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
