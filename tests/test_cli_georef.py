"""``standgrid georef`` on a mission written to disk with a known georeference."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyproj
import pytest
from click.testing import CliRunner

from standgrid.cli.georef import georef
from standgrid.geometry import invert_pose, pose_matrix
from standgrid.georeference import enu_to_lla
from standgrid.mission.sensors import GnssFixes, write_gnss
from standgrid.stamps import NS_PER_S

WYTHAM = (51.7735, -1.337, 120.0)
YAW = 0.6
T_MAP_ENU = pose_matrix([40.0, -25.0, 2.0], [0.0, 0.0, math.sin(YAW / 2), math.cos(YAW / 2)])


def test_help_has_an_example() -> None:
    result = CliRunner().invoke(georef, ["--help"])
    assert result.exit_code == 0
    assert "Example:" in result.output and "--crs" in result.output and "--method" in result.output


@pytest.fixture
def mission(tmp_path: Path) -> Path:
    pytest.importorskip("standgrid.mission.model")
    from mission_factory import make_mission

    syn = make_mission(tmp_path, n_nodes=60, points=20, seed=3)
    stamps = np.array([s.ns for s in syn.stamps], dtype=np.int64)
    positions = syn.poses[:, :3, 3]
    # Fixes every 0.7 s along the piecewise-linear node path, 2 cm noise, 4 gross outliers,
    # 3 invalid fixes and 2 fixes after the trajectory ends.
    rng = np.random.default_rng(7)
    fix_ns = np.concatenate(
        [
            np.arange(stamps[0], stamps[-1], 700_000_000, dtype=np.int64),
            stamps[-1] + np.array([1, 2], dtype=np.int64) * NS_PER_S,
        ]
    )
    pos_map = np.stack([np.interp(fix_ns, stamps, positions[:, k]) for k in range(3)], -1)
    T_enu_map = invert_pose(T_MAP_ENU)
    enu = pos_map @ T_enu_map[:3, :3].T + T_enu_map[:3, 3] + rng.normal(0, 0.02, (len(fix_ns), 3))
    enu[[20, 50, 90, 120]] += [[30.0, 0, 0], [0, -25.0, 0], [20.0, 20.0, 5.0], [0, 0, 40.0]]
    lat, lon, alt = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], WYTHAM)
    quality = np.full(len(fix_ns), 4, dtype=np.int8)
    quality[[5, 6, 7]] = 0
    fixes = GnssFixes(
        fix_ns, lat, lon, alt, quality, np.full(len(fix_ns), 0.02), np.full(len(fix_ns), 0.03)
    )
    (syn.path / "gnss").mkdir()
    write_gnss(fixes, syn.path / "gnss" / "fixes.txt")
    return syn.path


def test_georef_json_reports_the_fit(mission: Path) -> None:
    result = CliRunner().invoke(georef, [str(mission), "--json", "-q"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["method"] == "yaw2d" and report["crs"] == "EPSG:32630"
    assert report["rejected_by_reason"]["invalid"] == 3
    assert report["rejected_by_reason"]["outside_trajectory"] == 2
    assert report["rejected_by_reason"]["outlier"] == 4
    assert report["fixes_used"] == report["fixes_total"] - 9
    assert report["rmse_horizontal_m"] < 0.05 and report["rmse_vertical_m"] < 0.04
    assert abs(report["yaw_deg"] - math.degrees(-YAW)) < 0.05
    fixes = report["fixes"]
    assert len(fixes) == report["fixes_total"]
    assert [f["status"] for f in fixes if not f["inlier"]].count("outlier") == 4
    assert fixes[20]["status"] == "outlier" and np.linalg.norm(fixes[20]["residual_enu_m"]) > 25
    assert fixes[5]["residual_enu_m"] is None
    # The map origin lands where the truth puts it (compared through geodetic coordinates).
    T_enu_map = invert_pose(T_MAP_ENU)
    e, n, u = T_enu_map[:3, 3]
    lat, lon, h = enu_to_lla(e, n, u, WYTHAM)

    x, y, z = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:32630", always_xy=True).transform(
        lon, lat, h
    )
    np.testing.assert_allclose(report["map_origin_crs"], [x, y, z], atol=0.05)


def test_georef_human_output_and_options(mission: Path) -> None:
    result = CliRunner().invoke(
        georef, [str(mission), "--crs", "EPSG:25830", "--method", "rigid3d", "-q"]
    )
    assert result.exit_code == 0, result.output
    assert "ETRS89 / UTM zone 30N" in result.output
    assert (
        "rigid3d" in result.output and "outlier 4" in result.output and "invalid 3" in result.output
    )


def test_georef_errors_are_clean(mission: Path) -> None:
    from standgrid.cli import cli

    result = CliRunner().invoke(cli, ["georef", str(mission), "--crs", "EPSG:4326"])
    assert result.exit_code != 0 and "CRSError" in result.output
    result = CliRunner().invoke(cli, ["georef", str(mission), "--min-fixes", "500"])
    assert result.exit_code != 0 and "InsufficientGnssError" in result.output
    assert str(mission) in result.output
    (mission / "gnss" / "fixes.txt").unlink()
    result = CliRunner().invoke(cli, ["georef", str(mission)])
    assert result.exit_code != 0 and "NotGeoreferencedError" in result.output


def test_graph_anchor_read_from_disk(mission: Path) -> None:
    from standgrid.georeference import georeference_mission
    from standgrid.mission.opening import open_mission
    from standgrid.mission.posegraph import PoseGraph, read_pose_graph, write_pose_graph

    graph_path = mission / "slam_pose_graph.g2o"
    plain = read_pose_graph(graph_path)
    anchored = PoseGraph(
        vertices=plain.vertices,
        edges=plain.edges,
        platform_id=plain.platform_id,
        gnss_lla_ref=WYTHAM,
        gnss_lla_to_map=T_MAP_ENU,
    )
    write_pose_graph(anchored, graph_path)
    fit = georeference_mission(open_mission(mission))
    assert fit.method == "pose_graph" and fit.lla_ref == WYTHAM
    np.testing.assert_allclose(fit.T_enu_map, invert_pose(T_MAP_ENU), atol=1e-12)
    assert fit.rejected_by_reason["outlier"] == 4 and fit.rmse_m < 0.05
    result = CliRunner().invoke(georef, [str(mission), "-q"])
    assert result.exit_code == 0 and "pose_graph" in result.output
    result = CliRunner().invoke(georef, [str(mission), "-q", "--refit", "--json"])
    refit = json.loads(result.output)
    assert refit["method"] == "yaw2d" and abs(refit["yaw_deg"] - math.degrees(-YAW)) < 0.05
