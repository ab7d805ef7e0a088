"""The mission simulator: determinism, exact truth, GNSS, payload spacing, loop closures, epochs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from pyproj import Transformer
from scipy.spatial import cKDTree

from standgrid.clouds import read_cloud, read_cloud_header
from standgrid.errors import OutputExistsError
from standgrid.geometry import invert_pose, relative_pose, transform_points
from standgrid.mission.metadata import read_metadata
from standgrid.mission.mission_name import parse_mission_name
from standgrid.mission.opening import open_mission
from standgrid.mission.posegraph import EdgeKind, read_pose_graph
from standgrid.mission.sensors import read_gnss, read_imu
from standgrid.simulate import Truth, load_truth, simulate_mission, simulate_pair
from standgrid.stamps import stamp_from_filename

SMALL: dict[str, Any] = {"area": 70.0, "points_per_payload": 5000}
E1 = "2024-05-14-wytham-anymal-coyote"
E2 = "2028-05-20-wytham-frontier-v15"


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    simulate_pair(root, 3, **SMALL)
    return root


# --- an exact chain written independently of standgrid.simulate.chain --------------------

_ECEF_TO_LLA = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
_LLA_TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
_LLA_TO_UTM = Transformer.from_crs("EPSG:4979", "EPSG:32630", always_xy=True)


def _map_to_utm(xyz_map: np.ndarray, lla_ref: list[float], T_map_enu: np.ndarray) -> np.ndarray:
    lat, lon = np.radians(lla_ref[0]), np.radians(lla_ref[1])
    east = np.array([-np.sin(lon), np.cos(lon), 0.0])
    north = np.array([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)])
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    enu = transform_points(invert_pose(T_map_enu), xyz_map)
    ref = np.array(_LLA_TO_ECEF.transform(lla_ref[1], lla_ref[0], lla_ref[2]))
    ecef = ref + enu[:, :1] * east + enu[:, 1:2] * north + enu[:, 2:3] * up
    lon_d, lat_d, h = np.asarray(_ECEF_TO_LLA.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2]))
    x, y, z = _LLA_TO_UTM.transform(lon_d, lat_d, h)
    return np.column_stack([x, y, z])


def _points_in_crs(root: Path, name: str) -> tuple[np.ndarray, Truth]:
    truth = load_truth(root / "truth" / name)
    info = json.loads((root / "truth" / name / "truth.json").read_text())
    parts = []
    for pcd in sorted((root / "missions" / name / "payload_clouds").glob("*.pcd")):
        _, stamp, _ = stamp_from_filename(pcd.name)  # type: ignore[misc]
        cloud = read_cloud(pcd)
        xyz_map = transform_points(truth.true_pose(stamp), cloud.xyz)
        parts.append(_map_to_utm(xyz_map, info["lla_ref"], np.asarray(info["T_map_enu"])))
    return np.concatenate(parts), truth


# --- tests --------------------------------------------------------------------------------


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path: Path) -> None:
    kw: dict[str, Any] = {"area": 50.0, "points_per_payload": 1500}
    for sub, seed in (("a", 11), ("b", 11), ("c", 12)):
        simulate_mission(tmp_path / sub, seed=seed, epoch=1, **kw)
    files_a = sorted(
        p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file()
    )
    files_b = sorted(
        p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file()
    )
    assert files_a == files_b and len(files_a) > 10
    for rel in files_a:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    graph = Path("missions", E1, "slam_pose_graph.g2o")
    assert (tmp_path / "a" / graph).read_bytes() != (tmp_path / "c" / graph).read_bytes()
    clouds_a = sorted((tmp_path / "a" / "missions" / E1 / "payload_clouds").iterdir())
    clouds_c = sorted((tmp_path / "c" / "missions" / E1 / "payload_clouds").iterdir())
    assert clouds_a[0].read_bytes() != clouds_c[0].read_bytes()


def test_layout_opens_and_metadata(pair: Path) -> None:
    for name, robot, unit, year in ((E1, "anymal", "coyote", 2024), (E2, "frontier", "v15", 2028)):
        folder = pair / "missions" / name
        assert (
            not (folder / "truth.json").exists()
            and (pair / "truth" / name / "truth.json").is_file()
        )
        mission = open_mission(folder)
        assert mission.problems == []
        assert len(mission.payloads) >= 8
        assert all(p.node_id is not None for p in mission.payloads)
        parsed = parse_mission_name(name)
        meta = read_metadata(folder / "metadata.yaml")
        assert (meta.robot, meta.unit, meta.date.year) == (robot, unit, year)
        assert (parsed.robot, parsed.unit, parsed.place) == (robot, unit, "wytham")
        # Per-payload GNSS and IMU files carry the payload stamps and lie inside the mission.
        stamps = {p.stamp for p in mission.payloads}
        for sub, prefix in (("gnss", "gnss"), ("imu", "imu")):
            files = sorted((folder / "payloads" / sub).iterdir())
            assert {stamp_from_filename(f.name)[1] for f in files} == stamps  # type: ignore[index]
            assert all(stamp_from_filename(f.name)[0] == prefix for f in files)  # type: ignore[index]
        imu = read_imu(next((folder / "payloads" / "imu").iterdir()))
        assert np.allclose(np.linalg.norm(imu.accel, axis=1), 9.80665, atol=0.15)
        header = read_cloud_header(mission.payloads[0].path)
        assert "intensity" in header.fields


def test_payload_points_land_on_true_surfaces(pair: Path) -> None:
    xyz, truth = _points_in_crs(pair, E1)
    above = xyz[:, 2] - truth.terrain_height(xyz[:, 0], xyz[:, 1])
    on_ground = np.abs(above) < 0.04
    assert on_ground.mean() > 0.10  # ground returns exist ...
    assert np.std(above[on_ground]) < 0.02  # ... within the ~1 cm noise
    assert (above > -0.25).all()  # nothing below the terrain beyond noise (shrub rims on slopes)
    trees = truth.trees
    assert trees is not None
    standing = trees.standing
    axes = cKDTree(np.column_stack([trees.x[standing], trees.y[standing]]))
    dist, k = axes.query(xyz[:, :2])
    idx = np.flatnonzero(standing)[k]
    h = xyz[:, 2] - trees.z_ground[idx]
    breast = (h > 1.2) & (h < 1.4) & (dist < trees.dbh[idx] / 2 + 0.1)
    assert breast.sum() > 200
    residual = dist[breast] - trees.dbh[idx][breast] / 2
    assert np.quantile(np.abs(residual), 0.95) < 0.03
    assert len(np.unique(idx[breast])) > 0.7 * standing.sum()  # most stems are scanned at 1.3 m
    # Tree tops are sampled: the highest point near each well-scanned tree is close to its height.
    top_err = []
    for t in np.flatnonzero(standing)[:60]:
        near = np.hypot(xyz[:, 0] - trees.x[t], xyz[:, 1] - trees.y[t]) < trees.crown_radius[t]
        if near.sum() > 50:
            top_err.append(xyz[near, 2].max() - trees.z_ground[t] - trees.height[t])
    assert len(top_err) > 30
    assert np.sqrt(np.mean(np.square(top_err))) < 0.5
    assert max(top_err) < 0.1


def test_gnss_inliers_within_stated_noise(pair: Path) -> None:
    truth = load_truth(pair / "truth" / E1)
    fixes = read_gnss(pair / "missions" / E1 / "gnss" / "fixes.txt")
    np.testing.assert_array_equal(fixes.stamps_ns, truth.gnss_stamps_ns)
    x, y, z = _LLA_TO_UTM.transform(fixes.lon, fixes.lat, fixes.alt)
    err_h = np.hypot(x - truth.gnss_true_xyz[:, 0], y - truth.gnss_true_xyz[:, 1])
    err_v = np.abs(z - truth.gnss_true_xyz[:, 2])
    inlier = ~truth.gnss_outlier
    assert (err_h[inlier] < 4.0 * fixes.h_std[inlier]).all()
    assert (err_v[inlier] < 5.0 * fixes.v_std[inlier]).all()
    assert (err_h[truth.gnss_outlier] > 8.0).all() and truth.gnss_outlier.sum() >= 3
    rtk = fixes.quality == 4
    assert rtk.sum() > 10 and (fixes.h_std[rtk] <= 0.03).all()
    assert set(np.unique(fixes.quality)) <= {1, 2, 4}
    gaps = np.diff(fixes.stamps_ns) / 1e9
    assert gaps.max() > 5.0  # dropouts under canopy
    # The ENU origin of the truth is the first fix.
    assert truth.lla_ref == pytest.approx((fixes.lat[0], fixes.lon[0], fixes.alt[0]), abs=1e-12)


def test_payloads_every_20m_and_loop_closures(pair: Path) -> None:
    truth = load_truth(pair / "truth" / E1)
    mission = open_mission(pair / "missions" / E1)
    centres = np.stack([truth.true_pose(p.stamp)[:3, 3] for p in mission.payloads])
    positions = truth.true_poses.poses[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    node_of = {int(s): k for k, s in enumerate(truth.true_poses.stamps_ns)}
    along = np.array([arc[node_of[p.stamp.ns]] for p in mission.payloads])
    spacing = np.diff(along)
    assert 15.0 < np.median(spacing) < 25.0 and spacing.min() > 10.0 and spacing.max() < 32.0
    assert len(centres) == pytest.approx(arc[-1] / 20.0, abs=1.5)
    graph = read_pose_graph(pair / "missions" / E1 / "slam_pose_graph.g2o")
    assert graph.gnss_lla_ref is None and graph.gnss_lla_to_map is None
    counts = graph.edge_counts()
    assert counts[EdgeKind.ODOMETRY] == len(graph) - 1
    assert counts[EdgeKind.LOOP_CLOSURE] >= 1
    node_step = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert 1.0 < np.median(node_step) < 2.0
    true = {
        int(s): p for s, p in zip(truth.true_poses.stamps_ns, truth.true_poses.poses, strict=True)
    }
    ids = {v.id: v.stamp.ns for v in graph.vertices.values()}
    for edge in graph.edges:
        if edge.kind is EdgeKind.LOOP_CLOSURE:
            expect = relative_pose(true[ids[edge.i]], true[ids[edge.j]])
            assert np.linalg.norm(expect[:3, 3] - edge.relative_pose[:3, 3]) < 0.1
            assert np.linalg.norm(true[ids[edge.i]][:3, 3] - true[ids[edge.j]][:3, 3]) < 3.0
            assert (np.linalg.eigvalsh(edge.information) > 0).all()
    # The written estimate drifts only a few cm from the truth.
    est = graph.poses[:, :3, 3]
    assert 0.0 < np.abs(est - positions).max() < 0.2


def test_second_epoch_grown_thinned_reframed(pair: Path) -> None:
    t1, t2 = load_truth(pair / "truth" / E1), load_truth(pair / "truth" / E2)
    assert t1.terrain is not None and t2.terrain is not None
    assert t1.terrain.to_dict() == t2.terrain.to_dict()
    assert not np.allclose(t1.T_map_enu, t2.T_map_enu)
    a, b = t1.trees, t2.trees
    assert a is not None and b is not None
    same = {int(i): k for k, i in enumerate(b.tree_id)}
    alive = [
        (k, same[int(i)]) for k, i in enumerate(a.tree_id) if b.status[same[int(i)]] == "alive"
    ]
    ka, kb = np.array(alive).T
    assert np.allclose(a.x[ka], b.x[kb]) and (b.height[kb] > a.height[ka]).all()
    assert (b.dbh[kb] > a.dbh[ka]).all()
    harvested = np.flatnonzero(b.status == "harvested")
    assert 0.08 < len(harvested) / len(a) < 0.16
    xyz1, _ = _points_in_crs(pair, E1)
    xyz2, _ = _points_in_crs(pair, E2)
    new = b.status == "new"
    clean = [
        k
        for k in harvested
        if not new.any() or np.hypot(b.x[new] - b.x[k], b.y[new] - b.y[k]).min() > 1.5
    ]
    assert len(clean) >= 3

    def stem_hits(xyz: np.ndarray, k: int) -> int:
        d = np.hypot(xyz[:, 0] - b.x[k], xyz[:, 1] - b.y[k])
        h = xyz[:, 2] - b.z_ground[k]
        return int(((d < b.dbh[k] / 2 + 0.05) & (h > 0.3) & (h < 3.0)).sum())

    assert sum([stem_hits(xyz1, int(k)) for k in clean]) > 10 * len(clean) // 2  # scanned in 2024
    assert sum([stem_hits(xyz2, int(k)) for k in clean]) == 0  # gone in 2028


def test_write_georef_flag_and_overwrite(tmp_path: Path) -> None:
    sim = simulate_mission(
        tmp_path, seed=5, epoch=2, area=50.0, points_per_payload=1000, write_georef=True
    )
    graph = read_pose_graph(sim.mission_dir / "slam_pose_graph.g2o")  # type: ignore[operator]
    truth = load_truth(sim.truth_dir)  # type: ignore[arg-type]
    assert graph.gnss_lla_ref == pytest.approx(truth.lla_ref, abs=1e-9)
    assert graph.gnss_lla_to_map is not None
    assert np.allclose(graph.gnss_lla_to_map, truth.T_map_enu, atol=1e-9)
    with pytest.raises(OutputExistsError):
        simulate_mission(tmp_path, seed=5, epoch=2, area=50.0, points_per_payload=1000)
    simulate_mission(tmp_path, seed=5, epoch=2, area=50.0, points_per_payload=1000, overwrite=True)
    assert read_pose_graph(sim.mission_dir / "slam_pose_graph.g2o").gnss_lla_ref is None  # type: ignore[operator]
    # overwriting replaces the simulator's own folders only
    (sim.truth_dir / "truth.json").unlink()  # type: ignore[operator]
    with pytest.raises(OutputExistsError, match="not a simulator truth folder"):
        simulate_mission(
            tmp_path, seed=5, epoch=2, area=50.0, points_per_payload=1000, overwrite=True
        )
    assert sim.truth_dir.is_dir()  # type: ignore[union-attr]


def test_cli_simulate(tmp_path: Path) -> None:
    from standgrid.cli import cli

    args = [
        "simulate",
        str(tmp_path),
        "--seed",
        "2",
        "--epochs",
        "1",
        "--area",
        "50",
        "--points-per-payload",
        "1000",
        "--json",
    ]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert [d["name"] for d in data] == [E1]
    assert data[0]["payloads"] >= 3 and Path(data[0]["mission"]).is_dir()
    again = CliRunner().invoke(cli, args)
    assert again.exit_code != 0 and "OutputExistsError" in again.output
    assert CliRunner().invoke(cli, [*args, "--overwrite"]).exit_code == 0
    assert "Example:" in CliRunner().invoke(cli, ["simulate", "--help"]).output


def _same_text_to_the_last_bits(ours: bytes, theirs: bytes) -> bool:
    """Line by line, token by token equal, but for decimal numbers that differ by at most
    1e-12 (a quaternion's last digits: conversions from rotation matrices round in the last
    bit differently on different CPUs, e.g. with and without FMA)."""
    lines, others = ours.split(b"\n"), theirs.split(b"\n")
    if len(lines) != len(others):
        return False
    for line, other in zip(lines, others, strict=True):
        if line == other:
            continue
        tokens, words = line.replace(b",", b" ").split(), other.replace(b",", b" ").split()
        if len(tokens) != len(words):
            return False
        for a, b in zip(tokens, words, strict=True):
            if a == b:
                continue
            try:
                if abs(float(a) - float(b)) > 1e-12 or b"." not in a:
                    return False
            except ValueError:
                return False
    return True


def test_bundled_pair_is_reproducible(tmp_path: Path) -> None:
    """data/ holds what its documented command writes (rerun it when formats change): every
    file byte for byte, but the decimal numbers of text lines (poses, PCD viewpoints) to
    1e-12, as CPUs round a rotation's quaternion differently in its last bit."""
    bundled = Path(__file__).resolve().parents[1] / "data"
    if not (bundled / "missions" / E1).is_dir():
        pytest.skip("bundled sample data not present")
    simulate_pair(tmp_path, 7, area=80.0, points_per_payload=7000)
    for sub in ("missions", "truth"):
        ours = sorted(p.relative_to(tmp_path) for p in (tmp_path / sub).rglob("*") if p.is_file())
        theirs = sorted(p.relative_to(bundled) for p in (bundled / sub).rglob("*") if p.is_file())
        assert ours == theirs
        for rel in ours:
            mine, bundled_bytes = (tmp_path / rel).read_bytes(), (bundled / rel).read_bytes()
            if mine == bundled_bytes:
                continue
            if rel.suffix == ".pcd":  # the binary points byte for byte, the header's numbers
                head, _, data = mine.partition(b"DATA binary\n")
                head2, _, data2 = bundled_bytes.partition(b"DATA binary\n")
                assert data == data2, rel
                assert _same_text_to_the_last_bits(head, head2), rel
            else:
                assert _same_text_to_the_last_bits(mine, bundled_bytes), rel


