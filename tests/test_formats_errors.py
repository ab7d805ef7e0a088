"""Malformed inputs: each raises a typed error naming the file (and line where there is one)."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from standgrid.clouds import read_cloud, read_cloud_header, write_cloud
from standgrid.errors import (
    FormatError,
    MetadataError,
    MissionNotFoundError,
    PointCloudFormatError,
    PoseGraphFormatError,
    SensorLogFormatError,
    StandgridError,
)
from standgrid.mission.metadata import read_metadata
from standgrid.mission.posegraph import read_pose_graph
from standgrid.mission.poses_csv import read_poses_csv
from standgrid.mission.sensors import read_gnss, read_imu
from standgrid.pointcloud import PointCloud

HEADER = """# .PCD v0.7
VERSION 0.7
FIELDS x y z
SIZE 4 4 4
TYPE F F F
COUNT 1 1 1
WIDTH {w}
HEIGHT {h}
VIEWPOINT 0 0 0 1 0 0 0
POINTS {n}
DATA {data}
"""
VERTEX = "VERTEX_SE3:QUAT_TIME {id} 0 0 0 0 0 0 1 100 {nsec}"
INFO = " ".join(["1"] * 21)


def _pcd(path: Path, n: int, data: str, body: bytes, w: int | None = None, h: int = 1) -> Path:
    path.write_bytes(HEADER.format(w=n if w is None else w, h=h, n=n, data=data).encode() + body)
    return path


def _graph(tmp_path: Path, *lines: str) -> Path:
    path = tmp_path / "graph.g2o"
    path.write_text(
        "\n".join([VERTEX.format(id=0, nsec=1), VERTEX.format(id=1, nsec=2), *lines]) + "\n"
    )
    return path


def _raises(
    exc_type: type[StandgridError],
    fn: Callable[[Path], Any],
    path: Path,
    line: int | None = None,
    match: str | None = None,
) -> StandgridError:
    with pytest.raises(exc_type, match=match) as info:
        fn(path)
    err = info.value
    assert err.path == path
    assert str(path) in str(err)
    if line is not None:
        assert err.line == line
        assert f"{path}:{line}:" in str(err)
    return err


# --- point clouds -------------------------------------------------------------------------


def test_truncated_binary_pcd(tmp_path: Path) -> None:
    body = np.zeros((9, 3), np.float32).tobytes() + b"\x00\x00"  # header says 10 points
    path = _pcd(tmp_path / "trunc.pcd", 10, "binary", body)
    _raises(PointCloudFormatError, read_cloud, path, match="truncated.*10 points.*9 whole points")


def test_truncated_binary_compressed_pcd(tmp_path: Path) -> None:
    body = struct.pack("II", 100, 120) + b"\x01" * 40
    path = _pcd(tmp_path / "trunc_c.pcd", 10, "binary_compressed", body)
    _raises(PointCloudFormatError, read_cloud, path, match="truncated compressed")


def test_corrupt_compressed_pcd_is_typed_and_chained(tmp_path: Path) -> None:
    body = struct.pack("II", 40, 120) + b"\xff" * 40  # right sizes, garbage LZF stream
    path = _pcd(tmp_path / "garbage.pcd", 10, "binary_compressed", body)
    err = _raises(PointCloudFormatError, read_cloud, path)
    assert err.__cause__ is not None  # pypcd4/lzf's own error, chained


def test_width_height_points_mismatch(tmp_path: Path) -> None:
    path = _pcd(
        tmp_path / "wh.pcd", 12, "binary", np.zeros((12, 3), np.float32).tobytes(), w=5, h=2
    )
    _raises(PointCloudFormatError, read_cloud, path, line=10, match=r"WIDTH\*HEIGHT")
    _raises(PointCloudFormatError, read_cloud_header, path, line=10)


def test_ascii_row_count_mismatch(tmp_path: Path) -> None:
    path = _pcd(tmp_path / "rows.pcd", 4, "ascii", b"1 2 3\n4 5 6\n7 8 9\n")
    _raises(PointCloudFormatError, read_cloud, path, line=15, match="POINTS 4, data holds 3")


def test_ascii_bad_row_names_its_line(tmp_path: Path) -> None:
    path = _pcd(tmp_path / "badrow.pcd", 3, "ascii", b"1 2 3\n4 5\n7 8 9\n")
    _raises(PointCloudFormatError, read_cloud, path, line=13, match="2 values")


def test_nan_coordinates_in_pcd(tmp_path: Path) -> None:
    xyz = np.ones((20, 3), np.float32)
    xyz[[7, 11, 12], 1] = np.nan
    path = _pcd(tmp_path / "nan.pcd", 20, "binary", xyz.tobytes())
    _raises(
        PointCloudFormatError, read_cloud, path, match=r"3 of 20 points .* \(first at index 7\)"
    )


def test_nan_coordinates_in_ply(tmp_path: Path) -> None:
    from plyfile import PlyData, PlyElement

    data = np.zeros(5, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    data["z"][4] = np.inf
    path = tmp_path / "nan.ply"
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
    _raises(PointCloudFormatError, read_cloud, path, match="first at index 4")


def test_pcd_without_xyz(tmp_path: Path) -> None:
    path = tmp_path / "noxyz.pcd"
    path.write_text(
        HEADER.format(w=1, h=1, n=1, data="ascii").replace("FIELDS x y z", "FIELDS a b c")
        + "1 2 3\n"
    )
    _raises(PointCloudFormatError, read_cloud, path, line=3, match="no 'x' field")


def test_bad_viewpoint_line(tmp_path: Path) -> None:
    path = tmp_path / "vp.pcd"
    path.write_text(
        HEADER.format(w=1, h=1, n=1, data="ascii").replace(
            "VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 0 0 0 1"
        )
        + "1 2 3\n"
    )
    _raises(PointCloudFormatError, read_cloud_header, path, line=9, match="VIEWPOINT")


def test_corrupt_las(tmp_path: Path) -> None:
    path = tmp_path / "bad.laz"
    path.write_bytes(b"LASF" + b"\x00" * 50)
    err = _raises(PointCloudFormatError, read_cloud, path)
    assert "54 bytes" in str(err)  # refused before laspy reads past the end


def test_corrupt_ply(tmp_path: Path) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
        b"property float x\nend_header\n\x00\x00"
    )
    _raises(PointCloudFormatError, read_cloud, path)


def test_unknown_cloud_extension(tmp_path: Path) -> None:
    path = tmp_path / "cloud.xyz"
    path.write_text("1 2 3\n")
    _raises(PointCloudFormatError, read_cloud, path, match="extension")


# --- pose graphs ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "line, match",
    [
        ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 " + " ".join(["1"] * 20), "needs 30 values, got 29"),
        ("EDGE_SE3:QUAT 0 1 0 0 zero 0 0 0 1 " + INFO, "non-numeric token 'zero'"),
        ("EDGE_SE3:QUAT 0 1 0 nan 0 0 0 0 1 " + INFO, "NaN"),
        ("EDGE_SE3:QUAT 0 7 0 0 0 0 0 0 1 " + INFO, "missing vertex 7"),
        ("EDGE_SE3_SWITCHABLE 0 1 0 0 0 0 0 0 1 " + INFO, "needs 31 values"),
        ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 0 " + INFO, "zero quaternion"),
        (VERTEX.format(id=1, nsec=3), "duplicate vertex id 1"),
        ("VERTEX_SE3:QUAT 2 0 0 0 0 0 0 1", "no time stamp"),
        ("VERTEX_SE3:QUAT_TIME 2 0 0 0 0 0 0 1 100 1000000000", "invalid stamp"),
        ("VERTEX_SE3:QUAT_TIME 2.5 0 0 0 0 0 0 1 100 1", "not an integer"),
        ("GNSS_LLA_REF 95 0 0", "out of range"),
        ("PLATFORM_ID", "needs 1 values"),
    ],
)
def test_bad_g2o_line(tmp_path: Path, line: str, match: str) -> None:
    path = _graph(tmp_path, "# comment", line)
    _raises(PoseGraphFormatError, read_pose_graph, path, line=4, match=match)


def test_unknown_tags_are_skipped_and_counted(tmp_path: Path) -> None:
    path = _graph(
        tmp_path, "TAG_DETECTION 0 1 2", "FIX 0", "FIX 1", "EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 " + INFO
    )
    graph = read_pose_graph(path)
    assert graph.skipped_tags == {"TAG_DETECTION": 1, "FIX": 2}
    assert len(graph.edges) == 1 and len(graph) == 2


def test_bad_pose_csv_row(tmp_path: Path) -> None:
    path = tmp_path / "slam_poses.csv"
    path.write_text(
        "# counter, sec, nsec, x, y, z, qx, qy, qz, qw\n"
        "0, 1, 2, 0, 0, 0, 0, 0, 0, 1\n1, 1, x, 0, 0, 0, 0, 0, 0, 1\n"
    )
    _raises(PoseGraphFormatError, read_poses_csv, path, line=3, match="nsec")
    path.write_text("0, 1, 2, 0, 0, 0, 0, 0, 0, 1\n1, 1, 3, 0, 0, 0, 0, 0, 1\n")
    _raises(PoseGraphFormatError, read_poses_csv, path, line=2, match="9 values")


# --- metadata -------------------------------------------------------------------------------


def test_metadata_invalid_yaml(tmp_path: Path) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text("date: 2023-01-13\nplace: [unclosed\nrobot: anymal\n")
    _raises(MetadataError, read_metadata, path, match="invalid YAML")


def test_metadata_is_a_rosbag(tmp_path: Path) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text("rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n")
    _raises(MetadataError, read_metadata, path, match="ROS 2 bag")


def test_metadata_missing_date(tmp_path: Path) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text("place: wytham\nrobot: anymal\n")
    _raises(MetadataError, read_metadata, path, match="'date'")


def test_metadata_invalid_date(tmp_path: Path) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text("place: wytham\ndate: 2023-13-45\nrobot: anymal\n")
    _raises(MetadataError, read_metadata, path, line=2)
    path.write_text("place: wytham\ndate: last tuesday\nrobot: anymal\n")
    _raises(MetadataError, read_metadata, path, line=2, match="date")


def test_metadata_bad_gnss(tmp_path: Path) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text(
        "date: 2023-01-13\nplace: w\nrobot: r\ngnss: {latitude: 100, longitude: 0, altitude: 0}\n"
    )
    _raises(MetadataError, read_metadata, path, line=4, match="gnss")


# --- sensor logs ----------------------------------------------------------------------------

GNSS_HEAD = "# sec, nsec, latitude, longitude, altitude, quality, h_std, v_std\n"
GOOD_FIX = "10, 0, 51.5, -1.2, 100, 4, 0.02, 0.05\n"


@pytest.mark.parametrize(
    "row, match",
    [
        ("11, 0, 91.5, -1.2, 100, 4, 0.02, 0.05", "latitude"),
        ("11, 0, 51.5, 181, 100, 4, 0.02, 0.05", "longitude"),
        ("11, 0, 51.5, -1.2, 100, 3, 0.02, 0.05", "quality"),
        ("11, 0, 51.5, -1.2, 100, 4.5, 0.02, 0.05", "quality"),
        ("11, 0, 51.5, -1.2, 100, 4, 0.02", "7 values"),
        ("11, 0, 51.5, north, 100, 4, 0.02, 0.05", "longitude"),
        ("11, 0, nan, -1.2, 100, 4, 0.02, 0.05", "NaN position"),
        ("11, 0, 51.5, -1.2, 100, 4, -1, 0.05", "std"),
        ("11, 1000000000, 51.5, -1.2, 100, 4, 0.02, 0.05", "stamp"),
    ],
)
def test_bad_gnss_row(tmp_path: Path, row: str, match: str) -> None:
    path = tmp_path / "fixes.txt"
    path.write_text(GNSS_HEAD + GOOD_FIX + "\n" + row + "\n" + GOOD_FIX)
    _raises(SensorLogFormatError, read_gnss, path, line=4, match=match)


def test_bad_imu_row(tmp_path: Path) -> None:
    path = tmp_path / "imu.txt"
    path.write_text(
        "# sec, nsec, ax, ay, az, wx, wy, wz\n1, 0, 0, 0, 9.8, 0, 0, 0\n2, 0, 0, 0, inf, 0, 0, 0\n"
    )
    _raises(SensorLogFormatError, read_imu, path, line=3, match="infinite")


# --- empty and missing files ----------------------------------------------------------------

READERS: list[tuple[str, Callable[[Path], Any], type[FormatError]]] = [
    ("cloud.pcd", read_cloud, PointCloudFormatError),
    ("cloud.ply", read_cloud, PointCloudFormatError),
    ("cloud.las", read_cloud, PointCloudFormatError),
    ("graph.g2o", read_pose_graph, PoseGraphFormatError),
    ("slam_poses.csv", read_poses_csv, PoseGraphFormatError),
    ("fixes.txt", read_gnss, SensorLogFormatError),
    ("imu.txt", read_imu, SensorLogFormatError),
    ("metadata.yaml", read_metadata, MetadataError),
]


@pytest.mark.parametrize("name, reader, error", READERS, ids=[r[0] for r in READERS])
def test_empty_file(
    tmp_path: Path, name: str, reader: Callable[[Path], Any], error: type[FormatError]
) -> None:
    path = tmp_path / name
    path.write_bytes(b"")
    _raises(error, reader, path)


@pytest.mark.parametrize("name, reader, error", READERS, ids=[r[0] for r in READERS])
def test_file_not_found(
    tmp_path: Path, name: str, reader: Callable[[Path], Any], error: type[FormatError]
) -> None:
    path = tmp_path / "absent" / name
    err = _raises(MissionNotFoundError, reader, path)
    assert isinstance(err, FileNotFoundError)


def test_failed_write_leaves_no_file(tmp_path: Path) -> None:
    out = tmp_path / "x.pcd"
    with pytest.raises(ValueError, match="cannot be stored"):
        write_cloud(PointCloud(np.zeros((2, 3)), {"c": np.array([1 + 1j, 2j])}), out)
    assert list(tmp_path.iterdir()) == []


def test_binary_pcd_with_more_points_than_header(tmp_path: Path) -> None:
    path = _pcd(tmp_path / "extra.pcd", 4, "binary", np.zeros((6, 3), np.float32).tobytes())
    _raises(PointCloudFormatError, read_cloud, path, line=10, match="6 whole points")
