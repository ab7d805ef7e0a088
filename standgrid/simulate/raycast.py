"""A ray-casting laser scanner with occlusion: the first hit of every ray.

From each sensor position rays are cast in the directions of a :class:`RaycastScanner`;
each keeps its first hit among the terrain (marching with a Lipschitz bound, then
bisection), the stems (frustums of :func:`~standgrid.simulate.canopy.stem_segments`) and
porous volumes: crowns (conifer cone, broadleaf ellipsoid) and shrubs (ellipsoids on the
ground). A ray crossing a porous volume over a path ``L`` stops in it with probability
``1 - exp(-lambda L)``, at an exponentially distributed depth (overlapping volumes add their
lambdas). Stem hits get bark roughness (a smooth, per-tree radial offset), every hit range
noise along the ray. Ground hits outside the stand's bounds and rays that hit nothing
within range give no point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from standgrid.simulate.canopy import StemSegments, crown_centres, stem_segments
from standgrid.simulate.forest import BROADLEAF, CONIFER, Shrubs, Trees
from standgrid.simulate.scanner import (
    CROWN,
    GROUND,
    STEM,
    UNDERSTORY,
    ScanPoints,
    _intensity,
)
from standgrid.simulate.terrain import Terrain

#: Foliage density (lambda, 1/m) of the shrubs.
SHRUB_FOLIAGE_DENSITY = 1.5
#: Standard deviation (m) of the radial bark roughness per species.
BARK_ROUGHNESS = {CONIFER: 0.005, BROADLEAF: 0.0025}
_BARK_TERMS = 8
_BARK_SEED = 0x6BA2C
#: Rays cast at once (bounds the memory of the ray-object pairs).
RAY_BATCH = 8192
_BASE_INTENSITY = {GROUND: 0.3, STEM: 0.55, CROWN: 0.35, UNDERSTORY: 0.25}


@dataclass(frozen=True)
class RaycastScanner:
    """Ray directions (elevation band, uniform in solid angle or ``rings`` channels), range
    (m), range noise (m, along the ray) and the sensor's height above the nodes (m, drawn
    per payload)."""

    kind: str
    elevation_deg: tuple[float, float]
    max_range: float = 40.0
    min_range: float = 0.5
    noise_std: float = 0.008
    rings: int = 0
    altitude: tuple[float, float] = (0.0, 0.0)

    def directions(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        """``n`` random unit ray directions (n, 3)."""
        lo, hi = np.radians(self.elevation_deg)
        if self.rings:
            el = np.linspace(lo, hi, self.rings)[rng.integers(0, self.rings, n)]
        else:
            el = np.arcsin(rng.uniform(np.sin(lo), np.sin(hi), n))
        az = rng.uniform(-np.pi, np.pi, n)
        return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


RAYCAST_SCANNERS: dict[str, RaycastScanner] = {
    # A rotating lidar tilted on a handheld or backpack rig.
    "handheld": RaycastScanner("handheld", (-50.0, 90.0), 40.0, 0.5, 0.008),
    # A VLP-16-like lidar on a legged robot: 16 rings from -15 to +15 degrees.
    "legged": RaycastScanner("legged", (-15.0, 15.0), 40.0, 0.5, 0.010, rings=16),
    # Near-nadir rays (+-20 degrees) from 300-400 m above the path.
    "airborne": RaycastScanner(
        "airborne", (-90.0, -70.0), 600.0, 1.0, 0.010, altitude=(300.0, 400.0)
    ),
}


@dataclass(frozen=True, eq=False)
class Scene:
    """What rays can hit, as flat arrays. Objects ``0..S-1`` are stem frustums, then the
    porous volumes (cones: ``centre`` is the apex and ``half`` the depth; ellipsoids:
    ``centre`` and the vertical semi-axis ``half``); ``bb_*`` bound every object by a
    vertical cylinder, ``box`` (xmin, ymin, zmin, xmax, ymax, zmax) everything a ray can
    return from (objects and the terrain inside the bounds). Per frustum, ``bark`` holds its
    tree's roughness terms (order around the stem, wavenumber along it, phase) and ``frame``
    two unit vectors perpendicular to its axis, from which the angle around it is measured."""

    terrain: Terrain
    bounds: tuple[float, float, float, float]
    gradient_bound: float
    stems: StemSegments
    stem_tree_id: NDArray[np.int64]
    bark_std: NDArray[np.float64]
    bark: NDArray[np.float64]
    frame: NDArray[np.float64]
    vol_centre: NDArray[np.float64]
    vol_radius: NDArray[np.float64]
    vol_half: NDArray[np.float64]
    vol_cone: NDArray[np.bool_]
    vol_lambda: NDArray[np.float64]
    vol_label: NDArray[np.uint8]
    vol_tree_id: NDArray[np.int64]
    bb_xy: NDArray[np.float64]
    bb_r: NDArray[np.float64]
    bb_z: NDArray[np.float64]
    box: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RayHits:
    """The first hits of the rays that returned: ``ray`` (index), range ``t`` (noisy),
    the point, its class and tree (0: ground, shrubs)."""

    ray: NDArray[np.intp]
    t: NDArray[np.float64]
    xyz: NDArray[np.float64]
    label: NDArray[np.uint8]
    tree_id: NDArray[np.int64]


def _gradient_bound(terrain: Terrain) -> float:
    """An upper bound of ``|grad h|``: the plane's slope plus each hill's steepest flank."""
    hills = terrain.hills.reshape(-1, 4)
    steep = np.abs(hills[:, 2]) / hills[:, 3] * math.exp(-0.5)
    return float(math.hypot(*terrain.slope) + steep.sum())


def _box(
    terrain: Terrain,
    bounds: tuple[float, float, float, float],
    gradient_bound: float,
    bb_xy: NDArray[np.float64],
    bb_r: NDArray[np.float64],
    bb_z: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The box holding the objects and the terrain over ``bounds`` (a grid's heights
    widened by the most the terrain can change between its nodes)."""
    xmin, ymin, xmax, ymax = bounds
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, 101), np.linspace(ymin, ymax, 101))
    h = terrain.height(gx, gy)
    margin = gradient_bound * math.hypot(xmax - xmin, ymax - ymin) / 200.0 + 0.1
    lo = np.array([xmin, ymin, h.min() - margin])
    hi = np.array([xmax, ymax, h.max() + margin])
    if len(bb_r):
        lo = np.minimum(lo, [*(bb_xy - bb_r[:, None]).min(axis=0), bb_z[:, 0].min()])
        hi = np.maximum(hi, [*(bb_xy + bb_r[:, None]).max(axis=0), bb_z[:, 1].max()])
    return np.concatenate([lo, hi])


