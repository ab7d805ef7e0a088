"""open_mission: attachment by integer stamps, typed errors, frames, re-alignment, summary."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from mission_factory import make_graph, make_mission

from standgrid.clouds import write_cloud
from standgrid.errors import DuplicateStampError, MissionNotFoundError, OrphanPayloadError
from standgrid.geometry import pose_matrix, transform_points
from standgrid.mission.model import Mission
from standgrid.mission.opening import open_mission
from standgrid.mission.posegraph import EdgeKind, PoseGraph, Vertex, read_pose_graph
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp


def count_reads(mission: Mission) -> list[Path]:
    """Wrap the mission's own cloud reader; return the list of paths it reads."""
    reads: list[Path] = []
    inner = mission.read_cloud

    def counting(path: Path) -> PointCloud:
        reads.append(path)
        return inner(path)

    mission.read_cloud = counting
    return reads


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(MissionNotFoundError):
        open_mission(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MissionNotFoundError, match="no mission files"):
        open_mission(tmp_path / "empty")


def test_attach_by_integer_stamp_with_unpadded_graph_nsec(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)
    text = (syn.path / "slam_pose_graph.g2o").read_text()
    # the graph writes nsec unpadded, file names pad it: they must still pair up
    assert f" {syn.stamps[1].sec} {syn.stamps[1].nsec}\n" in text
    assert (
        syn.path / "payload_clouds" / f"cloud_{syn.stamps[1].sec}_{syn.stamps[1].nsec:09d}.pcd"
    ).exists()
    m = open_mission(syn.path)
    assert [p.stamp for p in m.payloads] == syn.stamps
    assert [p.node_id for p in m.payloads] == list(range(5))
    assert m.name == "2024-05-14-wytham-anymal-coyote"
    assert m.metadata is not None  # generated from the conventional folder name
    assert m.graph is not None and len(m.graph) == 5
    assert m.problems == []


def test_real_vilens_graph_and_clouds(tmp_path: Path, vilens: Path) -> None:
    root = tmp_path / "2023-05-01-14-01-05"
    (root / "individual_clouds").mkdir(parents=True)
    shutil.copy(vilens / "slam_tutorial/graphs/ground_truth.slam", root / "slam_pose_graph.slam")
    for pcd in sorted((vilens / "slam_tutorial/individual_clouds").glob("*.pcd")):
        (root / "individual_clouds" / pcd.name).symlink_to(pcd)
    m = open_mission(root)
    assert m.payloads == []
    assert [s.node_id for s in m.scans] == [0, 1]
    assert m.scans[0].stamp == Stamp(1583840261, 39995392)
    # the VILENS logger's date-time name gives the date and time (no place, no robot)
    assert m.metadata is not None and m.metadata.date.isoformat() == "2023-05-01"
    assert m.metadata.place is None and m.metadata.robot is None
    cloud = m.load_payload(m.scans[0], frame="map")
    assert cloud.xyz.dtype == np.float64 and len(cloud) == 65536
    base = m.load_payload(m.scans[0], frame="base")
    expected = transform_points(m.graph.vertices[0].pose, base.xyz)  # type: ignore[union-attr]
    np.testing.assert_allclose(cloud.xyz, expected, rtol=0, atol=1e-9)
    assert m.summary()["points"] == 0  # no payloads; scans are not payloads


def test_orphan_payload_strict_and_lenient(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)
    orphan = syn.path / "payload_clouds" / "cloud_1800000000_000000001.pcd"
    write_cloud(PointCloud(np.zeros((3, 3)), {"intensity": np.zeros(3, np.float32)}), orphan)
    with pytest.raises(OrphanPayloadError) as info:
        open_mission(syn.path)
    assert info.value.path == orphan and orphan.name in str(info.value)
    m = open_mission(syn.path, strict=False)
    kept = [p for p in m.payloads if p.path == orphan]
    assert len(kept) == 1 and kept[0].node_id is None
    assert any(orphan.name in msg for msg in m.problems)
    assert len(m.payloads) == 6
    # the orphan is skipped when streaming map-frame clouds, the rest still come
    assert len(list(m.iter_payload_clouds())) == 5
    with pytest.raises(OrphanPayloadError):
        m.pose_of(kept[0])