def test_the_last_bits_tolerance_still_tells_real_changes() -> None:
    assert _same_text_to_the_last_bits(b"1 0.1234567890123457", b"1 0.1234567890123456")
    assert not _same_text_to_the_last_bits(b"1 0.12345678901", b"1 0.12345678902")
    assert not _same_text_to_the_last_bits(b"7 0.5", b"8 0.5")  # integers exactly
    assert not _same_text_to_the_last_bits(b"a 0.5", b"b 0.5")
    assert not _same_text_to_the_last_bits(b"0.5\n", b"0.5\n0.5\n")


def test_truth_errors_are_typed_and_name_the_file(pair: Path, tmp_path: Path) -> None:
    import shutil

    from standgrid.errors import FormatError, MissionNotFoundError, StandgridError
    from standgrid.stamps import Stamp

    truth_dir = tmp_path / E1
    shutil.copytree(pair / "truth" / E1, truth_dir)
    truth = load_truth(truth_dir)
    with pytest.raises(StandgridError, match="no true poses") as lookup:
        truth.true_pose(Stamp(1, 2))
    assert isinstance(lookup.value, LookupError)
    with pytest.raises(MissionNotFoundError) as missing_points:
        truth.payload_points(Stamp(1, 2))
    assert missing_points.value.path == truth_dir / "payload_points" / "points_1_000000002.npy"
    meta = truth_dir / "truth.json"
    info = json.loads(meta.read_text())
    del info["seed"]
    meta.write_text(json.dumps(info))
    with pytest.raises(FormatError, match="missing key 'seed'") as bad:
        load_truth(truth_dir)
    assert bad.value.path == meta and isinstance(bad.value.__cause__, KeyError)
    shutil.copy(pair / "truth" / E1 / "truth.json", meta)
    (truth_dir / "gnss_truth.csv").unlink()
    with pytest.raises(MissionNotFoundError) as no_gnss:
        load_truth(truth_dir)
    assert no_gnss.value.path == truth_dir / "gnss_truth.csv"
    (truth_dir / "gnss_truth.csv").mkdir()
    with pytest.raises(FormatError, match="cannot read GNSS truth"):
        load_truth(truth_dir)


