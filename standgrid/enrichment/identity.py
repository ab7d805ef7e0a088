"""One identity per tree across epochs: trees of two surveys paired one to one, and each
epoch's trees given the ``tree_uid`` of the same tree in the catalog's other epochs.

Pairing rule (shared with ``standgrid compare``, :mod:`standgrid.comparison.trees`): a tree of
the earlier epoch and one of the later are candidates within ``max_distance`` (2 m) of each
other that did not lose more than ``max_height_loss`` (30 %) of their height; the cost of a
pair is ``(d / max_distance)^2 + (loss / max_height_loss)^2 + (gain / max_height_gain)^2``,
leaving a tree unpaired costs :data:`UNMATCHED_COST`, and the assignment of least total cost
is solved exactly (``scipy.optimize.linear_sum_assignment``) per connected group of
candidates. Trees are compared where they stand: a stem seen in both surveys is the same
stem to a few centimetres, whatever its crown did.

Tree uids (:func:`assign_tree_uids`): an epoch's trees are paired with the trees of the
other enriched epochs, the nearest in time first (a tree missed by one survey is found in
the next); a paired tree takes the other's ``tree_uid``, the others get new ones (one more
than the largest in the catalog). So an epoch's tree list is a re-measurement of the trees
of the others: the panel growth models are calibrated on.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping

import numpy as np
import pandas as pd

UNMATCHED_COST = 1.0
#: Components with more trees than this are solved sparse (dense needs (n+m)^2 floats).
DENSE_LIMIT = 400
MAX_DISTANCE_M = 2.0
MAX_HEIGHT_LOSS = 0.30
MAX_HEIGHT_GAIN = 1.0


def candidate_pairs(
    xy_a: np.ndarray, xy_b: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of ``a`` and ``b`` within ``max_distance`` of each other, and their distance."""
    from scipy.spatial import cKDTree

    if not len(xy_a) or not len(xy_b):
        empty = np.empty(0, np.int64)
        return empty, empty, np.empty(0)
    neighbours = cKDTree(xy_b).query_ball_point(xy_a, r=max_distance)
    counts = np.fromiter((len(n) for n in neighbours), np.int64, len(neighbours))
    rows = np.repeat(np.arange(len(xy_a), dtype=np.int64), counts)
    cols = np.fromiter((j for n in neighbours for j in n), np.int64, int(counts.sum()))
    distance = np.hypot(*(xy_b[cols] - xy_a[rows]).T) if len(rows) else np.empty(0)
    return rows, cols, distance


def pair_trees(
    xy_a: np.ndarray,
    h_a: np.ndarray,
    xy_b: np.ndarray,
    h_b: np.ndarray,
    *,
    max_distance: float = MAX_DISTANCE_M,
    max_height_loss: float = MAX_HEIGHT_LOSS,
    max_height_gain: float = MAX_HEIGHT_GAIN,
) -> tuple[np.ndarray, np.ndarray]:
    """Trees of an earlier (``a``) and a later (``b``) survey paired one to one (module
    doc): the paired rows of each."""
    rows, cols, distance = candidate_pairs(xy_a, xy_b, max_distance)
    cost, allowed = pair_costs(
        h_a[rows],
        h_b[cols],
        distance,
        max_distance=max_distance,
        max_height_loss=max_height_loss,
        max_height_gain=max_height_gain,
    )
    return solve_pairs(len(xy_a), len(xy_b), rows[allowed], cols[allowed], cost[allowed])