def test_duplicate_vertex_stamp(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, csv_name=None)
    graph_file = syn.path / "slam_pose_graph.g2o"
    lines = graph_file.read_text().splitlines()
    vertex_1 = next(line for line in lines if line.startswith("VERTEX_SE3:QUAT_TIME 1 "))
    lines.append(vertex_1.replace("VERTEX_SE3:QUAT_TIME 1 ", "VERTEX_SE3:QUAT_TIME 99 ", 1))
    graph_file.write_text("\n".join(lines) + "\n")
    with pytest.raises(DuplicateStampError) as info:
        open_mission(syn.path)
    assert info.value.path == graph_file
    m = open_mission(syn.path, strict=False)
    assert any("share the stamp" in msg and str(graph_file) in msg for msg in m.problems)
    assert m.payloads[1].node_id == 1  # first vertex of the duplicated stamp


def test_map_points_equal_pose_times_base(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, fields=("intensity", "normal_x"))
    m = open_mission(syn.path)
    for payload, cloud in m.iter_payload_clouds(frame="map"):
        i = syn.stamps.index(payload.stamp)
        truth = syn.clouds[payload.stamp]
        np.testing.assert_allclose(
            cloud.xyz, transform_points(syn.poses[i], truth.xyz), rtol=0, atol=1e-9
        )
        np.testing.assert_allclose(m.pose_of(payload), syn.poses[i], rtol=0, atol=1e-12)
        assert set(cloud.fields) == {"intensity", "normal_x"}
        np.testing.assert_array_equal(cloud.fields["intensity"], truth.fields["intensity"])


def test_clouds_in_map_are_brought_to_base(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, cloud_folder="payload_clouds_in_map")
    m = open_mission(syn.path)
    assert all(p.frame == "map" for p in m.payloads)
    p = m.payloads[2]
    base = m.load_payload(p, frame="base")
    np.testing.assert_allclose(base.xyz, syn.clouds[p.stamp].xyz, rtol=0, atol=1e-9)


def test_graph_from_pose_csv_only(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, graph_name=None, csv_name="slam-poses.csv")
    m = open_mission(syn.path)
    assert m.graph is not None and len(m.graph.edges) == 0
    np.testing.assert_allclose(m.pose_of(m.payloads[3]), syn.poses[3], atol=1e-12)


def test_viewpoint_pose_without_graph(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, graph_name=None, csv_name=None, viewpoints=True)
    m = open_mission(syn.path)
    assert m.graph is None and all(p.node_id is None for p in m.payloads)
    np.testing.assert_allclose(m.pose_of(m.payloads[4]), syn.poses[4], atol=1e-6)
    stamps, positions = m.trajectory()
    assert stamps.tolist() == [s.ns for s in syn.stamps]
    np.testing.assert_allclose(positions, syn.poses[:, :3, 3], atol=1e-6)


def test_with_graph_realigns_without_reading_again(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)
    m = open_mission(syn.path)
    reads = count_reads(m)
    before = {p.stamp: c.xyz.copy() for p, c in m.iter_payload_clouds("map")}
    assert len(reads) == 5
    # a re-optimised graph: every pose moved by a known correction
    correction = pose_matrix([2.0, -1.0, 0.5], [0.0, 0.0, np.sin(0.1), np.cos(0.1)])
    new_poses = correction @ syn.poses
    new_graph = make_graph(syn.stamps, new_poses)
    for f in (syn.path / "payload_clouds").iterdir():
        f.unlink()  # no file left to re-read
    view = m.with_graph(new_graph)
    for payload, cloud in view.iter_payload_clouds("map"):
        expected = transform_points(correction, before[payload.stamp])
        np.testing.assert_allclose(cloud.xyz, expected, rtol=0, atol=1e-9)
        assert not np.allclose(cloud.xyz, before[payload.stamp])
    assert len(reads) == 5
    # the original view keeps its own poses
    np.testing.assert_allclose(m.pose_of(m.payloads[0]), syn.poses[0])