def test_imu_yaw_rate_is_that_of_the_current_node_interval() -> None:
    from scipy.spatial.transform import Rotation

    from standgrid.simulate.gnss import simulate_imu

    t0 = 1_700_000_000 * 10**9
    node_ns = t0 + np.array([0, 1, 2, 3], dtype=np.int64) * 10**9
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", [[0.0], [0.0], [1.0], [1.0]]).as_matrix()
    imu = simulate_imu(np.random.default_rng(0), node_ns, poses, t0, int(node_ns[-1]), 10.0)
    t_s = (imu.stamps_ns - t0) / 1e9
    expected = np.where((t_s >= 1.0) & (t_s < 2.0), 1.0, 0.0)  # turning only in (1 s, 2 s)
    assert np.abs(imu.gyro[:, 2] - expected).max() < 0.01


def test_imu_windows_cover_the_mission_contiguously(pair: Path) -> None:
    folder = pair / "missions" / E1
    files = sorted((folder / "payloads" / "imu").iterdir())
    stamps = np.concatenate([read_imu(f).stamps_ns for f in files])
    nodes = read_pose_graph(folder / "slam_pose_graph.g2o")
    node_ns = np.array(sorted(v.stamp.ns for v in nodes.vertices.values()))
    period_ns = round(1e9 / 5.0)  # SimulationConfig.imu_rate_hz
    assert (np.diff(stamps) == period_ns).all()  # no gap, no overlap between payload files
    assert stamps[0] == node_ns[0] and stamps[-1] > node_ns[-1] - period_ns


def test_failed_install_keeps_the_previous_mission_truth_pair(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    from standgrid.errors import OutputNotWritableError

    kw: dict[str, Any] = {"area": 50.0, "points_per_payload": 500}
    simulate_mission(tmp_path, seed=5, epoch=1, **kw)

    def snapshot() -> dict[Path, bytes]:
        return {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}

    before = snapshot()
    truth_dir = tmp_path / "truth" / E1
    real_replace = os.replace
    failed: list[bool] = []

    def replace_failing_once_onto_truth(src: Any, dst: Any) -> None:
        if Path(dst) == truth_dir and Path(src).name.endswith(".tmp") and not failed:
            failed.append(True)
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace_failing_once_onto_truth)
    with pytest.raises(OutputNotWritableError):
        simulate_mission(tmp_path, seed=6, epoch=1, overwrite=True, **kw)
    assert failed
    assert snapshot() == before  # old mission beside old truth, no temporaries left
    monkeypatch.undo()
    simulate_mission(tmp_path, seed=6, epoch=1, overwrite=True, **kw)
    after = snapshot()
    assert after.keys() != before.keys() or after != before
    assert not [p for p in tmp_path.rglob(".*")]
