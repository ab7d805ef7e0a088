"""A mission cut from a real georeferenced scan reproduces the scan's coordinates exactly."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
from pyproj import CRS, Transformer

from standgrid.clouds import read_cloud
from standgrid.geometry import invert_pose, transform_points
from standgrid.mission.opening import open_mission
from standgrid.mission.posegraph import read_pose_graph
from standgrid.mission.sensors import read_gnss
from standgrid.simulate import load_truth, mission_from_scan
from tests.conftest import real_file

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def scan_mission(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    las = real_file("als/lasR_bcts/bcts_1.laz")
    root = tmp_path_factory.mktemp("scan")
    result = mission_from_scan([las], root, seed=4, radius=20.0)
    return las, result


def _map_to_crs(xyz_map: np.ndarray, info: dict) -> np.ndarray:
    """map -> ENU -> ECEF -> geodetic -> scan CRS, written here independently of the simulator."""
    lat0, lon0, h0 = info["lla_ref"]
    lat, lon = np.radians(lat0), np.radians(lon0)
    rot = np.array(
        [
            [-np.sin(lon), np.cos(lon), 0.0],
            [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)],
        ]
    )
    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    to_crs = Transformer.from_crs("EPSG:4979", info["crs"], always_xy=True)
    enu = transform_points(invert_pose(np.asarray(info["T_map_enu"])), xyz_map)
    ecef = np.asarray(to_ecef.transform(lon0, lat0, h0)) + enu @ rot
    lon_d, lat_d, h = to_ecef.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2], direction="INVERSE")
    return np.column_stack(to_crs.transform(lon_d, lat_d, h))


def test_payloads_reproduce_original_coordinates(scan_mission: tuple[Path, object]) -> None:
    las_path, result = scan_mission
    truth_dir = result.truth_dir  # type: ignore[attr-defined]
    info = json.loads((truth_dir / "truth.json").read_text())
    assert info["crs"] == "EPSG:3005" and info["kind"] == "from_scan"
    truth = load_truth(truth_dir)
    mission = open_mission(result.mission_dir)  # type: ignore[attr-defined]
    assert mission.problems == [] and len(mission.payloads) >= 8
    las = laspy.read(las_path)
    original = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    seen: list[np.ndarray] = []
    worst = 0.0
    for payload in mission.payloads:
        cloud = read_cloud(payload.path)
        xyz_truth, index = truth.payload_points(payload.stamp)
        assert len(cloud) == len(index) > 1000
        np.testing.assert_array_equal(xyz_truth, original[index])
        back = _map_to_crs(transform_points(truth.true_pose(payload.stamp), cloud.xyz), info)
        worst = max(worst, float(np.abs(back - original[index]).max()))
        np.testing.assert_array_equal(cloud.fields["intensity"], np.asarray(las.intensity)[index])
        seen.append(index)
    assert worst < 1e-3
    all_idx = np.concatenate(seen)
    assert len(np.unique(all_idx)) == len(all_idx) == info["points_kept"]  # no point twice
    # Every kept point lies within the radius of the path; the graph poses are the true ones.
    path = truth.true_poses.poses[:, :3, 3]
    graph = read_pose_graph(result.mission_dir / "slam_pose_graph.g2o")  # type: ignore[attr-defined]
    assert np.abs(graph.poses[:, :3, 3] - path).max() < 1e-9
    assert graph.gnss_lla_ref is None


def test_scan_gnss_through_the_chain(scan_mission: tuple[Path, object]) -> None:
    _, result = scan_mission
    truth = load_truth(result.truth_dir)  # type: ignore[attr-defined]
    fixes = read_gnss(result.mission_dir / "gnss" / "fixes.txt")  # type: ignore[attr-defined]
    to_crs = Transformer.from_crs("EPSG:4979", "EPSG:3005", always_xy=True)
    x, y, _ = to_crs.transform(fixes.lon, fixes.lat, fixes.alt)
    err = np.hypot(x - truth.gnss_true_xyz[:, 0], y - truth.gnss_true_xyz[:, 1])
    inlier = ~truth.gnss_outlier
    assert np.median(err[inlier]) < 0.05 and err[inlier].max() < 0.15
    assert (err[truth.gnss_outlier] > 8.0).all()
    assert 0.02 < truth.gnss_outlier.mean() < 0.09
    assert (fixes.quality == 4).all()
    assert len(fixes) >= 100


def test_scan_without_crs_or_file_raises_typed_errors(tmp_path: Path) -> None:
    from standgrid.errors import CRSError, MissionNotFoundError

    local = real_file("als/TreeLS/pine_plot.laz")  # a terrestrial scan with no CRS
    with pytest.raises(CRSError, match="no CRS"):
        mission_from_scan([local], tmp_path, seed=0)
    with pytest.raises(CRSError, match="unusable CRS"):
        mission_from_scan([local], tmp_path, seed=0, crs="EPSG:0")
    with pytest.raises(MissionNotFoundError):
        mission_from_scan([tmp_path / "missing.laz"], tmp_path, seed=0)
    assert not (tmp_path / "missions").exists()


def test_given_crs_is_normalised_and_proj_strings_refused(tmp_path: Path) -> None:
    from standgrid.errors import CRSError

    local = real_file("als/TreeLS/pine_plot.laz")
    proj = "+proj=utm +zone=30 +datum=WGS84 +units=m +no_defs"
    with pytest.raises(CRSError, match="PROJ strings"):
        mission_from_scan([local], tmp_path, seed=0, crs=proj)
    with pytest.raises(CRSError, match="geographic"):
        mission_from_scan([local], tmp_path, seed=0, crs="EPSG:4326")
    assert not (tmp_path / "missions").exists()
    from standgrid.simulate.from_scan import _normalise_crs

    assert _normalise_crs(" epsg:32630 ") == "EPSG:32630"
    wkt = CRS.from_epsg(3005).to_wkt()
    assert _normalise_crs(wkt) == "EPSG:3005"
