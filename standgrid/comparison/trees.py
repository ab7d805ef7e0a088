"""Match the trees of two epochs one to one: grown, new and removed trees.

Definitions
-----------
Annualisation
    Every ``*_per_year`` value is a change divided by the interval between the two epochs'
    dates, in years = days / 365.25 (:func:`interval_years`; fractional days count when the
    dates carry a time).

Tree-matching rule
    A tree of the *from* epoch and a tree of the *to* epoch are candidates when

    * their horizontal distance is ``<= max_distance`` (default 2.0 m), and
    * the tree did not shrink by more than ``max_height_loss`` (default 0.30, i.e. 30 %) of
      its *from* height: a live tree does not lose a third of its height, so such a pair is
      a fallen or broken tree beside a different tree, not one tree re-observed.

    The cost of matching a candidate pair is::

        (d / max_distance)^2 + (loss / max_height_loss)^2 + (gain / max_height_gain)^2

    with ``d`` the horizontal distance, ``loss = max(0, (h_from - h_to) / h_from)`` and
    ``gain = max(0, (h_to - h_from) / h_from)`` (relative height changes; ``max_height_gain``,
    default 1.0 = a doubling, weighs growth but forbids nothing). Leaving a tree unmatched
    costs 1.0, so a pair is matched only if its cost is below 2.0 (both trees unmatched) and
    no competing assignment is cheaper; a pair within ``max_distance`` that shrank less than
    ``max_height_loss`` and at most doubled is matched when it has no competitor. The
    assignment minimising the total cost is solved exactly
    (``scipy.optimize.linear_sum_assignment``) per connected group of candidates, so dense
    neighbours with ambiguous candidates are resolved optimally, not greedily.

    A matched pair whose height dropped by more than ``height_tolerance_m`` (default 0.5 m,
    the height noise of a lidar tree top) is kept as ``grown`` but flagged ``suspicious``
    (broken top, or a doubtful match).

DBH sources
    With a ``dbh_source`` column in both tree lists (``measured`` / ``imputed``), a matched
    tree gets ``dbh_m_delta`` / ``dbh_m_per_year`` only when a stem fit measured its DBH in
    both epochs; ``dbh_growth_source`` says what the change rests on (``measured``,
    ``imputed`` in both, ``mixed``, ``none``; ``dbh_mixed_sources`` flags ``mixed``): the
    difference of two height-diameter model estimates, or of a fit and a model, is not
    growth (each epoch's DBH stays in ``dbh_m_from`` / ``dbh_m_to``).

Statuses
    ``grown``: matched (re-observed). ``new``: only in *to* (ingrowth, or a tree hidden
    before). ``removed``: only in *from*, i.e. not re-observed within ``max_distance``:
    harvested or fallen. A stand's harvest count is the number of removed trees whose
    position lies inside the stand (see :mod:`standgrid.comparison.stands`).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any, TypeAlias

import numpy as np
import pandas as pd

from standgrid.enrichment.identity import pair_trees
from standgrid.errors import FormatError, StandgridError

DAYS_PER_YEAR = 365.25
REQUIRED_TREE_COLUMNS = ("tree_id", "x", "y", "height_m")
#: Numeric tree attributes compared between epochs (absent columns give null changes).
TREE_ATTRIBUTES = ("height_m", "dbh_m", "crown_area_m2")
STATUSES = ("grown", "new", "removed")

DateLike: TypeAlias = dt.date | dt.datetime | str | np.datetime64 | pd.Timestamp


class ChangeInputError(StandgridError, ValueError):
    """Inputs of a comparison that cannot be compared (bad dates, missing columns, ...)."""


def _timestamp(value: DateLike, name: str) -> pd.Timestamp:
    try:
        stamp = pd.Timestamp(value)
    except (ValueError, TypeError) as exc:
        raise ChangeInputError(f"{name}: not a date: {value!r}") from exc
    if pd.isna(stamp):
        raise ChangeInputError(f"{name}: not a date: {value!r}")
    return stamp.tz_localize(None) if stamp.tzinfo is not None else stamp


def interval_years(date_from: DateLike, date_to: DateLike) -> float:
    """Years between two epoch dates: days / 365.25. ``date_to`` must be later."""
    start = _timestamp(date_from, "date_from")
    end = _timestamp(date_to, "date_to")
    days = (end - start) / pd.Timedelta(days=1)
    if days <= 0:
        raise ChangeInputError(
            f"date_to ({end.isoformat()}) must be after date_from ({start.isoformat()})"
        )
    return float(days / DAYS_PER_YEAR)


@dataclass(frozen=True)
class TreeMatches:
    """The result of :func:`match_trees`.

    ``table`` has one row per tree (a matched pair is one row): ``status``, ``tree_id_from``,
    ``tree_id_to``, ``x``, ``y`` (the *to* position, or the *from* position of a removed
    tree), ``x_from``, ``y_from``, ``x_to``, ``y_to``, ``distance_m``, and for each of
    :data:`TREE_ATTRIBUTES` ``<a>_from``, ``<a>_to``, ``<a>_delta``, ``<a>_per_year``, then
    ``suspicious``. Deltas are null unless the tree is ``grown``.
    """

    table: pd.DataFrame
    years: float
    date_from: pd.Timestamp
    date_to: pd.Timestamp

    def _of(self, status: str) -> pd.DataFrame:
        return self.table[self.table["status"] == status]

    @property
    def grown(self) -> pd.DataFrame:
        return self._of("grown")

    @property
    def new(self) -> pd.DataFrame:
        return self._of("new")

    @property
    def removed(self) -> pd.DataFrame:
        return self._of("removed")

    def counts(self) -> dict[str, int]:
        """Number of trees per status (every status present, zero when none)."""
        counts = self.table["status"].value_counts()
        return {status: int(counts.get(status, 0)) for status in STATUSES}


def _check_trees(trees: pd.DataFrame, name: str) -> pd.DataFrame:
    missing = [c for c in REQUIRED_TREE_COLUMNS if c not in trees.columns]
    if missing:
        raise FormatError(f"{name}: tree table lacks column(s) {', '.join(missing)}")
    trees = trees.reset_index(drop=True)
    xyh = trees[["x", "y", "height_m"]].to_numpy(dtype=np.float64)
    bad = ~np.isfinite(xyh).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise FormatError(
            f"{name}: {int(bad.sum())} tree(s) with non-finite x, y or height_m "
            f"(first: row {first}, tree_id {trees['tree_id'].iloc[first]!r})"
        )
    if trees["tree_id"].duplicated().any():
        dup = trees["tree_id"][trees["tree_id"].duplicated()].iloc[0]
        raise FormatError(f"{name}: duplicate tree_id {dup!r}")
    return trees


def _nullable_ids(values: pd.Series, index: np.ndarray, present: np.ndarray) -> pd.Series:
    """Ids taken at ``index`` where ``present``, null elsewhere, keeping integer ids integer."""
    picked = values.to_numpy()[np.where(present, index, 0)] if len(values) else None
    if picked is None:
        return pd.Series([pd.NA] * len(index), dtype="object")
    series = pd.Series(picked)
    if pd.api.types.is_integer_dtype(values.dtype):
        series = series.astype("Int64")
    else:
        series = series.astype("object")
    series[~present] = pd.NA
    return series


def dbh_growth_source(
    source_from: np.ndarray, source_to: np.ndarray, matched: np.ndarray
) -> np.ndarray:
    """What a matched tree's DBH change rests on: ``measured`` (a stem fit in both epochs:
    the only growth reported), ``imputed`` (the height-diameter model in both), ``mixed``
    (a fit and a model), ``none`` (no DBH in an epoch); None for an unmatched tree."""
    fits = (source_from == "measured") & (source_to == "measured")
    models = (source_from == "imputed") & (source_to == "imputed")
    known = np.isin(source_from, ["measured", "imputed"]) & np.isin(
        source_to, ["measured", "imputed"]
    )
    out = np.select([fits, models, known], ["measured", "imputed", "mixed"], "none").astype(object)
    out[~matched] = None
    return out


def _take_text(values: pd.Series, index: np.ndarray, present: np.ndarray) -> np.ndarray:
    out = np.full(len(index), None, dtype=object)
    out[present] = values.astype(object).to_numpy()[index[present]]
    return out


def _same_uid(a: pd.DataFrame, b: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``a`` and ``b`` holding the same ``tree_uid``."""
    for name, frame in (("trees_from", a), ("trees_to", b)):
        if "tree_uid" not in frame.columns or frame["tree_uid"].isna().any():
            raise FormatError(f"{name}: tree table lacks tree_uid (enrich the epoch again)")
    uid_a = a["tree_uid"].to_numpy(np.int64)
    uid_b = b["tree_uid"].to_numpy(np.int64)
    _, rows_a, rows_b = np.intersect1d(uid_a, uid_b, return_indices=True)
    return rows_a.astype(np.int64), rows_b.astype(np.int64)