def _box_span(
    box: NDArray[np.float64], origin: NDArray[np.float64], dirs: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Entry and exit ranges of the rays through ``box`` (entry > exit: missed)."""
    d = np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    a, b = (box[:3] - origin) / d, (box[3:] - origin) / d
    return np.minimum(a, b).max(axis=1), np.maximum(a, b).min(axis=1)


def _bark_table(max_id: int) -> NDArray[np.float64]:
    """Per tree id: harmonic order around the stem (2-16), wavenumber along it (1-10 rad/m)
    and phase of each roughness term (ids, terms, 3); the same for every payload."""
    u = np.random.default_rng(_BARK_SEED).random((max_id + 1, _BARK_TERMS, 3))
    return np.stack(
        [2.0 + np.floor(15.0 * u[..., 0]), 1.0 + 9.0 * u[..., 1], 2.0 * np.pi * u[..., 2]], axis=-1
    )


def build_scene(
    trees: Trees, shrubs: Shrubs, terrain: Terrain, bounds: tuple[float, float, float, float]
) -> Scene:
    """The standing trees' stems and crowns, and the shrubs, as ray-castable objects."""
    trees = trees.select(trees.standing)
    seg = stem_segments(trees)
    end = seg.start + seg.length[:, None] * seg.axis
    rmax = np.maximum(seg.r0, seg.r1) + 0.05
    frame1 = np.cross(seg.axis, [1.0, 0.0, 0.0])
    frame1 /= np.linalg.norm(frame1, axis=1)[:, None]
    frame = np.stack([frame1, np.cross(seg.axis, frame1)], axis=1)
    # Crowns.
    crowned = np.flatnonzero(
        (trees.crown_radius > 0) & (trees.foliage_density > 0) & (trees.height > trees.crown_base)
    )
    cxy = crown_centres(trees)[crowned]
    top = trees.z_ground[crowned] + trees.height[crowned]
    depth = trees.height[crowned] - trees.crown_base[crowned]
    cone = trees.species[crowned] == CONIFER
    cz = np.where(cone, top, top - depth / 2.0)
    n_c, n_s = len(crowned), len(shrubs)
    vol_centre = np.vstack(
        [np.column_stack([cxy, cz]), np.column_stack([shrubs.x, shrubs.y, shrubs.z_ground])]
    )
    vol_radius = np.concatenate([trees.crown_radius[crowned], shrubs.radius])
    vol_half = np.concatenate([np.where(cone, depth, depth / 2.0), shrubs.height])
    vol_cone = np.concatenate([cone, np.zeros(n_s, dtype=bool)])
    vol_zlo = vol_centre[:, 2] - vol_half
    vol_zhi = np.where(vol_cone, vol_centre[:, 2], vol_centre[:, 2] + vol_half)
    bark = _bark_table(int(trees.tree_id.max(initial=0)))
    bb_xy = np.vstack([(seg.start[:, :2] + end[:, :2]) / 2.0, vol_centre[:, :2]])
    bb_r = np.concatenate(
        [np.linalg.norm(end[:, :2] - seg.start[:, :2], axis=1) / 2 + rmax, vol_radius]
    )
    bb_z = np.column_stack(
        [
            np.concatenate([np.minimum(seg.start[:, 2], end[:, 2]) - rmax, vol_zlo]),
            np.concatenate([np.maximum(seg.start[:, 2], end[:, 2]) + rmax, vol_zhi]),
        ]
    )
    gradient_bound = _gradient_bound(terrain)
    return Scene(
        terrain=terrain,
        bounds=bounds,
        gradient_bound=gradient_bound,
        stems=seg,
        stem_tree_id=trees.tree_id[seg.tree],
        bark_std=np.array([BARK_ROUGHNESS.get(str(s), 0.003) for s in trees.species])[seg.tree],
        bark=bark[trees.tree_id[seg.tree]],
        frame=frame,
        vol_centre=vol_centre,
        vol_radius=vol_radius,
        vol_half=vol_half,
        vol_cone=vol_cone,
        vol_lambda=np.concatenate(
            [trees.foliage_density[crowned], np.full(n_s, SHRUB_FOLIAGE_DENSITY)]
        ),
        vol_label=np.concatenate(
            [np.full(n_c, CROWN, np.uint8), np.full(n_s, UNDERSTORY, np.uint8)]
        ),
        vol_tree_id=np.concatenate([trees.tree_id[crowned], np.zeros(n_s, np.int64)]),
        bb_xy=bb_xy,
        bb_r=bb_r,
        bb_z=bb_z,
        box=_box(terrain, bounds, gradient_bound, bb_xy, bb_r, bb_z),
    )


def _pairs(
    origin: NDArray[np.float64],
    dirs: NDArray[np.float64],
    scene: Scene,
    objects: NDArray[np.intp],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(ray, object) pairs whose azimuth and elevation fall in the object's bounding
    cylinder as seen from ``origin``."""
    az = np.arctan2(dirs[:, 1], dirs[:, 0])
    el = np.arcsin(np.clip(dirs[:, 2], -1.0, 1.0))
    order = np.argsort(az)
    az_sorted = az[order]
    rel = scene.bb_xy[objects] - origin[:2]
    d = np.hypot(rel[:, 0], rel[:, 1])
    r = scene.bb_r[objects]
    full = d <= r
    half = np.arcsin(np.clip(r / np.maximum(d, 1e-12), 0.0, 1.0))
    mid = np.arctan2(rel[:, 1], rel[:, 0])
    lo = np.where(full, -np.pi, mid - half)
    hi = np.where(full, np.pi, mid + half)
    # Intervals crossing +-pi: the part beyond, wrapped, as an extra interval.
    over = np.flatnonzero(hi > np.pi)
    under = np.flatnonzero(lo < -np.pi)
    pos = np.concatenate([np.arange(len(objects)), over, under])
    ilo = np.concatenate(
        [np.maximum(lo, -np.pi), np.full(len(over), -np.pi), lo[under] + 2 * np.pi]
    )
    ihi = np.concatenate([np.minimum(hi, np.pi), hi[over] - 2 * np.pi, np.full(len(under), np.pi)])
    first = np.searchsorted(az_sorted, ilo, side="left")
    count = np.searchsorted(az_sorted, ihi, side="right") - first
    total = int(count.sum())
    owner = np.repeat(pos, count)
    offset = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
    ray = order[np.repeat(first, count) + offset]
    pair_obj = objects[owner]
    # Elevation range of the bounding cylinder.
    dmin, dmax = np.maximum(d - r, 0.0)[owner], (d + r)[owner]
    zlo = scene.bb_z[pair_obj, 0] - origin[2]
    zhi = scene.bb_z[pair_obj, 1] - origin[2]
    el_lo = np.arctan2(zlo, np.where(zlo < 0, dmin, dmax))
    el_hi = np.arctan2(zhi, np.where(zhi > 0, dmin, dmax))
    keep = (el[ray] >= el_lo) & (el[ray] <= el_hi)
    return ray[keep], pair_obj[keep]


def _stem_hits(
    origin: NDArray[np.float64],
    dirs: NDArray[np.float64],
    seg: StemSegments,
    ray: NDArray[np.intp],
    j: NDArray[np.intp],
    t_min: float,
) -> NDArray[np.float64]:
    """Range of the first hit of each (ray, frustum) pair on the frustum's side (inf: none)."""
    v, a = dirs[ray], seg.axis[j]
    w0 = origin - seg.start[j]
    k = (seg.r1[j] - seg.r0[j]) / seg.length[j]
    h0 = np.einsum("ij,ij->i", w0, a)
    c0 = seg.r0[j] + k * h0
    hv = np.einsum("ij,ij->i", v, a)
    qa = 1.0 - hv**2 * (1.0 + k**2)
    qb = 2.0 * (np.einsum("ij,ij->i", w0, v) - h0 * hv - c0 * k * hv)
    qc = np.einsum("ij,ij->i", w0, w0) - h0**2 - c0**2
    disc = qb**2 - 4.0 * qa * qc
    ok = (disc >= 0) & (np.abs(qa) > 1e-12)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    denom = np.where(ok, 2.0 * qa, 1.0)
    best = np.full(len(ray), np.inf)
    for t in ((-qb - sq) / denom, (-qb + sq) / denom):
        h = h0 + t * hv
        valid = ok & (t >= t_min) & (h >= 0) & (h <= seg.length[j]) & (c0 + k * t * hv >= 0)
        best = np.where(valid & (t < best), t, best)
    return best


def _volume_spans(
    origin: NDArray[np.float64],
    dirs: NDArray[np.float64],
    scene: Scene,
    ray: NDArray[np.intp],
    j: NDArray[np.intp],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Entry and exit ranges of each (ray, volume) pair (entry >= exit: missed)."""
    v = dirs[ray]
    c, radius, half = scene.vol_centre[j], scene.vol_radius[j], scene.vol_half[j]
    cone = scene.vol_cone[j]
    q = origin - c
    # Ellipsoid: the unit sphere after scaling by the semi-axes.
    scale = np.column_stack([radius, radius, half])
    u, d = q / scale, v / scale
    ea = np.einsum("ij,ij->i", d, d)
    eb = 2.0 * np.einsum("ij,ij->i", u, d)
    ec = np.einsum("ij,ij->i", u, u) - 1.0
    # Cone (apex at c, opening downwards): rho^2 <= (k (z_apex - z))^2 within the slab.
    k2 = (radius / half) ** 2
    ca = v[:, 0] ** 2 + v[:, 1] ** 2 - k2 * v[:, 2] ** 2
    cb = 2.0 * (q[:, 0] * v[:, 0] + q[:, 1] * v[:, 1] - k2 * q[:, 2] * v[:, 2])
    cc = q[:, 0] ** 2 + q[:, 1] ** 2 - k2 * q[:, 2] ** 2
    qa, qb, qc = np.where(cone, ca, ea), np.where(cone, cb, eb), np.where(cone, cc, ec)
    disc = qb**2 - 4.0 * qa * qc
    real = disc >= 0
    sq = np.sqrt(np.where(real, disc, 0.0))
    safe = np.where(np.abs(qa) > 1e-15, qa, 1e-15)
    r1 = np.minimum((-qb - sq) / (2 * safe), (-qb + sq) / (2 * safe))
    r2 = np.maximum((-qb - sq) / (2 * safe), (-qb + sq) / (2 * safe))
    big = np.full(len(ray), 1e18)  # finite: no inf - inf below
    up = qa > 0  # inside between the roots; else outside them (or everywhere, disc < 0)
    p1_lo = np.where(up, np.where(real, r1, big), -big)
    p1_hi = np.where(up, np.where(real, r2, -big), np.where(real, r1, big))
    p2_lo = np.where(up | ~real, big, r2)
    # Cones are cut to their slab z in [apex - depth, apex].
    vz = np.where(np.abs(v[:, 2]) > 1e-12, v[:, 2], 1e-12)
    za, zb = (-half - q[:, 2]) / vz, -q[:, 2] / vz
    s_lo = np.where(cone, np.minimum(za, zb), -big)
    s_hi = np.where(cone, np.maximum(za, zb), big)
    a_lo, a_hi = np.maximum(p1_lo, s_lo), np.minimum(p1_hi, s_hi)
    b_lo, b_hi = np.maximum(p2_lo, s_lo), s_hi
    second = (b_hi - b_lo) > (a_hi - a_lo)
    return np.where(second, b_lo, a_lo), np.where(second, b_hi, a_hi)


def _terrain_hits(
    scene: Scene,
    origin: NDArray[np.float64],
    dirs: NDArray[np.float64],
    t_from: NDArray[np.float64],
    t_lim: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Range of the first terrain crossing of each ray between ``t_from`` and ``t_lim``
    (inf: none).

    Steps of ``clearance / max descent rate`` cannot cross the terrain (its gradient is
    bounded); steps of at least 0.25 m may, and the crossing is then found by bisection."""
    h_min = 0.25
    terrain = scene.terrain
    descent = scene.gradient_bound * np.hypot(dirs[:, 0], dirs[:, 1]) - dirs[:, 2]

    def clearance(i: NDArray[np.intp], t: NDArray[np.float64]) -> NDArray[np.float64]:
        p = origin + t[:, None] * dirs[i]
        return p[:, 2] - terrain.height(p[:, 0], p[:, 1])

    out = np.full(len(dirs), np.inf)
    active = np.flatnonzero((descent > 0) & (t_lim > t_from))
    t = t_from[active]
    f = clearance(active, t)
    lo_i, lo_t, hi_t = [np.empty(0, np.intp)], [np.empty(0)], [np.empty(0)]
    while len(active):
        t_new = np.minimum(t + np.maximum(f / descent[active], h_min), t_lim[active])
        f_new = clearance(active, t_new)
        crossed = f_new <= 0
        lo_i.append(active[crossed])
        lo_t.append(t[crossed])
        hi_t.append(t_new[crossed])
        going = ~crossed & (t_new < t_lim[active])
        active, t, f = active[going], t_new[going], f_new[going]
    idx, lo, hi = np.concatenate(lo_i), np.concatenate(lo_t), np.concatenate(hi_t)
    for _ in range(14):
        mid = (lo + hi) / 2.0
        below = clearance(idx, mid) <= 0
        hi = np.where(below, mid, hi)
        lo = np.where(below, lo, mid)
    out[idx] = hi
    return out


def _bark_offset(
    scene: Scene, j: NDArray[np.intp], xyz: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Radial bark roughness (m) at stem points ``xyz`` of frustums ``j``, and the outward
    normals."""
    seg = scene.stems
    w = xyz - seg.start[j]
    h = np.einsum("ij,ij->i", w, seg.axis[j])
    radial = w - h[:, None] * seg.axis[j]
    normal = radial / np.maximum(np.linalg.norm(radial, axis=1), 1e-12)[:, None]
    frame = scene.frame[j]
    theta = np.arctan2(
        np.einsum("ij,ij->i", normal, frame[:, 1]), np.einsum("ij,ij->i", normal, frame[:, 0])
    )
    s = seg.s0[j] + h
    bark = scene.bark[j]
    waves = np.cos(bark[..., 0] * theta[:, None] + bark[..., 1] * s[:, None] + bark[..., 2])
    return scene.bark_std[j] * np.sqrt(2.0 / _BARK_TERMS) * waves.sum(axis=1), normal


def cast_rays(
    rng: np.random.Generator,
    scene: Scene,
    origin: NDArray[np.float64],
    dirs: NDArray[np.float64],
    *,
    min_range: float,
    max_range: float,
    noise_std: float,
) -> RayHits:
    """The first hit of every ray from ``origin`` (CRS) along unit ``dirs`` (n, 3)."""
    n_stem = len(scene.stems)
    t_from, t_to = _box_span(scene.box, origin, dirs)
    t_from, t_to = np.maximum(t_from, min_range), np.minimum(t_to, max_range)
    live = np.flatnonzero(t_to > t_from)  # the others cannot return anything
    dirs, t_from, t_to = dirs[live], t_from[live], t_to[live]
    rel = scene.bb_xy - origin[:2]
    near = np.flatnonzero(np.hypot(rel[:, 0], rel[:, 1]) - scene.bb_r < max_range)
    ray, obj = _pairs(origin, dirs, scene, near)
    stem = obj < n_stem
    t_stem = _stem_hits(origin, dirs, scene.stems, ray[stem], obj[stem], min_range)
    vray, vol = ray[~stem], obj[~stem] - n_stem
    enter, leave = _volume_spans(origin, dirs, scene, vray, vol)
    enter = np.maximum(enter, min_range)
    crossing = np.flatnonzero(leave > enter)
    t_vol = enter[crossing] + rng.exponential(1.0, len(crossing)) / scene.vol_lambda[vol[crossing]]
    inside = t_vol < leave[crossing]
    hit_ray = np.concatenate([ray[stem], vray[crossing[inside]]])
    hit_obj = np.concatenate([obj[stem], obj[~stem][crossing[inside]]])
    hit_t = np.concatenate([t_stem, t_vol[inside]])
    finite = np.isfinite(hit_t) & (hit_t <= max_range)
    hit_ray, hit_obj, hit_t = hit_ray[finite], hit_obj[finite], hit_t[finite]
    best = np.full(len(dirs), np.inf)
    np.minimum.at(best, hit_ray, hit_t)
    first = np.full(len(dirs), -1)
    win = hit_t == best[hit_ray]
    first[hit_ray[win]] = hit_obj[win]
    t_ground = _terrain_hits(scene, origin, dirs, t_from, np.minimum(best, t_to))
    ground = np.isfinite(t_ground)
    t = np.where(ground, t_ground, best)
    returned = np.flatnonzero(np.isfinite(t))
    t, obj_of, is_ground = t[returned], first[returned], ground[returned]
    xyz = origin + t[:, None] * dirs[returned]
    label = np.full(len(returned), GROUND, dtype=np.uint8)
    tree_id = np.zeros(len(returned), dtype=np.int64)
    on_stem = ~is_ground & (obj_of < n_stem)
    on_vol = ~is_ground & (obj_of >= n_stem)
    label[on_stem] = STEM
    tree_id[on_stem] = scene.stem_tree_id[obj_of[on_stem]]
    label[on_vol] = scene.vol_label[obj_of[on_vol] - n_stem]
    tree_id[on_vol] = scene.vol_tree_id[obj_of[on_vol] - n_stem]
    offset, normal = _bark_offset(scene, obj_of[on_stem], xyz[on_stem])
    xyz[on_stem] += offset[:, None] * normal
    noise = rng.normal(0.0, noise_std, len(returned))
    xyz += noise[:, None] * dirs[returned]
    xmin, ymin, xmax, ymax = scene.bounds
    outside = is_ground & (
        (xyz[:, 0] < xmin) | (xyz[:, 0] > xmax) | (xyz[:, 1] < ymin) | (xyz[:, 1] > ymax)
    )
    keep = ~outside
    return RayHits(live[returned[keep]], (t + noise)[keep], xyz[keep], label[keep], tree_id[keep])


def _cast_node(
    rng: np.random.Generator,
    scene: Scene,
    origin: NDArray[np.float64],
    n_rays: int,
    model: RaycastScanner,
) -> RayHits:
    parts = []
    for start in range(0, n_rays, RAY_BATCH):
        dirs = model.directions(rng, min(RAY_BATCH, n_rays - start))
        hits = cast_rays(
            rng,
            scene,
            origin,
            dirs,
            min_range=model.min_range,
            max_range=model.max_range,
            noise_std=model.noise_std,
        )
        parts.append(replace(hits, ray=hits.ray + start))
    return RayHits(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in RayHits.__dataclass_fields__)
    )


def raycast_scan(
    rng: np.random.Generator,
    sensors: NDArray[np.float64],
    trees: Trees,
    shrubs: Shrubs,
    terrain: Terrain,
    bounds: tuple[float, float, float, float],
    n_points: int,
    model: RaycastScanner,
) -> ScanPoints:
    """About ``n_points`` first returns from the nodes ``sensors`` (CRS, (M, 3)).

    Every node casts the same number of rays: a pilot of ``n_points / M`` rays each gives
    the hit rate, then each casts the rays still needed for ``n_points`` at that rate."""
    scene = build_scene(trees, shrubs, terrain, bounds)
    origins = sensors + np.array([0.0, 0.0, rng.uniform(*model.altitude)])
    m = len(origins)
    pilot = math.ceil(n_points / m)
    hits = [[_cast_node(rng, scene, o, pilot, model)] for o in origins]
    got = sum(len(h[0].t) for h in hits)
    rate = max(got / (pilot * m), 0.02)
    extra = math.ceil(max(n_points - got, 0) / rate / m)
    if extra:
        for node, o in zip(hits, origins, strict=True):
            node.append(_cast_node(rng, scene, o, extra, model))
    parts = [p for node in hits for p in node]
    xyz = np.concatenate([p.xyz for p in parts])
    label = np.concatenate([p.label for p in parts])
    dist = np.concatenate([p.t for p in parts])
    intensity = np.zeros(len(xyz), np.float32)
    for cls, base in _BASE_INTENSITY.items():
        sel = label == cls
        intensity[sel] = _intensity(rng, base, dist[sel])
    return ScanPoints(xyz, intensity, label, np.concatenate([p.tree_id for p in parts]))
