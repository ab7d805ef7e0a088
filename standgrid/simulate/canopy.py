"""A mixed, uneven-aged stand for under-canopy scanning, and the exact geometry of its trees.

Stem geometry (what :mod:`standgrid.simulate.raycast` draws and the truth describes):

* The stem axis starts at the base ``(x, y, z_ground)`` and runs along the unit vector
  ``u`` leaning ``lean_deg`` towards ``lean_azimuth_deg`` (:func:`~forest.stem_axes`);
  ``s`` is the distance along it. The top is at ``s = height / cos(lean)`` (vertical height
  ``height``), breast height at ``s = 1.3`` (``x_bh, y_bh``).
* Taper: ``r(s) = DBH / 2 * g(s)`` measured perpendicular to the axis, ``g`` the
  piecewise-linear interpolation, at the knots ``s = -0.5, 0, 0.65, 1.3`` and
  ``1.3 + (l - 1.3) * (0.25, 0.5, 0.75, 0.9, 1)``, of

      g*(s) = 1 + 0.15 * ((1.3 - s) / 1.3)^2     for s <= 1.3 (butt swell, +15 % at s = 0),
      g*(s) = ((l - s) / (l - 1.3))^0.8          for s >= 1.3 (to 0 at s = l),

  constant below ground (``s < 0``) and 0 beyond ``l``. So ``r(1.3) = DBH / 2`` exactly and
  a stem is a stack of frustums. ``l`` is the stem length ``height / cos(lean)``; for a snag
  (broken top) the length of the unbroken stem, ``reference_height(dbh) / cos(lean)``,
  cut at its height.
* A forked stem's trunk ends at ``s_f = fork_height_m / cos(lean)``; two leaders, cones of
  base radius ``r(s_f) / sqrt(2)``, leave the fork at +-20 degrees from the axis, in the plane
  of the axis and the horizontal perpendicular to the lean, and end at the tree's height.
* Crowns are vertical and centred over the stem top ``base + height / cos(lean) * u``:
  conifers a cone from the top down to ``crown_base`` (radius ``crown_radius`` there),
  broadleaves an ellipsoid between ``crown_base`` and the top. Snags have none.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from standgrid.simulate.forest import (
    ALIVE,
    BREAST_HEIGHT,
    BROADLEAF,
    CONIFER,
    OVERSTOREY,
    SNAG,
    UNDERSTOREY,
    Shrubs,
    Trees,
    breast_height_xy,
    draw_leans,
    stem_axes,
)
from standgrid.simulate.terrain import Terrain

BUTT_SWELL = 0.15
TAPER_EXPONENT = 0.8
FORK_ANGLE_DEG = 20.0
_KNOTS_BELOW = np.array([-0.5, 0.0, 0.65, BREAST_HEIGHT])
_KNOT_FRACTIONS = np.array([0.25, 0.5, 0.75, 0.9, 1.0])


def reference_height(dbh: NDArray[np.float64]) -> NDArray[np.float64]:
    """The overstorey height-diameter curve (m) without noise: ``1.3 + 34 (1 - e^(-0.05 d))``."""
    return BREAST_HEIGHT + 34.0 * (1.0 - np.exp(-0.05 * dbh * 100.0))


def taper_length(trees: Trees) -> NDArray[np.float64]:
    """``l`` of the taper: the stem length, or a snag's unbroken length."""
    top = np.where(
        trees.kind == SNAG, np.maximum(reference_height(trees.dbh), trees.height), trees.height
    )
    return top / np.cos(np.radians(trees.lean_deg))