def match_trees(
    trees_from: pd.DataFrame,
    trees_to: pd.DataFrame,
    *,
    date_from: DateLike,
    date_to: DateLike,
    max_distance: float = 2.0,
    max_height_loss: float = 0.30,
    max_height_gain: float = 1.0,
    height_tolerance_m: float = 0.5,
    by_uid: bool = False,
) -> TreeMatches:
    """Match trees of two epochs one to one (rule and thresholds: module docstring).

    Tree tables need ``tree_id``, ``x``, ``y`` (float64, projected metres) and ``height_m``;
    ``dbh_m`` and ``crown_area_m2`` are compared when present. Other columns are ignored.
    ``by_uid``: the trees of one catalog's epochs, paired by their ``tree_uid`` (given by the
    same rule when each epoch was enriched, :mod:`standgrid.enrichment.identity`).
    """
    if not max_distance > 0 or not 0 < max_height_loss < 1 or not max_height_gain > 0:
        raise ChangeInputError(
            "need max_distance > 0, 0 < max_height_loss < 1 and max_height_gain > 0"
        )
    years = interval_years(date_from, date_to)
    a = _check_trees(trees_from, "trees_from")
    b = _check_trees(trees_to, "trees_to")
    xy_a = a[["x", "y"]].to_numpy(dtype=np.float64)
    xy_b = b[["x", "y"]].to_numpy(dtype=np.float64)
    h_a = a["height_m"].to_numpy(dtype=np.float64)
    h_b = b["height_m"].to_numpy(dtype=np.float64)

    if by_uid:
        match_a, match_b = _same_uid(a, b)
    else:
        match_a, match_b = pair_trees(
            xy_a,
            h_a,
            xy_b,
            h_b,
            max_distance=max_distance,
            max_height_loss=max_height_loss,
            max_height_gain=max_height_gain,
        )

    unmatched_a = np.setdiff1d(np.arange(len(a)), match_a)
    unmatched_b = np.setdiff1d(np.arange(len(b)), match_b)
    idx_a = np.concatenate([match_a, np.full(len(unmatched_b), -1), unmatched_a])
    idx_b = np.concatenate([match_b, unmatched_b, np.full(len(unmatched_a), -1)])
    status = np.array(
        ["grown"] * len(match_a) + ["new"] * len(unmatched_b) + ["removed"] * len(unmatched_a),
        dtype=object,
    )
    has_a = idx_a >= 0
    has_b = idx_b >= 0

    def take(frame: pd.DataFrame, column: str, index: np.ndarray, present: np.ndarray) -> Any:
        out = np.full(len(index), np.nan)
        if column in frame.columns and len(frame):
            values = pd.to_numeric(frame[column], errors="coerce").to_numpy(np.float64)
            out[present] = values[index[present]]
        return out

    table = pd.DataFrame(
        {
            "status": pd.Series(status, dtype="object"),
            "tree_id_from": _nullable_ids(a["tree_id"], idx_a, has_a),
            "tree_id_to": _nullable_ids(b["tree_id"], idx_b, has_b),
        }
    )
    x_from, y_from = take(a, "x", idx_a, has_a), take(a, "y", idx_a, has_a)
    x_to, y_to = take(b, "x", idx_b, has_b), take(b, "y", idx_b, has_b)
    table["x"] = np.where(has_b, x_to, x_from)
    table["y"] = np.where(has_b, y_to, y_from)
    table["x_from"], table["y_from"], table["x_to"], table["y_to"] = x_from, y_from, x_to, y_to
    table["distance_m"] = np.hypot(x_to - x_from, y_to - y_from)
    for attribute in TREE_ATTRIBUTES:
        before = take(a, attribute, idx_a, has_a)
        after = take(b, attribute, idx_b, has_b)
        table[f"{attribute}_from"] = before
        table[f"{attribute}_to"] = after
        table[f"{attribute}_delta"] = after - before
        table[f"{attribute}_per_year"] = (after - before) / years
    if "dbh_source" in a.columns and "dbh_source" in b.columns:
        # diameter growth is measured only between two stem fits: a model estimate (in
        # either epoch) minus anything is no growth measurement
        source_from = _take_text(a["dbh_source"], idx_a, has_a)
        source_to = _take_text(b["dbh_source"], idx_b, has_b)
        table["dbh_source_from"], table["dbh_source_to"] = source_from, source_to
        growth = dbh_growth_source(source_from, source_to, has_a & has_b)
        table["dbh_growth_source"] = pd.array(growth, dtype="string")
        table["dbh_mixed_sources"] = growth == "mixed"
        table.loc[growth != "measured", ["dbh_m_delta", "dbh_m_per_year"]] = np.nan
    table["suspicious"] = (table["status"] == "grown") & (
        table["height_m_delta"] < -height_tolerance_m
    )
    return TreeMatches(
        table=table,
        years=years,
        date_from=_timestamp(date_from, "date_from"),
        date_to=_timestamp(date_to, "date_to"),
    )
