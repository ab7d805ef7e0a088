"""Stand metrics per grid cell: the area-based set of lidR ``stdmetrics_z`` and the tree-based
set growth models use. Definitions and cutoffs: docs/METRICS.md.

Area-based metrics are vectorised over all cells at once: the points are sorted once by
(cell, height) and every metric is a gather or a ``np.add.reduceat`` over the sorted order,
so there is no per-cell Python loop. Cells that cannot be measured keep their row with NaN
metrics and a ``null_reason`` (never a silent zero).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import Literal

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import EnrichError

QUANTILE_PERCENTS: tuple[int, ...] = tuple(range(5, 100, 5))
DEFAULT_STRATA: tuple[float, ...] = (0.5, 2.0, 5.0, 10.0, 20.0, 30.0)
REASON_NO_POINTS = "no points"
REASON_NO_HEIGHT = "no height above ground (no ground/DTM)"
REASON_NO_TREES = "no trees detected"
REASON_NO_DBH = "basal area and QMD unknown: trees without a DBH"


def fmt_break(value: float) -> str:
    """2 -> '2', 0.5 -> '0p5' (column-name safe)."""
    text = f"{value:g}"
    return text.replace(".", "p").replace("-", "m")


def strata_columns(strata: Sequence[float] = DEFAULT_STRATA) -> list[str]:
    """Names of the strata proportions: ``pz_below0p5``, ``pz0p5to2``, ..., ``pz30plus``."""
    edges = list(strata)
    names = [f"pz_below{fmt_break(edges[0])}"]
    names += [f"pz{fmt_break(lo)}to{fmt_break(hi)}" for lo, hi in pairwise(edges)]
    names.append(f"pz{fmt_break(edges[-1])}plus")
    return names


def cell_index(
    x: ArrayLike, y: ArrayLike, *, origin: tuple[float, float], cell_size: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Column and row (counted from the origin, half-open cells) of each point's stand cell."""
    col = np.floor((np.asarray(x, dtype=np.float64) - origin[0]) / cell_size).astype(np.int64)
    row = np.floor((np.asarray(y, dtype=np.float64) - origin[1]) / cell_size).astype(np.int64)
    return col, row


def area_metrics(
    cell: ArrayLike,
    heights: ArrayLike,
    *,
    cell_area_m2: float | None = None,
    cells: ArrayLike | None = None,
    height_break: float = 2.0,
    strata: Sequence[float] = DEFAULT_STRATA,
    zmin: float = 0.0,
    entropy_bin: float = 1.0,
    first_return: ArrayLike | None = None,
) -> pd.DataFrame:
    """Area-based metrics of heights above ground, one row per cell key.

    ``cell`` holds an integer key per point (e.g. a ``CellId.key``); ``heights`` the height
    above ground (NaN = unknown, e.g. no DTM there: excluded and counted in
    ``n_no_height``). ``cells`` lists cells that must appear even without points.
    ``cell_area_m2`` gives ``density_pts_m2``; ``first_return`` (bool per point) gives
    ``cover_first_above<height_break>`` (e.g. ``cover_first_above2``: percent of first returns
    above ``height_break``). ``zsd`` is 0 and ``zskew``/``zkurt`` NaN where all heights of a
    cell are equal; ``zsd`` is NaN for a single height.
    """
    table, _ = area_metrics_sorted(
        cell,
        heights,
        cell_area_m2=cell_area_m2,
        cells=cells,
        height_break=height_break,
        strata=strata,
        zmin=zmin,
        entropy_bin=entropy_bin,
        first_return=first_return,
    )
    return table


