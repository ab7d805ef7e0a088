"""Write the change between two epochs: flat tables and styled GeoPackage layers.

Outputs of :func:`write_change_outputs`:

- ``<out_dir>/stand_changes.{csv,parquet}``: one row per stand, keyed by
  ``cell_id, epoch_from, epoch_to`` (first columns), every change column of
  :func:`standgrid.comparison.stands.compare_stands`; no geometry.
- ``<out_dir>/tree_changes.{csv,parquet}`` (with tree changes): one row per tree of
  :func:`standgrid.comparison.trees.match_trees`, plus ``epoch_from, epoch_to``.
- GeoPackage layers ``stand_changes`` (cell polygons + change columns; default QGIS style:
  diverging RdBu ramp centred on 0 over ``style_field``) and ``tree_changes`` (points at the
  tree positions; default style: one colour per ``status``): :func:`change_layers`, written
  by the catalog's compare through :class:`standgrid.catalog.index.CatalogIndex`, or into
  a GeoPackage file atomically through :class:`standgrid.export.gpkg.IndexWriter` (other
  layers are kept).

Null values stay null in every output (empty CSV field, Parquet/GeoPackage NULL).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from standgrid._atomic import atomic_output
from standgrid.comparison.trees import ChangeInputError, TreeMatches

STAND_LAYER = "stand_changes"
TREE_LAYER = "tree_changes"
KEY_COLUMNS = ("cell_id", "epoch_from", "epoch_to")
DEFAULT_STYLE_FIELDS = ("tree_height_growth_m_per_year", "zq95_per_year")
#: Colours of the tree statuses (grown green, new blue, removed red, missed grey).
STATUS_COLOURS = {
    "grown": "#1a9641",
    "new": "#2c7bb6",
    "removed": "#d7191c",
    "missed": "#969696",
}


@dataclass(frozen=True)
class ChangeOutputs:
    """The files :func:`write_change_outputs` wrote."""

    stand_csv: Path
    stand_parquet: Path
    tree_csv: Path | None
    tree_parquet: Path | None
    gpkg: Path | None  # None: the layers are the caller's to write (change_layers)
    style_field: str | None
    style_range: tuple[float, float] | None


@dataclass(frozen=True)
class ChangeLayer:
    """A GeoPackage layer of the change (in the index CRS) and its default QGIS style."""

    name: str
    frame: Any
    style: str | None


def _with_keys(frame: pd.DataFrame, epoch_from: str, epoch_to: str) -> pd.DataFrame:
    frame = frame.copy()
    for column, value in (("epoch_from", epoch_from), ("epoch_to", epoch_to)):
        if column not in frame.columns:
            frame[column] = value
    keys = [c for c in KEY_COLUMNS if c in frame.columns]
    return frame[[*keys, *(c for c in frame.columns if c not in keys)]]


def _write_table(
    frame: pd.DataFrame, folder: Path, stem: str, overwrite: bool
) -> tuple[Path, Path]:
    flat = pd.DataFrame(frame.drop(columns="geometry", errors="ignore"))
    csv_path, parquet_path = folder / f"{stem}.csv", folder / f"{stem}.parquet"
    with atomic_output(csv_path, overwrite=overwrite) as tmp:
        flat.to_csv(tmp, index=False, lineterminator="\n")
    with atomic_output(parquet_path, overwrite=overwrite) as tmp:
        flat.to_parquet(tmp, index=False, engine="pyarrow")
    return csv_path, parquet_path


def _pick_style_field(frame: pd.DataFrame, style_field: str | None) -> str | None:
    if style_field is not None:
        if style_field not in frame.columns:
            raise ChangeInputError(f"style field {style_field!r} is not a stand change column")
        return style_field
    for candidate in DEFAULT_STYLE_FIELDS:
        if candidate in frame.columns and frame[candidate].notna().any():
            return candidate
    per_year = [c for c in frame.columns if c.endswith("_per_year") and frame[c].notna().any()]
    return per_year[0] if per_year else None


def _symmetric_range(values: pd.Series) -> tuple[float, float]:
    """±(98th percentile of |change|): robust to outliers, centred on zero."""
    finite = pd.to_numeric(values, errors="coerce").to_numpy(dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    half = float(np.percentile(np.abs(finite), 98)) if len(finite) else 0.0
    half = half if half > 0 else 1.0
    return -half, half


def _stand_geometries(stand_changes: Any, cells: Any | None, crs: Any | None) -> Any:
    import geopandas as gpd

    if isinstance(stand_changes, gpd.GeoDataFrame):
        return stand_changes
    if cells is None:
        raise ChangeInputError("stand changes without geometry need cells (cell_id + polygon)")
    polygons = pd.DataFrame({"cell_id": cells["cell_id"].to_numpy(), "geometry": cells.geometry})
    merged = (
        pd.DataFrame(stand_changes)
        .drop(columns="geometry", errors="ignore")
        .merge(polygons, on="cell_id", how="left", validate="many_to_one")
    )
    missing = merged.loc[merged["geometry"].isna(), "cell_id"]
    if len(missing):
        shown = ", ".join(map(str, missing.iloc[:5]))
        raise ChangeInputError(f"{len(missing)} stand(s) have no cell polygon: {shown}")
    return gpd.GeoDataFrame(merged, geometry="geometry", crs=cells.crs if crs is None else crs)


def _tree_points(trees: pd.DataFrame, crs: Any) -> Any:
    import geopandas as gpd

    points = gpd.points_from_xy(trees["x"], trees["y"])
    return gpd.GeoDataFrame(trees, geometry=points, crs=crs)


def write_change_outputs(
    out_dir: str | os.PathLike[str],
    gpkg_path: str | os.PathLike[str],
    stand_changes: pd.DataFrame,
    tree_changes: TreeMatches | pd.DataFrame | None = None,
    *,
    epoch_from: str,
    epoch_to: str,
    cells: Any | None = None,
    crs: str | None = None,
    style_field: str | None = None,
    overwrite: bool = True,
) -> ChangeOutputs:
    """Write the flat change tables to ``out_dir`` and the styled layers to ``gpkg_path``.

    ``stand_changes``: a GeoDataFrame, or a DataFrame plus ``cells`` (GeoDataFrame with
    ``cell_id`` and polygons). ``crs`` (``EPSG:XXXX`` or WKT2) defaults to the geometry's.
    ``style_field`` is the change column coloured in QGIS (default: mean tree height growth
    per year, else canopy height p95 per year, else the first ``*_per_year`` column).
    Existing layers of the same names are replaced; other layers are kept.
    """
    from standgrid.export.gpkg import IndexWriter

    outputs, layers = change_layers(
        out_dir,
        stand_changes,
        tree_changes,
        epoch_from=epoch_from,
        epoch_to=epoch_to,
        cells=cells,
        crs=crs,
        style_field=style_field,
        overwrite=overwrite,
    )
    layer_crs = crs or layers[0].frame.crs.to_wkt()
    with IndexWriter(gpkg_path, layer_crs) as index:
        for layer in layers:
            index.write_layer(layer.name, layer.frame, style=layer.style)
    return dataclasses.replace(outputs, gpkg=Path(gpkg_path))


def change_layers(
    out_dir: str | os.PathLike[str],
    stand_changes: pd.DataFrame,
    tree_changes: TreeMatches | pd.DataFrame | None = None,
    *,
    epoch_from: str,
    epoch_to: str,
    cells: Any | None = None,
    crs: str | None = None,
    style_field: str | None = None,
    overwrite: bool = True,
) -> tuple[ChangeOutputs, list[ChangeLayer]]:
    """Write the flat change tables to ``out_dir``; return them and the styled layers, for the
    caller to write (arguments: :func:`write_change_outputs`)."""
    from standgrid.export.styles import categorized_style, diverging_style

    folder = Path(out_dir)
    stands = _with_keys(_stand_geometries(stand_changes, cells, crs), epoch_from, epoch_to)
    layer_crs = crs or (stands.crs.to_wkt() if stands.crs is not None else None)
    if layer_crs is None:
        raise ChangeInputError("no CRS: pass crs= or geometry with a CRS")
    if stands.crs is None:
        stands = stands.set_crs(layer_crs)

    trees: pd.DataFrame | None = None
    if tree_changes is not None:
        table = tree_changes.table if isinstance(tree_changes, TreeMatches) else tree_changes
        trees = _with_keys(table, epoch_from, epoch_to)

    field = _pick_style_field(stands, style_field)
    value_range = _symmetric_range(stands[field]) if field else None
    stand_csv, stand_parquet = _write_table(stands, folder, STAND_LAYER, overwrite)
    tree_csv = tree_parquet = None
    if trees is not None:
        tree_csv, tree_parquet = _write_table(trees, folder, TREE_LAYER, overwrite)

    stand_style = (
        diverging_style(field, *value_range, geometry="polygon") if field and value_range else None
    )
    layers = [ChangeLayer(STAND_LAYER, stands, stand_style)]
    if trees is not None:
        tree_style = categorized_style(
            "status",
            list(STATUS_COLOURS),
            geometry="point",
            colours=list(STATUS_COLOURS.values()),
        )
        layers.append(ChangeLayer(TREE_LAYER, _tree_points(trees, stands.crs), tree_style))
    outputs = ChangeOutputs(
        stand_csv=stand_csv,
        stand_parquet=stand_parquet,
        tree_csv=tree_csv,
        tree_parquet=tree_parquet,
        gpkg=None,
        style_field=field,
        style_range=value_range,
    )
    return outputs, layers
