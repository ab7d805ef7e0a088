"""The mixed stand and the ray-casting scanners: occlusion, exact stems, porous crowns,
under-canopy versus airborne views, stand structure, truth, determinism, the default demo."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

from standgrid.simulate import SimulationConfig, load_truth, run_simulation
from standgrid.simulate.canopy import (
    FORK_ANGLE_DEG,
    crown_centres,
    generate_mixed_forest,
    stem_radius_at,
    taper_length,
)
from standgrid.simulate.forest import (
    CONIFER,
    HARVESTED,
    OVERSTOREY,
    SNAG,
    UNDERSTOREY,
    Shrubs,
    Trees,
    generate_forest,
    grow_forest,
    stem_axes,
)
from standgrid.simulate.mission import stand_bounds
from standgrid.simulate.raycast import RAYCAST_SCANNERS, build_scene, cast_rays
from standgrid.simulate.scanner import CROWN, GROUND, STEM, UNDERSTORY
from standgrid.simulate.terrain import Terrain, random_terrain
from standgrid.simulate.truth import TREE_COLUMNS, write_trees_csv

BOUNDS = (-100.0, -100.0, 100.0, 100.0)
FLAT = Terrain(0.0, (0.0, 0.0), (0.0, 0.0), np.zeros((0, 4)))
NO_SHRUBS = Shrubs(*(np.zeros(0) for _ in range(5)))
HANDHELD = RAYCAST_SCANNERS["handheld"]


def _trees(terrain: Terrain = FLAT, **cols: Any) -> Trees:
    """A hand-made tree list; unspecified columns get plain values."""
    n = len(cols["x"])
    base: dict[str, Any] = {
        "tree_id": np.arange(1, n + 1, dtype=np.int64),
        "dbh": np.full(n, 0.4),
        "height": np.full(n, 20.0),
        "crown_base": np.full(n, 12.0),
        "crown_radius": np.zeros(n),
        "species": np.full(n, CONIFER).astype(np.str_),
        "status": np.full(n, "alive").astype(np.str_),
    }
    base.update({k: np.asarray(v) for k, v in cols.items()})
    base["z_ground"] = terrain.height(base["x"], base["y"])
    if "lean_deg" in cols:
        axis = stem_axes(base["lean_deg"], base["lean_azimuth_deg"])
        base["x_bh"] = base["x"] + 1.3 * axis[:, 0]
        base["y_bh"] = base["y"] + 1.3 * axis[:, 1]
    return Trees(**base)


def _cast(
    trees: Trees,
    origin: Any,
    dirs: Any,
    terrain: Terrain = FLAT,
    seed: int = 0,
    noise: float = 0.008,
) -> Any:
    scene = build_scene(trees, NO_SHRUBS, terrain, BOUNDS)
    return cast_rays(
        np.random.default_rng(seed),
        scene,
        np.asarray(origin, float),
        np.asarray(dirs, float),
        min_range=0.5,
        max_range=40.0,
        noise_std=noise,
    )


def _fan(rng: np.random.Generator, n: int, az_deg: float, el_deg: tuple[float, float]) -> Any:
    az = np.radians(rng.uniform(-az_deg, az_deg, n))
    el = np.radians(rng.uniform(*el_deg, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _aimed(rng: np.random.Generator, origin: Any, centre: Any, half: Any, n: int) -> Any:
    target = np.asarray(centre) + rng.uniform(-1, 1, (n, 3)) * np.asarray(half)
    d = target - np.asarray(origin)
    return d / np.linalg.norm(d, axis=1)[:, None]


# --- occlusion ----------------------------------------------------------------------------


def test_a_stem_shadows_the_ground_behind_it() -> None:
    rng = np.random.default_rng(1)
    dirs = _fan(rng, 40_000, 12.0, (-12.0, -3.0))  # ground hits 4.7-19 m ahead
    stem = _trees(x=[5.0], y=[0.0], dbh=[0.6])
    empty = stem.select(np.zeros(1, dtype=bool))
    shadow = np.degrees(np.arcsin(0.3 / 5.0)) * 0.9
    for trees, blocked in ((stem, True), (empty, False)):
        hits = _cast(trees, [0.0, 0.0, 1.0], dirs)
        ground = hits.xyz[hits.label == GROUND]
        behind = np.hypot(ground[:, 0], ground[:, 1]) > 5.3
        bearing = np.degrees(np.abs(np.arctan2(ground[:, 1], ground[:, 0])))
        in_shadow = int((behind & (bearing < shadow)).sum())
        if blocked:
            assert in_shadow == 0
            assert (hits.label == STEM).sum() > 300
            assert (behind & (bearing > shadow + 1.0)).sum() > 5000  # the rest is seen
        else:
            assert in_shadow > 500


# --- exact stems ----------------------------------------------------------------------------


def _slope() -> Terrain:
    return Terrain(0.0, (0.0, 0.0), (0.06, -0.03), np.zeros((0, 4)))


def test_stem_points_lie_on_the_tapered_leaning_stem_and_give_its_dbh() -> None:
    terrain = _slope()
    trees = _trees(
        terrain,
        x=[0.0],
        y=[0.0],
        dbh=[0.42],
        height=[24.0],
        crown_base=[15.0],
        crown_radius=[2.0],
        foliage_density=[0.5],
        lean_deg=[12.0],
        lean_azimuth_deg=[60.0],
    )
    u = stem_axes(trees.lean_deg, trees.lean_azimuth_deg)[0]
    base = np.array([0.0, 0.0, trees.z_ground[0]])
    bh = base + 1.3 * u
    rng = np.random.default_rng(2)
    xyz = []
    for ang in np.radians([20.0, 110.0, 200.0, 290.0]):
        origin = bh + np.array([5.0 * np.cos(ang), 5.0 * np.sin(ang), 0.0])
        origin[2] = terrain.height(origin[0], origin[1]) + 1.2
        dirs = np.vstack(
            [HANDHELD.directions(rng, 30_000), _aimed(rng, origin, bh, [0.4, 0.4, 0.12], 6000)]
        )
        hits = _cast(trees, origin, dirs, terrain, seed=int(np.degrees(ang)))
        xyz.append(hits.xyz[hits.label == STEM])
    pts = np.vstack(xyz)
    w = pts - base
    s = w @ u
    radial = np.linalg.norm(w - s[:, None] * u, axis=1)
    expected = stem_radius_at(trees.dbh[[0] * len(s)], taper_length(trees)[[0] * len(s)], s)
    tolerance = 4.0 * np.hypot(0.008, 0.005)  # range noise and conifer bark roughness
    assert len(pts) > 2000 and s.max() > 6.0
    assert np.abs(radial - expected).max() < tolerance
    assert abs(np.mean(radial - expected)) < 0.002
    # Circle fit in the plane perpendicular to the axis, 1.3 m +- 2 cm along it.
    e1 = np.cross(u, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    sl = np.abs(s - 1.3) < 0.02
    p, q = w[sl] @ e1, w[sl] @ e2
    assert sl.sum() > 100
    coef = np.linalg.lstsq(np.column_stack([p, q, np.ones(len(p))]), -(p**2 + q**2), rcond=None)[0]
    cp, cq = -coef[0] / 2, -coef[1] / 2
    dbh = 2.0 * np.sqrt(cp**2 + cq**2 - coef[2])
    centre = base + 1.3 * u + cp * e1 + cq * e2
    assert abs(dbh - 0.42) < 0.01
    assert np.hypot(centre[0] - trees.x_bh[0], centre[1] - trees.y_bh[0]) < 0.02
    assert np.hypot(bh[0] - trees.x_bh[0], bh[1] - trees.y_bh[0]) < 1e-9


def test_a_forked_stem_has_two_leaders_on_their_cones() -> None:
    trees = _trees(
        x=[0.0],
        y=[0.0],
        dbh=[0.36],
        height=[22.0],
        lean_deg=[4.0],
        lean_azimuth_deg=[200.0],
        fork_height_m=[10.0],
    )
    u = stem_axes(trees.lean_deg, trees.lean_azimuth_deg)[0]
    s_f = 10.0 / u[2]
    fork = s_f * u
    az = np.radians(200.0)
    side = np.array([np.cos(az), -np.sin(az), 0.0])
    alpha = np.radians(FORK_ANGLE_DEG)
    length = taper_length(trees)[0]
    r_fork = stem_radius_at(trees.dbh, np.array([length]), np.array([s_f]))[0] / np.sqrt(2)
    lead = (22.0 - 10.0) / (np.cos(alpha) * u[2])
    rng = np.random.default_rng(3)
    pts = []
    for k, ang in enumerate(np.radians([0.0, 120.0, 240.0])):
        origin = np.array([7.0 * np.cos(ang), 7.0 * np.sin(ang), 1.2])
        dirs = _aimed(rng, origin, fork + np.array([0.0, 0.0, 5.0]), [2.5, 2.5, 8.0], 30_000)
        hits = _cast(trees, origin, dirs, seed=k)
        pts.append(hits.xyz[hits.label == STEM])
    p = np.vstack(pts)
    devs = []
    for sign in (1.0, -1.0):
        d = np.cos(alpha) * u + sign * np.sin(alpha) * side
        h = (p - fork) @ d
        radial = np.linalg.norm(p - fork - h[:, None] * d, axis=1)
        devs.append(np.where((h >= -0.05) & (h <= lead), radial - r_fork * (1 - h / lead), 1.0))
    s = p @ u
    trunk_dev = np.linalg.norm(p - s[:, None] * u, axis=1) - stem_radius_at(
        np.full(len(s), 0.36), np.full(len(s), length), s
    )
    dev = np.min(np.abs([*devs, np.where(s <= s_f, trunk_dev, 1.0)]), axis=0)
    on_leader = [(np.abs(d) < 0.04) & (s > s_f + 0.5) for d in devs]
    assert dev.max() < 4.0 * np.hypot(0.008, 0.005)
    assert all(m.sum() > 50 for m in on_leader)  # both leaders are seen
    assert (p[:, 2] > 12.0).sum() > 100


# --- porous crowns --------------------------------------------------------------------------


def _truncated_exponential_check(depth: Any, lam: float, length: float, n_rays: int) -> None:
    p_hit = 1.0 - np.exp(-lam * length)
    assert abs(len(depth) / n_rays - p_hit) < 4.0 * np.sqrt(p_hit * (1 - p_hit) / n_rays)
    cdf = lambda d: (1.0 - np.exp(-lam * d)) / p_hit  # noqa: E731
    assert stats.kstest(depth, cdf).pvalue > 1e-3
    mean = 1.0 / lam - length * np.exp(-lam * length) / p_hit
    assert abs(depth.mean() - mean) < 0.05
    assert depth.min() >= -1e-9 and depth.max() <= length + 1e-9


def test_crowns_are_porous_with_exponential_hit_depths() -> None:
    n = 20_000
    # A broadleaf (sphere of radius 3 around (10, 0, 13)) crossed 1.5 m off its centre.
    ball = _trees(
        x=[10.0],
        y=[0.0],
        height=[16.0],
        crown_base=[10.0],
        crown_radius=[3.0],
        species=["broadleaf"],
        foliage_density=[0.3],
    )
    hits = _cast(ball, [0.0, 1.5, 13.0], np.tile([1.0, 0.0, 0.0], (n, 1)), noise=0.0)
    chord = 2.0 * np.sqrt(9.0 - 1.5**2)
    assert set(hits.label.tolist()) == {CROWN}
    _truncated_exponential_check(hits.t - (10.0 - chord / 2), 0.3, chord, n)
    # A conifer (cone from 8 m to its 16 m apex, radius 2) crossed upwards 1 m off its axis.
    cone = _trees(
        x=[0.0], y=[0.0], height=[16.0], crown_base=[8.0], crown_radius=[2.0], foliage_density=[0.5]
    )
    hits = _cast(cone, [1.0, 0.0, 1.0], np.tile([0.0, 0.0, 1.0], (n, 1)), noise=0.0)
    assert set(hits.label.tolist()) == {CROWN}
    _truncated_exponential_check(hits.t - 7.0, 0.5, 8.0 - 1.0 / (2.0 / 8.0), n)


# --- the whole scanner in a mixed stand -----------------------------------------------------


MIXED = SimulationConfig(
    area=60.0, points_per_payload=20_000, forest="mixed", scanner_kind="handheld", lane_spacing=15.0
)


@pytest.fixture(scope="module")
def handheld() -> Any:
    sim = run_simulation(3, 1, MIXED)
    return sim, [sim.payload(k)[1] for k in range(len(sim.spans))]


def _highest_crown_gaps(sim: Any, scans: list[Any]) -> dict[int, float]:
    """True top minus the highest crown point, for overstorey trees with >= 30 crown points."""
    xyz = np.vstack([p.xyz for p in scans])
    crown = np.concatenate([p.label for p in scans]) == CROWN
    ids, inv, count = np.unique(
        np.concatenate([p.tree_id for p in scans])[crown], return_inverse=True, return_counts=True
    )
    zmax = np.full(len(ids), -np.inf)
    np.maximum.at(zmax, inv, xyz[crown, 2])
    t = sim.world.trees
    row = np.searchsorted(t.tree_id, ids)
    keep = (t.kind[row] == OVERSTOREY) & (count >= 30)
    gap = (t.z_ground + t.height)[row] - zmax
    return dict(zip(ids[keep].tolist(), gap[keep].tolist(), strict=True))


def test_handheld_sees_crowns_from_below_and_understorey_stems(handheld: Any) -> None:
    sim, scans = handheld
    n = np.array([len(p.xyz) for p in scans])
    assert abs(n.mean() / MIXED.points_per_payload - 1.0) < 0.05
    labels = np.concatenate([p.label for p in scans])
    assert {GROUND, STEM, CROWN, UNDERSTORY} <= set(labels.tolist())
    gaps = np.array(list(_highest_crown_gaps(sim, scans).values()))
    assert len(gaps) > 50 and gaps.mean() > 1.0 and gaps.min() > -0.05
    # Understorey stems within 5 m of the path get points around 1.3 m along the stem.
    t = sim.world.trees
    xyz = np.vstack([p.xyz for p in scans])
    tid = np.concatenate([p.tree_id for p in scans])
    stem = labels == STEM
    row = np.searchsorted(t.tree_id, tid[stem])
    u = stem_axes(t.lean_deg, t.lean_azimuth_deg)[row]
    s = np.einsum("ij,ij->i", xyz[stem] - np.column_stack([t.x, t.y, t.z_ground])[row], u)
    seen = np.unique(tid[stem][np.abs(s - 1.3) < 0.2])
    under = np.flatnonzero(t.kind == UNDERSTOREY)
    dist = np.hypot(
        t.x_bh[under, None] - sim.node_crs[None, :, 0],
        t.y_bh[under, None] - sim.node_crs[None, :, 1],
    ).min(axis=1)
    near = t.tree_id[under[dist < 5.0]]
    assert len(near) > 30 and np.isin(near, seen).mean() > 0.8
    assert not np.isin(t.tree_id[t.kind == SNAG], tid[labels == CROWN]).any()


def test_airborne_sees_crowns_and_ground_and_reaches_the_tops(handheld: Any) -> None:
    sim, scans = handheld
    air = replace(sim, config=replace(MIXED, scanner_kind="airborne"))
    ks = range(0, len(sim.spans), 3)
    above = [air.payload(k)[1] for k in ks]
    labels = np.concatenate([p.label for p in above])
    share = np.bincount(labels, minlength=5) / len(labels)
    assert share[CROWN] + share[GROUND] > 0.85 and share[STEM] < 0.03 and share[CROWN] > 0.3
    below = _highest_crown_gaps(sim, scans)
    from_air = _highest_crown_gaps(air, above)
    common = sorted(set(below) & set(from_air))
    assert len(common) > 30
    gap_air = np.mean([from_air[i] for i in common])
    gap_below = np.mean([below[i] for i in common])
    assert gap_air < 0.6 and gap_below > gap_air + 0.7


def test_same_seed_same_points() -> None:
    config = replace(MIXED, area=40.0, points_per_payload=3000, scanner_kind="legged")
    a = run_simulation(5, 1, config).payload(1)
    b = run_simulation(5, 1, config).payload(1)
    for x, y in zip(a[1].__dict__.values(), b[1].__dict__.values(), strict=True):
        assert np.array_equal(x, y)
    assert np.array_equal(a[0].xyz, b[0].xyz)
    other = run_simulation(5, 1, config).payload(2)[1]
    assert len(a[1].xyz) > 2000 and not np.array_equal(other.xyz[:100], a[1].xyz[:100])


# --- the stand ------------------------------------------------------------------------------


def test_mixed_stand_structure_and_growth() -> None:
    rng = np.random.default_rng(4)
    bounds = stand_bounds(100.0)
    terrain = random_terrain(rng, bounds)
    trees, shrubs = generate_mixed_forest(rng, bounds, terrain)
    kind = trees.kind
    over, under, snag = kind == OVERSTOREY, kind == UNDERSTOREY, kind == SNAG
    assert (over.sum(), under.sum(), snag.sum(), len(shrubs)) == (300, 350, 20, 600)
    assert np.array_equal(trees.tree_id, np.arange(1, len(trees) + 1))
    assert trees.dbh[over].min() >= 0.15 and trees.dbh[over].max() <= 0.70
    assert trees.height[over].min() >= 18.0 and trees.height[over].max() <= 35.0
    assert trees.dbh[under].min() >= 0.06 and trees.dbh[under].max() <= 0.15
    assert trees.height[under].min() >= 3.0 and trees.height[under].max() <= 12.0
    assert np.all((trees.crown_radius[under] >= 0.6) & (trees.crown_radius[under] <= 2.0))
    assert np.all(trees.crown_base[under] >= 1.5) and np.all(trees.crown_base[under] <= 5.0)
    ratio = trees.crown_base[over] / trees.height[over]
    assert ratio.min() >= 0.35 and ratio.max() <= 0.65
    assert trees.dbh[snag].min() >= 0.10 and trees.dbh[snag].max() <= 0.45
    assert trees.height[snag].min() >= 3.0 and trees.height[snag].max() <= 18.0
    assert np.all(trees.crown_radius[snag] == 0) and np.all(trees.foliage_density[snag] == 0)
    assert set(np.unique(trees.species).tolist()) == {"conifer", "broadleaf"}
    # Understorey under overstorey crowns (horizontally inside one).
    centres = crown_centres(trees)[over]
    d = np.hypot(
        trees.x[under, None] - centres[None, :, 0], trees.y[under, None] - centres[None, :, 1]
    )
    assert (d < trees.crown_radius[over][None, :]).any(axis=1).mean() > 0.6
    # Leaning and forked stems.
    assert np.all((trees.lean_deg > 0) & (trees.lean_deg <= 15.0))
    assert 0.08 < (trees.lean_deg > 5).mean() < 0.22
    forked = np.isfinite(trees.fork_height_m)
    assert np.all(over[forked]) and 0.03 < forked[over].mean() < 0.14
    fork_ratio = trees.fork_height_m[forked] / trees.height[forked]
    assert fork_ratio.min() >= 0.4 and fork_ratio.max() <= 0.75
    assert trees.fork_height_m[forked].min() > 2.0
    axis = stem_axes(trees.lean_deg, trees.lean_azimuth_deg)
    assert np.allclose(trees.x_bh, trees.x + 1.3 * axis[:, 0])
    assert np.allclose(trees.y_bh, trees.y + 1.3 * axis[:, 1])
    # DBH is the diameter 1.3 m along the axis; the butt swells, the top tapers to 0.
    length = taper_length(trees)
    at = lambda s: stem_radius_at(trees.dbh, length, np.full(len(trees), s))  # noqa: E731
    assert np.allclose(at(1.3), trees.dbh / 2) and np.all(at(0.0) > at(1.3))
    assert np.allclose(stem_radius_at(trees.dbh, length, length)[~snag], 0.0)
    assert np.all(stem_radius_at(trees.dbh, length, trees.height / axis[:, 2])[snag] > 0.005)
    assert (shrubs.height.min(), shrubs.height.max()) >= (0.3, 2.0)
    assert shrubs.height.max() <= 2.5
    # Growth: the understorey slowly, snags not at all, and only living trees are harvested.
    grown = grow_forest(np.random.default_rng(5), trees, terrain, years=4.0)
    dh = grown.height[: len(trees)] - trees.height
    alive = grown.status[: len(trees)] != HARVESTED
    assert np.all(dh[under & alive] >= 0.8 - 1e-9) and np.all(dh[under & alive] <= 1.6 + 1e-9)
    assert np.all(dh[over & alive] >= 1.2 - 1e-9)
    assert np.all(dh[snag] == 0) and np.all(grown.dbh[: len(trees)][snag] == trees.dbh[snag])
    assert not np.any(grown.status[: len(trees)][snag] == HARVESTED)
    new = grown.select(grown.status == "new")
    assert len(new) == 3 and np.all(new.lean_deg > 0) and np.all(new.kind == OVERSTOREY)
    for col in ("lean_deg", "lean_azimuth_deg", "fork_height_m", "x_bh", "y_bh"):
        np.testing.assert_array_equal(getattr(grown, col)[: len(trees)], getattr(trees, col))


# --- truth, wiring, the default demo --------------------------------------------------------


def test_truth_holds_the_stand_and_old_tree_lists_still_read(tmp_path: Path) -> None:
    from standgrid.cli import cli

    out = tmp_path / "sim"
    args = [
        "simulate",
        str(out),
        "--area",
        "40",
        "--points-per-payload",
        "500",
        "--forest",
        "mixed",
        "--scanner",
        "legged",
        "--lane-spacing",
        "12",
        "-q",
    ]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    sim = run_simulation(
        0,
        2,
        replace(MIXED, area=40.0, points_per_payload=500, scanner_kind="legged", lane_spacing=12.0),
    )
    truth = load_truth(out / "truth" / sim.name)
    assert truth.trees is not None
    assert truth.info["forest"] == "mixed" and truth.info["scanner"]["kind"] == "legged"
    assert truth.info["lane_spacing_m"] == 12.0
    expected = sim.world.trees
    assert np.array_equal(truth.trees.kind, expected.kind)
    for col in ("lean_deg", "lean_azimuth_deg", "fork_height_m", "x_bh", "y_bh", "dbh"):
        np.testing.assert_allclose(getattr(truth.trees, col), getattr(expected, col), atol=6e-4)
    assert np.isnan(truth.trees.fork_height_m).sum() == np.isnan(expected.fork_height_m).sum()
    # A tree list without the new columns reads with the plantation's values.
    plain = generate_forest(np.random.default_rng(0), BOUNDS, FLAT)[0]
    write_trees_csv(plain, tmp_path / "trees.csv")
    header = (tmp_path / "trees.csv").read_text().splitlines()[0]
    assert header == ",".join(TREE_COLUMNS)
    sim_dir = out / "truth" / sim.name
    (sim_dir / "trees.csv").write_text((tmp_path / "trees.csv").read_text())
    old = load_truth(sim_dir).trees
    assert old is not None and old.is_plantation
    assert np.all(old.kind == OVERSTOREY) and np.array_equal(old.x_bh, old.x)
    assert np.all(np.isnan(old.fork_height_m)) and np.all(old.lean_deg == 0)
    # The surface scanner cannot draw the mixed stand.
    bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "x"), "--forest", "mixed"])
    assert bad.exit_code == 2 and "ray-casting" in bad.output
    with pytest.raises(ValueError, match="scanner must be one of"):
        SimulationConfig(scanner_kind="lidar")


#: Recorded with the simulator before the mixed stand and the ray caster existed
#: (seed 11, area 50 m, 600 points per payload, everything else default).
BEFORE = {
    1: (
        581,
        [0, 83, 210, 240, 48],
        15481,
        [614713.4585423403, 5737139.755568268, 149.53402377915566],
        3690530787.169237,
        190.5162898376584,
        81,
        22.859521133044893,
        2083.3178594214046,
        96,
    ),
    2: (
        577,
        [0, 79, 210, 240, 48],
        11316,
        [614723.2916539717, 5737141.327201445, 148.8958731941025],
        3665123019.1970286,
        189.43964244425297,
        84,
        25.073131158884813,
        2253.6170752148732,
        89,
    ),
}


@pytest.mark.parametrize("epoch", [1, 2])
def test_the_default_demo_is_unchanged(epoch: int, tmp_path: Path) -> None:
    config = SimulationConfig(area=50.0, points_per_payload=600)
    assert (config.forest, config.scanner_kind, config.lane_spacing) == (
        "plantation",
        "surface",
        32.0,
    )
    sim = run_simulation(11, epoch, config)
    _, pts = sim.payload(0)
    n, counts, ids, first, total, intensity, n_trees, dbh, height, nodes = BEFORE[epoch]
    assert len(pts.xyz) == n and np.bincount(pts.label).tolist() == counts
    assert int(pts.tree_id.sum()) == ids
    np.testing.assert_allclose(pts.xyz[0], first, rtol=0, atol=1e-6)
    np.testing.assert_allclose(pts.xyz.sum(), total, rtol=1e-12)
    np.testing.assert_allclose(pts.intensity.astype(np.float64).sum(), intensity, rtol=1e-9)
    trees = sim.world.trees
    assert len(trees) == n_trees and trees.is_plantation and len(sim.node_crs) == nodes
    np.testing.assert_allclose([trees.dbh.sum(), trees.height.sum()], [dbh, height], rtol=1e-12)
    from standgrid.simulate.mission import write_truth_folder

    write_truth_folder(sim, tmp_path, config)
    info = json.loads((tmp_path / "truth.json").read_text())
    assert not {"forest", "lane_spacing_m"} & set(info) and "kind" not in info["scanner"]
    assert (tmp_path / "trees.csv").read_text().splitlines()[0] == ",".join(TREE_COLUMNS)