def _knots(length: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Taper knots (n, 9) along the stem and ``g*`` at them."""
    above = BREAST_HEIGHT + (length[:, None] - BREAST_HEIGHT) * _KNOT_FRACTIONS
    s = np.hstack([np.broadcast_to(_KNOTS_BELOW, (len(length), 4)), above])
    below = 1.0 + BUTT_SWELL * np.clip((BREAST_HEIGHT - s) / BREAST_HEIGHT, 0.0, 1.0) ** 2
    rel = np.clip((length[:, None] - s) / (length[:, None] - BREAST_HEIGHT), 0.0, None)
    return s, np.where(s <= BREAST_HEIGHT, below, rel**TAPER_EXPONENT)


def stem_radius_at(
    dbh: NDArray[np.float64], length: NDArray[np.float64], s: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Stem radius (m, perpendicular to the axis) ``s`` m along the axis (elementwise)."""
    knots, g = _knots(np.asarray(length, dtype=np.float64))
    s = np.clip(s, knots[:, 0], knots[:, -1])
    j = np.clip((s[:, None] >= knots).sum(axis=1) - 1, 0, knots.shape[1] - 2)
    rows = np.arange(len(s))
    s0, s1 = knots[rows, j], knots[rows, j + 1]
    g0, g1 = g[rows, j], g[rows, j + 1]
    return dbh / 2.0 * (g0 + (s - s0) / (s1 - s0) * (g1 - g0))


@dataclass(frozen=True, eq=False)
class StemSegments:
    """Stems as frustums: ``start`` (S, 3), unit ``axis``, ``length``, end radii ``r0, r1``,
    ``s0`` (distance of ``start`` along its stem or leader) and ``tree`` (row in the list)."""

    tree: NDArray[np.intp]
    start: NDArray[np.float64]
    axis: NDArray[np.float64]
    length: NDArray[np.float64]
    r0: NDArray[np.float64]
    r1: NDArray[np.float64]
    s0: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.tree)


def stem_segments(trees: Trees) -> StemSegments:
    """The frustums of every stem of ``trees`` (trunks, then the leaders of forked stems)."""
    base = np.column_stack([trees.x, trees.y, trees.z_ground])
    u = stem_axes(trees.lean_deg, trees.lean_azimuth_deg)
    cos_lean = u[:, 2]
    length = taper_length(trees)
    forked = np.isfinite(trees.fork_height_m)
    end = np.where(forked, trees.fork_height_m, trees.height) / cos_lean
    knots, _ = _knots(length)
    a, b = knots[:, :-1], np.minimum(knots[:, 1:], end[:, None])
    row, col = np.nonzero(a < end[:, None])
    a, b = a[row, col], b[row, col]
    r0 = stem_radius_at(trees.dbh[row], length[row], a)
    r1 = stem_radius_at(trees.dbh[row], length[row], b)
    trunk = StemSegments(row, base[row] + a[:, None] * u[row], u[row], b - a, r0, r1, a)
    f = np.flatnonzero(forked)
    if len(f) == 0:
        return trunk
    s_f = end[f]
    fork = base[f] + s_f[:, None] * u[f]
    az = np.radians(trees.lean_azimuth_deg[f])
    side = np.column_stack([np.cos(az), -np.sin(az), np.zeros(len(f))])
    alpha = np.radians(FORK_ANGLE_DEG)
    lead_len = (trees.height[f] - trees.fork_height_m[f]) / (np.cos(alpha) * cos_lean[f])
    r_fork = stem_radius_at(trees.dbh[f], length[f], s_f) / np.sqrt(2.0)
    dirs = [np.cos(alpha) * u[f] + sign * np.sin(alpha) * side for sign in (1.0, -1.0)]
    return StemSegments(
        tree=np.concatenate([trunk.tree, f, f]),
        start=np.vstack([trunk.start, fork, fork]),
        axis=np.vstack([trunk.axis, *dirs]),
        length=np.concatenate([trunk.length, lead_len, lead_len]),
        r0=np.concatenate([trunk.r0, r_fork, r_fork]),
        r1=np.concatenate([trunk.r1, np.zeros(2 * len(f))]),
        s0=np.concatenate([trunk.s0, s_f, s_f]),
    )


def crown_centres(trees: Trees) -> NDArray[np.float64]:
    """Horizontal centres (n, 2) of the crowns: over the stem top."""
    u = stem_axes(trees.lean_deg, trees.lean_azimuth_deg)
    reach = trees.height / u[:, 2]
    return np.column_stack([trees.x + reach * u[:, 0], trees.y + reach * u[:, 1]])