def area_metrics_sorted(
    cell: ArrayLike,
    heights: ArrayLike,
    *,
    cell_area_m2: float | None = None,
    cells: ArrayLike | None = None,
    height_break: float = 2.0,
    strata: Sequence[float] = DEFAULT_STRATA,
    zmin: float = 0.0,
    entropy_bin: float = 1.0,
    first_return: ArrayLike | None = None,
) -> tuple[pd.DataFrame, NDArray[np.floating]]:
    """:func:`area_metrics`, and the finite heights its sort put in order: by cell, then
    height (float32 heights stay float32; each cell's ``n_points - n_no_height`` of them)."""
    keys = np.asarray(cell)
    h_given = np.asarray(heights)
    h_all = np.asarray(h_given, dtype=np.float64)
    if keys.shape != h_all.shape or keys.ndim != 1:
        raise EnrichError(
            f"cell keys {keys.shape} and heights {h_all.shape} must be equal 1-D arrays"
        )
    if not np.issubdtype(keys.dtype, np.integer):
        raise EnrichError(f"cell keys must be integers, got {keys.dtype}")
    edges = [float(s) for s in strata]
    if any(b <= a for a, b in pairwise(edges)) or not edges:
        raise EnrichError(f"strata breaks must increase, got {strata}")
    keys = keys.astype(np.int64, copy=False)
    finite = np.isfinite(h_all)
    first = None if first_return is None else np.asarray(first_return, dtype=bool)
    if first is not None and first.shape != h_all.shape:
        raise EnrichError(f"first_return {first.shape} does not match heights {h_all.shape}")

    present, dense_all = _dense_groups(keys)
    n_points = np.bincount(dense_all, minlength=len(present))
    all_cells = present
    if cells is not None:
        all_cells = np.union1d(present, np.asarray(cells, dtype=np.int64))
    n_total = np.zeros(len(all_cells), dtype=np.int64)
    n_total[np.searchsorted(all_cells, present)] = n_points

    all_finite = bool(finite.all())
    h = h_all if all_finite else h_all[finite]
    # float32 heights (as enrichment stores them) are sorted as such: the same order
    narrow = None
    if h_given.dtype == np.float32:
        narrow = h_given if all_finite else h_given[finite]
    if all_finite:
        measured, dense = present, dense_all
    else:
        measured, dense = _dense_groups(keys[finite])
    table, ordered = _sorted_metrics(
        dense, h, len(measured), height_break, edges, zmin, entropy_bin, narrow=narrow
    )
    if first is not None:
        f = first if all_finite else first[finite]
        n_first = np.bincount(dense[f], minlength=len(measured))
        above = np.bincount(dense[f & (h > height_break)], minlength=len(measured))
        with np.errstate(invalid="ignore", divide="ignore"):
            table[f"cover_first_above{fmt_break(height_break)}"] = np.where(
                n_first > 0, 100.0 * above / np.maximum(n_first, 1), np.nan
            )

    out = pd.DataFrame(table, index=pd.Index(measured, name="cell")).reindex(
        pd.Index(all_cells, name="cell")
    )
    n_valid = out.pop("n_height").fillna(0).astype(np.int64).to_numpy()
    out.insert(0, "n_points", n_total)
    out.insert(1, "n_no_height", n_total - n_valid)
    density_value = n_total / cell_area_m2 if cell_area_m2 else np.full(len(all_cells), np.nan)
    out.insert(2, "density_pts_m2", density_value)
    reason = np.full(len(all_cells), None, dtype=object)
    reason[n_valid == 0] = REASON_NO_HEIGHT
    reason[n_total == 0] = REASON_NO_POINTS
    out["null_reason"] = pd.array(reason, dtype="string")
    return out, ordered