def pair_costs(
    h_from: np.ndarray,
    h_to: np.ndarray,
    distance: np.ndarray,
    *,
    max_distance: float,
    max_height_loss: float,
    max_height_gain: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cost of each candidate pair and whether the pair is allowed (see module docstring)."""
    base = np.where(h_from > 0, h_from, np.nan)
    relative = (h_to - h_from) / base
    relative = np.nan_to_num(relative, nan=0.0)
    loss = np.maximum(0.0, -relative)
    gain = np.maximum(0.0, relative)
    allowed = loss <= max_height_loss
    cost = (
        (distance / max_distance) ** 2
        + (loss / max_height_loss) ** 2
        + (gain / max_height_gain) ** 2
    )
    return cost, allowed


def _solve_dense(
    nr: int, nc: int, r: np.ndarray, c: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One component, dense square augmentation solved by ``linear_sum_assignment``."""
    from scipy.optimize import linear_sum_assignment

    forbidden = 1e6  # larger than any total of allowed costs in one component
    matrix = np.full((nr + nc, nc + nr), forbidden)
    matrix[r, c] = w
    matrix[np.arange(nr), nc + np.arange(nr)] = UNMATCHED_COST  # from tree unmatched
    matrix[nr + np.arange(nc), np.arange(nc)] = UNMATCHED_COST  # to tree unmatched
    matrix[nr:, nc:] = 0.0
    row_ind, col_ind = linear_sum_assignment(matrix)
    real = (row_ind < nr) & (col_ind < nc) & (matrix[row_ind, col_ind] < forbidden)
    return row_ind[real], col_ind[real]


def _solve_sparse(
    nr: int, nc: int, r: np.ndarray, c: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One large component: the same augmentation kept sparse (memory ~ candidate pairs).

    Rows: from trees, then one dummy per to tree; columns: to trees, then one dummy per
    from tree. Edges: candidate pairs (cost w), tree -> own dummy (unmatched cost), and
    dummy -> dummy along each candidate pair reversed (cost 0). Every edge gets the same
    +1 offset (a full matching has nr + nc edges, so the optimum is unchanged) because
    the sparse solver cannot store zero weights.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import min_weight_full_bipartite_matching

    size = nr + nc
    rows = np.concatenate([r, np.arange(nr), nr + np.arange(nc), nr + c])
    cols = np.concatenate([c, nc + np.arange(nr), np.arange(nc), nc + r])
    weights = 1.0 + np.concatenate(
        [w, np.full(nr, UNMATCHED_COST), np.full(nc, UNMATCHED_COST), np.zeros(len(r))]
    )
    graph = coo_matrix((weights, (rows, cols)), shape=(size, size)).tocsr()
    row_ind, col_ind = min_weight_full_bipartite_matching(graph)
    real = (row_ind < nr) & (col_ind < nc)
    return row_ind[real], col_ind[real]


def solve_pairs(
    n_from: int, n_to: int, rows: np.ndarray, cols: np.ndarray, cost: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Optimal partial one-to-one assignment over sparse candidate pairs.

    Solved per connected component of the candidate graph, each with the square
    "unmatched" augmentation (dummy rows/columns at :data:`UNMATCHED_COST`): dense for
    components up to :data:`DENSE_LIMIT` trees, sparse above (a very dense stand can link
    thousands of trees into one component).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(rows) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    size = n_from + n_to
    graph = coo_matrix((np.ones(len(rows)), (rows, cols + n_from)), shape=(size, size)).tocsr()
    _, labels = connected_components(graph, directed=False)
    pair_component = labels[rows]
    order = np.argsort(pair_component, kind="stable")
    splits = np.flatnonzero(np.diff(pair_component[order])) + 1
    matched_from: list[np.ndarray] = []
    matched_to: list[np.ndarray] = []
    for group in np.split(order, splits):
        r, c, w = rows[group], cols[group], cost[group]
        if len(group) == 1:  # lone pair: match it when cheaper than two unmatched trees
            keep = w < 2 * UNMATCHED_COST
            matched_from.append(r[keep])
            matched_to.append(c[keep])
            continue
        ur, r_local = np.unique(r, return_inverse=True)
        uc, c_local = np.unique(c, return_inverse=True)
        solve = _solve_dense if len(ur) + len(uc) <= DENSE_LIMIT else _solve_sparse
        i, j = solve(len(ur), len(uc), r_local, c_local, w)
        matched_from.append(ur[i])
        matched_to.append(uc[j])
    return np.concatenate(matched_from), np.concatenate(matched_to)


def _when(date: dt.date | str) -> float:
    """An epoch's date in days (an unreadable one: -inf, far from every other)."""
    try:
        stamp = pd.Timestamp(date)
    except (ValueError, TypeError):
        return -np.inf
    if pd.isna(stamp):
        return -np.inf
    return float(stamp.value) / 86_400e9


def _gap(a: float, b: float) -> float:
    """Days between two epochs; infinite when either date is unknown."""
    return abs(a - b) if np.isfinite(a) and np.isfinite(b) else np.inf


def assign_tree_uids(
    epochs: Mapping[str, pd.DataFrame],
    dates: Mapping[str, dt.date | str],
    others: Mapping[str, pd.DataFrame],
) -> dict[str, np.ndarray]:
    """A ``tree_uid`` for every tree of ``epochs`` (tree tables with ``x``, ``y``,
    ``height_m``), in date order; ``others``: tree tables of the catalog's other epochs with
    their ``tree_uid``; ``dates``: every epoch's date (module doc)."""
    known = {e: t for e, t in others.items() if "tree_uid" in t.columns and len(t)}
    next_uid = 1 + max((int(t["tree_uid"].max()) for t in known.values()), default=0)
    when = {e: _when(d) for e, d in dates.items()}
    out: dict[str, np.ndarray] = {}
    for epoch in sorted(epochs, key=lambda e: (when[e], e)):
        trees = epochs[epoch]
        uid = np.zeros(len(trees), dtype=np.int64)
        xy = trees[["x", "y"]].to_numpy(dtype=np.float64)
        h = trees["height_m"].to_numpy(dtype=np.float64)
        by_nearness = sorted(known, key=lambda e: (_gap(when[e], when[epoch]), when[e], e))
        for other in by_nearness:
            ref = known[other]
            free = np.flatnonzero(uid == 0)
            unused = np.flatnonzero(~np.isin(ref["tree_uid"].to_numpy(np.int64), uid))
            if not len(free) or not len(unused):
                break
            ref_xy = ref[["x", "y"]].to_numpy(dtype=np.float64)[unused]
            ref_h = ref["height_m"].to_numpy(dtype=np.float64)[unused]
            if when[other] <= when[epoch]:
                i_ref, i_new = pair_trees(ref_xy, ref_h, xy[free], h[free])
            else:
                i_new, i_ref = pair_trees(xy[free], h[free], ref_xy, ref_h)
            uid[free[i_new]] = ref["tree_uid"].to_numpy(np.int64)[unused[i_ref]]
        new = np.flatnonzero(uid == 0)
        uid[new] = next_uid + np.arange(len(new))
        next_uid += len(new)
        out[epoch] = uid
        known[epoch] = trees.assign(tree_uid=uid)
    return out
