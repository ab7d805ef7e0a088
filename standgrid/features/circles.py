"""Circle fits to stem cross-sections, and the single-linkage clusters they are fitted to.

A circle is fitted robustly: RANSAC over 3-point circles scored by MSAC (truncated squared
residuals), then geometric least squares with a soft-L1 loss on the inliers of the best
circle, started from their algebraic (Kasa) fit; many point sets are fitted at once
(:func:`fit_circles`), so a slice's clusters cost one batch of array operations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class CircleFit:
    """A fitted stem cross-section: centre, radius, inlier RMSE, inliers, arc covered."""

    x: float
    y: float
    radius: float
    rmse: float
    n_inliers: int
    arc_deg: float


def kasa_circle(xy: NDArray[np.float64]) -> tuple[float, float, float]:
    """Algebraic least-squares circle (Kasa): centre x, y and radius."""
    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    cx, cy, r = kasa_circles(pts, np.zeros(len(pts), dtype=np.int64), 1)[0]
    return float(cx), float(cy), float(r)


def fit_circle(
    xy: NDArray[np.float64],
    *,
    inlier_tolerance: float = 0.02,
    iterations: int = 300,
    seed: int = 0,
    max_ransac_points: int = 1500,
) -> CircleFit | None:
    """Robust circle: RANSAC over 3-point circles scored by MSAC (truncated squared residual),
    then geometric least squares (soft-L1) on the inliers of the best circle, started from
    their algebraic fit. ``None`` when fewer than 3 points."""
    return fit_circles(
        [xy],
        inlier_tolerance=inlier_tolerance,
        iterations=iterations,
        seed=seed,
        max_ransac_points=max_ransac_points,
    )[0]


def fit_circles(
    point_sets: Sequence[NDArray[np.float64]],
    *,
    inlier_tolerance: float = 0.02,
    iterations: int = 300,
    seed: int = 0,
    max_ransac_points: int = 1500,
) -> list[CircleFit | None]:
    """:func:`fit_circle` of each point set, all sets at once (:func:`fit_packed`). None for
    a set of fewer than 3 points or without a circle (all on one spot)."""
    sets = [np.asarray(xy, dtype=np.float64).reshape(-1, 2) for xy in point_sets]
    fitted = [k for k, xy in enumerate(sets) if len(xy) >= 3]
    out: list[CircleFit | None] = [None] * len(sets)
    if not fitted:
        return out
    fits = fit_packed(
        np.concatenate([sets[k] for k in fitted]),
        np.array([len(sets[k]) for k in fitted]),
        inlier_tolerance=inlier_tolerance,
        iterations=iterations,
        seed=seed,
        max_ransac_points=max_ransac_points,
    )
    for j, k in enumerate(fitted):
        if np.isfinite(fits.radius[j]):
            out[k] = CircleFit(
                float(fits.x[j]),
                float(fits.y[j]),
                float(fits.radius[j]),
                float(fits.rmse[j]),
                int(fits.n_inliers[j]),
                float(fits.arc_deg[j]),
            )
    return out


@dataclass(frozen=True)
class CircleFits:
    """Circle fits of many point sets, one entry per set (:class:`CircleFit`'s fields as
    arrays; radius NaN where a set has no circle)."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    radius: NDArray[np.float64]
    rmse: NDArray[np.float64]
    n_inliers: NDArray[np.int64]
    arc_deg: NDArray[np.float64]


