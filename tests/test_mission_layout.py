"""Layout discovery: every folder layout of MISSION_FORMAT.md sections 1 and 6."""

from __future__ import annotations

from pathlib import Path

import pytest

from standgrid.errors import MissionNotFoundError
from standgrid.mission.layout import discover_layout, frame_of_folder, layer_name
from standgrid.stamps import Stamp


def touch(path: Path, text: str = "") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_ros1_vilens_layout(tmp_path: Path) -> None:
    root = tmp_path / "2023-05-01-14-01-05"
    touch(root / "slam_pose_graph.g2o")
    touch(root / "slam_poses.csv")
    touch(root / "individual_clouds" / "cloud_1583840261_039995392.pcd")
    touch(root / "individual_clouds" / "cloud_1583840262_000000001.pcd")
    touch(root / "payload_clouds" / "cloud_1583840261_039995392.pcd")
    touch(root / "payload_clouds_in_map" / "cloud_1583840261_039995392.pcd")
    touch(root / "payload_clouds_in_utm" / "cloud_1583840261_039995392.ply")
    layout = discover_layout(root)
    assert layout.graph == root / "slam_pose_graph.g2o"
    assert layout.poses_csv == root / "slam_poses.csv"
    assert [f.name for f in layout.payload_folders] == [
        "payload_clouds",
        "payload_clouds_in_map",
        "payload_clouds_in_utm",
    ]
    assert [f.frame for f in layout.payload_folders] == ["base", "map", "utm"]
    assert layout.payload_source is not None and layout.payload_source.name == "payload_clouds"
    assert layout.scans is not None and layout.scans.name == "individual_clouds"
    assert [f.stamp for f in layout.scans.files] == [
        Stamp(1583840261, 39995392),
        Stamp(1583840262, 1),
    ]
    assert layout.is_mission


def test_payload_source_falls_back_to_map_never_utm(tmp_path: Path) -> None:
    touch(tmp_path / "m" / "payload_clouds_in_utm" / "cloud_1_000000002.ply")
    layout = discover_layout(tmp_path / "m")
    assert layout.payload_source is None
    touch(tmp_path / "m" / "payload_clouds_in_map" / "cloud_1_000000002.pcd")
    layout = discover_layout(tmp_path / "m")
    assert layout.payload_source is not None and layout.payload_source.frame == "map"


@pytest.mark.parametrize(
    ("graph_names", "expected"),
    [
        (["slam_pose_graph.slam"], "slam_pose_graph.slam"),
        (["mission.g2o"], "mission.g2o"),
        (["mission.g2o", "slam_pose_graph.slam", "slam_pose_graph.g2o"], "slam_pose_graph.g2o"),
    ],
)
def test_graph_names(tmp_path: Path, graph_names: list[str], expected: str) -> None:
    for name in graph_names:
        touch(tmp_path / name)
    layout = discover_layout(tmp_path)
    assert layout.graph == tmp_path / expected
    assert len(layout.other_graphs) == len(graph_names) - 1


@pytest.mark.parametrize("name", ["slam_poses.csv", "slam-poses.csv", "poses.txt"])
def test_pose_csv_names(tmp_path: Path, name: str) -> None:
    touch(tmp_path / name)
    layout = discover_layout(tmp_path)
    assert layout.poses_csv == tmp_path / name
    assert layout.graph is None and layout.is_mission


def test_ros2_layout_with_images(tmp_path: Path) -> None:
    root = tmp_path / "2024-03-26_13-47-27_rec004_site"
    touch(root / "slam_pose_graph.slam")
    touch(root / "slam_poses.csv")
    touch(root / "slam_clouds" / "cloud_1711460847_100000000.pcd")
    for cam in ("cam_front", "cam_left", "cam_right"):
        touch(root / "images_rectified" / cam / "image_1711460847_100000000.jpg")
    layout = discover_layout(root)
    assert layout.scans is not None and layout.scans.name == "slam_clouds"
    assert layout.payload_source is None
    assert sorted(layout.cameras) == ["cam_front", "cam_left", "cam_right"]
    assert layout.cameras["cam_left"][0].stamp == Stamp(1711460847, 100000000)


@pytest.mark.parametrize(
    "folder", ["undist-clouds", "raw_data/raw_clouds", "individual_clouds", "slam_clouds"]
)
def test_scan_folders(tmp_path: Path, folder: str) -> None:
    touch(tmp_path / folder / "cloud_10_000000005.pcd")
    layout = discover_layout(tmp_path)
    assert layout.scans is not None and layout.scans.name == folder
    assert layout.scans.role == "scans" and layout.scans.frame == "base"


def test_ground_layer_and_our_files(tmp_path: Path) -> None:
    touch(tmp_path / "metadata.yaml", "robot: anymal\n")
    touch(tmp_path / "payload_clouds" / "cloud_10_000000005.pcd")
    touch(tmp_path / "ground_clouds" / "cloud_10_000000005.pcd")
    touch(tmp_path / "gnss" / "fixes.txt")
    touch(tmp_path / "payloads" / "gnss" / "gnss_10_000000005.txt")
    touch(tmp_path / "payloads" / "imu" / "imu_10_000000005.txt")
    touch(tmp_path / "payloads" / "cameras" / "front" / "image_10_000000005.png")
    touch(tmp_path / "payload_clouds" / "README.txt")
    layout = discover_layout(tmp_path)
    assert layout.metadata == tmp_path / "metadata.yaml"
    assert layout.gnss_log == tmp_path / "gnss" / "fixes.txt"
    assert [f.stamp for f in layout.gnss_payloads] == [Stamp(10, 5)]
    assert [f.stamp for f in layout.imu_payloads] == [Stamp(10, 5)]
    assert list(layout.cameras) == ["front"]
    assert len(layout.layer_folders) == 1 and layer_name(layout.layer_folders[0]) == "ground"
    assert layout.unrecognised == (tmp_path / "payload_clouds" / "README.txt",)


def test_frames_and_missing(tmp_path: Path) -> None:
    assert frame_of_folder("payload_clouds_in_map") == "map"
    assert frame_of_folder("payload_clouds_in_utm") == "utm"
    assert frame_of_folder("slam_clouds") == "base"
    with pytest.raises(MissionNotFoundError, match="does not exist"):
        discover_layout(tmp_path / "nope")
    assert not discover_layout(tmp_path).is_mission
