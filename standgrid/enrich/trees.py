"""Individual trees: crowns from the canopy height model, stems (DBH) from a slice at 1.3 m.

Segmentation (points already height-normalised, i.e. ground removed by height):

1. a canopy height model (CHM) of the points above ``min_height`` at ``pixel_size``, lightly
   smoothed (3x3 Gaussian);
2. tree tops = CHM local maxima within a height-dependent circular window (lidR ``lmf``,
   default diameter ``2 + 0.05 h`` m, 2-6 m), plateaus merged;
3. crowns = marker-controlled watershed of the inverted CHM (scikit-image), a pixel kept
   only while it is at least ``crown_fraction`` of its tree's height;
4. points get the label of their pixel's crown (points above ``point_min_height``).

Each tree's position is its highest point; its ``tree_id`` is derived from that position at
0.1 m (:func:`tree_id_from_xy`), so the same tree found in two overlapping processing blocks
has the same id. Process blocks with a halo wider than a crown and keep a tree in the block
that contains its top (``keep_bounds``; half-open, like the stand cells).

DBH: points 1.3 +- 0.15 m above ground are linked into clusters (``link_distance``); each
cluster gets a RANSAC circle (3-point samples) refined by robust geometric least squares
(soft-L1 loss, iteratively reweighted Gauss-Newton) seeded by the algebraic (Kasa) fit, and is
rejected with a reason when it has too few inliers, a large residual, a short arc or an
implausible radius. Accepted stems are matched to the nearest tree top in whose crown
they stand (or within ``max_stem_offset``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from standgrid.enrich.ground import PointsLike, as_xyz
from standgrid.enrich.rasters import RasterGrid, chm
from standgrid.errors import EnrichError

ID_RESOLUTION_M = 0.1
#: Each canopy point also marks a disc of this radius in the CHM (lidR's ``subcircle``): a
#: pit-free surface, so sparse crowns do not split into several tops.
CHM_SUBCIRCLE_M = 0.2
#: With ``keep_bounds``, stems are fitted this far around the block's own area only (a stem
#: stands within its crown, and a tree is kept where its top is).
STEM_SEARCH_MARGIN_M = 3.0
_X_OFFSET = 1 << 30
_Y_OFFSET = 1 << 31

REASON_NO_STEM = "no stem points at 1.3 m near the tree"
TREE_COLUMNS = [
    "tree_id",
    "x",
    "y",
    "z_ground",
    "height_m",
    "crown_area_m2",
    "n_points",
    "dbh_m",
    "dbh_reason",
    "stem_x",
    "stem_y",
    "dbh_rmse_m",
    "dbh_n_points",
    "dbh_arc_deg",
    "owned",
    "crown",
]


def tree_id_from_xy(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.int64]:
    """Stable int64 id of a tree top: its x, y rounded to 0.1 m, packed as
    ``(round(x/0.1) + 2**30) << 32 | (round(y/0.1) + 2**31)`` (|x| < 1.07e7 m, |y| < 2.1e7 m)."""
    ix = np.round(np.asarray(x, dtype=np.float64) / ID_RESOLUTION_M).astype(np.int64) + _X_OFFSET
    iy = np.round(np.asarray(y, dtype=np.float64) / ID_RESOLUTION_M).astype(np.int64) + _Y_OFFSET
    if (ix < 0).any() or (ix >= 1 << 31).any() or (iy < 0).any() or (iy >= 1 << 32).any():
        raise EnrichError("tree position out of the range a tree id can encode")
    return (ix << 32) | iy


def xy_from_tree_id(tree_id: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The 0.1 m tree-top position encoded in ``tree_id``."""
    ids = np.asarray(tree_id, dtype=np.int64)
    ix = (ids >> 32) - _X_OFFSET
    iy = (ids & 0xFFFFFFFF) - _Y_OFFSET
    return (ix * ID_RESOLUTION_M).astype(np.float64), (iy * ID_RESOLUTION_M).astype(np.float64)


def default_window(height: NDArray[np.float64]) -> NDArray[np.float64]:
    """Local-maximum window diameter (m) for a tree of ``height`` m: 2 + 0.05 h, in [2, 6].

    Narrow enough that a tree 3-4 m from a taller neighbour keeps its own top (tuned on the
    simulator's stands and the synthetic crowns of the tests)."""
    return np.clip(2.0 + 0.05 * np.asarray(height, dtype=np.float64), 2.0, 6.0)


