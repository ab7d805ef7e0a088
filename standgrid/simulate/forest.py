"""Known trees and shrubs of a simulated stand, and how they change between epochs."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from standgrid.simulate.terrain import Terrain

CONIFER = "conifer"
BROADLEAF = "broadleaf"
ALIVE, HARVESTED, NEW = "alive", "harvested", "new"
OVERSTOREY, UNDERSTOREY, SNAG = "overstorey", "understorey", "snag"
#: Breast height (m) at which DBH is defined (along the stem axis).
BREAST_HEIGHT = 1.3
#: Foliage density (extinction coefficient lambda, 1/m) of a crown when none is given.
DEFAULT_FOLIAGE_DENSITY = 0.6


def _empty() -> NDArray[np.float64]:
    return np.empty(0)


@dataclass(frozen=True, eq=False)
class Trees:
    """Columns of a tree list (CRS metres; dbh in metres). ``status`` alive/harvested/new.

    ``x, y`` is the stem base on the ground; heights (``height``, ``crown_base``,
    ``fork_height_m``) are vertical, above ``z_ground``. A stem leans ``lean_deg`` from the
    vertical towards ``lean_azimuth_deg`` (degrees clockwise from grid north); ``x_bh, y_bh``
    is its axis 1.3 m along the stem; ``fork_height_m`` (NaN: none) is where it splits into
    two leaders; ``foliage_density`` is the crown's lambda (1/m, 0: no crown). ``kind`` is
    overstorey, understorey or snag (dead, standing: its ``status`` still says whether it is
    in the stand). Columns left out take the plantation values: overstorey, vertical, no
    fork, ``x_bh, y_bh = x, y``, :data:`DEFAULT_FOLIAGE_DENSITY`.
    """

    tree_id: NDArray[np.int64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    z_ground: NDArray[np.float64]
    dbh: NDArray[np.float64]
    height: NDArray[np.float64]
    crown_base: NDArray[np.float64]
    crown_radius: NDArray[np.float64]
    species: NDArray[np.str_]
    status: NDArray[np.str_]
    kind: NDArray[np.str_] = field(default_factory=lambda: np.empty(0, np.str_))
    lean_deg: NDArray[np.float64] = field(default_factory=_empty)
    lean_azimuth_deg: NDArray[np.float64] = field(default_factory=_empty)
    fork_height_m: NDArray[np.float64] = field(default_factory=_empty)
    x_bh: NDArray[np.float64] = field(default_factory=_empty)
    y_bh: NDArray[np.float64] = field(default_factory=_empty)
    foliage_density: NDArray[np.float64] = field(default_factory=_empty)

    def __post_init__(self) -> None:
        n = len(self.tree_id)
        defaults = {
            "kind": np.full(n, OVERSTOREY).astype(np.str_),
            "lean_deg": np.zeros(n),
            "lean_azimuth_deg": np.zeros(n),
            "fork_height_m": np.full(n, np.nan),
            "x_bh": np.asarray(self.x, dtype=np.float64),
            "y_bh": np.asarray(self.y, dtype=np.float64),
            "foliage_density": np.full(n, DEFAULT_FOLIAGE_DENSITY),
        }
        for name, default in defaults.items():
            if n and len(getattr(self, name)) == 0:
                object.__setattr__(self, name, default)

    def __len__(self) -> int:
        return len(self.tree_id)

    @property
    def is_plantation(self) -> bool:
        """True when every new column holds its plantation value (vertical overstorey, ...)."""
        return bool(
            np.all(self.kind == OVERSTOREY)
            and np.all(self.lean_deg == 0.0)
            and np.all(np.isnan(self.fork_height_m))
            and np.all(self.foliage_density == DEFAULT_FOLIAGE_DENSITY)
        )

    def select(self, mask: NDArray[np.bool_]) -> Trees:
        return Trees(**{k: v[mask] for k, v in self.__dict__.items()})

    @property
    def standing(self) -> NDArray[np.bool_]:
        """Trees present in the stand at this epoch (not harvested)."""
        return self.status != HARVESTED

    @staticmethod
    def concat(parts: list[Trees]) -> Trees:
        return Trees(
            **{k: np.concatenate([getattr(p, k) for p in parts]) for k in parts[0].__dict__}
        )


@dataclass(frozen=True, eq=False)
class Shrubs:
    """Understory shrubs as ellipsoids: centre ``(x, y)`` on the ground, radius and height < 3 m."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    z_ground: NDArray[np.float64]
    radius: NDArray[np.float64]
    height: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.x)


