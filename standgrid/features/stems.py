"""Stems as vertical chains of circles: every stem seen under the canopy is a tree.

Height-normalised points are cut into thin horizontal slices (bands) from 0.7 m to 3.4 m
above ground, every 0.3 m, breast height (1.3 m) among them. In each band the points are
linked into clusters (single linkage), and each cluster of stem size gets a robust circle
(RANSAC, then soft-L1 least squares: :func:`standgrid.features.circles.fit_circles`),
accepted on its inliers, residual, arc and radius. Accepted circles of neighbouring bands
(up to two bands apart, a band hidden by a branch or a shrub) are linked when each is the
other's nearest one within a lean of ``max_lean_deg`` and a plausible change of radius, so
every circle has at most one link up and one down: the chains are stems. A chain of at
least ``min_circles`` circles is a stem: its axis is a least-squares line through the
centres (it follows the lean), its radius a least-squares taper line, and its DBH that
line at breast height, measured across the axis (a horizontal slice of a leaning stem is
an ellipse, whose fitted circle is larger by about ``(1 + 1 / cos lean) / 2``).

Ground robots scan stems from all sides at short range: understorey stems and dead snags
are found as well as overstorey stems. Airborne scans give few points on stems, and short
arcs: they yield few or no stems, and trees come from the canopy (:mod:`.trees`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from standgrid.features.circles import CircleFits, fit_packed, link_clusters

#: Columns of a stem table (one row per stem; positions at breast height, CRS metres).
STEM_COLUMNS = [
    "stem_x",
    "stem_y",
    "dbh_m",
    "dbh_se_m",
    "dbh_rmse_m",
    "dbh_n_points",
    "dbh_arc_deg",
    "lean_deg",
    "lean_azimuth_deg",
    "stem_low_m",
    "stem_high_m",
    "stem_circles",
    "axis_dx",
    "axis_dy",
    "radius_m",
    "taper",
]


@dataclass(frozen=True)
class StemOptions:
    """Parameters of :func:`find_stems` (documented in docs/METRICS.md, "Trees")."""

    breast_height: float = 1.3
    #: band centres: ``breast_height + band_step * k`` for k in ``-bands_below..bands_above``
    band_step: float = 0.3
    bands_below: int = 2
    bands_above: int = 7
    band_half_width: float = 0.1
    link_distance: float = 0.15
    min_points: int = 8
    inlier_tolerance: float = 0.02
    #: RANSAC samples per cluster, and the points each candidate circle is scored on (a
    #: stem's cluster is at least half on its circle: 60 samples miss it with p < 4e-4)
    ransac_iterations: int = 60
    ransac_points: int = 100
    max_rmse: float = 0.025
    min_arc_deg: float = 90.0
    min_radius: float = 0.025
    max_radius: float = 0.6
    #: circles a chain needs to be a stem, and the height between its lowest and highest
    min_circles: int = 2
    min_span: float = 0.5
    #: chains of one stem are joined across a gap of up to this (m)
    max_gap: float = 1.5
    max_lean_deg: float = 25.0
    #: the radius may change between linked circles by this share (plus 1.5 cm)
    max_radius_change: float = 0.3
    #: the radius line is fitted to the circles from this height up (above the butt swell)
    taper_from: float = 1.0
    #: a chain whose radius shrinks faster than this (m per m of height; the diameter by
    #: 8 cm per m) is no stem
    min_taper: float = -0.04

    def band_heights(self) -> NDArray[np.float64]:
        k = np.arange(-self.bands_below, self.bands_above + 1, dtype=np.float64)
        return np.asarray(self.breast_height + self.band_step * k, dtype=np.float64)


@dataclass(frozen=True)
class StemSet:
    """The stems of some points: ``table`` (:data:`STEM_COLUMNS`), and the fits at breast
    height that were rejected (``rejected``: x, y, reason), which explain a missing DBH."""

    table: pd.DataFrame
    rejected: pd.DataFrame

    def __len__(self) -> int:
        return len(self.table)


def empty_stems() -> StemSet:
    table = pd.DataFrame({c: pd.Series(dtype=float) for c in STEM_COLUMNS})
    for column in ("dbh_n_points", "stem_circles"):
        table[column] = table[column].astype(np.int64)
    rejected = pd.DataFrame(
        {"x": pd.Series(dtype=float), "y": pd.Series(dtype=float), "reason": []}
    )
    return StemSet(table, rejected)


def find_stems(
    xyz: NDArray[np.float64],
    heights: NDArray[np.float64],
    *,
    within: tuple[float, float, float, float] | None = None,
    options: StemOptions | None = None,
) -> StemSet:
    """Stems in height-normalised points (module doc). ``within``: only stems whose breast
    height centre lies in these half-open bounds (the points around them are used whole)."""
    o = options or StemOptions()
    centres = o.band_heights()
    hw = o.band_half_width
    h = np.asarray(heights, dtype=np.float64)
    band_rows = np.flatnonzero((h >= centres[0] - hw - 1e-6) & (h <= centres[-1] + hw + 1e-6))
    if within is not None:  # the bounds grown by a stem's width: clusters stay whole
        pad = 2 * o.max_radius + 4 * o.link_distance
        x0, y0, x1, y1 = within
        bx, by = xyz[band_rows, 0], xyz[band_rows, 1]
        inside = (bx >= x0 - pad) & (bx < x1 + pad) & (by >= y0 - pad) & (by < y1 + pad)
        band_rows = band_rows[inside]
    if len(band_rows) < o.min_points:
        return empty_stems()
    # each point's band (slices are thinner than their spacing: at most one)
    band = np.rint((h[band_rows] - centres[0]) / o.band_step).astype(np.int64)
    band = np.clip(band, 0, len(centres) - 1)
    keep = np.abs(h[band_rows] - centres[band]) <= hw
    band_rows, band = band_rows[keep], band[keep]
    if len(band_rows) < o.min_points:
        return empty_stems()

    # 1. clusters of every band at once (bands set far apart in x), in a canonical order:
    # a fit does not depend on the order of the points
    xy = xyz[band_rows, :2]
    origin = xy.min(axis=0)
    spread = float((xy.max(axis=0) - origin).max()) + 10.0
    _, comp = link_clusters(xy - origin + np.outer(band * spread, [1.0, 0.0]), o.link_distance)
    order = np.lexsort((xy[:, 1], xy[:, 0], comp))
    comp, xy, band = comp[order], xy[order], band[order]
    starts = np.flatnonzero(np.r_[True, comp[1:] != comp[:-1]])
    sizes = np.diff(np.r_[starts, len(comp)])
    lo = np.minimum.reduceat(xy, starts)
    hi = np.maximum.reduceat(xy, starts)
    # big enough, no wider than any stem (wider: a shrub, a crown, a wall of points)
    ok = (sizes >= o.min_points) & ((hi - lo) <= 2 * o.max_radius + 0.1).all(axis=1)
    if not ok.any():
        return empty_stems()
    member = np.repeat(ok, sizes)
    corner = lo[ok]
    sizes, cluster_band = sizes[ok], band[starts[ok]]
    local = xy[member] - np.repeat(corner, sizes, axis=0)  # each from its own corner

    # 2. circles, accepted or rejected with a reason
    fits = fit_packed(
        local,
        sizes,
        inlier_tolerance=o.inlier_tolerance,
        iterations=o.ransac_iterations,
        max_ransac_points=o.ransac_points,
    )
    cx, cy = fits.x + corner[:, 0], fits.y + corner[:, 1]
    accepted, rejected = [], []
    for k in np.flatnonzero(np.isfinite(fits.radius)).tolist():
        reason = _rejection(fits, k, int(sizes[k]), o)
        if reason is None:
            accepted.append(
                (
                    cluster_band[k],
                    cx[k],
                    cy[k],
                    fits.radius[k],
                    fits.rmse[k],
                    fits.n_inliers[k],
                    fits.arc_deg[k],
                )
            )
        elif abs(centres[cluster_band[k]] - o.breast_height) < 1e-9:
            rejected.append((cx[k], cy[k], reason))
    rejected_table = pd.DataFrame(rejected, columns=["x", "y", "reason"])
    if within is not None and len(rejected_table):
        rejected_table = rejected_table[
            _inside(rejected_table["x"].to_numpy(), rejected_table["y"].to_numpy(), within)
        ].reset_index(drop=True)
    if not accepted:
        return StemSet(empty_stems().table, rejected_table)
    circles = np.array(accepted, dtype=np.float64)
    # sorted by band, then position: chains (and their numbering) do not depend on order
    circles = circles[np.lexsort((circles[:, 2], circles[:, 1], circles[:, 0]))]

    # 3. chains of mutually nearest circles of neighbouring bands
    chains = _join(_chains(circles, centres, o), circles, centres, o)
    stems = [_stem(circles[chain], centres, o) for chain in chains if len(chain) >= o.min_circles]
    table = _distinct(pd.DataFrame([r for r in stems if r is not None], columns=STEM_COLUMNS))
    if within is not None and len(table):
        keep = _inside(table["stem_x"].to_numpy(), table["stem_y"].to_numpy(), within)
        table = table[keep]
    table = table.sort_values(["stem_x", "stem_y"], kind="stable").reset_index(drop=True)
    for column in ("dbh_n_points", "stem_circles"):
        table[column] = table[column].astype(np.int64)
    return StemSet(table, rejected_table)


def _inside(
    x: NDArray[np.float64], y: NDArray[np.float64], bounds: tuple[float, float, float, float]
) -> NDArray[np.bool_]:
    x0, y0, x1, y1 = bounds
    return (x >= x0) & (x < x1) & (y >= y0) & (y < y1)


def _rejection(fits: CircleFits, k: int, n_points: int, o: StemOptions) -> str | None:
    """Why circle ``k`` is no stem cross-section, or None."""
    n_in, radius = int(fits.n_inliers[k]), float(fits.radius[k])
    if n_in < o.min_points:
        return f"{n_in} inliers < {o.min_points}"
    if not o.min_radius <= radius <= o.max_radius:
        return f"radius {radius:.3f} m outside [{o.min_radius}, {o.max_radius}]"
    if fits.rmse[k] > o.max_rmse:
        return f"residual {fits.rmse[k]:.3f} m > {o.max_rmse}"
    if fits.arc_deg[k] < o.min_arc_deg:
        return f"arc {fits.arc_deg[k]:.0f} deg < {o.min_arc_deg:.0f}"
    if n_in < 0.5 * n_points:
        return f"only {n_in} of {n_points} points on the circle"
    return None


def _chains(
    circles: NDArray[np.float64], centres: NDArray[np.float64], o: StemOptions
) -> list[NDArray[np.int64]]:
    """Chains (index arrays, bottom up) of circles linked to their mutual nearest neighbour
    one or two bands up (rows of ``circles``: band, x, y, r, ...)."""
    from scipy.spatial import cKDTree

    band = circles[:, 0].astype(np.int64)
    xy, r = circles[:, 1:3], circles[:, 3]
    n = len(circles)
    tan_lean = math.tan(math.radians(o.max_lean_deg))
    up = np.full(n, -1)
    down = np.full(n, -1)
    best_up = np.full(n, np.inf)
    best_down = np.full(n, np.inf)
    by_band = {int(b): np.flatnonzero(band == b) for b in np.unique(band)}
    trees = {b: cKDTree(xy[rows]) for b, rows in by_band.items()}
    for gap in (1, 2):
        for b, rows in by_band.items():
            if b + gap not in by_band:
                continue
            above = by_band[b + gap]
            reach = 0.05 + tan_lean * gap * o.band_step
            pairs = trees[b + gap].query_ball_point(xy[rows], reach)
            for i, hits in zip(rows.tolist(), pairs, strict=True):
                for k in hits:
                    j = int(above[k])
                    change = abs(r[i] - r[j])
                    if change > o.max_radius_change * max(r[i], r[j]) + 0.015:
                        continue
                    # gap-2 links only where the band between holds no candidate
                    d = float(np.hypot(*(xy[i] - xy[j]))) + (gap - 1) * 1e3
                    if d < best_up[i]:
                        best_up[i], up[i] = d, j
                    if d < best_down[j]:
                        best_down[j], down[j] = d, i
    mutual = (up >= 0) & (down[np.maximum(up, 0)] == np.arange(n))
    link = np.where(mutual, up, -1)
    has_below = np.zeros(n, dtype=bool)
    has_below[link[link >= 0]] = True
    chains = []
    for start in np.flatnonzero(~has_below):
        chain = [int(start)]
        while link[chain[-1]] >= 0:
            chain.append(int(link[chain[-1]]))
        chains.append(np.array(chain, dtype=np.int64))
    return chains


def _join(
    chains: list[NDArray[np.int64]],
    circles: NDArray[np.float64],
    centres: NDArray[np.float64],
    o: StemOptions,
) -> list[NDArray[np.int64]]:
    """Chains of one stem broken by a gap (a branch, a shrub, a hidden side) joined: a chain
    starting at most ``max_gap`` m above another's end, on its axis carried up (within
    5 cm + 15 % of the radius) and of a similar radius. Each chain joins at most one above
    it, nearest first."""
    if len(chains) < 2:
        return chains
    band = circles[:, 0].astype(np.int64)
    z = centres[band]
    ends = []
    for chain in chains:
        c = circles[chain]
        zc = z[chain] - o.breast_height
        w = np.ones(len(chain))
        (x0, ax), (y0, ay) = _line(zc, c[:, 1], w), _line(zc, c[:, 2], w)
        ends.append((z[chain].min(), z[chain].max(), x0, ax, y0, ay, float(np.median(c[:, 3]))))
    e = np.array(ends)
    candidates = []
    for i in range(len(chains)):  # i below, j above
        gap = e[:, 0] - e[i, 1]
        for j in np.flatnonzero((gap > 0) & (gap <= o.max_gap + 1e-9)).tolist():
            zj = e[j, 0] - o.breast_height
            zi = e[i, 1] - o.breast_height
            # each chain's axis carried to the other's nearest end
            d_up = math.hypot(
                e[i, 2] + e[i, 3] * zj - circles[chains[j][0], 1],
                e[i, 4] + e[i, 5] * zj - circles[chains[j][0], 2],
            )
            d_down = math.hypot(
                e[j, 2] + e[j, 3] * zi - circles[chains[i][-1], 1],
                e[j, 4] + e[j, 5] * zi - circles[chains[i][-1], 2],
            )
            r = max(e[i, 6], e[j, 6])
            if min(d_up, d_down) > 0.05 + 0.15 * r:
                continue
            if r > 2.5 * min(e[i, 6], e[j, 6]):
                continue  # one stem's parts: their radii are sorted out by the taper line
            candidates.append((min(d_up, d_down), i, j))
    above = np.full(len(chains), -1)
    below = np.full(len(chains), -1)
    for _, i, j in sorted(candidates):
        if above[i] < 0 and below[j] < 0:
            above[i], below[j] = j, i
    joined = []
    for start in np.flatnonzero(below < 0).tolist():
        parts, k = [chains[start]], start
        while above[k] >= 0:
            k = int(above[k])
            parts.append(chains[k])
        joined.append(np.concatenate(parts))
    return joined


def _distinct(table: pd.DataFrame) -> pd.DataFrame:
    """One row per stem: of stems standing within half the larger radius (+ 5 cm) of each
    other (two arcs of one stem fitted apart, or a stem's slices split by a shrub pressed
    against it), the one seen in the most slices, then with the most inliers."""
    if len(table) < 2:
        return table
    from scipy.spatial import cKDTree

    xy = table[["stem_x", "stem_y"]].to_numpy()
    r = table["radius_m"].to_numpy()
    order = np.lexsort(
        (xy[:, 1], xy[:, 0], -table["dbh_n_points"].to_numpy(), -table["stem_circles"].to_numpy())
    )
    keep = np.ones(len(table), dtype=bool)
    index = cKDTree(xy)
    for k in order.tolist():
        if not keep[k]:
            continue
        for j in index.query_ball_point(xy[k], 0.05 + 0.5 * float(r.max())):
            d = math.hypot(*(xy[j] - xy[k]))
            if j != k and keep[j] and d <= 0.05 + 0.5 * max(r[j], r[k]):
                keep[j] = False
    return table[keep].reset_index(drop=True)


def _stem(
    chain: NDArray[np.float64], centres: NDArray[np.float64], o: StemOptions
) -> list[float] | None:
    """One stem row from its chain's circles (band, x, y, r, rmse, inliers, arc), or None
    when its centres do not lie on a plausible axis."""
    z = centres[chain[:, 0].astype(np.int64)] - o.breast_height
    x, y, r = chain[:, 1], chain[:, 2], chain[:, 3]
    w = chain[:, 5]
    keep = np.ones(len(chain), dtype=bool)
    for _ in range(2):  # the axis, then again without the centres far off it
        (x0, ax), (y0, ay) = _line(z[keep], x[keep], w[keep]), _line(z[keep], y[keep], w[keep])
        off = np.hypot(x - (x0 + ax * z), y - (y0 + ay * z))
        far = off > np.maximum(0.04, 0.25 * r)
        if not (far & keep).any() or (keep & ~far).sum() < o.min_circles:
            break
        keep &= ~far
    lean = math.degrees(math.atan(math.hypot(ax, ay)))
    if lean > o.max_lean_deg:
        return None
    z, r, w, used = z[keep], r[keep], w[keep], chain[keep]
    low, high = float(z.min()), float(z.max())
    if high - low < o.min_span - 1e-9:
        return None
    # the radius line, from the circles above the butt swell, again without those far off
    # it (a shrub pressed against the stem widens a slice's circle)
    fit = z >= o.taper_from - o.breast_height - 1e-9
    if fit.sum() < 3:
        fit = np.ones(len(z), dtype=bool)
    for _ in range(3):
        if fit.sum() >= 2 and np.ptp(z[fit]) > 0:
            r0, taper = _line(z[fit], r[fit], w[fit])
            if taper < o.min_taper and np.ptp(z[fit]) >= 0.5:
                return None  # narrowing faster than any stem: a shrub, a cone of twigs
            taper = min(max(taper, o.min_taper), 0.01)
            r0 = float(np.average(r[fit] - taper * z[fit], weights=w[fit]))
        else:
            r0, taper = float(np.median(r[fit])), 0.0
        far = np.abs(r - (r0 + taper * z)) > np.maximum(0.01, 0.2 * max(r0, 0.0))
        if not (far & fit).any() or (fit & ~far).sum() < max(2, fit.sum() // 2 + 1):
            break  # only a minority of the circles are dropped
        fit &= ~far
    z, r, w, used = z[fit], r[fit], w[fit], used[fit]
    resid = r - (r0 + taper * z)
    if len(z) > 2:
        se_r = math.sqrt(float(np.sum(w * resid**2) / np.sum(w)) / (len(z) - 2))
    else:
        se_r = float(np.max(np.abs(resid))) if len(z) > 1 else float(used[0, 4])
    cos_lean = math.cos(math.radians(lean))
    across = 2.0 * cos_lean / (1.0 + cos_lean)  # a horizontal slice's circle is wider
    dbh = 2.0 * r0 * across
    rmse = float(np.sqrt(np.average(used[:, 4] ** 2, weights=w)))
    n_in = int(used[:, 5].sum())
    se = 2.0 * math.hypot(se_r, rmse / math.sqrt(max(n_in, 1)))
    azimuth = math.degrees(math.atan2(ay, ax)) % 360.0 if lean > 0 else 0.0
    half = o.band_half_width
    return [
        x0,
        y0,
        dbh,
        se,
        rmse,
        n_in,
        float(np.median(used[:, 6])),
        lean,
        azimuth,
        low + o.breast_height - half,
        high + o.breast_height + half,
        int(keep.sum()),
        ax,
        ay,
        r0,
        taper,
    ]


def _line(
    z: NDArray[np.float64], v: NDArray[np.float64], w: NDArray[np.float64]
) -> tuple[float, float]:
    """Weighted least-squares line ``v = a + b z``: (a, b); b = 0 for a single height."""
    zm = float(np.average(z, weights=w))
    vm = float(np.average(v, weights=w))
    dz = z - zm
    s = float(np.sum(w * dz * dz))
    b = float(np.sum(w * dz * (v - vm)) / s) if s > 1e-12 else 0.0
    return vm - b * zm, b


def stem_points(
    xyz: NDArray[np.float64],
    heights: NDArray[np.float64],
    stems: pd.DataFrame,
    *,
    breast_height: float = 1.3,
    margin: float = 0.25,
    slab: float = 2.0,
    max_gap: float = 2.0,
    trunk_slenderness: float = 100.0,
    widen: float = 0.0,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The points on each stem: rows of ``xyz`` and their stem (row of ``stems``).

    A point is on a stem when it lies within the stem's radius + max(3 cm, 30 % of it)
    (+ ``widen``: for voxel centres) of its axis, both carried along its lean and taper
    lines, from ``stem_low_m - margin`` up, through its slices and on up the trunk as long
    as it is seen, with gaps of at most ``max_gap`` m, up to ``1.3 + trunk_slenderness x
    DBH`` m (a thin stem's trunk does not run on into the crown over it). A point near two
    axes goes to the nearer. Points are taken in horizontal slabs of ``slab`` m, each with
    the stems' axes at its middle."""
    from scipy.spatial import cKDTree

    if not len(stems):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    h = np.asarray(heights, dtype=np.float64)
    lo = stems["stem_low_m"].to_numpy() - margin
    cap = breast_height + trunk_slenderness * stems["dbh_m"].to_numpy()
    cap = np.maximum(cap, stems["stem_high_m"].to_numpy() + margin)
    sx, sy = stems["stem_x"].to_numpy(), stems["stem_y"].to_numpy()
    ax, ay = stems["axis_dx"].to_numpy(), stems["axis_dy"].to_numpy()
    r0, taper = stems["radius_m"].to_numpy(), stems["taper"].to_numpy()
    rows = np.flatnonzero((h >= lo.min()) & (h <= cap.max()))
    slab_of = np.floor((h[rows] - lo.min()) / slab).astype(np.int64)
    order = np.argsort(slab_of, kind="stable")
    rows, slab_of = rows[order], slab_of[order]
    slabs, starts = np.unique(slab_of, return_index=True)
    points, owners, dists = [], [], []
    for number, a, b in zip(slabs, starts, np.r_[starts[1:], len(rows)], strict=True):
        part = rows[a:b]
        z_mid = lo.min() + (number + 0.5) * slab - breast_height
        height = z_mid + breast_height
        live = np.flatnonzero((lo <= height + slab) & (cap >= height - slab))
        if not len(live):
            continue
        radius_mid = np.maximum(r0[live] + taper[live] * z_mid, 0.01)
        # within a slab an axis moves by at most lean x slab / 2
        lean = np.hypot(ax[live], ay[live])
        reach = radius_mid + np.maximum(0.03, 0.3 * radius_mid) + widen + lean * slab
        k = min(2, len(live))
        dist0, near = cKDTree(
            np.column_stack([sx[live] + ax[live] * z_mid, sy[live] + ay[live] * z_mid])
        ).query(xyz[part, :2], k=k, distance_upper_bound=float(reach.max()) + 0.05)
        near = near.reshape(len(part), k)
        found = np.isfinite(dist0.reshape(len(part), k)).ravel()
        point = np.repeat(part, k)[found]
        stem = live[near.ravel()[found]]
        dz = h[point] - breast_height
        dist = np.hypot(
            xyz[point, 0] - (sx[stem] + ax[stem] * dz), xyz[point, 1] - (sy[stem] + ay[stem] * dz)
        )
        radius = np.maximum(r0[stem] + taper[stem] * dz, 0.01)
        on = dist <= radius + np.maximum(0.03, 0.3 * radius) + widen
        on &= (h[point] >= lo[stem]) & (h[point] <= cap[stem])
        points.append(point[on])
        owners.append(stem[on])
        dists.append(dist[on])
    if not points:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    point, stem, dist = np.concatenate(points), np.concatenate(owners), np.concatenate(dists)
    order = np.lexsort((dist, point))
    point, stem = point[order], stem[order]
    first = np.concatenate([[True], point[1:] != point[:-1]])
    point, stem = point[first], stem[first]
    # each trunk up to its first gap wider than max_gap above its slices
    order = np.lexsort((h[point], stem))
    point, stem = point[order], stem[order]
    z = h[point]
    top = stems["stem_high_m"].to_numpy() + margin
    gap = np.diff(z, prepend=-np.inf) > max_gap
    gap &= z > top[stem]
    gap[np.r_[True, stem[1:] != stem[:-1]]] = False  # a stem's lowest point starts it
    # a point is kept while no gap lies below it on its stem
    broken = np.cumsum(gap) - np.maximum.accumulate(
        np.where(np.r_[True, stem[1:] != stem[:-1]], np.cumsum(gap) - gap, 0)
    )
    keep = broken == 0
    return point[keep], stem[keep]