@dataclass(frozen=True)
class TreeSegmentation:
    """``table``: one row per tree (columns :data:`TREE_COLUMNS`; ``crown`` holds shapely
    polygons); ``labels``: per point, 1-based row of ``table`` (uint32, 0 = no tree)."""

    table: pd.DataFrame
    labels: NDArray[np.uint32]

    def owned(self) -> pd.DataFrame:
        """The trees whose top lies in the block (``keep_bounds``) of the segmentation."""
        return self.table[self.table["owned"].to_numpy(dtype=bool)].reset_index(drop=True)

    def point_tree_ids(self) -> NDArray[np.int64]:
        """Per point, the stable ``tree_id`` of its tree (0 = none)."""
        ids = np.concatenate([[0], self.table["tree_id"].to_numpy(dtype=np.int64)])
        return ids[self.labels]


def segment_trees(
    points: PointsLike,
    heights: NDArray[np.floating],
    *,
    pixel_size: float = 0.5,
    min_height: float = 2.0,
    window: Callable[[NDArray[np.float64]], NDArray[np.float64]] = default_window,
    crown_fraction: float = 0.3,
    point_min_height: float = 0.5,
    keep_bounds: tuple[float, float, float, float] | None = None,
    fit_dbh: bool = True,
    max_stem_offset: float = 1.0,
    stem_options: dict[str, Any] | None = None,
) -> TreeSegmentation:
    """Segment trees in height-normalised points (``heights`` = height above ground)."""
    from scipy import ndimage
    from skimage.measure import label as label_regions
    from skimage.segmentation import watershed

    xyz = as_xyz(points)
    h = np.asarray(heights, dtype=np.float64)
    if h.shape != (len(xyz),):
        raise EnrichError(f"{h.shape} heights for {len(xyz)} points")
    labels = np.zeros(len(xyz), dtype=np.uint32)
    finite = np.isfinite(h)
    canopy = finite & (h >= min_height)
    if not canopy.any():
        return TreeSegmentation(_empty_table(), labels)

    # 1. CHM on a lattice aligned to multiples of the pixel size (same pixels in every block)
    canopy_index = np.flatnonzero(canopy)
    canopy_xyz = xyz.take(canopy_index, axis=0)
    cx, cy = canopy_xyz[:, 0], canopy_xyz[:, 1]
    # with room for the sub-circles and the smoothing around the outermost points: a crown
    # at the data's edge is not clipped by a raster that ends where one block's points end
    margin = CHM_SUBCIRCLE_M + 2 * pixel_size
    grid = RasterGrid.covering(
        (cx.min() - margin, cy.min() - margin, cx.max() + margin, cy.max() + margin),
        origin=(0.0, 0.0),
        cell_size=pixel_size,
        pixel_size=pixel_size,
    )
    raw = chm(canopy_xyz, h[canopy_index], grid, fill_empty=True, subcircle=CHM_SUBCIRCLE_M)
    raw = np.nan_to_num(raw, nan=0.0).astype(np.float64)
    smooth = ndimage.gaussian_filter(raw, sigma=0.5, truncate=2.0)

    # 2. tree tops: local maxima within a height-dependent circular window
    radius_px = np.maximum(np.round(window(smooth) / 2.0 / pixel_size).astype(np.int64), 1)
    is_top = np.zeros(smooth.shape, dtype=bool)
    candidate = smooth >= min_height
    for r in np.unique(radius_px[candidate]):
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        disc = xx * xx + yy * yy <= r * r
        local_max = ndimage.maximum_filter(smooth, footprint=disc, mode="constant", cval=0.0)
        use = candidate & (radius_px == r)
        is_top |= use & (smooth >= local_max)
    markers = label_regions(is_top, connectivity=2)  # a plateau of equal maxima is one top

    # 3. crowns: watershed of the inverted CHM, cut where the canopy drops below the tree
    crowns = watershed(-smooth, markers, mask=smooth >= min_height)
    n_seeds = int(markers.max())
    if n_seeds == 0:
        return TreeSegmentation(_empty_table(), labels)
    seed_height = ndimage.maximum(raw, labels=crowns, index=np.arange(1, n_seeds + 1))
    seed_height = np.concatenate([[0.0], np.asarray(seed_height, dtype=np.float64)])
    crowns[raw < crown_fraction * seed_height[crowns]] = 0

    # 4. points by pixel; a tree is its canopy points (top = highest point)
    pixel, col = grid.pixel_of(xyz[:, 0], xyz[:, 1])
    outside = (pixel < 0) | (pixel >= grid.nrows) | (col < 0) | (col >= grid.ncols)
    pixel *= grid.ncols
    pixel += col
    # one lookup: the points outside the raster read the 0 appended after its pixels
    pixel[outside] = crowns.size
    del col, outside
    pixel_label = np.append(crowns.ravel(), 0).astype(np.int64)[pixel]
    in_tree = (pixel_label > 0) & canopy
    if not in_tree.any():
        return TreeSegmentation(_empty_table(), labels)
    idx = np.flatnonzero(in_tree)
    # highest point per crown; ties broken by x then y (deterministic across blocks): only
    # the points as high as their crown's highest are sorted
    crown_of, height_of = pixel_label[idx], h[idx]
    highest = np.full(n_seeds + 1, -np.inf)
    np.maximum.at(highest, crown_of, height_of)
    at_top = height_of >= highest[crown_of]
    idx = idx[at_top]
    order = idx[np.lexsort((xyz[idx, 1], xyz[idx, 0], crown_of[at_top]))]
    seg = pixel_label[order]
    first = np.concatenate([[True], seg[1:] != seg[:-1]])
    tops = order[first]
    seeds = seg[first]

    top_x, top_y = xyz[tops, 0], xyz[tops, 1]
    n_trees = len(tops)
    row_of_seed = np.zeros(n_seeds + 1, dtype=np.int64)
    row_of_seed[seeds] = np.arange(1, n_trees + 1)
    # crowns without a tree and the points outside any crown (pixel label 0) read 0
    point_rows = row_of_seed[pixel_label]
    point_rows[~(finite & (h >= point_min_height))] = 0
    labels = point_rows.astype(np.uint32)

    crown_pixels = np.bincount(crowns.ravel(), minlength=n_seeds + 1)[seeds]
    table = pd.DataFrame(
        {
            "tree_id": tree_id_from_xy(top_x, top_y),
            "x": top_x,
            "y": top_y,
            "z_ground": xyz[tops, 2] - h[tops],
            "height_m": h[tops],
            "crown_area_m2": crown_pixels * pixel_size**2,
            "n_points": np.bincount(point_rows, minlength=n_trees + 1)[1:],
        }
    )
    table["crown"] = _crown_polygons(crowns, seeds, grid)
    if keep_bounds is None:
        table["owned"] = True
    else:
        xmin, ymin, xmax, ymax = keep_bounds
        table["owned"] = (top_x >= xmin) & (top_x < xmax) & (top_y >= ymin) & (top_y < ymax)

    table["dbh_m"] = np.nan
    table["dbh_reason"] = pd.array([REASON_NO_STEM] * n_trees, dtype="string")
    table["stem_x"] = np.nan
    table["stem_y"] = np.nan
    table["dbh_rmse_m"] = np.nan
    table["dbh_n_points"] = 0
    table["dbh_arc_deg"] = np.nan
    if fit_dbh:
        within = None
        if keep_bounds is not None:  # only stems that can belong to the block's own trees
            x0, y0, x1, y1 = keep_bounds
            m = STEM_SEARCH_MARGIN_M
            within = (x0 - m, y0 - m, x1 + m, y1 + m)
        stems = fit_stems(xyz, h, within=within, **(stem_options or {}))
        _attach_stems(table, stems, crowns, row_of_seed, grid, max_stem_offset)
    return TreeSegmentation(table[TREE_COLUMNS], labels)


