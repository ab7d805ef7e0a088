"""A mobile laser scanner: points sampled on the true surfaces seen from each node.

Visibility is approximated (no occlusion between objects): a stem shows the half facing
the sensor, crowns and shrubs show their whole surface (foliage is porous), and the number
of points an object returns falls with its distance. Every point lies on a
true surface (terrain, stem cylinder, crown cone/ellipsoid, shrub ellipsoid) plus Gaussian
range noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from standgrid.simulate.forest import BREAST_HEIGHT, CONIFER, Shrubs, Trees
from standgrid.simulate.terrain import Terrain

GROUND, STEM, CROWN, UNDERSTORY = 1, 2, 3, 4
#: Share of a payload's points per surface class.
DEFAULT_SHARES = {GROUND: 0.17, STEM: 0.35, CROWN: 0.40, UNDERSTORY: 0.08}


@dataclass(frozen=True)
class ScannerModel:
    """Sensor range (horizontal, m), noise (m, per axis) and the class shares of the points."""

    max_range: float = 25.0
    noise_std: float = 0.008
    min_range: float = 1.0


@dataclass(frozen=True, eq=False)
class ScanPoints:
    """Sampled points in the CRS with their intensity and, for truth, their class and tree."""

    xyz: NDArray[np.float64]
    intensity: NDArray[np.float32]
    label: NDArray[np.uint8]
    tree_id: NDArray[np.int64]


def stem_radius(trees: Trees, idx: NDArray[np.intp], h: NDArray[np.float64]) -> NDArray[np.float64]:
    """Stem radius at height ``h`` above ground: linear taper, exactly DBH/2 at 1.3 m."""
    top = trees.height[idx]
    return trees.dbh[idx] / 2.0 * np.clip((top - h) / (top - BREAST_HEIGHT), 0.0, None)


def _allocate(
    rng: np.random.Generator, weights: NDArray[np.float64], total: int
) -> NDArray[np.int64]:
    if total <= 0 or weights.size == 0 or weights.sum() <= 0:
        return np.zeros(weights.shape, dtype=np.int64)
    flat = weights.ravel() / weights.sum()
    return rng.multinomial(total, flat).reshape(weights.shape)


def _pairs(counts: NDArray[np.int64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Expand a (nodes, objects) count matrix into per-point node and object indices."""
    node_idx, obj_idx = np.nonzero(counts)
    reps = counts[node_idx, obj_idx]
    return np.repeat(node_idx, reps), np.repeat(obj_idx, reps)


def _intensity(
    rng: np.random.Generator, base: float, dist: NDArray[np.float64]
) -> NDArray[np.float32]:
    value = base * (1.0 - 0.5 * np.clip(dist / 40.0, 0, 1)) + rng.normal(0.0, 0.03, len(dist))
    return np.clip(value, 0.0, 1.0).astype(np.float32)


def scan(
    rng: np.random.Generator,
    sensors: NDArray[np.float64],
    trees: Trees,
    shrubs: Shrubs,
    terrain: Terrain,
    bounds: tuple[float, float, float, float],
    n_points: int,
    model: ScannerModel = ScannerModel(),
    shares: dict[int, float] | None = None,
) -> ScanPoints:
    """About ``n_points`` points seen from the sensor positions ``sensors`` (CRS, (M, 3))."""
    shares = shares or DEFAULT_SHARES
    parts = [
        _scan_ground(rng, sensors, terrain, bounds, round(n_points * shares[GROUND]), model),
        _scan_stems(rng, sensors, trees, round(n_points * shares[STEM]), model),
        _scan_crowns(rng, sensors, trees, round(n_points * shares[CROWN]), model),
        _scan_shrubs(rng, sensors, shrubs, round(n_points * shares[UNDERSTORY]), model),
    ]
    xyz = np.concatenate([p.xyz for p in parts])
    xyz = xyz + rng.normal(0.0, model.noise_std, xyz.shape)
    return ScanPoints(
        xyz=xyz,
        intensity=np.concatenate([p.intensity for p in parts]),
        label=np.concatenate([p.label for p in parts]),
        tree_id=np.concatenate([p.tree_id for p in parts]),
    )


def _result(
    xyz: NDArray[np.float64], intensity: NDArray[np.float32], label: int, tree_id: NDArray[np.int64]
) -> ScanPoints:
    return ScanPoints(xyz, intensity, np.full(len(xyz), label, dtype=np.uint8), tree_id)


def _scan_ground(
    rng: np.random.Generator,
    sensors: NDArray[np.float64],
    terrain: Terrain,
    bounds: tuple[float, float, float, float],
    total: int,
    model: ScannerModel,
) -> ScanPoints:
    per_node = _allocate(rng, np.ones(len(sensors)), total)
    node = np.repeat(np.arange(len(sensors)), per_node)
    r = rng.uniform(model.min_range, model.max_range, len(node))
    theta = rng.uniform(0, 2 * np.pi, len(node))
    x = sensors[node, 0] + r * np.cos(theta)
    y = sensors[node, 1] + r * np.sin(theta)
    xmin, ymin, xmax, ymax = bounds
    inside = (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)  # the stand ends at its bounds
    x, y, r = x[inside], y[inside], r[inside]
    xyz = np.column_stack([x, y, terrain.height(x, y)])
    return _result(xyz, _intensity(rng, 0.3, r), GROUND, np.zeros(len(xyz), np.int64))


