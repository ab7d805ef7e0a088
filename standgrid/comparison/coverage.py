"""Change over co-observed ground: the ground both epochs observed, and nothing else.

Two campaigns rarely cover the same ground. Tree counts, basal area and harvest are
compared only where both observed the ground (the intersection of their
``rasters/<epoch>/observed.tif`` masks, :mod:`standgrid.enrichment.coverage`):

- a tree removed or new outside that ground was not seen twice: ``unobserved``, neither
  harvest nor ingrowth;
- per stand, ``co_observed_m2`` / ``co_observed_fraction`` and the tree-based values of
  both epochs over that area (``stems_ha``, ``basal_area_m2_ha``, ``qmd_cm``: from, to,
  delta, per year), counting the trees whose stem stands on it;
- a stand whose co-observed fraction is below the coverage rule gets null changes with a
  ``null_reason`` starting ``insufficient_coverage``.
Definitions: docs/METRICS.md ("Change").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from standgrid.comparison.rasters import read_aligned_pair
from standgrid.enrichment.coverage import polygon_mask_area, sample_mask
from standgrid.enrichment.stands import INSUFFICIENT_COVERAGE
from standgrid.rastergrid import RasterGrid

UNOBSERVED = "unobserved"
#: Tree-based stand values recomputed over the co-observed ground.
CO_OBSERVED_METRICS = ("stems_ha", "basal_area_m2_ha", "qmd_cm")


@dataclass(frozen=True)
class CoObserved:
    """The ground observed in both epochs, on the joint pixel grid."""

    mask: NDArray[np.bool_]
    grid: RasterGrid

    @classmethod
    def read(cls, observed_from: Path, observed_to: Path) -> CoObserved:
        a, b, grid = read_aligned_pair(observed_from, observed_to, extent="union")
        return cls((a == 1) & (b == 1), grid)

    def within(self, *polygon_sets: list[Any]) -> CoObserved:
        """Only the pixels inside one polygon of every set (e.g. each epoch's measured
        cells)."""
        from standgrid.enrichment.coverage import cells_mask

        mask = self.mask.copy()
        for polygons in polygon_sets:
            mask &= cells_mask(self.grid, polygons)
        return CoObserved(mask, self.grid)

    def at(self, x: Any, y: Any) -> NDArray[np.bool_]:
        return sample_mask(self.mask, self.grid, x, y)

    def area_m2(self, polygon: Any) -> float:
        """Co-observed area inside ``polygon`` (m²): :func:`polygon_mask_area`."""
        return polygon_mask_area(self.mask, self.grid, polygon)


def mark_unobserved(table: pd.DataFrame, co: CoObserved) -> pd.DataFrame:
    """``co_observed`` per matched tree (its stem: the later epoch's for grown and new
    trees, the earlier one's for removed trees), and removed/new trees off that ground
    re-labelled ``unobserved``."""
    table = table.copy()
    table["co_observed"] = co.at(table["stem_x"].to_numpy(), table["stem_y"].to_numpy())
    off = table["status"].isin(["removed", "new"]).to_numpy() & ~table["co_observed"].to_numpy()
    table.loc[off, "status"] = UNOBSERVED
    return table


def stand_change(
    table: pd.DataFrame,
    key: str,
    polygons: pd.DataFrame,
    co: CoObserved,
    *,
    years: float,
    min_fraction: float,
) -> pd.DataFrame:
    """Per stand (``polygons``: ``cell_id`` + geometry): co-observed area and the tree-based
    values of both epochs over it; ``table`` is :func:`mark_unobserved`'s, ``key`` the column
    giving each tree's stand."""
    on = table[table["co_observed"] & table[key].notna()]
    rows = []
    for cell_id, polygon in zip(polygons["cell_id"], polygons.geometry, strict=True):
        area = co.area_m2(polygon)
        fraction = area / polygon.area if polygon.area > 0 else math.nan
        trees = on[on[key] == cell_id]
        row: dict[str, Any] = {
            "cell_id": cell_id,
            "co_observed_m2": area,
            "co_observed_fraction": fraction,
        }
        # a missed tree stands in both surveys: counted in both, with the DBH one measured
        missed = trees[trees["status"] == "missed"]
        either = missed["dbh_m_from"].fillna(missed["dbh_m_to"])
        before = pd.concat(
            [trees[trees["status"].isin(["grown", "removed"])]["dbh_m_from"], either]
        )
        after = pd.concat(
            [
                trees[trees["status"].isin(["grown", "new"])]["dbh_m_to"],
                missed["dbh_m_to"].fillna(missed["dbh_m_from"]),
            ]
        )
        sides = {"from": _per_ha(before, area), "to": _per_ha(after, area)}
        for metric in CO_OBSERVED_METRICS:
            a, b = sides["from"][metric], sides["to"][metric]
            row[f"{metric}_from"], row[f"{metric}_to"] = a, b
            row[f"{metric}_delta"] = b - a
            row[f"{metric}_per_year"] = (b - a) / years
        counts = trees["status"].value_counts()
        for status in ("grown", "removed", "new", "missed"):
            n = int(counts.get(status, 0))
            row[f"trees_{status}"] = n
            row[f"trees_{status}_per_ha"] = n / area * 10_000.0 if area > 0 else math.nan
        grown = trees[trees["status"] == "grown"]["height_m_delta"]
        row["tree_height_growth_m"] = float(grown.mean()) if len(grown) else math.nan
        row["tree_height_growth_m_per_year"] = row["tree_height_growth_m"] / years
        row["coverage_reason"] = (
            None
            if fraction >= min_fraction
            else f"{INSUFFICIENT_COVERAGE}: {100 * fraction:.0f} % of the stand observed in "
            f"both epochs (minimum {100 * min_fraction:.0f} %)"
        )
        rows.append(row)
    return pd.DataFrame(rows)


def _per_ha(dbh_m: pd.Series, area_m2: float) -> dict[str, float]:
    """stems/ha, basal area/ha and QMD of trees with these DBHs over ``area_m2`` (the stand
    metrics' own formulas, :func:`standgrid.enrichment.metrics.tree_metrics`)."""
    from standgrid.enrichment.metrics import tree_metrics

    if area_m2 <= 0:
        return dict.fromkeys(CO_OBSERVED_METRICS, math.nan)
    d = dbh_m.to_numpy(dtype=np.float64)
    row = tree_metrics(
        np.zeros(len(d), dtype=np.int64), np.zeros(len(d)), d, cell_area_m2=area_m2, cells=[0]
    ).iloc[0]
    return {metric: float(row[metric]) for metric in CO_OBSERVED_METRICS}