def test_with_merged_graph_picks_vertices_by_stamp(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)
    other = make_mission(tmp_path, "2024-05-15-wytham-anymal-coyote", seed=5)
    m = open_mission(syn.path)
    shifted = [Stamp(s.sec + 10_000, s.nsec) for s in other.stamps]
    g0 = make_graph(shifted, other.poses, id_offset=0)
    g1 = make_graph(syn.stamps, syn.poses + 0.0, id_offset=10_000)
    merged = PoseGraph(vertices={**g0.vertices, **g1.vertices}, edges=g0.edges + g1.edges)
    view = m.with_graph(merged)
    assert [p.node_id for p in view.payloads] == [10_000 + i for i in range(5)]
    stamps, positions = view.trajectory()
    assert stamps.tolist() == [s.ns for s in syn.stamps]
    np.testing.assert_allclose(positions, syn.poses[:, :3, 3])
    # a merged graph that lacks one of this mission's stamps -> orphan
    del merged.vertices[10_002]
    with pytest.raises(OrphanPayloadError):
        m.with_graph(merged)


def test_cache_is_bounded(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, points=100)
    m = open_mission(syn.path, cache_points=250)
    reads = count_reads(m)
    for _ in range(2):
        list(m.iter_payload_clouds("base"))
    assert len(reads) == 10  # 2 clouds fit; sequential sweeps evict before reuse
    m2 = open_mission(syn.path)
    reads2 = count_reads(m2)
    for _ in range(3):
        list(m2.iter_payload_clouds("base"))
    assert len(reads2) == 5


def test_sensors_images_and_summary(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, gnss=True, imu=True, cameras=("front", "left"))
    m = open_mission(syn.path)
    assert m.gnss is not None and syn.gnss is not None
    np.testing.assert_array_equal(m.gnss.stamps_ns, syn.gnss.stamps_ns)
    assert m.imu is not None and syn.imu is not None
    np.testing.assert_array_equal(m.imu.stamps_ns, syn.imu.stamps_ns)
    np.testing.assert_allclose(m.imu.accel, syn.imu.accel)
    assert len(m.images) == 4 and {i.camera for i in m.images} == {"front", "left"}
    s = m.summary()
    assert s["nodes"] == 5 and s["payloads"] == 5 and s["points"] == 5 * 200
    assert s["edges"] == {str(EdgeKind.LOOP_CLOSURE): 1, str(EdgeKind.ODOMETRY): 4}
    assert s["gnss_fixes"] == 15 and s["imu_samples"] == 50 and s["images"] == 4
    assert s["time_span"]["seconds"] == pytest.approx(
        (syn.imu.stamps_ns[-1] - syn.stamps[0].ns) / 1e9
    )
    np.testing.assert_allclose(s["extent_map"]["min"], syn.poses[:, :3, 3].min(axis=0))


def test_gnss_from_payload_files(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, gnss=True)
    fixes = (syn.path / "gnss" / "fixes.txt").read_text().splitlines()
    (syn.path / "payloads" / "gnss").mkdir(parents=True)
    for k, chunk in enumerate((fixes[1:8], fixes[8:])):
        stamp = syn.stamps[k]
        (syn.path / "payloads" / "gnss" / stamp.filename("gnss", "txt")).write_text(
            "\n".join([fixes[0], *chunk]) + "\n"
        )
    (syn.path / "gnss" / "fixes.txt").unlink()
    m = open_mission(syn.path)
    assert m.gnss is not None and syn.gnss is not None
    np.testing.assert_array_equal(m.gnss.stamps_ns, syn.gnss.stamps_ns)
    np.testing.assert_array_equal(m.gnss.lat, syn.gnss.lat)


