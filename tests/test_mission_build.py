"""build_payloads: per-node scans -> payloads in the centre node's base frame."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from mission_factory import make_mission

from standgrid.clouds import read_cloud, write_cloud
from standgrid.errors import MissionConsistencyError, OutputExistsError
from standgrid.geometry import transform_points
from standgrid.mission.build import build_payloads, group_by_area, group_by_distance
from standgrid.mission.opening import open_mission
from standgrid.pointcloud import PointCloud


def union_in_map(syn, indices) -> np.ndarray:  # type: ignore[no-untyped-def]
    return np.concatenate(
        [transform_points(syn.poses[i], syn.clouds[syn.stamps[i]].xyz) for i in indices]
    )


def sort_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


def test_group_by_distance_centres() -> None:
    positions = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], axis=1)
    groups = group_by_distance(positions, 4.0)
    assert groups == [([0, 1, 2, 3], 1), ([4, 5, 6, 7], 5), ([8, 9], 8)]
    with pytest.raises(ValueError):
        group_by_distance(positions, 0.0)


def test_group_by_area() -> None:
    positions = np.array([[1.0, 1, 0], [4, 4, 0], [6, 1, 0], [9, 9, 0], [2.6, 2.4, 0]])
    groups = group_by_area(positions, 5.0)
    assert groups == [([2], 2), ([3], 3), ([0, 1, 4], 4)]  # in time order of the centres


def test_synthetic_union_preserved(tmp_path: Path) -> None:
    syn = make_mission(
        tmp_path / "in",
        n_nodes=12,
        spacing=1.5,
        cloud_folder="individual_clouds",
        fields=("intensity",),
        gnss=True,
        imu=True,
        cameras=("front",),
    )
    out = build_payloads(syn.path, tmp_path / "out", distance=6.0)
    built = open_mission(out)
    assert built.scans == []
    groups = group_by_distance(syn.poses[:, :3, 3], 6.0)
    assert len(groups) >= 2 and len(built.payloads) == len(groups)
    for payload, (members, centre) in zip(built.payloads, groups, strict=True):
        assert payload.stamp == syn.stamps[centre]
        assert payload.node_id == centre
        cloud = built.load_payload(payload, "map")
        np.testing.assert_allclose(cloud.xyz, union_in_map(syn, members), rtol=0, atol=1e-9)
        # expressed in the centre node's base frame
        base = built.load_payload(payload, "base")
        np.testing.assert_allclose(
            transform_points(syn.poses[centre], base.xyz), cloud.xyz, atol=1e-9
        )
        assert list(cloud.fields) == ["intensity"]
    total = sum(len(c) for _, c in built.iter_payload_clouds())
    assert total == 12 * 200  # every scan point exactly once
    assert built.gnss is not None and len(built.gnss) == len(syn.gnss)  # type: ignore[arg-type]
    assert built.imu is not None and len(built.imu) == len(syn.imu)  # type: ignore[arg-type]
    np.testing.assert_array_equal(built.imu.stamps_ns, syn.imu.stamps_ns)  # type: ignore[union-attr]
    # the per-payload logs are named after the built payloads (their centre nodes' stamps)
    for sub in ("gnss", "imu"):
        names = sorted(p.name for p in (out / "payloads" / sub).iterdir())
        assert names == sorted(p.stamp.filename(sub, "txt") for p in built.payloads), sub
    assert len(built.images) == 2
    assert built.metadata is not None


def test_area_tiles(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in", n_nodes=10, spacing=2.0, cloud_folder="slam_clouds")
    out = build_payloads(syn.path, tmp_path / "out", area=5.0)
    built = open_mission(out)
    groups = group_by_area(syn.poses[:, :3, 3], 5.0)
    assert len(built.payloads) == len(groups)
    all_map = np.concatenate([c.xyz for _, c in built.iter_payload_clouds()])
    np.testing.assert_allclose(
        sort_rows(all_map), sort_rows(union_in_map(syn, range(10))), atol=1e-9
    )


def test_field_mismatch_is_a_clear_error(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in", n_nodes=4, cloud_folder="individual_clouds")
    odd = syn.path / "individual_clouds" / syn.stamps[2].filename("cloud", "pcd")
    write_cloud(PointCloud(np.zeros((2, 3)), {"reflectivity": np.zeros(2, np.float32)}), odd)
    with pytest.raises(MissionConsistencyError, match="reflectivity") as info:
        build_payloads(syn.path, tmp_path / "out")
    assert info.value.path == odd
    assert not (tmp_path / "out").exists()


def test_no_scans_and_overwrite(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in", n_nodes=3)  # payload_clouds only
    with pytest.raises(MissionConsistencyError, match="no per-node scans"):
        build_payloads(syn.path, tmp_path / "out")
    scans = make_mission(tmp_path / "in2", n_nodes=3, cloud_folder="individual_clouds")
    out = build_payloads(scans.path, tmp_path / "out")
    with pytest.raises(OutputExistsError):
        build_payloads(scans.path, out)
    build_payloads(scans.path, out, overwrite=True, distance=1.0)
    assert len(open_mission(out).payloads) == 3


def test_real_vilens_scans(tmp_path: Path, vilens: Path) -> None:
    root = tmp_path / "2020-03-10-newer-college-handheld"
    (root / "individual_clouds").mkdir(parents=True)
    shutil.copy(vilens / "slam_tutorial/graphs/ground_truth.slam", root / "slam_pose_graph.slam")
    pcds = sorted((vilens / "slam_tutorial/individual_clouds").glob("*.pcd"))
    for pcd in pcds:
        (root / "individual_clouds" / pcd.name).symlink_to(pcd)
    out = build_payloads(root, tmp_path / "out", distance=20.0)
    built = open_mission(out)
    assert len(built.payloads) == 1  # the two scans are ~6 m apart
    source = open_mission(root)
    expected = np.concatenate([source.load_payload(s, "map").xyz for s in source.scans])
    got = built.load_payload(built.payloads[0], "map").xyz
    assert len(got) == 2 * 65536
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    assert built.payloads[0].stamp in {s.stamp for s in source.scans}
    assert len(read_cloud(pcds[0])) == 65536
    assert built.metadata is not None and built.graph is not None and len(built.graph) == 50


def test_real_folder_with_its_graph_in_graphs_is_refused_then_built_with_graph(
    tmp_path: Path, vilens: Path
) -> None:
    """The tutorial's layout as published: graphs/ beside individual_clouds/."""
    from click.testing import CliRunner

    from standgrid.cli import cli

    root = tmp_path / "slam_tutorial"
    for sub in ("individual_clouds", "graphs"):
        (root / sub).mkdir(parents=True)
        for f in sorted((vilens / "slam_tutorial" / sub).iterdir()):
            (root / sub / f.name).symlink_to(f)
    with pytest.raises(MissionConsistencyError, match="cannot pose the scans") as info:
        build_payloads(root, tmp_path / "out")
    message = str(info.value)
    assert "same VIEWPOINT" in message  # both real scans carry the identity VIEWPOINT
    assert "graphs/ground_truth.slam (its nodes match 2 of 2 scans)" in message
    assert "graphs/slam_pose_graph.slam (its nodes match 0 of 2 scans)" in message
    assert not (tmp_path / "out").exists()

    result = CliRunner().invoke(cli, ["payloads", "build", str(root), "-o", str(tmp_path / "o")])
    assert result.exit_code != 0 and "--graph" in result.output

    graph = root / "graphs" / "ground_truth.slam"
    out = build_payloads(root, tmp_path / "out", graph=graph)
    built = open_mission(out)
    assert len(built.payloads) == 1 and built.graph is not None and len(built.graph) == 50
    got = built.load_payload(built.payloads[0], "map").xyz
    source = open_mission(root).with_graph(built.graph)
    expected = np.concatenate([source.load_payload(s, "map").xyz for s in source.scans])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    # the two scans are 5-6 m apart in the map frame, not stacked at the identity
    centres = [source.load_payload(s, "map").xyz.mean(axis=0) for s in source.scans]
    assert np.linalg.norm(centres[1] - centres[0]) > 4.0


def test_scans_with_distinct_viewpoints_need_no_graph(tmp_path: Path) -> None:
    syn = make_mission(
        tmp_path,
        n_nodes=3,
        cloud_folder="individual_clouds",
        graph_name=None,
        csv_name=None,
        viewpoints=True,
    )
    out = build_payloads(syn.path, tmp_path / "out", distance=100.0)
    built = open_mission(out)
    assert len(built.payloads) == 1
    expected = union_in_map(syn, range(3))
    got = built.load_payload(built.payloads[0], "map").xyz
    np.testing.assert_allclose(sort_rows(got), sort_rows(expected), rtol=0, atol=1e-6)
