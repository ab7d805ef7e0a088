"""What enrichment writes: COG rasters with QGIS styles, the stand-metric and tree tables,
and the GeoPackage layers ``stand_metrics`` and ``trees`` (all staged in one transaction)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.catalog import paths
from standgrid.geotiff import NODATA

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog, Transaction
    from standgrid.enrichment.coverage import Coverage
    from standgrid.rastergrid import RasterGrid


def write_raster(
    txn: Transaction, rel: str, array: NDArray[np.float32], grid: RasterGrid, text: str
) -> None:
    """One raster of an epoch (in its grid's CRS), with its QGIS style."""
    from standgrid.export.styles import raster_style_path, write_raster_style
    from standgrid.geotiff import write_cog

    data = np.where(np.isfinite(array), array, NODATA).astype(np.float32)
    tif = txn.stage(rel)
    write_cog(tif, data, grid, nodata=NODATA, description=text)
    write_raster_style(tif, qml=txn.stage(raster_style_path(rel)))  # QGIS default style


def write_coverage(txn: Transaction, rel: str, coverage: Coverage) -> None:
    """An epoch's coverage mask (in its grid's CRS), with its QGIS style."""
    from standgrid.enrichment.coverage import MASK_NODATA
    from standgrid.export.styles import raster_style_path, write_raster_style
    from standgrid.geotiff import write_cog

    tif = txn.stage(rel)
    write_cog(
        tif,
        coverage.as_mask_raster(),
        coverage.grid,
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
    if "tree_id" in table.columns:  # by cell, then tree: the same rows whatever the chunks
        table = table.sort_values(["cell_id", "tree_id"], kind="stable")
        # a top on a shared Voronoi edge: the first cell keeps it
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
    """GeoPackage layers ``stand_metrics`` and ``trees`` (the enriched epochs' rows replaced)
    with default QGIS styles over the whole layer's range."""
    import geopandas as gpd
    import pandas as pd

    from standgrid.catalog.index import CatalogIndex
    from standgrid.export.styles import stand_metric_style

    index = CatalogIndex(catalog, txn)
    epochs = set(metric_tables) | set(tree_tables)
    cells = index.read("cells")[["cell_id", "epoch", "geometry"]]
    new_metrics = pd.concat(metric_tables.values(), ignore_index=True)
    stands = gpd.GeoDataFrame(
        new_metrics,
        geometry=stand_polygons(catalog, new_metrics["cell_id"], cells),
        crs=catalog.crs,
    )
    column = "zq95" if "zq95" in stands.columns else "zmax"
    lo, hi = _range(_kept_and_new(index, "stand_metrics", epochs, stands, column))
    index.replace("stand_metrics", stands, epochs=epochs, style=stand_metric_style("zq95", lo, hi))
    tree_rows = [t for t in tree_tables.values() if len(t)]
    if tree_rows or "trees" in index.layers():
        table = pd.concat(tree_rows, ignore_index=True) if tree_rows else None
        trees = gpd.GeoDataFrame(
            table.drop(columns=["crown"]) if table is not None else pd.DataFrame(),
            geometry=list(table["crown"]) if table is not None else [],
            crs=catalog.crs,
        )
        if len(trees):
            trees["tree_id"] = trees["tree_id"].astype(np.int64)
        lo, hi = _range(_kept_and_new(index, "trees", epochs, trees, "height_m"))
        index.replace("trees", trees, epochs=epochs, style=stand_metric_style("height_m", lo, hi))
    index.save()


def _kept_and_new(index: Any, layer: str, epochs: set[str], new: Any, column: str) -> Any:
    """The values of ``column`` the layer will hold: rows of other epochs, and ``new``."""
    import pandas as pd

    old = index.read(layer)
    parts = [new[column]] if column in new.columns else []
    if len(old) and column in old.columns:
        parts.append(old.loc[~old["epoch"].astype(str).isin(epochs), column])
    return pd.concat(parts, ignore_index=True) if parts else None


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
