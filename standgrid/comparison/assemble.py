"""Assembling a comparison from its parts: where matched trees stand, which stands each
epoch measured, the metric columns worth comparing, the co-observed change joined to the
stand changes (null short of coverage), and the report's counts and averages."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from standgrid.comparison.coverage import CO_OBSERVED_METRICS
from standgrid.enrichment.stands import SAMPLE_COLUMNS, TREE_COUNT_COLUMNS

if TYPE_CHECKING:
    import geopandas as gpd
    import pandas as pd


def locate_trees(matches: Any, trees_from: pd.DataFrame, trees_to: pd.DataFrame) -> Any:
    """Give every matched tree its cell, 1 ha stand and stem position.

    A tree's stand is where enrich put it (the cell it stands in, half-open), taken from the
    tree lists: the later epoch's for grown and new trees, the earlier one's for removed
    trees; so is its stem position (the fitted stem, or the top without a stem fit).
    """
    table = matches.table.copy()
    removed = (table["status"] == "removed").to_numpy()
    for frame in (trees_from, trees_to):
        for xy in ("x", "y"):
            stem = f"stem_{xy}"
            values = frame[stem] if stem in frame.columns else frame[xy]
            frame[f"_{stem}"] = values.where(values.notna(), frame[xy])
    columns = [c for c in ("cell_id", "stand_id") if c in trees_from.columns]
    columns += ["_stem_x", "_stem_y"]
    by_id_from = trees_from.set_index("tree_id")[columns]
    by_id_to = trees_to.set_index("tree_id")[columns]
    for column in columns:
        later = table["tree_id_to"].map(by_id_to[column])
        earlier = table["tree_id_from"].map(by_id_from[column])
        table[column.lstrip("_")] = later.where(~removed, earlier)
    if "stand_id" not in table.columns:
        table["stand_id"] = None
    return replace(matches, table=table)


#: stand_metrics columns that describe the sample or are recomputed over co-observed ground.
_NOT_COMPARED = frozenset((*SAMPLE_COLUMNS, *TREE_COUNT_COLUMNS, *CO_OBSERVED_METRICS))


#: Shape statistics of the height distribution: their change is given, not as a yearly rate.
_SHAPES = ("zskew", "zkurt", "zentropy", "zpcum")


def measured_cells(cells: gpd.GeoDataFrame, metrics: pd.DataFrame) -> list[Any]:
    """Polygons of the 20 m cells (or Voronoi cells) whose metrics an epoch reports: ground
    that failed its coverage rule (too few points, no terrain) is not compared either."""
    level0 = metrics[metrics["level"] == 0]
    measured = set(level0.loc[level0["stems_ha"].notna(), "cell_id"])
    return list(cells.loc[cells["cell_id"].isin(measured), "geometry"])


def forest_metrics(metrics: pd.DataFrame) -> pd.DataFrame:
    """The metric columns whose change means something about the forest."""
    return metrics.drop(columns=[c for c in metrics.columns if c in _NOT_COMPARED])


def with_coverage(
    changes: pd.DataFrame, trees: pd.DataFrame, a: pd.DataFrame, b: pd.DataFrame
) -> pd.DataFrame:
    """Join the co-observed tree change; null every change of a stand short of coverage."""
    import pandas as pd

    out = changes.merge(trees, on="cell_id", how="left")
    for side, frame in (("from", a), ("to", b)):
        observed = frame.set_index("cell_id")["observed_fraction"]
        out[f"observed_fraction_{side}"] = out["cell_id"].map(observed)
    short = out["coverage_reason"].notna().to_numpy()
    changed = [c for c in out.columns if c.endswith(("_delta", "_per_year"))]
    changed += [c for c in out.columns if c.startswith("trees_") or c.startswith("tree_height")]
    changed += [f"{m}_{side}" for m in CO_OBSERVED_METRICS for side in ("from", "to")]
    out.loc[short, list(dict.fromkeys(changed))] = np.nan
    reason = out["null_reason"].astype("string").fillna("")
    extra = out["coverage_reason"].astype("string").fillna("")
    joined = (extra + "; " + reason).str.strip("; ")
    out["null_reason"] = joined.where(joined != "", pd.NA)
    for column in ("trees_grown", "trees_removed", "trees_new"):
        out[column] = out[column].astype("Int64")
    no_rate = [c for c in out.columns if c.endswith("_per_year") and c.startswith(_SHAPES)]
    return out.drop(columns=["coverage_reason", *no_rate]).copy()


def presence(changes: pd.DataFrame) -> dict[str, int]:
    """How many stands are in both epochs, or in one only."""
    return {
        name: int((changes["presence"] == value).sum())
        for name, value in (("in_both", "both"), ("from_only", "from_only"), ("to_only", "to_only"))
    }


def headline(changes: pd.DataFrame, matches: Any) -> dict[str, float | None]:
    """A few stand-level averages for the human report."""
    import math

    out: dict[str, float | None] = {}
    cells = changes[changes["level"] == 0]
    for column in ("tree_height_growth_m_per_year", "zq95_per_year", "zmean_per_year"):
        if column in cells.columns:
            value = float(cells[column].mean(skipna=True))
            out[column] = value if math.isfinite(value) else None
    out["trees_removed"] = float(matches.counts().get("removed", 0))
    return out
