"""fit_georeference / fit_from_pose_graph / georeference_mission against a known ground truth.

A true trajectory is made in ENU around Wytham Woods, mapped into a SLAM map frame by a known
T_map_enu; GNSS fixes are the true ENU positions at their own stamps plus noise, ~10 % gross
outliers (20-50 m) and some invalid fixes, converted to geodetic coordinates exactly.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from standgrid.errors import GeoreferenceError, InsufficientGnssError, NotGeoreferencedError
from standgrid.geometry import invert_pose, pose_matrix
from standgrid.georeference import (
    FIX_STATUS,
    GeoreferenceFit,
    enu_to_lla,
    fit_from_pose_graph,
    fit_georeference,
    georeference_mission,
)
from standgrid.georeference.fit import (
    GAP,
    OUTSIDE,
    USED,
    fix_sigmas,
    interpolate_trajectory,
    solve_rigid3d,
    solve_yaw2d,
)
from standgrid.mission.posegraph import PoseGraph, Vertex
from standgrid.mission.sensors import GnssFixes
from standgrid.stamps import NS_PER_S, Stamp

WYTHAM = (51.7735, -1.337, 120.0)
T0_NS = 1_715_680_000 * NS_PER_S


@dataclass
class Scenario:
    T_map_enu: np.ndarray
    node_stamps_ns: np.ndarray
    node_map: np.ndarray
    fix_stamps_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    quality: np.ndarray
    h_std: np.ndarray
    v_std: np.ndarray
    gross: np.ndarray  # bool: gross outlier injected
    invalid: np.ndarray  # bool: quality 0

    @property
    def T_enu_map(self) -> np.ndarray:
        return invert_pose(self.T_map_enu)

    def fit(self, **kw: object) -> GeoreferenceFit:
        return fit_georeference(
            fixes_of(self),
            self.node_stamps_ns,
            self.node_map,
            **kw,  # type: ignore[arg-type]
        )


def make_scenario(
    seed: int = 0,
    *,
    n_nodes: int = 300,
    noise: float = 0.03,
    outlier_fraction: float = 0.1,
    invalid_fraction: float = 0.05,
    roll_pitch_deg: float = 0.0,
    quality: int = 4,
    stated_h_std: float | None = None,
    straight: bool = False,
    static: bool = False,
) -> Scenario:
    rng = np.random.default_rng(seed)
    node_stamps = T0_NS + np.arange(n_nodes, dtype=np.int64) * NS_PER_S
    s = np.linspace(0.0, 4.0 * np.pi, n_nodes)
    if static:
        enu_nodes = np.zeros((n_nodes, 3)) + rng.normal(0, 0.01, (n_nodes, 3))
    elif straight:
        enu_nodes = np.stack(
            [2.0 * np.arange(n_nodes), np.zeros(n_nodes), 0.1 * np.arange(n_nodes)], -1
        )
    else:
        enu_nodes = np.stack(
            [120 * np.cos(s / 2) + 10 * s, 90 * np.sin(s), 8 * np.sin(0.7 * s)], -1
        )
    # Piecewise-linear truth between nodes, so time interpolation of the map is exact.
    fix_stamps = T0_NS + np.sort(rng.integers(0, (n_nodes - 1) * NS_PER_S, n_nodes))
    enu_fix_true = np.stack(
        [np.interp(fix_stamps - T0_NS, node_stamps - T0_NS, enu_nodes[:, k]) for k in range(3)], -1
    )
    yaw = rng.uniform(-np.pi, np.pi)
    rp = np.radians(roll_pitch_deg) * rng.choice([-1.0, 1.0], 2)
    rot = Rotation.from_euler("xyz", [rp[0], rp[1], yaw])
    T_map_enu = pose_matrix(rng.uniform(-500, 500, 3) * [1, 1, 0.1], rot.as_quat())
    node_map = enu_nodes @ T_map_enu[:3, :3].T + T_map_enu[:3, 3]
    n = len(fix_stamps)
    fix = enu_fix_true + rng.normal(0.0, noise, (n, 3))
    gross = rng.random(n) < outlier_fraction
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    fix[gross] += direction[gross] * rng.uniform(20.0, 50.0, (int(gross.sum()), 1))
    lat, lon, alt = enu_to_lla(fix[:, 0], fix[:, 1], fix[:, 2], WYTHAM)
    invalid = rng.random(n) < invalid_fraction
    invalid[0] = False  # the ENU reference is the first valid fix
    q = np.full(n, quality, dtype=np.int8)
    q[invalid] = 0
    lat[invalid] = np.where(rng.random(int(invalid.sum())) < 0.5, np.nan, lat[invalid])
    h = np.full(n, noise if stated_h_std is None else stated_h_std)
    return Scenario(
        T_map_enu, node_stamps, node_map, fix_stamps, lat, lon, alt, q, h, 1.0 * h, gross, invalid
    )


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude()))


def map_origin_error_m(fit: GeoreferenceFit, sc: Scenario, points: np.ndarray) -> float:
    """Max position error (m) of map points mapped to ENU by the fit vs. the truth.

    The ENU frame of the fit is centred on the first valid fix, not on WYTHAM, so both are
    compared as ENU around WYTHAM via geodetic coordinates.
    """
    from standgrid.georeference import lla_to_enu

    enu_fit = fit.map_to_enu(points)
    lat, lon, alt = enu_to_lla(enu_fit[:, 0], enu_fit[:, 1], enu_fit[:, 2], fit.lla_ref)
    e, n, u = lla_to_enu(lat, lon, alt, WYTHAM)
    truth = points @ sc.T_enu_map[:3, :3].T + sc.T_enu_map[:3, 3]
    return float(np.abs(np.stack([e, n, u], -1) - truth).max())


def test_yaw2d_recovers_truth_and_rejects_outliers() -> None:
    sc = make_scenario(1)
    fit = sc.fit(lla_ref=WYTHAM)
    assert fit.method == "yaw2d"
    true_yaw = math.degrees(math.atan2(sc.T_enu_map[1, 0], sc.T_enu_map[0, 0]))
    assert abs((fit.yaw_deg - true_yaw + 180) % 360 - 180) < 0.05
    np.testing.assert_allclose(fit.translation, sc.T_enu_map[:3, 3], atol=0.05)
    # Every gross outlier is flagged, invalid fixes are marked invalid, good fixes kept.
    valid = ~sc.invalid
    assert not fit.inliers[sc.gross].any()
    assert np.all(fit.status[sc.gross & valid] == FIX_STATUS.index("outlier"))
    assert np.all(fit.status[sc.invalid] == FIX_STATUS.index("invalid"))
    good = valid & ~sc.gross
    assert fit.inliers[good].mean() > 0.97
    assert fit.n_used == int(fit.inliers.sum()) and fit.n_used + fit.n_rejected == len(sc.lat)
    assert fit.rejected_by_reason["invalid"] == int(sc.invalid.sum())
    # Residual RMSE near the noise level (sqrt(2) * 3 cm horizontally, 3 cm vertically).
    assert 0.7 * math.sqrt(2) * 0.03 < fit.rmse_m < 1.3 * math.sqrt(2) * 0.03
    assert 0.7 * 0.03 < fit.rmse_vertical_m < 1.3 * 0.03
    assert np.all(np.isnan(fit.residuals_m[sc.invalid]))
    assert np.all(np.linalg.norm(fit.residuals_m[sc.gross & valid], axis=1) > 10.0)
    assert np.all(fit.weights[~fit.inliers] == 0) and np.all(fit.weights[fit.inliers] > 0)


def test_default_reference_is_first_valid_fix() -> None:
    sc = make_scenario(2)
    fit = sc.fit()
    first = int(np.flatnonzero(~sc.invalid)[0])
    assert fit.lla_ref == (sc.lat[first], sc.lon[first], sc.alt[first])
    pts = np.random.default_rng(0).uniform(-300, 300, (50, 3))
    assert map_origin_error_m(fit, sc, pts) < 0.08


def test_rigid3d_recovers_roll_pitch() -> None:
    sc = make_scenario(3, roll_pitch_deg=1.5)
    fit = sc.fit(method="rigid3d", lla_ref=WYTHAM)
    assert fit.method == "rigid3d"
    assert rotation_error_deg(fit.T_enu_map, sc.T_enu_map) < 0.05
    np.testing.assert_allclose(fit.translation, sc.T_enu_map[:3, 3], atol=0.05)
    assert not fit.inliers[sc.gross].any()
    assert fit.rmse_vertical_m < 1.3 * 0.03
    # yaw2d cannot absorb 1.5 deg of tilt: its vertical residuals are far above the noise.
    yaw_only = sc.fit(method="yaw2d", lla_ref=WYTHAM, min_fixes=2)
    assert yaw_only.rmse_vertical_m > 3 * fit.rmse_vertical_m


def test_optimistic_sigmas_are_scaled_not_trimmed_away() -> None:
    # Receiver claims 1 cm, the truth is 10 cm: a robust variance factor keeps the good fixes.
    sc = make_scenario(4, noise=0.10, stated_h_std=0.01)
    fit = sc.fit(lla_ref=WYTHAM)
    good = ~sc.invalid & ~sc.gross
    assert fit.inliers[good].mean() > 0.95
    assert not fit.inliers[sc.gross].any()
    np.testing.assert_allclose(fit.translation, sc.T_enu_map[:3, 3], atol=0.05)


def test_quality_table_sigmas_with_heavy_contamination() -> None:
    # No h_std, DGPS quality (0.7 m), 35 % gross outliers: RANSAC still finds the consensus.
    sc = make_scenario(5, noise=0.5, outlier_fraction=0.35, quality=2, n_nodes=400)
    sc.h_std[:] = np.nan
    sc.v_std[:] = np.nan
    fit = sc.fit(lla_ref=WYTHAM)
    assert not fit.inliers[sc.gross & (np.linalg.norm(fit.residuals_m, axis=1) > 10)].any()
    assert fit.inliers[~sc.gross & ~sc.invalid].mean() > 0.95
    true_yaw = math.atan2(sc.T_enu_map[1, 0], sc.T_enu_map[0, 0])
    assert abs(math.degrees(fit.yaw_rad - true_yaw)) % 360 < 0.2


def test_fix_sigmas_by_quality_and_std() -> None:
    sh, sv = fix_sigmas(
        [4, 5, 2, 1, 6], [np.nan, 0.0, 0.3, np.nan, np.nan], [np.nan, 0.5, np.nan, np.nan, 1.0]
    )
    np.testing.assert_allclose(sh, [0.02, 0.2, 0.3, 2.0, 5.0])
    np.testing.assert_allclose(sv, [0.03, 0.5, 0.45, 3.0, 1.0])


def test_interpolation_and_time_matching() -> None:
    t = np.array([0, 10, 20, 100, 110], dtype=np.int64) * NS_PER_S
    p = np.array([[0, 0, 0], [10, 0, 0], [10, 20, 0], [10, 20, 80], [0, 0, 0]], dtype=np.float64)
    q = np.array([-1, 0, 5, 15, 20, 50, 105, 110, 111], dtype=np.int64) * NS_PER_S
    pos, status = interpolate_trajectory(t[::-1], p[::-1], q, max_gap_ns=30 * NS_PER_S)
    assert status.tolist() == [OUTSIDE, USED, USED, USED, USED, GAP, USED, USED, OUTSIDE]
    np.testing.assert_allclose(
        pos[[1, 2, 3, 4, 6, 7]],
        [[0, 0, 0], [5, 0, 0], [10, 10, 0], [10, 20, 0], [5, 10, 40], [0, 0, 0]],
    )
    assert np.isnan(pos[[0, 5, 8]]).all()


def test_unmatched_fixes_are_reported() -> None:
    sc = make_scenario(6, outlier_fraction=0.0)
    node_t, node_p = sc.node_stamps_ns, sc.node_map
    # Drop nodes 100..139 (a 41 s gap) and shift fixes so some precede the trajectory.
    keep = np.ones(len(node_t), dtype=bool)
    keep[100:140] = False
    stamps = sc.fix_stamps_ns.copy()
    stamps[:5] = T0_NS - NS_PER_S
    fixes = fixes_with(stamps, sc.lat, sc.lon, sc.alt, sc.quality, sc.h_std)
    fit = fit_georeference(fixes, node_t[keep], node_p[keep], lla_ref=WYTHAM)
    in_gap = (stamps > node_t[99]) & (stamps < node_t[140])
    by = fit.rejected_by_reason
    assert by["trajectory_gap"] == int((in_gap & ~sc.invalid).sum()) > 0
    assert by["outside_trajectory"] == int((~sc.invalid[:5]).sum()) > 0
    assert np.all(fit.status[in_gap & ~sc.invalid] == GAP)
    np.testing.assert_allclose(fit.translation, sc.T_enu_map[:3, 3], atol=0.05)


def test_too_few_fixes_names_the_counts() -> None:
    sc = make_scenario(7, n_nodes=40, invalid_fraction=0.0, outlier_fraction=0.0)
    with pytest.raises(InsufficientGnssError) as info:
        sc.fit(min_fixes=50, source=Path("missions/m1"))
    msg = str(info.value)
    assert (
        "missions/m1" in msg
        and "40 GNSS fixes" in msg
        and "0 invalid" in msg
        and "min_fixes=50" in msg
    )
    q = sc.quality.copy()
    q[:] = 0
    with pytest.raises(InsufficientGnssError, match="none valid"):
        fit_georeference(
            fixes_with(sc.fix_stamps_ns, sc.lat, sc.lon, sc.alt, q),
            sc.node_stamps_ns,
            sc.node_map,
        )
    q[:8] = 4
    with pytest.raises(InsufficientGnssError, match="32 invalid"):
        fit_georeference(
            fixes_with(sc.fix_stamps_ns, sc.lat, sc.lon, sc.alt, q),
            sc.node_stamps_ns,
            sc.node_map,
        )


def test_unobservable_geometries_are_refused() -> None:
    static = make_scenario(8, static=True, outlier_fraction=0.0, noise=0.01)
    with pytest.raises(InsufficientGnssError, match="yaw is unobservable"):
        static.fit()
    line = make_scenario(9, straight=True, outlier_fraction=0.0)
    with pytest.raises(InsufficientGnssError, match="along a line"):
        line.fit(method="rigid3d")
    line.fit(method="yaw2d")  # a straight line still fixes the yaw


def test_bad_arguments() -> None:
    sc = make_scenario(10, n_nodes=30)
    with pytest.raises(GeoreferenceError, match="unknown georeference method"):
        sc.fit(method="similarity")
    with pytest.raises(GeoreferenceError, match="differ in length"):
        fit_georeference(
            fixes_with(sc.fix_stamps_ns[:-1], sc.lat, sc.lon, sc.alt, sc.quality),
            sc.node_stamps_ns,
            sc.node_map,
        )
    with pytest.raises(GeoreferenceError, match="trajectory positions"):
        fit_georeference(fixes_of(sc), sc.node_stamps_ns, sc.node_map[:-1])


def test_closed_form_solvers_are_exact_without_noise() -> None:
    rng = np.random.default_rng(11)
    p = rng.uniform(-50, 50, (20, 3))
    T = pose_matrix([3.0, -7.0, 1.5], Rotation.from_euler("xyz", [0.02, -0.03, 2.0]).as_quat())
    q = p @ T[:3, :3].T + T[:3, 3]
    w = rng.uniform(0.5, 2.0, 20)
    np.testing.assert_allclose(solve_rigid3d(p, q, w), T, atol=1e-12)
    T2 = pose_matrix([3.0, -7.0, 1.5], Rotation.from_euler("z", -2.5).as_quat())
    q2 = p @ T2[:3, :3].T + T2[:3, 3]
    np.testing.assert_allclose(solve_yaw2d(p, q2, w, w), T2, atol=1e-12)
    np.testing.assert_allclose(solve_yaw2d(p, q2, w, w, robust_z=True), T2, atol=1e-12)


def test_dict_round_trip_is_exact_through_json() -> None:
    sc = make_scenario(12)
    fit = sc.fit()
    text = json.dumps(fit.to_dict(), allow_nan=False)
    back = GeoreferenceFit.from_dict(json.loads(text))
    assert back.lla_ref == fit.lla_ref and back.method == fit.method
    assert np.array_equal(back.T_enu_map, fit.T_enu_map)
    assert np.array_equal(back.residuals_m, fit.residuals_m, equal_nan=True)
    assert np.array_equal(back.fix_stamps_ns, fit.fix_stamps_ns)
    assert np.array_equal(back.inliers, fit.inliers)
    assert np.array_equal(back.status, fit.status)
    assert np.array_equal(back.weights, fit.weights)
    assert (back.rmse_m, back.rmse_vertical_m, back.n_used, back.n_rejected) == (
        fit.rmse_m,
        fit.rmse_vertical_m,
        fit.n_used,
        fit.n_rejected,
    )
    bad = json.loads(text)
    bad["n_used"] += 1
    with pytest.raises(GeoreferenceError, match="inconsistent"):
        GeoreferenceFit.from_dict(bad)
    del bad["fixes"]
    with pytest.raises(GeoreferenceError, match="malformed"):
        GeoreferenceFit.from_dict(bad)


# --- pose graph anchor and the mission-level function --------------------------------------


def graph_of(sc: Scenario, anchored: bool, source: Path | None = None) -> PoseGraph:
    quat = np.array([0.0, 0.0, 0.0, 1.0])
    vertices = {
        i: Vertex(i, Stamp.from_ns(int(t)), pose_matrix(p, quat))
        for i, (t, p) in enumerate(zip(sc.node_stamps_ns, sc.node_map, strict=True))
    }
    return PoseGraph(
        vertices=vertices,
        gnss_lla_ref=WYTHAM if anchored else None,
        gnss_lla_to_map=sc.T_map_enu.copy() if anchored else None,
        source=source,
    )


def fixes_of(sc: Scenario) -> GnssFixes:
    return GnssFixes(sc.fix_stamps_ns, sc.lat, sc.lon, sc.alt, sc.quality, sc.h_std, sc.v_std)


def fixes_with(
    stamps: np.ndarray,
    lat: np.ndarray,
    lon: np.ndarray,
    alt: np.ndarray,
    quality: np.ndarray,
    h_std: np.ndarray | None = None,
) -> GnssFixes:
    """Fixes without stated stds where none are given (NaN: the quality's sigma)."""
    nan = np.full(len(lat), np.nan)
    return GnssFixes(stamps, lat, lon, alt, quality, nan if h_std is None else h_std, nan)


@dataclass
class StandInMission:
    """Our own container with the attributes georeference_mission reads (not a library mock)."""

    path: Path
    graph: PoseGraph | None
    gnss: GnssFixes | None


def test_fit_from_pose_graph() -> None:
    sc = make_scenario(13, n_nodes=20)
    assert fit_from_pose_graph(graph_of(sc, anchored=False)) is None
    fit = fit_from_pose_graph(graph_of(sc, anchored=True))
    assert fit is not None and fit.method == "pose_graph"
    np.testing.assert_allclose(fit.T_enu_map @ sc.T_map_enu, np.eye(4), atol=1e-12)
    assert fit.lla_ref == WYTHAM and fit.n_used == 0 and len(fit.fix_stamps_ns) == 0
    back = GeoreferenceFit.from_dict(json.loads(json.dumps(fit.to_dict(), allow_nan=False)))
    assert np.array_equal(back.T_enu_map, fit.T_enu_map) and math.isnan(back.rmse_m)


def test_mission_with_anchor_reports_fix_residuals() -> None:
    sc = make_scenario(14)
    mission = StandInMission(Path("m/anchored"), graph_of(sc, anchored=True), fixes_of(sc))
    fit = georeference_mission(mission)
    assert fit.method == "pose_graph" and fit.lla_ref == WYTHAM
    np.testing.assert_allclose(fit.T_enu_map, sc.T_enu_map, atol=1e-12)
    assert 0.7 * math.sqrt(2) * 0.03 < fit.rmse_m < 1.3 * math.sqrt(2) * 0.03
    assert not fit.inliers[sc.gross].any()
    assert georeference_mission(StandInMission(Path("m"), mission.graph, None)).n_used == 0
    refit = georeference_mission(mission, use_graph_anchor=False, method="rigid3d")
    assert refit.method == "rigid3d"
    assert rotation_error_deg(refit.T_enu_map, sc.T_enu_map) < 0.05


def test_mission_without_anchor_is_fitted() -> None:
    sc = make_scenario(15)
    fit = georeference_mission(
        StandInMission(Path("m/plain"), graph_of(sc, anchored=False), fixes_of(sc))
    )
    assert fit.method == "yaw2d"
    pts = np.random.default_rng(1).uniform(-200, 200, (20, 3))
    assert map_origin_error_m(fit, sc, pts) < 0.08


def test_mission_errors_name_the_mission() -> None:
    sc = make_scenario(16, n_nodes=30)
    with pytest.raises(NotGeoreferencedError, match=r"m/nogps.*no GNSS log"):
        georeference_mission(StandInMission(Path("m/nogps"), graph_of(sc, anchored=False), None))
    with pytest.raises(NotGeoreferencedError, match=r"m/nograph.*no pose graph"):
        georeference_mission(StandInMission(Path("m/nograph"), None, fixes_of(sc)))
    no_f = np.zeros(0)
    empty = GnssFixes(np.zeros(0, np.int64), no_f, no_f, no_f, np.zeros(0, np.int8), no_f, no_f)
    with pytest.raises(InsufficientGnssError, match=r"m/empty.*no fixes"):
        georeference_mission(StandInMission(Path("m/empty"), graph_of(sc, anchored=False), empty))
    with pytest.raises(InsufficientGnssError, match="m/few"):
        georeference_mission(
            StandInMission(Path("m/few"), graph_of(sc, anchored=False), fixes_of(sc)), min_fixes=100
        )


def test_systematic_blocks_of_bad_fixes() -> None:
    # A run of fixes 30 m off to the north (multipath under canopy) and a run with 25 m of
    # height error only: least squares + trimming alone would be dragged; the consensus is not.
    sc = make_scenario(17, outlier_fraction=0.0, invalid_fraction=0.0, n_nodes=300)
    from standgrid.georeference import lla_to_enu

    e, n, u = lla_to_enu(sc.lat, sc.lon, sc.alt, WYTHAM)
    north_block = np.zeros(len(e), dtype=bool)
    north_block[60:150] = True
    up_block = np.zeros(len(e), dtype=bool)
    up_block[200:260] = True
    n = n + 30.0 * north_block
    u = u + 25.0 * up_block
    lat, lon, alt = enu_to_lla(e, n, u, WYTHAM)
    fixes = fixes_with(sc.fix_stamps_ns, lat, lon, alt, sc.quality, sc.h_std)
    fit = fit_georeference(fixes, sc.node_stamps_ns, sc.node_map, lla_ref=WYTHAM)
    assert not fit.inliers[north_block | up_block].any()
    assert fit.inliers[~(north_block | up_block)].mean() > 0.97
    np.testing.assert_allclose(fit.translation, sc.T_enu_map[:3, 3], atol=0.05)