def _hardcore(
    candidates: NDArray[np.float64], n: int, d_min: float, existing: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The first ``n`` candidates at least ``d_min`` from ``existing`` and from each other."""
    ok = np.ones(len(candidates), dtype=bool)
    if len(existing):
        ok = cKDTree(existing).query(candidates)[0] >= d_min
    neighbours = cKDTree(candidates).query_ball_point(candidates, d_min)
    taken = np.zeros(len(candidates), dtype=bool)
    for i in np.flatnonzero(ok):
        if not taken[neighbours[i]].any():
            taken[i] = True
            if taken.sum() == n:
                break
    return candidates[taken]


def _uniform(
    rng: np.random.Generator, bounds: tuple[float, float, float, float], n: int
) -> NDArray[np.float64]:
    xmin, ymin, xmax, ymax = bounds
    return np.column_stack([rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)])


def _layer(
    rng: np.random.Generator,
    terrain: Terrain,
    xy: NDArray[np.float64],
    kind: str,
    conifer_fraction: float,
    **cols: NDArray[np.float64],
) -> Trees:
    """Trees of one kind at ``xy`` with the given sizes; species, leans and crown lambda
    (conifers 0.5-1.0, broadleaves 0.3-0.8, snags 0 per m) drawn here."""
    n = len(xy)
    species = np.where(rng.random(n) < conifer_fraction, CONIFER, BROADLEAF).astype(np.str_)
    lean, azimuth = draw_leans(rng, n)
    foliage = np.where(species == CONIFER, rng.uniform(0.5, 1.0, n), rng.uniform(0.3, 0.8, n))
    x_bh, y_bh = breast_height_xy(xy[:, 0], xy[:, 1], lean, azimuth)
    return Trees(
        **{"fork_height_m": np.full(n, np.nan), **cols},
        tree_id=np.zeros(n, dtype=np.int64),
        x=xy[:, 0],
        y=xy[:, 1],
        z_ground=terrain.height(xy[:, 0], xy[:, 1]),
        species=species,
        status=np.full(n, ALIVE).astype(np.str_),
        kind=np.full(n, kind).astype(np.str_),
        lean_deg=lean,
        lean_azimuth_deg=azimuth,
        x_bh=x_bh,
        y_bh=y_bh,
        foliage_density=foliage if kind != SNAG else np.zeros(n),
    )


def _overstorey(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    terrain: Terrain,
    n: int,
    spacing: float,
    conifer_fraction: float,
    fork_fraction: float,
) -> Trees:
    xy = _hardcore(_uniform(rng, bounds, 8 * n), n, spacing, np.empty((0, 2)))
    n = len(xy)
    dbh = np.clip(0.15 + rng.gamma(2.0, 0.08, n), 0.15, 0.70)
    height = np.clip(reference_height(dbh) + rng.normal(0.0, 1.5, n), 18.0, 35.0)
    fork = np.where(rng.random(n) < fork_fraction, height * rng.uniform(0.4, 0.75, n), np.nan)
    trees = _layer(
        rng,
        terrain,
        xy,
        OVERSTOREY,
        conifer_fraction,
        dbh=dbh,
        height=height,
        crown_base=height * rng.uniform(0.35, 0.65, n),
        crown_radius=np.zeros(n),
        fork_height_m=fork,
    )
    centres = crown_centres(trees)
    nearest = cKDTree(centres).query(centres, k=2)[0][:, 1] if n > 1 else np.full(n, np.inf)
    radius = np.minimum(1.0 + 7.0 * dbh + rng.normal(0.0, 0.3, n), 0.8 * nearest)
    return replace(trees, crown_radius=np.maximum(radius, 1.2))


def _understorey(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    terrain: Terrain,
    over: Trees,
    n: int,
    under_crown_fraction: float,
    conifer_fraction: float,
) -> Trees:
    # Candidates under a random overstorey crown (uniform in 0.9 of its disc) or anywhere.
    xmin, ymin, xmax, ymax = bounds
    m = 6 * n
    cand = _uniform(rng, bounds, m)
    centres = crown_centres(over)
    if len(over):
        host = rng.integers(0, len(over), m)
        rho = 0.9 * over.crown_radius[host] * np.sqrt(rng.random(m))
        phi = rng.uniform(0.0, 2.0 * np.pi, m)
        below = centres[host] + np.column_stack([rho * np.cos(phi), rho * np.sin(phi)])
        cand = np.where((rng.random(m) < under_crown_fraction)[:, None], below, cand)
    inside = (cand[:, 0] >= xmin) & (cand[:, 0] <= xmax)
    cand = cand[inside & (cand[:, 1] >= ymin) & (cand[:, 1] <= ymax)]
    xy = _hardcore(cand, n, 1.0, np.column_stack([over.x, over.y]))
    n = len(xy)
    dbh = 0.06 + 0.09 * rng.beta(1.5, 2.0, n)
    height = 1.3 + 13.0 * (1.0 - np.exp(-0.08 * dbh * 100.0)) ** 1.3
    height = np.clip(height + rng.normal(0.0, 1.0, n), 3.0, 12.0)
    # Below the lowest overstorey crown over the tree, by 1 m (at least 3 m tall).
    pairs = cKDTree(xy).sparse_distance_matrix(
        cKDTree(centres), float(over.crown_radius.max(initial=0.0)), output_type="coo_matrix"
    )
    covered = pairs.data < over.crown_radius[pairs.col]
    ceiling = np.full(n, np.inf)
    np.minimum.at(
        ceiling, pairs.row[covered], (over.z_ground + over.crown_base)[pairs.col[covered]] - 1.0
    )
    height = np.maximum(np.minimum(height, ceiling - terrain.height(xy[:, 0], xy[:, 1])), 3.0)
    return _layer(
        rng,
        terrain,
        xy,
        UNDERSTOREY,
        conifer_fraction,
        dbh=dbh,
        height=height,
        crown_base=np.minimum(rng.uniform(1.5, 5.0, n), height - 1.0),
        crown_radius=rng.uniform(0.6, 2.0, n),
    )


def _snags(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    terrain: Terrain,
    stems: NDArray[np.float64],
    n: int,
    conifer_fraction: float,
) -> Trees:
    xy = _hardcore(_uniform(rng, bounds, 6 * n), n, 1.0, stems)
    n = len(xy)
    dbh = 0.10 + 0.35 * rng.beta(1.5, 2.5, n)
    height = rng.uniform(3.0, np.minimum(18.0, 0.9 * reference_height(dbh)))
    return _layer(
        rng,
        terrain,
        xy,
        SNAG,
        conifer_fraction,
        dbh=dbh,
        height=height,
        crown_base=height,
        crown_radius=np.zeros(n),
    )


def generate_mixed_forest(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    terrain: Terrain,
    *,
    overstorey_ha: float = 300.0,
    understorey_ha: float = 350.0,
    snags_ha: float = 20.0,
    shrub_density_ha: float = 600.0,
    conifer_fraction: float = 0.4,
    fork_fraction: float = 0.08,
    under_crown_fraction: float = 0.7,
) -> tuple[Trees, Shrubs]:
    """A mixed stand: overstorey, understorey, snags (tree_id in that order) and shrubs.

    Overstorey: DBH 15-70 cm, 18-35 m (:func:`reference_height` plus noise), crown base at
    35-65 % of the height, crown radius ``1 + 7 DBH`` limited to 0.8 x the distance to the
    nearest crown, stems at least ``min(3, half the mean spacing)`` m apart (fewer trees
    than asked when they do not fit), ``fork_fraction`` forked at 40-75 % of the height.
    Understorey: DBH 6-15 cm, 3-12 m (1 m below the crown base over it), crowns of radius
    0.6-2 m from 1.5-5 m, ``under_crown_fraction`` placed under overstorey crowns, the rest
    anywhere, >= 1 m from other stems. Snags: DBH 10-45 cm, 3-18 m (broken below 90 % of
    their unbroken height), no crown. Every stem leans (:func:`~forest.draw_leans`). Shrubs:
    anywhere, also against stems, 0.3-2.5 m tall, radius 0.3-1.5 m.
    """
    xmin, ymin, xmax, ymax = bounds
    area_ha = (xmax - xmin) * (ymax - ymin) / 10_000.0
    spacing = min(3.0, 0.5 * np.sqrt(10_000.0 / max(overstorey_ha, 1e-9)))
    over = _overstorey(
        rng,
        bounds,
        terrain,
        round(overstorey_ha * area_ha),
        spacing,
        conifer_fraction,
        fork_fraction,
    )
    under = _understorey(
        rng,
        bounds,
        terrain,
        over,
        round(understorey_ha * area_ha),
        under_crown_fraction,
        conifer_fraction,
    )
    stems = np.column_stack([np.concatenate([over.x, under.x]), np.concatenate([over.y, under.y])])
    snags = _snags(rng, bounds, terrain, stems, round(snags_ha * area_ha), conifer_fraction)
    trees = Trees.concat([over, under, snags])
    trees = replace(trees, tree_id=np.arange(1, len(trees) + 1, dtype=np.int64))
    n = round(shrub_density_ha * area_ha)
    xy = _uniform(rng, bounds, n)
    shrubs = Shrubs(
        xy[:, 0],
        xy[:, 1],
        terrain.height(xy[:, 0], xy[:, 1]),
        rng.uniform(0.3, 1.5, n),
        rng.uniform(0.3, 2.5, n),
    )
    return trees, shrubs
