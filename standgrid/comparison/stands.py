"""Per-stand change between two epochs: metric deltas, annualised rates and tree change.

Definitions
-----------
Annualisation
    ``<metric>_per_year = <metric>_delta / years`` with years = days between the two epochs'
    dates / 365.25 (:func:`standgrid.comparison.trees.interval_years`).

Stands in one epoch only
    Listed, never dropped: ``presence`` is ``"both"``, ``"from_only"`` or ``"to_only"``, the
    missing side's values and every delta are null and ``null_reason`` says why.

Null metrics
    A metric that is null in either epoch gives null ``_delta`` / ``_per_year`` (never a
    silent zero); ``null_reason`` carries the input's ``null_reason`` over, prefixed with the
    epoch (``"from: <reason>"``). ``null_reason`` is empty when every change is defined.

Tree-based change (when matched trees are given)
    Each tree is placed in the stand that contains its position (the *to* position of a
    grown or new tree, the *from* position of a removed tree). Per stand: ``trees_grown``,
    ``trees_removed`` (harvested or fallen: not re-observed within the matching distance),
    ``trees_new`` (ingrowth), the same per hectare of stand area (``*_per_ha``), and
    ``tree_height_growth_m`` / ``tree_height_growth_m_per_year``: the mean height change of
    the stand's grown trees. Trees outside every stand are counted in the result's
    ``attrs["trees_outside_stands"]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from standgrid.comparison.trees import ChangeInputError, DateLike, TreeMatches, interval_years
from standgrid.errors import FormatError, GridMismatchError

KEY = "cell_id"
NULL_REASON = "null_reason"
#: Numeric columns that are identifiers or bookkeeping, not metrics.
NON_METRIC_COLUMNS = frozenset({KEY, NULL_REASON, "epoch", "level", "cell_key", "geometry"})
PRESENCE = ("both", "from_only", "to_only", "trees_only")
#: Index names taken as the stand key when there is no ``cell_id`` column (enrich's
#: metric tables are indexed by ``cell``, the grid's integer cell key).
INDEX_KEYS = (KEY, "cell")


def check_same_grid(
    fingerprint_a: str | Any,
    fingerprint_b: str | Any,
    *,
    label_a: str = "from",
    label_b: str = "to",
) -> None:
    """Refuse to compare two catalogs or epochs whose stand grids differ.

    Each argument is a grid fingerprint, or anything with a ``fingerprint`` attribute
    (``StandGrid``, ``Catalog``). Raises :class:`GridMismatchError` naming both.
    """
    a = str(getattr(fingerprint_a, "fingerprint", fingerprint_a))
    b = str(getattr(fingerprint_b, "fingerprint", fingerprint_b))
    if a != b:
        raise GridMismatchError(
            f"cannot compare epochs on different stand grids: {label_a} grid {a} != "
            f"{label_b} grid {b}"
        )


def _check_metrics(metrics: pd.DataFrame, name: str) -> pd.DataFrame:
    if KEY not in metrics.columns:
        if metrics.index.name in INDEX_KEYS:
            metrics = metrics.rename_axis(KEY).reset_index()
        else:
            raise FormatError(f"{name}: stand metrics lack the {KEY!r} column")
    if metrics[KEY].isna().any():
        raise FormatError(f"{name}: {int(metrics[KEY].isna().sum())} row(s) without {KEY}")
    duplicated = metrics[KEY].duplicated()
    if duplicated.any():
        raise FormatError(
            f"{name}: {KEY} {metrics[KEY][duplicated].iloc[0]!r} appears more than once"
        )
    return metrics.reset_index(drop=True)


def _metric_columns(metrics: pd.DataFrame) -> list[str]:
    return [
        column
        for column in metrics.columns
        if column not in NON_METRIC_COLUMNS
        and pd.api.types.is_numeric_dtype(metrics[column])
        and not pd.api.types.is_bool_dtype(metrics[column])
    ]


def _reason_text(value: Any) -> str:
    if value is None or value is pd.NA or (isinstance(value, float) and np.isnan(value)):
        return ""
    return str(value)


def assign_stands(
    x: Sequence[float] | np.ndarray,
    y: Sequence[float] | np.ndarray,
    cells: Any,
) -> pd.Series:
    """The ``cell_id`` of the stand polygon containing each point (null outside all).

    ``cells``: a GeoDataFrame with ``cell_id`` and polygon geometry. A point on a shared
    edge goes to the first containing cell in ``cells`` order (deterministic).
    """
    import shapely

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    out = pd.Series([None] * len(x), dtype="object")
    if len(x) == 0 or len(cells) == 0:
        return out
    points = shapely.points(x, y)
    geometries = np.asarray(cells.geometry.values)
    tree = shapely.STRtree(geometries)
    point_index, cell_index = tree.query(points, predicate="intersects")
    order = np.lexsort((cell_index, point_index))
    point_index, cell_index = point_index[order], cell_index[order]
    first = np.unique(point_index, return_index=True)[1]
    ids = cells[KEY].to_numpy()
    out.iloc[point_index[first]] = ids[cell_index[first]]
    return out


def _tree_change(
    matches: TreeMatches,
    cells: Any | None,
    stand_area_m2: pd.Series | float | None,
) -> tuple[pd.DataFrame, int]:
    """Per-stand tree counts and mean height growth, and the number of trees in no stand."""
    table = matches.table
    if KEY in table.columns:
        stand = table[KEY]
    elif cells is not None:
        stand = assign_stands(table["x"].to_numpy(), table["y"].to_numpy(), cells)
    else:
        raise ChangeInputError(
            "tree change per stand needs the stand of each tree: a 'cell_id' column in the "
            "matched trees, or cells (GeoDataFrame of cell polygons)"
        )
    inside = stand.notna().to_numpy()
    trees = table.loc[inside, ["status", "height_m_delta"]].assign(**{KEY: stand[inside].values})
    counts = pd.crosstab(trees[KEY], trees["status"])
    counts = counts.reindex(columns=["grown", "removed", "new"], fill_value=0)
    counts.columns = ["trees_grown", "trees_removed", "trees_new"]
    growth = trees[trees["status"] == "grown"].groupby(KEY)["height_m_delta"].mean()
    result = counts.join(growth.rename("tree_height_growth_m"), how="left")
    result["tree_height_growth_m_per_year"] = result["tree_height_growth_m"] / matches.years
    if cells is not None and stand_area_m2 is None:
        stand_area_m2 = pd.Series(
            np.asarray(cells.geometry.area, dtype=np.float64), index=cells[KEY].to_numpy()
        )
    if stand_area_m2 is not None:
        area_ha = (
            stand_area_m2.reindex(result.index)
            if isinstance(stand_area_m2, pd.Series)
            else pd.Series(float(stand_area_m2), index=result.index)
        ) / 10_000.0
        for column in ("trees_removed", "trees_new", "trees_grown"):
            result[f"{column}_per_ha"] = result[column] / area_ha
    return result.reset_index().rename(columns={"index": KEY}), int((~inside).sum())


def compare_stands(
    metrics_from: pd.DataFrame,
    metrics_to: pd.DataFrame,
    *,
    date_from: DateLike,
    date_to: DateLike,
    epoch_from: str | None = None,
    epoch_to: str | None = None,
    tree_matches: TreeMatches | None = None,
    cells: Any | None = None,
    stand_area_m2: pd.Series | float | None = None,
) -> pd.DataFrame:
    """Change of every numeric stand metric between two epochs (definitions: module doc).

    ``metrics_*``: stand metrics keyed by a ``cell_id`` column (or an index named ``cell_id``
    or ``cell``) with numeric metric columns and an optional ``null_reason``.
    ``tree_matches`` (from :func:`match_trees`) adds tree-based change; the stand of each
    tree comes from a ``cell_id`` column of its table or from ``cells`` (GeoDataFrame:
    ``cell_id`` + polygon); per-hectare values need the stand area (``stand_area_m2`` per
    cell_id or one value for all, else the ``cells`` polygon area).
    Returns one row per stand in either epoch, sorted by ``cell_id``.
    """
    years = interval_years(date_from, date_to)
    a = _check_metrics(metrics_from, "metrics_from")
    b = _check_metrics(metrics_to, "metrics_to")
    metrics_a, metrics_b = _metric_columns(a), _metric_columns(b)
    metrics = metrics_a + [m for m in metrics_b if m not in metrics_a]

    reasons_a = a.get(NULL_REASON, pd.Series([None] * len(a))).map(_reason_text)
    reasons_b = b.get(NULL_REASON, pd.Series([None] * len(b))).map(_reason_text)
    left = a[[KEY, *metrics_a]].assign(_reason=reasons_a.values, _in_from=True)
    right = b[[KEY, *metrics_b]].assign(_reason=reasons_b.values, _in_to=True)
    left = left.rename(columns={m: f"{m}_from" for m in metrics_a} | {"_reason": "_reason_from"})
    right = right.rename(columns={m: f"{m}_to" for m in metrics_b} | {"_reason": "_reason_to"})
    merged = left.merge(right, on=KEY, how="outer", sort=True)
    in_from = merged["_in_from"].eq(True).to_numpy()
    in_to = merged["_in_to"].eq(True).to_numpy()

    constants: dict[str, Any] = {}
    if epoch_from is not None:
        constants["epoch_from"] = epoch_from
    if epoch_to is not None:
        constants["epoch_to"] = epoch_to
    constants["date_from"] = pd.Timestamp(date_from).date().isoformat()
    constants["date_to"] = pd.Timestamp(date_to).date().isoformat()
    constants["years"] = years
    out = pd.DataFrame({KEY: merged[KEY]}).assign(**constants)
    out["presence"] = np.where(in_from & in_to, "both", np.where(in_from, "from_only", "to_only"))

    reasons: list[list[str]] = [[] for _ in range(len(merged))]
    for i in np.flatnonzero(~in_to):
        reasons[i].append(f"stand not observed in the {epoch_to or 'to'} epoch")
    for i in np.flatnonzero(~in_from):
        reasons[i].append(f"stand not observed in the {epoch_from or 'from'} epoch")
    columns: dict[str, Any] = {}
    for metric in metrics:
        before, after = (
            pd.to_numeric(merged[column], errors="coerce").astype("float64")
            if column in merged.columns
            else pd.Series(np.nan, index=merged.index)
            for column in (f"{metric}_from", f"{metric}_to")
        )
        delta = after - before
        columns[f"{metric}_from"] = before
        columns[f"{metric}_to"] = after
        columns[f"{metric}_delta"] = delta
        columns[f"{metric}_per_year"] = delta / years
        for side, values, present, column_present in (
            ("from", before, in_from, metric in metrics_a),
            ("to", after, in_to, metric in metrics_b),
        ):
            for i in np.flatnonzero(values.isna().to_numpy() & present):
                own = merged[f"_reason_{side}"].iloc[i]
                if not column_present:
                    text = f"{side}: metric {metric} not computed in this epoch"
                elif own:
                    text = f"{side}: {own}"
                else:
                    text = f"{side}: {metric} is null (no reason given)"
                if text not in reasons[i]:
                    reasons[i].append(text)
    out = pd.concat([out, pd.DataFrame(columns, index=out.index)], axis=1)
    out["null_reason_from"] = merged["_reason_from"].fillna("").astype(str)
    out["null_reason_to"] = merged["_reason_to"].fillna("").astype(str)
    out[NULL_REASON] = ["; ".join(r) for r in reasons]

    if tree_matches is not None:
        tree_change, outside = _tree_change(tree_matches, cells, stand_area_m2)
        out = out.merge(tree_change, on=KEY, how="outer", sort=True)
        trees_only = out["presence"].isna()
        out.loc[trees_only, "presence"] = "trees_only"
        out.loc[trees_only, NULL_REASON] = "stand has trees but no metrics in either epoch"
        for column, value in constants.items():
            out.loc[trees_only, column] = value
        for column in ("null_reason_from", "null_reason_to"):
            out[column] = out[column].fillna("")
        # a stand seen in both epochs without any tree in it changed by zero trees (real zero)
        no_trees = out["presence"].eq("both") & out["trees_grown"].isna()
        for column in tree_change.columns:
            if column.startswith(("trees_grown", "trees_removed", "trees_new")):
                out.loc[no_trees, column] = 0.0
        for column in ("trees_grown", "trees_removed", "trees_new"):
            out[column] = out[column].astype("Int64")
        out.attrs["trees_outside_stands"] = outside
    out.attrs["years"] = years
    return out.reset_index(drop=True)