def _horizontal_distance(
    sensors: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]
) -> NDArray[np.float64]:
    return np.hypot(sensors[:, None, 0] - x[None, :], sensors[:, None, 1] - y[None, :])


def _scan_stems(
    rng: np.random.Generator,
    sensors: NDArray[np.float64],
    trees: Trees,
    total: int,
    model: ScannerModel,
) -> ScanPoints:
    standing = np.flatnonzero(trees.standing)
    d = _horizontal_distance(sensors, trees.x[standing], trees.y[standing])
    visible_len = np.minimum(trees.crown_base[standing], 12.0)
    w = trees.dbh[standing][None, :] * visible_len[None, :] / np.maximum(d, 4.0) ** 1.2
    w[d > model.max_range] = 0.0
    node, obj = _pairs(_allocate(rng, w, total))
    t = standing[obj]
    # Half the points fall on the lower stem (0.3-3 m), the rest anywhere below the crown.
    low = rng.random(len(t)) < 0.5
    h = np.where(
        low,
        rng.uniform(0.3, 3.0, len(t)),
        rng.uniform(0.0, 1.0, len(t)) * np.minimum(trees.crown_base[t], 12.0),
    )
    facing = np.arctan2(sensors[node, 1] - trees.y[t], sensors[node, 0] - trees.x[t])
    theta = facing + rng.uniform(-1.35, 1.35, len(t))
    r = stem_radius(trees, t, h)
    xyz = np.column_stack(
        [trees.x[t] + r * np.cos(theta), trees.y[t] + r * np.sin(theta), trees.z_ground[t] + h]
    )
    dist = np.hypot(sensors[node, 0] - xyz[:, 0], sensors[node, 1] - xyz[:, 1])
    return _result(xyz, _intensity(rng, 0.55, dist), STEM, trees.tree_id[t])


def _scan_crowns(
    rng: np.random.Generator,
    sensors: NDArray[np.float64],
    trees: Trees,
    total: int,
    model: ScannerModel,
) -> ScanPoints:
    standing = np.flatnonzero(trees.standing)
    d = _horizontal_distance(sensors, trees.x[standing], trees.y[standing])
    depth = trees.height[standing] - trees.crown_base[standing]
    area = trees.crown_radius[standing] * depth
    z_mid = trees.z_ground[standing] + (trees.height[standing] + trees.crown_base[standing]) / 2
    d3 = np.sqrt(d**2 + (z_mid[None, :] - sensors[:, 2:3]) ** 2)
    w = area[None, :] / np.maximum(d3, 8.0) ** 1.5
    w[d > model.max_range] = 0.0
    node, obj = _pairs(_allocate(rng, w, total))
    t = standing[obj]
    n = len(t)
    phi = rng.uniform(0, 2 * np.pi, n)
    top = trees.z_ground[t] + trees.height[t]
    depth_t = trees.height[t] - trees.crown_base[t]
    radius = trees.crown_radius[t]
    # Cone (conifer): fraction rho from the apex; a mix of area-uniform and height-uniform
    # samples so the apex is well covered.
    rho = np.where(rng.random(n) < 0.6, np.sqrt(rng.random(n)), rng.random(n))
    cone_r, cone_z = rho * radius, top - rho * depth_t
    # Ellipsoid (broadleaf): z uniform on [-1, 1] is area-uniform on a sphere; add an apex cap.
    zu = np.where(rng.random(n) < 0.15, rng.uniform(0.85, 1.0, n), rng.uniform(-1.0, 1.0, n))
    ell_r = radius * np.sqrt(np.clip(1.0 - zu**2, 0.0, None))
    ell_z = top - depth_t / 2 * (1.0 - zu)
    conifer = trees.species[t] == CONIFER
    r = np.where(conifer, cone_r, ell_r)
    z = np.where(conifer, cone_z, ell_z)
    xyz = np.column_stack([trees.x[t] + r * np.cos(phi), trees.y[t] + r * np.sin(phi), z])
    dist = np.linalg.norm(xyz - sensors[node], axis=1)
    return _result(xyz, _intensity(rng, 0.35, dist), CROWN, trees.tree_id[t])


def _scan_shrubs(
    rng: np.random.Generator,
    sensors: NDArray[np.float64],
    shrubs: Shrubs,
    total: int,
    model: ScannerModel,
) -> ScanPoints:
    if len(shrubs) == 0:
        return _result(np.empty((0, 3)), np.empty(0, np.float32), UNDERSTORY, np.empty(0, np.int64))
    d = _horizontal_distance(sensors, shrubs.x, shrubs.y)
    w = (shrubs.radius * shrubs.height)[None, :] / np.maximum(d, 2.0) ** 2
    w[d > model.max_range] = 0.0
    node, s = _pairs(_allocate(rng, w, total))
    n = len(s)
    phi = rng.uniform(0, 2 * np.pi, n)
    zu = rng.uniform(0.0, 1.0, n)  # upper half of an ellipsoid sitting on the ground
    r = shrubs.radius[s] * np.sqrt(1.0 - zu**2)
    xyz = np.column_stack(
        [
            shrubs.x[s] + r * np.cos(phi),
            shrubs.y[s] + r * np.sin(phi),
            shrubs.z_ground[s] + zu * shrubs.height[s],
        ]
    )
    dist = np.linalg.norm(xyz - sensors[node], axis=1)
    return _result(xyz, _intensity(rng, 0.25, dist), UNDERSTORY, np.zeros(n, np.int64))