def _empty_table() -> pd.DataFrame:
    table = pd.DataFrame({name: pd.Series(dtype=float) for name in TREE_COLUMNS})
    table["tree_id"] = table["tree_id"].astype(np.int64)
    table["n_points"] = table["n_points"].astype(np.int64)
    table["dbh_n_points"] = table["dbh_n_points"].astype(np.int64)
    table["owned"] = table["owned"].astype(bool)
    table["dbh_reason"] = table["dbh_reason"].astype("string")
    table["crown"] = table["crown"].astype(object)
    return table


def _crown_polygons(
    crowns: NDArray[np.int64], seeds: NDArray[np.int64], grid: RasterGrid
) -> list[object]:
    """Outline of each crown's pixels (shapely (Multi)Polygon, in map coordinates)."""
    from rasterio import features
    from shapely.geometry import shape
    from shapely.ops import unary_union

    parts: dict[int, list[object]] = {}
    raster = crowns.astype(np.int32)
    for geometry, value in features.shapes(raster, mask=raster > 0, transform=grid.transform):
        parts.setdefault(int(value), []).append(shape(geometry))
    return [unary_union(parts[int(s)]) if int(s) in parts else None for s in seeds]


def _attach_stems(
    table: pd.DataFrame,
    stems: pd.DataFrame,
    crowns: NDArray[np.int64],
    row_of_seed: NDArray[np.int64],
    grid: RasterGrid,
    max_offset: float,
) -> None:
    """Give each tree the nearest accepted stem in its crown (or within ``max_offset`` of its
    top); one stem per tree. Trees without a stem keep NaN and the reason of the nearest
    rejected fit, if any."""
    if stems.empty:
        return
    from scipy.spatial import cKDTree

    sx, sy = stems["x"].to_numpy(), stems["y"].to_numpy()
    row, col = grid.pixel_of(sx, sy)
    inside = (row >= 0) & (row < grid.nrows) & (col >= 0) & (col < grid.ncols)
    stem_tree = np.zeros(len(stems), dtype=np.int64)  # 1-based table row of the crown
    stem_tree[inside] = row_of_seed[crowns[row[inside], col[inside]]]
    tx, ty = table["x"].to_numpy(), table["y"].to_numpy()
    # candidate (stem, tree) pairs: the crown a stem stands in, and tops within max_offset
    near = cKDTree(np.column_stack([tx, ty])).query_ball_point(
        np.column_stack([sx, sy]), max_offset
    )
    candidates = {(s, t) for s, trees in enumerate(near) for t in trees}
    candidates |= {(s, int(t) - 1) for s, t in enumerate(stem_tree) if t > 0}
    if not candidates:
        return
    pairs = np.array(sorted(candidates), dtype=np.int64)
    dist = np.hypot(sx[pairs[:, 0]] - tx[pairs[:, 1]], sy[pairs[:, 0]] - ty[pairs[:, 1]])
    pairs = pairs[np.argsort(dist, kind="stable")]
    ok = stems["ok"].to_numpy(dtype=bool)
    stem_reason = stems["reason"].to_numpy(dtype=object)
    stem_dbh = stems["dbh_m"].to_numpy(dtype=float)
    stem_rmse = stems["rmse_m"].to_numpy(dtype=float)
    stem_inliers = stems["n_inliers"].to_numpy(dtype=np.int64)
    stem_arc = stems["arc_deg"].to_numpy(dtype=float)
    used_stem, used_tree = set(), set()
    reasons = table["dbh_reason"].to_numpy(dtype=object, copy=True)
    dbh = table["dbh_m"].to_numpy(dtype=float, copy=True)
    stem_x = table["stem_x"].to_numpy(dtype=float, copy=True)
    stem_y = table["stem_y"].to_numpy(dtype=float, copy=True)
    rmse = table["dbh_rmse_m"].to_numpy(dtype=float, copy=True)
    n_used = table["dbh_n_points"].to_numpy(dtype=np.int64, copy=True)
    arc = table["dbh_arc_deg"].to_numpy(dtype=float, copy=True)
    for s, t in pairs.tolist():
        if s in used_stem or t in used_tree:
            continue
        if not ok[s]:
            if reasons[t] == REASON_NO_STEM:
                reasons[t] = f"stem fit rejected: {stem_reason[s]}"
            continue
        used_stem.add(s)
        used_tree.add(t)
        dbh[t] = stem_dbh[s]
        stem_x[t], stem_y[t] = sx[s], sy[s]
        rmse[t] = stem_rmse[s]
        n_used[t] = stem_inliers[s]
        arc[t] = stem_arc[s]
        reasons[t] = None
    table["dbh_m"] = dbh
    table["stem_x"], table["stem_y"], table["dbh_rmse_m"] = stem_x, stem_y, rmse
    table["dbh_n_points"], table["dbh_arc_deg"] = n_used, arc
    table["dbh_reason"] = pd.array(reasons, dtype="string")