def draw_leans(rng: np.random.Generator, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Stem leans (degrees): most 0-5, ~15 % 5-15, towards a uniform random azimuth."""
    steep = rng.random(n) < 0.15
    lean = np.where(steep, rng.uniform(5.0, 15.0, n), rng.uniform(0.0, 5.0, n))
    return lean, rng.uniform(0.0, 360.0, n)


def stem_axes(
    lean_deg: NDArray[np.float64], azimuth_deg: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Unit stem-axis vectors (n, 3) of stems leaning ``lean_deg`` towards ``azimuth_deg``."""
    lean, az = np.radians(lean_deg), np.radians(azimuth_deg)
    return np.column_stack([np.sin(lean) * np.sin(az), np.sin(lean) * np.cos(az), np.cos(lean)])


def breast_height_xy(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    lean_deg: NDArray[np.float64],
    azimuth_deg: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where the stem axis is 1.3 m along the stem from its base ``(x, y)``."""
    axis = stem_axes(lean_deg, azimuth_deg)
    return x + BREAST_HEIGHT * axis[:, 0], y + BREAST_HEIGHT * axis[:, 1]


def _allometric_height(rng: np.random.Generator, dbh_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Chapman-Richards height-diameter curve plus noise, clipped to 12-35 m."""
    dbh_cm = dbh_m * 100.0
    h = 1.3 + 36.0 * (1.0 - np.exp(-0.045 * dbh_cm)) ** 1.1
    return np.clip(h + rng.normal(0.0, 1.2, len(h)), 12.0, 35.0)


def _stem_positions(
    rng: np.random.Generator, bounds: tuple[float, float, float, float], density_ha: float
) -> NDArray[np.float64]:
    """A jittered grid (minimum spacing half a cell) covering ``bounds`` with ~density stems/ha."""
    xmin, ymin, xmax, ymax = bounds
    cell = np.sqrt(10_000.0 / density_ha)
    xs = np.arange(xmin + cell / 2, xmax, cell)
    ys = np.arange(ymin + cell / 2, ymax, cell)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    pts += rng.uniform(-0.25 * cell, 0.25 * cell, pts.shape)
    return pts


def generate_forest(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    terrain: Terrain,
    *,
    density_ha: float = 350.0,
    conifer_fraction: float = 0.4,
    shrub_density_ha: float = 300.0,
) -> tuple[Trees, Shrubs]:
    """Trees (DBH 15-60 cm, height 12-35 m, separable crowns) and understory shrubs."""
    pts = _stem_positions(rng, bounds, density_ha)
    n = len(pts)
    dbh = np.clip(0.15 + rng.gamma(2.0, 0.07, n), 0.15, 0.60)
    height = _allometric_height(rng, dbh)
    species = np.where(rng.random(n) < conifer_fraction, CONIFER, BROADLEAF)
    crown_base = height * rng.uniform(0.35, 0.6, n)
    nn_dist = cKDTree(pts).query(pts, k=2)[0][:, 1]
    crown_radius = np.minimum(1.0 + 6.0 * dbh + rng.normal(0, 0.2, n), 0.45 * nn_dist)
    crown_radius = np.maximum(crown_radius, 0.8)
    trees = Trees(
        tree_id=np.arange(1, n + 1, dtype=np.int64),
        x=pts[:, 0],
        y=pts[:, 1],
        z_ground=terrain.height(pts[:, 0], pts[:, 1]),
        dbh=dbh,
        height=height,
        crown_base=crown_base,
        crown_radius=crown_radius,
        species=species.astype(np.str_),
        status=np.full(n, ALIVE).astype(np.str_),
    )
    return trees, _generate_shrubs(rng, bounds, terrain, pts, shrub_density_ha)


def _generate_shrubs(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    terrain: Terrain,
    stems: NDArray[np.float64],
    density_ha: float,
) -> Shrubs:
    """Shrubs kept >= 1.5 m (plus their radius) away from every stem so stems stay clean."""
    xmin, ymin, xmax, ymax = bounds
    n_try = int(density_ha * (xmax - xmin) * (ymax - ymin) / 10_000.0 * 1.5)
    xy = np.column_stack([rng.uniform(xmin, xmax, n_try), rng.uniform(ymin, ymax, n_try)])
    radius = rng.uniform(0.3, 1.0, n_try)
    height = rng.uniform(0.5, 2.5, n_try)
    dist = cKDTree(stems).query(xy)[0]
    keep = dist > radius + 1.5
    keep &= np.cumsum(keep) <= int(density_ha * (xmax - xmin) * (ymax - ymin) / 10_000.0)
    xy, radius, height = xy[keep], radius[keep], height[keep]
    return Shrubs(xy[:, 0], xy[:, 1], terrain.height(xy[:, 0], xy[:, 1]), radius, height)


def grow_forest(
    rng: np.random.Generator,
    trees: Trees,
    terrain: Terrain,
    *,
    years: float = 4.0,
    harvest_fraction: float = 0.12,
    harvest_box: tuple[float, float, float, float] | None = None,
    new_trees: int = 3,
) -> Trees:
    """The same stand ``years`` later: growth, a harvest (kept as status) and a few new trees.

    Surviving trees keep their ``tree_id``; harvested trees keep their last dimensions.
    ``harvest_fraction`` of the living trees (of those inside ``harvest_box``, when given)
    are harvested. Understorey trees grow 0.2-0.4 m and 1-3 mm DBH a year, overstorey
    trees 0.3-0.6 m and 3-10 mm; snags do not grow and are not harvested. Leans and forks
    stay; ingrowth leans when the stand's trees do.
    """
    n = len(trees)
    height = trees.height + years * rng.uniform(0.3, 0.6, n)
    dbh = trees.dbh + years * rng.uniform(0.003, 0.010, n)
    under = trees.kind == UNDERSTOREY
    height[under] = trees.height[under] + years * rng.uniform(0.2, 0.4, int(under.sum()))
    dbh[under] = trees.dbh[under] + years * rng.uniform(0.001, 0.003, int(under.sum()))
    living = trees.kind != SNAG
    pts = np.column_stack([trees.x, trees.y])
    nn_dist = cKDTree(pts).query(pts, k=2)[0][:, 1]
    crown_radius = np.minimum(trees.crown_radius + years * 0.05, 0.45 * nn_dist)
    crown_radius = np.maximum(crown_radius, trees.crown_radius)
    harvested = np.zeros(n, dtype=bool)
    candidates = np.flatnonzero(living)
    if harvest_box is not None:  # a harvest confined to one area (e.g. one stand)
        x0, y0, x1, y1 = harvest_box
        inside = (trees.x >= x0) & (trees.x < x1) & (trees.y >= y0) & (trees.y < y1)
        candidates = np.flatnonzero(inside & living)
    size = round(harvest_fraction * len(candidates))
    harvested[rng.choice(candidates, size=size, replace=False)] = True
    still = harvested | ~living  # keeps its dimensions
    grown = replace(
        trees,
        height=np.where(still, trees.height, height),
        dbh=np.where(still, trees.dbh, dbh),
        crown_base=np.where(still, trees.crown_base, trees.crown_base + years * 0.1),
        crown_radius=np.where(still, trees.crown_radius, crown_radius),
        status=np.where(harvested, HARVESTED, ALIVE).astype(np.str_),
    )
    if new_trees <= 0 or not harvested.any():
        return grown
    # Ingrowth: young trees in the gaps left by the harvest, past the 15 cm threshold.
    gaps = rng.choice(
        np.flatnonzero(harvested), size=min(new_trees, int(harvested.sum())), replace=False
    )
    k = len(gaps)
    nx = trees.x[gaps] + rng.uniform(-0.5, 0.5, k)
    ny = trees.y[gaps] + rng.uniform(-0.5, 0.5, k)
    ndbh = rng.uniform(0.15, 0.18, k)
    nh = rng.uniform(12.0, 14.0, k)
    lean, azimuth = draw_leans(rng, k) if np.any(trees.lean_deg > 0) else (np.zeros(k),) * 2
    x_bh, y_bh = breast_height_xy(nx, ny, lean, azimuth)
    new = Trees(
        tree_id=np.arange(int(trees.tree_id.max()) + 1, int(trees.tree_id.max()) + 1 + k),
        x=nx,
        y=ny,
        z_ground=terrain.height(nx, ny),
        dbh=ndbh,
        height=nh,
        crown_base=nh * rng.uniform(0.35, 0.5, k),
        crown_radius=np.minimum(rng.uniform(1.2, 1.8, k), 0.45 * nn_dist[gaps]),
        species=trees.species[gaps],
        status=np.full(k, NEW).astype(np.str_),
        kind=np.full(k, OVERSTOREY).astype(np.str_),
        lean_deg=lean,
        lean_azimuth_deg=azimuth,
        fork_height_m=np.full(k, np.nan),
        x_bh=x_bh,
        y_bh=y_bh,
        foliage_density=trees.foliage_density[gaps],
    )
    return Trees.concat([grown, new])