def _dense_groups(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(sorted unique keys, dense index of each key into them): from the runs of sorted
    keys, else by hashing (O(N))."""
    if len(keys) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if bool((keys[1:] >= keys[:-1]).all()):  # sorted (cells one after another): runs
        starts = np.flatnonzero(keys[1:] != keys[:-1]) + 1
        codes = np.zeros(len(keys), dtype=np.int64)
        codes[starts] = 1
        np.cumsum(codes, out=codes)
        return keys[np.concatenate([[0], starts])].astype(np.int64), codes
    codes, unique = pd.factorize(keys, sort=True)
    return np.asarray(unique, dtype=np.int64), np.asarray(codes, dtype=np.int64)


def _sorted_metrics(
    group: NDArray[np.int64],
    h: NDArray[np.float64],
    n_groups: int,
    height_break: float,
    strata: list[float],
    zmin: float,
    entropy_bin: float,
    *,
    narrow: NDArray[np.float32] | None = None,
) -> tuple[dict[str, NDArray[np.float64]], NDArray[np.floating]]:
    """All height metrics per dense group index, from one sort by (group, height), and the
    heights in that order (as float32 with ``narrow``).

    The sort key is the complex number ``group + 1j * height``: numpy orders complex values
    lexicographically (real part, then imaginary part), so one ``np.sort`` orders points by
    cell then height with the heights kept exact, and counting the heights below a
    threshold in every cell is one exact ``np.searchsorted`` of ``cell + 1j * threshold``.
    ``narrow``: ``h`` as float32 (exactly), sorted in its place when the groups come one
    after another (the same order, half the bytes to move).
    """
    if n_groups == 0:
        names = ["n_height", *_metric_names(height_break, strata)]
        empty = np.zeros(0, dtype=(h if narrow is None else narrow).dtype)
        return {name: np.zeros(0) for name in names}, empty
    counts = np.bincount(group, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ends = starts + counts
    keyed = np.empty(len(h), dtype=np.complex128)
    keyed.real = group
    grouped = len(h) >= 64 * n_groups and bool((group[1:] >= group[:-1]).all())
    if grouped:
        # already grouped (stands measured one after another): sorting each group's heights
        # gives the same order as the complex sort, several times faster
        z = (h if narrow is None else narrow).copy()
        for start, end in zip(starts, ends, strict=True):
            group_z = z[start:end]
            # a stand's heights come as its cells' sorted runs: a merge sort takes them as such
            runs = 1 + np.count_nonzero(group_z[1:] < group_z[:-1])
            group_z.sort(kind="stable" if runs <= 64 else "quicksort")
        ordered = z
        z = z.astype(np.float64, copy=False)
        keyed.imag = z
    else:
        keyed.imag = h
        keyed.sort()
        z = np.ascontiguousarray(keyed.imag)
        ordered = z if narrow is None else z.astype(narrow.dtype)
    n = counts.astype(np.float64)
    group_ids = np.arange(n_groups, dtype=np.float64)

    def per_group(values: NDArray[np.generic]) -> NDArray[np.float64]:
        return np.add.reduceat(values, starts, dtype=np.float64)

    def count_below(
        threshold: NDArray[np.float64] | float,
        groups: NDArray[np.int64] | None = None,
        *,
        inclusive: bool = False,
    ) -> NDArray[np.float64]:
        """Points of each group (or of ``groups[i]``) with z < threshold (<= if ``inclusive``)."""
        side: Literal["left", "right"] = "right" if inclusive else "left"
        g = group_ids if groups is None else group_ids[groups]
        first = starts if groups is None else starts[groups]
        last = ends if groups is None else ends[groups]
        target = np.empty(len(g), dtype=np.complex128)
        target.real = g
        target.imag = threshold
        at = np.clip(np.searchsorted(keyed, target, side=side), first, last)
        return (at - first).astype(np.float64)

    out: dict[str, NDArray[np.float64]] = {}
    zmax = z[ends - 1]
    zmean = per_group(z) / n
    # central moments in the input order (no gather of the sort needed)
    if grouped:
        d = h.copy()
        for mean, start, end in zip(zmean, starts, ends, strict=True):
            d[start:end] -= mean
    else:
        d = h - zmean[group]
    power = d * d
    m2 = np.bincount(group, weights=power, minlength=n_groups)
    m4 = np.bincount(group, weights=power * power, minlength=n_groups)
    power *= d
    m3 = np.bincount(group, weights=power, minlength=n_groups)
    del d, power
    with np.errstate(invalid="ignore", divide="ignore"):
        out["zmax"] = zmax
        out["zmean"] = zmean
        # A constant group (max == min in the sorted order: exact, unlike m2, which keeps
        # round-off of the floating mean) has zsd 0 and no skewness or kurtosis.
        varies = zmax > z[starts]
        out["zsd"] = np.where(
            counts > 1, np.where(varies, np.sqrt(m2 / np.maximum(n - 1, 1)), 0.0), np.nan
        )
        out["zskew"] = np.where(varies, (m3 / n) / np.power(m2 / n, 1.5), np.nan)
        out["zkurt"] = np.where(varies, n * m4 / (m2 * m2), np.nan)
        out["zentropy"] = _entropy(count_below, zmax, entropy_bin)
        out["pzabovezmean"] = 100.0 * (n - count_below(zmean, inclusive=True)) / n
        out[f"pzabove{fmt_break(height_break)}"] = (
            100.0 * (n - count_below(height_break, inclusive=True)) / n
        )
        for p in QUANTILE_PERCENTS:  # R quantile type 7 (numpy 'linear')
            pos = (n - 1) * (p / 100.0)
            below = np.floor(pos).astype(np.int64)
            frac = pos - below
            i0 = starts + below
            i1 = np.minimum(i0 + 1, ends - 1)
            out[f"zq{p}"] = z[i0] + frac * (z[i1] - z[i0])
        # zpcum1..9 as lidR: breaks zmin + k*(zmax-zmin)/10 over points zmin < z; points on
        # or above the last break (z == zmax) are not counted (lidR's findInterval/fast_table)
        width = (zmax - zmin) / 10.0
        not_above_min = count_below(zmin, inclusive=True)
        denominator = count_below(zmin + 10 * width) - not_above_min
        for k in range(1, 10):
            below_k = count_below(zmin + k * width) - not_above_min
            out[f"zpcum{k}"] = np.where(zmax > zmin, 100.0 * below_k / denominator, 0.0)
        bounds = [-np.inf, *strata, np.inf]
        for name, a, b in zip(strata_columns(strata), bounds[:-1], bounds[1:], strict=True):
            upper = n if np.isinf(b) else count_below(b)
            lower = 0.0 if np.isinf(a) else count_below(a)
            out[name] = 100.0 * (upper - lower) / n
    out["n_height"] = n
    return out, ordered


def _entropy(
    count_below: Callable[..., NDArray[np.float64]],
    zmax: NDArray[np.float64],
    by: float,
) -> NDArray[np.float64]:
    """lidR ``entropy(z, by)``: normalised Shannon index of ``by``-m height bins
    [k*by, (k+1)*by) from 0 to ceiling(zmax/by)*by; NaN when zmax < 2*by. Heights below 0
    (ground noise) fall in no bin and are left out; lidR instead gives NA whenever any height
    is below 0, which ground noise in height-normalised data almost always causes.

    Bin counts are differences of ``count_below`` (group-wise z < edge) at the bin edges.
    """
    ok = zmax >= 2 * by
    nb = np.where(ok, np.maximum(np.ceil(zmax / by).astype(np.int64), 1), 1)
    group_of_edge = np.repeat(np.arange(len(nb)), nb + 1)
    first_edge = np.concatenate([[0], np.cumsum(nb + 1)[:-1]])
    k = np.arange(len(group_of_edge)) - np.repeat(first_edge, nb + 1)
    below = count_below(k * by, group_of_edge)
    hist = np.diff(below)
    hist = np.delete(hist, first_edge[1:] - 1)  # drop differences across two groups
    offsets = np.concatenate([[0], np.cumsum(nb)[:-1]])
    totals = np.add.reduceat(hist, offsets)
    p = hist / np.repeat(np.where(totals > 0, totals, 1.0), nb)
    plogp = np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0)
    s = -np.add.reduceat(plogp, offsets)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok & (nb > 1) & (totals > 0), s / np.log(nb), np.nan)


def _metric_names(height_break: float, strata: list[float]) -> list[str]:
    return [
        "zmax",
        "zmean",
        "zsd",
        "zskew",
        "zkurt",
        "zentropy",
        "pzabovezmean",
        f"pzabove{fmt_break(height_break)}",
        *(f"zq{p}" for p in QUANTILE_PERCENTS),
        *(f"zpcum{k}" for k in range(1, 10)),
        *strata_columns(strata),
    ]


def tree_metrics(
    cell: ArrayLike,
    height_m: ArrayLike,
    dbh_m: ArrayLike,
    *,
    cell_area_m2: float | ArrayLike,
    cells: ArrayLike | None = None,
    dominant_per_ha: float = 100.0,
    dbh_measured: ArrayLike | None = None,
) -> pd.DataFrame:
    """Tree-based stand metrics per cell from a tree list (one entry per tree).

    ``dbh_m`` is measured or imputed (``dbh_measured`` tells which; all measured when not
    given). ``stems_ha`` (trees per ha); ``basal_area_m2_ha`` and ``qmd_cm`` over **all**
    trees, null with a reason when any tree of the cell has no DBH (a sum over some trees
    is no basal area); ``n_dbh_measured``, ``n_dbh_imputed`` and ``dbh_measured_share``
    tell how much rests on stem fits; ``mean_height_m`` and ``dominant_height_m``: the mean
    height of the k = max(1, round(dominant_per_ha * area_ha)) largest-DBH trees of the
    cell, or of the k tallest when any tree of the cell lacks a DBH. ``cells`` lists cells
    that were measured (they get a row with 0 stems and a ``null_reason`` when they hold
    no tree). ``cell_area_m2`` is one area for every cell, or one per entry of ``cells``
    (sorted unique keys, which must then be given).
    """
    keys = np.asarray(cell, dtype=np.int64)
    height = np.asarray(height_m, dtype=np.float64)
    dbh = np.asarray(dbh_m, dtype=np.float64)
    if not (keys.shape == height.shape == dbh.shape) or keys.ndim != 1:
        raise EnrichError("cell, height_m and dbh_m must be 1-D arrays of one length")
    areas = np.asarray(cell_area_m2, dtype=np.float64)
    if areas.ndim == 1:
        if cells is None or len(np.unique(np.asarray(cells))) != len(areas):
            raise EnrichError("one cell area per cell needs the cells (sorted unique keys)")
        area_of = pd.Series(areas, index=np.unique(np.asarray(cells, dtype=np.int64)))
        if not set(np.unique(keys)) <= set(area_of.index):
            raise EnrichError("trees in cells without an area")
    elif areas.ndim == 0:
        area_of = None
    else:
        raise EnrichError(f"cell areas must be a number or 1-D, got shape {areas.shape}")
    if (areas <= 0).any():
        raise EnrichError(f"cell area must be > 0, got {areas.min()}")
    has_dbh = np.isfinite(dbh)
    measured = has_dbh if dbh_measured is None else np.asarray(dbh_measured, dtype=bool)
    if measured.shape != dbh.shape:
        raise EnrichError("dbh_measured must have one entry per tree")
    measured = measured & has_dbh
    trees = pd.DataFrame({"cell": keys, "h": height, "dbh": dbh})
    trees["has_dbh"] = has_dbh
    trees["measured"] = measured
    trees["ba"] = np.where(has_dbh, math.pi * (dbh / 2.0) ** 2, 0.0)
    trees["dbh2"] = np.where(has_dbh, dbh**2, 0.0)
    grouped = trees.groupby("cell", sort=True)
    out = pd.DataFrame(
        {
            "n_trees": grouped.size(),
            "n_dbh": grouped["has_dbh"].sum(),
            "n_measured": grouped["measured"].sum(),
            "ba_sum": grouped["ba"].sum(),
            "dbh2_sum": grouped["dbh2"].sum(),
            "mean_height_m": grouped["h"].mean(),
        }
    )
    all_dbh = grouped["has_dbh"].all()
    rank_key = np.where(all_dbh.reindex(trees["cell"]).to_numpy(), trees["dbh"], trees["h"])
    trees["rank_key"] = rank_key
    index = out.index.to_numpy(dtype=np.int64)
    if cells is not None:
        index = np.union1d(index, np.asarray(cells, dtype=np.int64))
    if area_of is None:
        area_ha_of = pd.Series(float(areas) / 10_000.0, index=index)
    else:
        area_ha_of = area_of.reindex(index) / 10_000.0
    # the k = max(1, round(dominant_per_ha * area_ha)) largest (by DBH, else height) per cell
    k_dominant = np.maximum(1, np.round(dominant_per_ha * area_ha_of)).astype(np.int64)
    ranked = trees.sort_values(["cell", "rank_key"], ascending=[True, False], kind="stable")
    rank = ranked.groupby("cell").cumcount().to_numpy()
    top = ranked[rank < k_dominant.reindex(ranked["cell"]).to_numpy()]
    out["dominant_height_m"] = top.groupby("cell")["h"].mean()
    out["dominant_by"] = np.where(all_dbh.reindex(out.index), "dbh", "height")
    out = out.reindex(pd.Index(index, name="cell"))
    area_ha = area_ha_of.reindex(index).to_numpy(dtype=np.float64)
    n_trees = out["n_trees"].fillna(0).astype(np.int64)
    n_dbh = out["n_dbh"].fillna(0).astype(np.int64)
    n_measured = out["n_measured"].fillna(0).astype(np.int64)
    complete = (n_dbh == n_trees) & (n_trees > 0)
    result = pd.DataFrame(index=out.index)
    result["n_trees"] = n_trees
    result["n_dbh_measured"] = n_measured
    result["n_dbh_imputed"] = n_dbh - n_measured
    with np.errstate(invalid="ignore", divide="ignore"):
        result["dbh_measured_share"] = np.where(n_trees > 0, n_measured / n_trees, np.nan)
        result["stems_ha"] = n_trees / area_ha
        result["basal_area_m2_ha"] = np.where(complete, out["ba_sum"] / area_ha, np.nan)
        result["qmd_cm"] = np.where(
            complete, 100.0 * np.sqrt(out["dbh2_sum"] / np.maximum(n_dbh, 1)), np.nan
        )
    result.loc[n_trees == 0, "basal_area_m2_ha"] = 0.0
    result["mean_height_m"] = out["mean_height_m"]
    result["dominant_height_m"] = out["dominant_height_m"]
    result["dominant_by"] = pd.array(out["dominant_by"].where(n_trees > 0, None), dtype="string")
    reason = np.full(len(result), None, dtype=object)
    incomplete = ((n_dbh < n_trees) & (n_trees > 0)).to_numpy()
    for i in np.flatnonzero(incomplete):
        missing = int(n_trees.iat[i] - n_dbh.iat[i])
        reason[i] = f"{REASON_NO_DBH}: {missing} of {int(n_trees.iat[i])} trees"
    reason[(n_trees == 0).to_numpy()] = REASON_NO_TREES
    result["null_reason"] = pd.array(reason, dtype="string")
    return result