def test_ground_layer(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)
    ground = PointCloud(
        np.array([[1.0, 2.0, -0.5], [3.0, 1.0, -0.4]]), {"intensity": np.ones(2, np.float32)}
    )
    (syn.path / "ground_clouds").mkdir()
    write_cloud(ground, syn.path / "ground_clouds" / syn.stamps[1].filename("cloud", "pcd"))
    m = open_mission(syn.path)
    p = m.payloads[1]
    assert list(p.layers) == ["ground"] and m.payloads[0].layers == {}
    layer = m.load_payload(p, frame="map", layer="ground")
    np.testing.assert_allclose(layer.xyz, transform_points(syn.poses[1], ground.xyz), atol=1e-6)
    assert [q.stamp for q, _ in m.iter_payload_clouds(layer="ground")] == [syn.stamps[1]]


def test_real_slam_graph_summary(tmp_path: Path, vilens: Path) -> None:
    root = tmp_path / "m"
    root.mkdir()
    (root / "slam_pose_graph.slam").symlink_to(vilens / "slam_tutorial/graphs/slam_pose_graph.slam")
    m = open_mission(root)
    s = m.summary()
    assert s["nodes"] == 178
    assert s["edges"] == {"loop_closure": 12, "odometry": 177}
    stamps, positions = m.trajectory()
    assert positions.shape == (178, 3)
    assert len(stamps) == 178 and np.all(np.diff(stamps) > 0)
    graph = read_pose_graph(root / "slam_pose_graph.slam")
    assert isinstance(next(iter(graph.vertices.values())), Vertex)


def test_unstamped_file_in_cloud_folder_is_an_error_when_strict(tmp_path: Path) -> None:
    from standgrid.errors import MissionConsistencyError

    syn = make_mission(tmp_path, n_nodes=3)
    stray = syn.path / "payload_clouds" / "cloud_latest.pcd"
    shutil.copy(next((syn.path / "payload_clouds").glob("*.pcd")), stray)
    with pytest.raises(MissionConsistencyError, match="carries no stamp") as info:
        open_mission(syn.path)
    assert info.value.path == stray
    m = open_mission(syn.path, strict=False)
    assert len(m.payloads) == 3
    assert any(str(stray) in p and "no stamp" in p for p in m.problems)


def test_unused_second_graph_is_reported_but_never_an_error(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, n_nodes=3)
    used = syn.path / "slam_pose_graph.g2o"
    spare = syn.path / "mission.g2o"  # a less preferred graph name
    shutil.copy(used, spare)
    strict = open_mission(syn.path)
    assert strict.graph is not None and strict.graph.source == used.absolute()
    assert strict.problems == []
    assert any(str(spare.name) in w and "not used" in w for w in strict.warnings)
    loose = open_mission(syn.path, strict=False)
    assert any(str(spare.name) in p and "not used" in p for p in loose.problems)
    assert loose.summary()["warnings"] == loose.warnings


def test_with_graph_reattaches_like_open(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, n_nodes=4)
    m = open_mission(syn.path)
    assert m.graph is not None
    partial = PoseGraph(vertices={9: Vertex(9, syn.stamps[1], syn.poses[1])}, edges=[])
    with pytest.raises(OrphanPayloadError):
        m.with_graph(partial)
    loose = open_mission(syn.path, strict=False).with_graph(partial)
    assert [p.node_id for p in loose.payloads] == [None, 9, None, None]
    assert sum("no pose-graph node" in p for p in loose.problems) == 3


def test_graph_and_pose_csv_paths_that_are_folders_are_typed_errors(tmp_path: Path) -> None:
    from standgrid.errors import PoseGraphFormatError
    from standgrid.mission.poses_csv import read_poses_csv

    folder = tmp_path / "slam_pose_graph.g2o"
    folder.mkdir()
    with pytest.raises(PoseGraphFormatError, match="cannot read") as info:
        read_pose_graph(folder)
    assert info.value.path == folder and isinstance(info.value.__cause__, OSError)
    with pytest.raises(PoseGraphFormatError, match="cannot read") as csv_info:
        read_poses_csv(folder)
    assert csv_info.value.path == folder and isinstance(csv_info.value.__cause__, OSError)
    with pytest.raises(MissionNotFoundError):
        read_pose_graph(tmp_path / "absent.g2o")