def fit_packed(
    points: NDArray[np.float64],
    sizes: NDArray[np.int64],
    *,
    inlier_tolerance: float = 0.02,
    iterations: int = 300,
    seed: int = 0,
    max_ransac_points: int = 1500,
) -> CircleFits:
    """Circles of point sets laid one after another in ``points`` (``sizes`` each, >= 3),
    all at once: array operations over the sets, no loop over them. Each set's fit depends
    on its own points alone: its RANSAC samples are the same uniform draws (``seed``)
    scaled to its size, and its candidate circles are scored on at most
    ``max_ransac_points`` of its points, evenly strided."""
    sizes = np.asarray(sizes, dtype=np.int64)
    n = len(sizes)
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    pts = np.asarray(points, dtype=np.float64)
    owner = np.repeat(np.arange(n), sizes)
    means = np.add.reduceat(pts, first, axis=0) / sizes[:, None]
    local = pts - means[owner]

    # RANSAC: 3-point circles from the same uniform draws in every set
    draws = np.random.default_rng(seed).random((iterations, 3))
    picks = np.floor(draws[None, :, :] * sizes[:, None, None]).astype(np.int64)
    distinct = (picks[..., 0] != picks[..., 1]) & (picks[..., 0] != picks[..., 2])
    distinct &= picks[..., 1] != picks[..., 2]
    centres, radii = _circles_through(local[first[:, None, None] + picks].reshape(-1, 3, 2))
    centres = centres.reshape(n, iterations, 2)
    radii = radii.reshape(n, iterations)
    radii[~distinct | ~np.isfinite(radii) | (radii >= 5.0)] = np.nan
    best = _msac(local, sizes, first, centres, radii, inlier_tolerance, max_ransac_points)

    # geometric fits on the inliers of the best circles, started from their algebraic fits
    circle = best[owner]
    dist = np.hypot(local[:, 0] - circle[:, 0], local[:, 1] - circle[:, 1]) - circle[:, 2]
    inlier = np.abs(dist) < inlier_tolerance
    counts = np.bincount(owner[inlier], minlength=n)
    refine = counts >= 3
    if refine.any():
        keep = inlier & refine[owner]
        start = kasa_circles(local[keep], owner[keep], n)[refine]
        inlier_sets = np.split(local[keep], np.cumsum(counts[refine])[:-1])
        best[refine] = _geometric_circles(inlier_sets, start, inlier_tolerance / 2.0)

    # each fit's inliers, RMSE and arc
    circle = best[owner]
    dx, dy = local[:, 0] - circle[:, 0], local[:, 1] - circle[:, 1]
    dist = np.hypot(dx, dy) - circle[:, 2]
    inlier = np.abs(dist) < inlier_tolerance
    n_in = np.bincount(owner[inlier], minlength=n)
    sq = np.bincount(owner[inlier], dist[inlier] ** 2, minlength=n)
    rmse = np.full(n, np.inf)
    rmse[n_in > 0] = np.sqrt(sq[n_in > 0] / n_in[n_in > 0])
    angles = np.arctan2(dy[inlier], dx[inlier])
    sectors = np.floor((angles + np.pi) / (2 * np.pi) * 36).astype(np.int64) % 36
    seen = np.unique(owner[inlier] * 36 + sectors)
    arc = 10.0 * np.bincount(seen // 36, minlength=n).astype(np.float64)
    bad = ~np.isfinite(best).all(axis=1)  # degenerate: all points on one spot or one line
    best[bad] = np.nan
    return CircleFits(
        best[:, 0] + means[:, 0], best[:, 1] + means[:, 1], best[:, 2], rmse, n_in, arc
    )


def kasa_circles(
    xy: NDArray[np.float64], owner: NDArray[np.int64], n_sets: int
) -> NDArray[np.float64]:
    """Algebraic (Kasa) circles (x, y, r per row) of the points of each set (``owner``:
    0..n_sets-1), all at once: the least-squares ``x^2 + y^2 = a x + b y + c`` of each set
    in coordinates centred on its mean (NaN for a set of fewer than 3 points)."""
    count = np.bincount(owner, minlength=n_sets).astype(np.float64)
    mean = (
        np.column_stack([np.bincount(owner, xy[:, i], minlength=n_sets) for i in range(2)])
        / np.maximum(count, 1.0)[:, None]
    )
    u, v = (xy - mean[owner]).T
    w = u * u + v * v

    def total(values: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(np.bincount(owner, values, minlength=n_sets), dtype=np.float64)

    suu, suv, svv, su, sv = total(u * u), total(u * v), total(v * v), total(u), total(v)
    normal = np.stack(
        [np.stack([suu, suv, su], -1), np.stack([suv, svv, sv], -1), np.stack([su, sv, count], -1)],
        1,
    )
    rhs = np.stack([total(u * w), total(v * w), total(w)], -1)
    small = count < 3
    normal[small] = np.eye(3)  # solvable placeholders, answered NaN below
    sol, solved = _solve_each(normal, rhs)
    cx, cy = sol[:, 0] / 2.0, sol[:, 1] / 2.0
    r = np.sqrt(np.maximum(sol[:, 2] + cx * cx + cy * cy, 0.0))
    out = np.column_stack([cx + mean[:, 0], cy + mean[:, 1], r])
    out[~solved | small] = np.nan
    return out


#: Candidate residuals scored at once by the MSAC step (float64 values: memory).
MSAC_BATCH = 2_000_000


def _msac(
    local: NDArray[np.float64],
    sizes: NDArray[np.int64],
    first: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    tolerance: float,
    max_points: int,
) -> NDArray[np.float64]:
    """Per set, the candidate circle (x, y, r) of least MSAC cost (truncated squared
    residuals: a tight circle beats a loose one touching as many points) on up to
    ``max_points`` of its points, evenly strided; its Kasa fit when no candidate has 3
    inliers."""
    n_sets, n_cand = radii.shape
    scored = np.minimum(sizes, max_points)
    ends = np.cumsum(scored)
    starts = ends - scored
    set_of = np.repeat(np.arange(n_sets), scored)
    step = np.arange(len(set_of)) - starts[set_of]
    index = first[set_of] + (step * sizes[set_of]) // scored[set_of]
    best = np.full((n_sets, 3), np.nan)
    tol2 = tolerance * tolerance
    lo = 0
    while lo < n_sets:
        hi = int(np.searchsorted(ends, starts[lo] + max(MSAC_BATCH // n_cand, 1), side="right"))
        hi = min(max(hi, lo + 1), n_sets)
        rows = slice(starts[lo], ends[hi - 1])
        p = local[index[rows]]
        owner = set_of[rows] - lo
        # |p - c|^2 - r, candidates of the point's own set, in place
        resid = np.square(p[:, :1] - centres[lo:hi, :, 0][owner])
        resid += np.square(p[:, 1:] - centres[lo:hi, :, 1][owner])
        np.sqrt(resid, out=resid)
        resid -= radii[lo:hi][owner]
        cost = np.minimum(resid * resid, tol2)
        cost[np.isnan(cost)] = np.inf  # no candidate there
        at = starts[lo:hi] - starts[lo]
        total = np.add.reduceat(cost, at, axis=0)  # (sets, candidates)
        k = np.argmin(total, axis=1)
        picked = resid[np.arange(len(owner)), k[owner]]
        hits = np.bincount(owner[np.abs(picked) < tolerance], minlength=hi - lo)
        chosen = np.flatnonzero((hits >= 3) & np.isfinite(total[np.arange(hi - lo), k]))
        best[lo + chosen, :2] = centres[lo + chosen, k[chosen]]
        best[lo + chosen, 2] = radii[lo + chosen, k[chosen]]
        lo = hi
    missing = np.flatnonzero(np.isnan(best[:, 2]))
    if len(missing):  # no candidate with 3 inliers: the algebraic fit of all the points
        every = kasa_circles(local, np.repeat(np.arange(n_sets), sizes), n_sets)
        best[missing] = every[missing]
    return best


def _geometric_circles(
    point_sets: Sequence[NDArray[np.float64]],
    starts: NDArray[np.float64],
    scale: float,
    iterations: int = 20,
) -> NDArray[np.float64]:
    """Geometric circle fits (x, y, r per row) with the soft-L1 loss of scale ``scale`` (the
    minimiser of ``sum(2 * scale^2 * (sqrt(1 + (d_i / scale)^2) - 1))``, d_i = distance to
    the circle, as ``scipy.optimize.least_squares(loss="soft_l1")``), by iteratively
    reweighted Gauss-Newton from ``starts``, all point sets at once: a set stops when its
    step is below 1e-10 (or its normal equations are singular)."""
    p = np.array(starts, dtype=np.float64).reshape(-1, 3)
    xy = np.concatenate(point_sets)
    x, y = xy[:, 0], xy[:, 1]
    active = np.arange(len(p))  # the sets still iterating, their points one after the other
    sizes = np.array([len(s) for s in point_sets])
    for _ in range(iterations):
        if not len(active):
            break
        first = np.concatenate([[0], np.cumsum(sizes[:-1])])
        q = np.repeat(p[active], sizes, axis=0)
        dx, dy = x - q[:, 0], y - q[:, 1]
        dist = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-12)
        resid = dist - q[:, 2]
        weight = 1.0 / np.sqrt(1.0 + (resid / scale) ** 2)
        # Jacobian rows (-ux, -uy, -1): the 3 x 3 normal equations by sums per set
        ux, uy = dx / dist, dy / dist
        wx, wy = weight * ux, weight * uy
        terms = (wx * ux, wx * uy, wx, wy * uy, wy, weight, wx * resid, wy * resid, weight * resid)
        sums = np.stack([np.add.reduceat(t, first) for t in terms], -1)
        normal = sums[:, [[0, 1, 2], [1, 3, 4], [2, 4, 5]]]  # (sets, 3, 3)
        step, solved = _solve_each(normal, sums[:, 6:])
        p[active[solved]] += step[solved]
        done = ~solved | (np.abs(step).max(axis=1) < 1e-10)
        if done.any():
            kept = np.repeat(~done, sizes)
            x, y = x[kept], y[kept]
            active, sizes = active[~done], sizes[~done]
    p[:, 2] = np.abs(p[:, 2])
    return p


def _solve_each(
    a: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Solutions of the stacked systems ``a[i] x = b[i]`` and which were solvable (not
    singular; the others' solution is 0)."""
    step = np.zeros(b.shape)
    try:
        step[:] = np.linalg.solve(a, b[..., None])[..., 0]
        return step, np.ones(len(a), dtype=bool)
    except np.linalg.LinAlgError:
        solved = np.zeros(len(a), dtype=bool)
        for i in range(len(a)):
            try:
                step[i] = np.linalg.solve(a[i], b[i])
                solved[i] = True
            except np.linalg.LinAlgError:
                pass
        return step, solved


def _circles_through(tri: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Circumcircles of (K, 3, 2) point triples: centres (K, 2), radii (K,) (inf if collinear)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    d = 2.0 * (
        a[:, 0] * (b[:, 1] - c[:, 1])
        + b[:, 0] * (c[:, 1] - a[:, 1])
        + c[:, 0] * (a[:, 1] - b[:, 1])
    )
    sa, sb, sc = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (sa * (b[:, 1] - c[:, 1]) + sb * (c[:, 1] - a[:, 1]) + sc * (a[:, 1] - b[:, 1])) / d
        uy = (sa * (c[:, 0] - b[:, 0]) + sb * (a[:, 0] - c[:, 0]) + sc * (b[:, 0] - a[:, 0])) / d
        r = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
    r[~np.isfinite(r)] = np.inf
    return np.column_stack([ux, uy]), r


def link_clusters(xy: NDArray[np.float64], distance: float) -> tuple[int, NDArray[np.int64]]:
    """Connected components of the points linked when within ``distance`` (single linkage),
    numbered in the order of their first point: ``(count, label per point)``.

    Exact, without listing every pair (dense stem slices have ~100 neighbours per point):
    two points in squares of side ``distance / sqrt(5)`` that share an edge are within the
    distance, so the components of the occupied squares' edge graph are parts of clusters;
    any two of those whose points come within the distance of each other are then merged.
    """
    n = len(xy)
    if n == 0:
        return 0, np.zeros(0, dtype=np.int64)
    if distance > 0:
        side = distance / np.sqrt(5.0) * (1.0 - 1e-9)  # the margin covers rounding
        square = np.floor(xy / side).astype(np.int64)
        square -= square.min(axis=0)
        stride = int(square[:, 1].max()) + 2  # key of the square (i, j): i * stride + j
        squares, of_point = np.unique(square[:, 0] * stride + square[:, 1], return_inverse=True)
        rows, cols = [], []
        for step in (stride, 1):  # the next square in x, in y
            pos = np.minimum(np.searchsorted(squares, squares + step), len(squares) - 1)
            hit = squares[pos] == squares + step
            rows.append(np.flatnonzero(hit))
            cols.append(pos[hit])
        _, part = _components(len(squares), np.concatenate(rows), np.concatenate(cols))
        comp = part[of_point.ravel()]
    else:
        comp = np.arange(n)
    # parts that come within the distance of each other: two such points both lie in
    # squares with a square of another part at most 3 squares away (distance / side is
    # sqrt(5)); only those frontier points are paired, in one k-d tree
    pairs = _touching_parts(xy, comp, distance)
    count, merged = _components(int(comp.max()) + 1, pairs[:, 0], pairs[:, 1])
    comp = merged[comp]
    # number the clusters in the order of their first point
    first = np.full(count, n)
    np.minimum.at(first, comp, np.arange(n))
    rank = np.empty(count, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(count)
    return count, rank[comp]


def _touching_parts(
    xy: NDArray[np.float64], comp: NDArray[np.int64], distance: float
) -> NDArray[np.int64]:
    """Pairs of parts (labels ``comp``) with points within ``distance`` of each other."""
    from scipy.spatial import cKDTree

    if distance <= 0 or len(xy) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    side = distance / np.sqrt(5.0) * (1.0 - 1e-9)
    reach = 3  # squares: ceil(sqrt(5)) covers a distance from any point of a square
    square = np.floor(xy / side).astype(np.int64)
    square -= square.min(axis=0) - reach  # j +- reach stays within its row
    stride = int(square[:, 1].max()) + reach + 1
    keys = square[:, 0] * stride + square[:, 1]
    squares, first, of_point = np.unique(keys, return_index=True, return_inverse=True)
    of_point = of_point.ravel()
    part = comp[first]  # a square's points are all of one part (edge-linked squares)
    frontier = np.zeros(len(squares), dtype=bool)
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            if di == 0 and dj == 0:
                continue
            other = squares + di * stride + dj
            pos = np.minimum(np.searchsorted(squares, other), len(squares) - 1)
            frontier |= (squares[pos] == other) & (part[pos] != part)
    rows = np.flatnonzero(frontier[of_point])
    if len(rows) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    found = cKDTree(xy[rows]).query_pairs(distance, output_type="ndarray")
    a, b = comp[rows[found[:, 0]]], comp[rows[found[:, 1]]]
    apart = a != b
    return np.unique(np.column_stack([a[apart], b[apart]]), axis=0)


def _components(
    n: int, rows: NDArray[np.int64], cols: NDArray[np.int64]
) -> tuple[int, NDArray[np.int64]]:
    """Connected components of the undirected graph on ``n`` nodes with edges ``rows``-``cols``,
    numbered in the order of their first node."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count, comp = connected_components(
        coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False
    )
    return int(count), comp.astype(np.int64)