# --- stems and circle fits ----------------------------------------------------------------


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
    mean = xy.mean(axis=0)
    local = xy - mean
    a = np.column_stack([local, np.ones(len(local))])
    b = (local**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    cx, cy = sol[0] / 2.0, sol[1] / 2.0
    r2 = sol[2] + cx * cx + cy * cy
    return float(cx + mean[0]), float(cy + mean[1]), float(np.sqrt(max(r2, 0.0)))


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
    """:func:`fit_circle` of each point set (each with the same ``seed``); the 3-point circles
    of all sets computed together, and their geometric refinements iterated together."""
    rng = np.random.default_rng(seed)
    seeded = rng.bit_generator.state
    means, locals_, scored, triples = [], [], [], []
    for xy in point_sets:
        pts = np.asarray(xy, dtype=np.float64)
        if len(pts) < 3:
            continue
        rng.bit_generator.state = seeded  # as a fresh default_rng(seed)
        mean = pts.mean(axis=0)
        local = pts - mean
        n = len(local)
        scored.append(
            local if n <= max_ransac_points else local[rng.choice(n, max_ransac_points, False)]
        )
        samples = rng.integers(0, n, size=(iterations, 3))
        distinct = (
            (samples[:, 0] != samples[:, 1])
            & (samples[:, 0] != samples[:, 2])
            & (samples[:, 1] != samples[:, 2])
        )
        triples.append(local[samples[distinct]])
        means.append(mean)
        locals_.append(local)
    if not locals_:
        return [None] * len(point_sets)
    centres, radii = _circles_through(np.concatenate(triples))
    cut = np.cumsum([len(t) for t in triples])[:-1]
    circles = [
        _msac_circle(local, score_pts, c, r, inlier_tolerance)
        for local, score_pts, c, r in zip(
            locals_, scored, np.split(centres, cut), np.split(radii, cut), strict=True
        )
    ]
    # geometric fits on the inliers of the RANSAC circles, started from their Kasa fits
    refine, inlier_sets, starts = [], [], []
    for k, (local, (cx, cy, r)) in enumerate(zip(locals_, circles, strict=True)):
        inliers = np.abs(np.hypot(local[:, 0] - cx, local[:, 1] - cy) - r) < inlier_tolerance
        if inliers.sum() >= 3:
            refine.append(k)
            inlier_sets.append(local[inliers])
            starts.append(kasa_circle(local[inliers]))
    if refine:
        refined = _geometric_circles(inlier_sets, np.array(starts), inlier_tolerance / 2.0)
        for k, (cx, cy, r) in zip(refine, refined.tolist(), strict=True):
            circles[k] = (cx, cy, r)
    fits = iter(
        _circle_fit(local, mean, circle, inlier_tolerance)
        for local, mean, circle in zip(locals_, means, circles, strict=True)
    )
    return [next(fits) if len(xy) >= 3 else None for xy in point_sets]


def _msac_circle(
    local: NDArray[np.float64],
    score_pts: NDArray[np.float64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    inlier_tolerance: float,
) -> tuple[float, float, float]:
    """The candidate circle (x, y, r) of least MSAC cost on ``score_pts``; the Kasa fit of
    ``local`` when none (of radius < 5 m) has 3 inliers."""
    good = np.isfinite(radii) & (radii < 5.0)
    if good.any():
        c, radius = centres[good], radii[good]
        # distances of every scored point to every candidate centre, |p - c|^2 expanded
        # (one matrix product; local coordinates of a stem keep it exact to ~1e-16 m^2),
        # then distance - radius, in place (-2 c exactly scales the product by -2)
        resid = (c * -2.0) @ score_pts.T
        resid += (score_pts**2).sum(axis=1)[None, :]
        resid += (c**2).sum(axis=1)[:, None]
        if resid.min() < 0.0:  # round-off where a point is at a centre
            np.maximum(resid, 0.0, out=resid)
        np.sqrt(resid, out=resid)
        resid -= radius[:, None]
        # MSAC: truncated squared residuals, so a tight circle beats a loose one that
        # happens to touch as many points; min(d^2, tol^2) is min(|d|, tol)^2 to the bit
        # (rounding a square is monotonic)
        cost = np.square(resid)
        np.minimum(cost, inlier_tolerance * inlier_tolerance, out=cost)
        k = int(np.argmin(cost.sum(axis=1)))
        if (np.abs(resid[k]) < inlier_tolerance).sum() >= 3:
            return float(c[k, 0]), float(c[k, 1]), float(radius[k])
    return kasa_circle(local)


def _circle_fit(
    local: NDArray[np.float64],
    mean: NDArray[np.float64],
    circle: tuple[float, float, float],
    inlier_tolerance: float,
) -> CircleFit:
    """``circle`` (in ``local`` coordinates) with its inliers' RMSE, count and arc."""
    cx, cy, r = circle
    dist = np.hypot(local[:, 0] - cx, local[:, 1] - cy) - r
    inliers = np.abs(dist) < inlier_tolerance
    n_in = int(inliers.sum())
    rmse = float(np.sqrt(np.mean(dist[inliers] ** 2))) if n_in else float("inf")
    angles = np.arctan2(local[inliers, 1] - cy, local[inliers, 0] - cx)
    sectors = np.floor((angles + np.pi) / (2 * np.pi) * 36).astype(np.int64) % 36
    n_sectors = int(np.count_nonzero(np.bincount(sectors, minlength=36)))
    return CircleFit(cx + mean[0], cy + mean[1], r, rmse, n_in, 10.0 * n_sectors)


def _geometric_circles(
    point_sets: Sequence[NDArray[np.float64]],
    starts: NDArray[np.float64],
    scale: float,
    iterations: int = 50,
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


def fit_stems(
    points: PointsLike,
    heights: NDArray[np.floating],
    *,
    breast_height: float = 1.3,
    slice_half_width: float = 0.15,
    link_distance: float = 0.2,
    min_points: int = 12,
    inlier_tolerance: float = 0.02,
    max_rmse: float = 0.02,
    min_arc_deg: float = 90.0,
    min_radius: float = 0.025,
    max_radius: float = 0.6,
    check_height: float = 2.3,
    min_check_points: int = 5,
    within: tuple[float, float, float, float] | None = None,
) -> pd.DataFrame:
    """Stems at breast height: one row per point cluster of the slice, with the circle fit.

    A fit is confirmed only when the stem continues: at least ``min_check_points`` points at
    ``check_height`` +- ``slice_half_width`` lie on the same circle (within
    max(3 cm, 30 % of the radius), allowing for taper). A shrub or a stump whose cross-section
    at 1.3 m looks like a stem has nothing there.

    Columns: x, y, dbh_m, rmse_m, n_points, n_inliers, arc_deg, ok, reason (why a fit was
    rejected). Clusters are connected components of the slice points within
    ``link_distance`` of each other. ``within``: only the points in these half-open bounds
    (xmin, ymin, xmax, ymax).
    """
    from scipy.spatial import cKDTree

    xyz = as_xyz(points)
    h = np.asarray(heights, dtype=np.float64)

    # the points of both slices (and between: a margin far wider than rounding), in bounds
    low = min(breast_height, check_height) - slice_half_width - 1e-6
    high = max(breast_height, check_height) + slice_half_width + 1e-6
    band = np.flatnonzero((h >= low) & (h <= high))  # NaN heights are in no slice
    if within is not None:
        x0, y0, x1, y1 = within
        x, y = xyz[:, 0][band], xyz[:, 1][band]
        band = band[(x >= x0) & (x < x1) & (y >= y0) & (y < y1)]

    def slice_at(height: float) -> NDArray[np.float64]:
        return xyz[band[np.abs(h[band] - height) <= slice_half_width], :2]

    xy = slice_at(breast_height)
    above = slice_at(check_height)
    columns = ["x", "y", "dbh_m", "rmse_m", "n_points", "n_inliers", "arc_deg", "ok", "reason"]
    if len(xy) < min_points:
        return pd.DataFrame({c: [] for c in columns})
    origin = xy.min(axis=0)
    local = xy - origin
    # built once and queried a few times: the unbalanced tree builds in half the time and
    # finds the same points
    above_tree = (
        cKDTree(above - origin, balanced_tree=False, compact_nodes=False) if len(above) else None
    )
    n_comp, comp = link_clusters(local, link_distance)
    sizes = np.bincount(comp, minlength=n_comp)
    rows = []
    order = np.argsort(comp, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    # RANSAC samples by index: each cluster's points in a canonical order, so a fit does not
    # depend on the order the tile stores them in; and counted from the cluster's own corner,
    # so its arithmetic does not depend on which other points the block holds
    clusters = [xy[order[bounds[c] : bounds[c + 1]]] for c in np.flatnonzero(sizes >= min_points)]
    clusters = [members[np.lexsort(members.T[::-1])] for members in clusters]
    corners = [members.min(axis=0) for members in clusters]
    clusters = [members - corner for members, corner in zip(clusters, corners, strict=True)]
    fits = fit_circles(clusters, inlier_tolerance=inlier_tolerance)
    for members, corner, fit in zip(clusters, corners, fits, strict=True):
        if fit is None:
            continue
        reason = None
        if fit.n_inliers < min_points:
            reason = f"{fit.n_inliers} inliers < {min_points}"
        elif not min_radius <= fit.radius <= max_radius:
            reason = f"radius {fit.radius:.3f} m outside [{min_radius}, {max_radius}]"
        elif fit.rmse > max_rmse:
            reason = f"residual {fit.rmse:.3f} m > {max_rmse}"
        elif fit.arc_deg < min_arc_deg:
            reason = f"arc {fit.arc_deg:.0f} deg < {min_arc_deg:.0f}"
        elif fit.n_inliers < 0.5 * len(members):
            reason = f"only {fit.n_inliers} of {len(members)} points on the circle"
        else:
            ring = max(0.03, 0.3 * fit.radius)
            on_stem = 0
            if above_tree is not None:
                centre = corner - origin + (fit.x, fit.y)
                near = above_tree.query_ball_point(centre, fit.radius + ring)
                d = np.hypot(*(above[near] - origin - centre).T) if near else []
                on_stem = int(np.sum(np.abs(np.asarray(d) - fit.radius) <= ring))
            if on_stem < min_check_points:
                reason = f"no stem at {check_height} m above the circle ({on_stem} points)"
        rows.append(
            {
                "x": fit.x + corner[0],
                "y": fit.y + corner[1],
                "dbh_m": 2.0 * fit.radius,
                "rmse_m": fit.rmse,
                "n_points": len(members),
                "n_inliers": fit.n_inliers,
                "arc_deg": fit.arc_deg,
                "ok": reason is None,
                "reason": reason,
            }
        )
    table = pd.DataFrame(rows, columns=columns)
    table["reason"] = table["reason"].astype("string")
    table["ok"] = table["ok"].astype(bool)
    return table


def link_clusters(xy: NDArray[np.float64], distance: float) -> tuple[int, NDArray[np.int64]]:
    """Connected components of the points linked when within ``distance`` (single linkage),
    numbered in the order of their first point: ``(count, label per point)``.

    Exact, without listing every pair (dense stem slices have ~100 neighbours per point):
    two points in squares of side ``distance / sqrt(5)`` that share an edge are within the
    distance, so the components of the occupied squares' edge graph are parts of clusters;
    any two of those whose points come within the distance of each other are then merged.
    """
    import shapely
    from scipy.spatial import cKDTree

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
    # parts that come within the distance of each other
    order = np.argsort(comp, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(comp[order]) != 0])
    lo = np.minimum.reduceat(xy[order], starts) - distance
    hi = np.maximum.reduceat(xy[order], starts) + distance
    boxes = shapely.box(lo[:, 0], lo[:, 1], hi[:, 0], hi[:, 1])
    a, b = shapely.STRtree(boxes).query(boxes, predicate="intersects")
    members = np.split(order, starts[1:])
    touching = []
    for i, j in zip(a[a < b], b[a < b], strict=True):
        d, _ = cKDTree(xy[members[j]]).query(xy[members[i]], distance_upper_bound=distance)
        if (d <= distance).any():
            touching.append((i, j))
    pairs = np.array(touching, dtype=np.int64).reshape(-1, 2)
    count, merged = _components(len(starts), pairs[:, 0], pairs[:, 1])
    comp = merged[comp]
    # number the clusters in the order of their first point
    first = np.full(count, n)
    np.minimum.at(first, comp, np.arange(n))
    rank = np.empty(count, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(count)
    return count, rank[comp]


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
