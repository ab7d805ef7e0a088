"""Point clouds: real PCDs, PCD in every encoding, PLY and LAS/LAZ read back by a second reader."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from plyfile import PlyData
from pypcd4 import PointCloud as PcdCloud

from standgrid.clouds import iter_cloud_chunks, read_cloud, read_cloud_header, write_cloud
from standgrid.errors import PointCloudFormatError
from standgrid.geometry import pose_matrix
from standgrid.mission.posegraph import read_pose_graph
from standgrid.pointcloud import PointCloud
from standgrid.stamps import stamp_from_filename
from tests.conftest import real_file

REAL_PCDS = [
    "vilens/slam_tutorial/individual_clouds/cloud_1583840261_039995392.pcd",
    "vilens/slam_tutorial/individual_clouds/cloud_1583840267_239448320.pcd",
]
NORMAL_FIELDS = ("intensity", "normal_x", "normal_y", "normal_z", "curvature")


def _cloud(n: int = 2000, seed: int = 0, offset: float = 0.0) -> PointCloud:
    """Float32-representable coordinates and fields that compress (quantised values)."""
    rng = np.random.default_rng(seed)
    xyz = (np.round(rng.uniform(-40, 40, (n, 3)) * 64) / 64).astype(np.float32).astype(np.float64)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    fields = {
        "intensity": np.round(rng.uniform(0, 255, n)).astype(np.float32),
        "normal_x": normals[:, 0].astype(np.float32),
        "normal_y": normals[:, 1].astype(np.float32),
        "normal_z": normals[:, 2].astype(np.float32),
        "curvature": (np.round(rng.uniform(0, 1, n) * 256) / 256).astype(np.float32),
    }
    return PointCloud(xyz + offset, fields)


@pytest.mark.realdata
@pytest.mark.parametrize("relative", REAL_PCDS)
def test_real_pcd(relative: str) -> None:
    path = real_file(relative)
    cloud = read_cloud(path)
    assert len(cloud) == 65_536
    assert cloud.xyz.dtype == np.float64 and cloud.xyz.shape == (65_536, 3)
    assert cloud.fields == {}
    raw = PcdCloud.from_path(path).numpy()  # second reader: pypcd4 directly
    np.testing.assert_array_equal(cloud.xyz, raw.astype(np.float64))
    header = read_cloud_header(path)
    assert header.points == 65_536 and header.fields == () and header.encoding == "binary"
    np.testing.assert_array_equal(header.viewpoint, np.eye(4))


@pytest.mark.realdata
def test_real_pcd_stamps_match_ground_truth_vertices() -> None:
    graph = read_pose_graph(real_file("vilens/slam_tutorial/graphs/ground_truth.slam"))
    for vertex_id, relative in enumerate(REAL_PCDS):
        parsed = stamp_from_filename(Path(relative).name)
        assert parsed is not None
        _, stamp, ext = parsed
        assert ext == "pcd"
        assert (stamp.sec, stamp.nsec) == tuple(graph.vertices[vertex_id].stamp)
        assert stamp.ns == graph.vertices[vertex_id].stamp.ns


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_round_trip_all_encodings(tmp_path: Path, encoding: str) -> None:
    cloud = _cloud()
    viewpoint = pose_matrix([1.0, -2.0, 0.5], [0.1, 0.2, 0.3, 0.9])
    out = tmp_path / f"cloud_{encoding}.pcd"
    write_cloud(cloud, out, viewpoint=viewpoint, encoding=encoding)  # type: ignore[arg-type]
    header_text = out.read_bytes().split(b"DATA")[1].split(b"\n")[0].strip().decode()
    assert header_text == encoding
    back = read_cloud(out)
    atol = 1e-9 if encoding == "ascii" else 0.0  # pypcd4 writes ASCII floats with 10 decimals
    np.testing.assert_allclose(back.xyz, cloud.xyz, rtol=0, atol=atol)
    assert tuple(back.fields) == NORMAL_FIELDS
    for name in NORMAL_FIELDS:
        assert back.fields[name].dtype == np.float32
        got = np.asarray(back.fields[name], dtype=np.float64)
        np.testing.assert_allclose(got, np.asarray(cloud.fields[name], np.float64), atol=atol)
    header = read_cloud_header(out)
    assert header.points == len(cloud) and header.fields == NORMAL_FIELDS
    assert header.viewpoint is not None
    np.testing.assert_allclose(header.viewpoint, viewpoint, atol=1e-15)
    # VIEWPOINT is tx ty tz qw qx qy qz: w first
    vp = next(ln for ln in out.read_bytes().split(b"\n") if ln.startswith(b"VIEWPOINT")).split()[1:]
    q = np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])
    np.testing.assert_allclose(np.array(vp, dtype=float), [1, -2, 0.5, q[3], q[0], q[1], q[2]])
    # second reader
    raw = PcdCloud.from_path(out)
    assert raw.fields == ("x", "y", "z", *NORMAL_FIELDS)


def test_pcd_float64_xyz_for_large_coordinates(tmp_path: Path) -> None:
    cloud = PointCloud(np.array([[500_000.123456, 5_700_000.654321, 312.5]]))
    out = tmp_path / "utm.pcd"
    write_cloud(cloud, out)
    assert read_cloud_header(out).dtypes["x"] == np.float64
    np.testing.assert_array_equal(read_cloud(out).xyz, cloud.xyz)
    small = tmp_path / "small.pcd"
    write_cloud(PointCloud(np.array([[1.0, 2.0, 3.0]])), small)
    assert read_cloud_header(small).dtypes["x"] == np.float32
    write_cloud(PointCloud(np.array([[0.1, 2.0, 3.0]])), small, xyz_dtype=np.float64)
    assert read_cloud(small).xyz[0, 0] == 0.1


def test_pcd_multi_count_and_integer_fields(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    hist = rng.random((10, 4)).astype(np.float32)
    cloud = PointCloud(
        rng.random((10, 3)).astype(np.float32),
        {
            "hist": hist,
            "ring": np.arange(10, dtype=np.uint16),
            "label": -np.arange(10, dtype=np.int32),
        },
    )
    out = tmp_path / "multi.pcd"
    write_cloud(cloud, out, encoding="binary_compressed")
    back = read_cloud(out)
    np.testing.assert_array_equal(back.fields["hist"], hist)
    assert back.fields["ring"].dtype == np.uint16 and back.fields["label"].dtype == np.int32
    np.testing.assert_array_equal(back.fields["label"], -np.arange(10))


def test_nan_in_other_fields_is_allowed(tmp_path: Path) -> None:
    cloud = _cloud(50)
    intensity = cloud.fields["intensity"].copy()
    intensity[3] = np.nan
    out = tmp_path / "nanfield.pcd"
    write_cloud(cloud.with_fields(intensity=intensity), out)
    back = read_cloud(out)
    assert np.isnan(back.fields["intensity"][3]) and len(back) == 50


def test_ply_round_trip_float64(tmp_path: Path) -> None:
    cloud = _cloud(500, offset=0.0)
    utm = PointCloud(
        cloud.xyz + [500_000.0, 5_700_000.0, 0.0] + 1e-4, {"intensity": cloud.fields["intensity"]}
    )
    out = tmp_path / "tile.ply"
    write_cloud(utm, out)
    back = read_cloud(out)
    np.testing.assert_array_equal(back.xyz, utm.xyz)
    np.testing.assert_array_equal(back.fields["intensity"], utm.fields["intensity"])
    ply = PlyData.read(str(out))  # second reader
    vertex = ply["vertex"]
    assert vertex["x"].dtype == np.float64
    np.testing.assert_array_equal(vertex["y"], utm.xyz[:, 1])
    header = read_cloud_header(out)
    assert header.points == 500 and header.fields == ("intensity",) and header.viewpoint is None


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_round_trip(tmp_path: Path, ext: str) -> None:
    rng = np.random.default_rng(2)
    n = 3000
    xyz = np.round(rng.uniform(0, 100, (n, 3)), 3) + np.array([612_000.0, 5_123_000.0, 300.0])
    cloud = PointCloud(
        xyz,
        {
            "intensity": rng.integers(0, 65535, n).astype(np.uint16),
            "classification": np.where(rng.random(n) < 0.3, 2, 1).astype(np.uint8),
            "gps_time": rng.uniform(1e8, 2e8, n),
            "curvature": rng.random(n).astype(np.float32),
        },
    )
    out = tmp_path / f"cloud.{ext}"
    write_cloud(cloud, out, crs="EPSG:25832")
    back = read_cloud(out)
    np.testing.assert_allclose(back.xyz, xyz, rtol=0, atol=1e-6)
    for name in ("intensity", "classification", "gps_time", "curvature"):
        np.testing.assert_array_equal(back.fields[name], cloud.fields[name])
    las = laspy.read(out)  # second reader
    assert las.header.point_count == n
    np.testing.assert_allclose(np.asarray(las.x), xyz[:, 0], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(las["curvature"]), cloud.fields["curvature"])
    assert las.header.parse_crs().to_epsg() == 25832
    assert las.header.are_points_compressed == (ext == "laz")  # .laz was plain LAS before
    header = read_cloud_header(out)
    assert header.points == n and header.format == ext and "curvature" in header.fields
    np.testing.assert_allclose(header.bounds[0], xyz.min(axis=0), atol=1e-6)  # type: ignore[index]
    chunks = list(iter_cloud_chunks(out, 1000))
    assert [len(c) for c in chunks] == [1000, 1000, 1000]
    np.testing.assert_allclose(np.concatenate([c.xyz for c in chunks]), xyz, atol=1e-6)


def test_las_refuses_lossy_standard_dimension(tmp_path: Path) -> None:
    cloud = _cloud(10)  # float32 intensity with no exact uint16 value for LAS intensity
    bad = cloud.with_fields(
        intensity=np.asarray(cloud.fields["intensity"], np.float32) + np.float32(0.5)
    )
    with pytest.raises(ValueError, match="intensity"):
        write_cloud(bad, tmp_path / "bad.las")
    assert not (tmp_path / "bad.las").exists()
    write_cloud(cloud, tmp_path / "ok.las")  # integral float intensity casts losslessly
    np.testing.assert_array_equal(
        read_cloud(tmp_path / "ok.las").fields["intensity"], cloud.fields["intensity"]
    )


@pytest.mark.realdata
def test_real_laz_reads_and_streams() -> None:
    path = real_file("als/lidR/MixedConifer.laz")
    cloud = read_cloud(path, fields=["classification", "treeID"])
    assert len(cloud) == 37_657 and set(cloud.fields) == {"classification", "treeID"}
    assert 2 in set(cloud.fields["classification"].tolist())
    las = laspy.read(path)
    np.testing.assert_array_equal(cloud.xyz[:, 0], np.asarray(las.x))
    assert sum(len(c) for c in iter_cloud_chunks(path, 10_000)) == 37_657
    assert read_cloud_header(path).points == 37_657


def test_pcd_chunks_slice_whole_file(tmp_path: Path) -> None:
    out = tmp_path / "c.pcd"
    cloud = _cloud(25)
    write_cloud(cloud, out)
    chunks = list(iter_cloud_chunks(out, 10))
    assert [len(c) for c in chunks] == [10, 10, 5]
    np.testing.assert_array_equal(
        np.concatenate([c.fields["curvature"] for c in chunks]), cloud.fields["curvature"]
    )


def test_pcd_organised_with_padding_field(tmp_path: Path) -> None:
    """HEIGHT > 1 (organised) and a PCL ``_`` padding field, written by hand."""
    rows = np.zeros(
        6, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "<f4"), ("ring", "<u2")]
    )
    rows["x"] = np.arange(6)
    rows["ring"] = [0, 0, 0, 1, 1, 1]
    rows["_"] = 99.0
    header = (
        "VERSION .7\nFIELDS x y z _ ring\nSIZE 4 4 4 4 2\nTYPE F F F F U\nCOUNT 1 1 1 1 1\n"
        "WIDTH 3\nHEIGHT 2\nPOINTS 6\nDATA binary\n"
    )
    path = tmp_path / "organised.pcd"
    path.write_bytes(header.encode() + rows.tobytes())
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz[:, 0], np.arange(6))
    assert list(cloud.fields) == ["ring"]
    np.testing.assert_array_equal(cloud.fields["ring"], [0, 0, 0, 1, 1, 1])
    info = read_cloud_header(path)
    assert info.viewpoint is None  # no VIEWPOINT line
    assert info.fields == ("ring",) and info.dtypes["ring"] == np.uint16


@pytest.mark.parametrize("text, byte_order", [(True, "="), (False, ">")])
def test_ply_ascii_and_big_endian(tmp_path: Path, text: bool, byte_order: str) -> None:
    from plyfile import PlyElement

    data = np.zeros(4, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f4"), ("intensity", ">u2")])
    data["x"] = [612_000.25, 612_001.5, 612_002.75, 612_003.0]
    data["intensity"] = [1, 2, 300, 65535]
    path = tmp_path / "v.ply"
    PlyData([PlyElement.describe(data, "vertex")], text=text, byte_order=byte_order).write(
        str(path)
    )
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz[:, 0], data["x"])
    assert cloud.fields["intensity"].dtype == np.uint16
    np.testing.assert_array_equal(cloud.fields["intensity"], [1, 2, 300, 65535])
    assert read_cloud_header(path).encoding == ("ascii" if text else "binary_big_endian")


def test_pcd_float32_only_for_base_frame_magnitudes(tmp_path: Path) -> None:
    """A map-frame cloud a few km from its origin keeps float64 (float32 steps ~0.5 mm there)."""
    cloud = PointCloud(np.array([[4321.0012345, -1234.5678901, 12.3456789]]))
    out = tmp_path / "map.pcd"
    write_cloud(cloud, out)
    assert PcdCloud.from_path(out).fields[0] == "x"
    assert read_cloud_header(out).dtypes["x"] == np.float64
    np.testing.assert_array_equal(read_cloud(out).xyz, cloud.xyz)
    base = tmp_path / "base.pcd"
    write_cloud(PointCloud(np.array([[999.5, -20.25, 3.0]])), base)
    assert read_cloud_header(base).dtypes["x"] == np.float32


def test_las_gps_time_is_flagged_adjusted_standard(tmp_path: Path) -> None:
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    timed = tmp_path / "timed.las"
    write_cloud(PointCloud(xyz, {"gps_time": np.array([3.9e8, 3.9e8 + 0.1])}), timed)
    las = laspy.read(timed)
    assert las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    assert int(las.header.global_encoding.value) & 1 == 1  # bit 0 of the raw field
    np.testing.assert_allclose(las.gps_time, [3.9e8, 3.9e8 + 0.1])
    plain = tmp_path / "plain.las"
    write_cloud(PointCloud(xyz), plain)
    assert (
        laspy.read(plain).header.global_encoding.gps_time_type == laspy.header.GpsTimeType.WEEK_TIME
    )


def test_open_cloud_reads_header_points_and_chunks_of_every_format(tmp_path: Path) -> None:
    """One reader per format from the registry: header first (no points read), the CRS of
    a LAS header, chunks that add up to the points; a file named unlike any format is told
    by its first bytes, one that is no cloud is refused naming it."""
    from standgrid.clouds import open_cloud

    cloud = _cloud(250)
    for ext in ("pcd", "ply", "las", "laz"):
        named = tmp_path / f"cloud.{ext}"
        write_cloud(cloud, named, **({"crs": "EPSG:25832"} if ext in ("las", "laz") else {}))
        unnamed = tmp_path / f"{ext}.bin"
        unnamed.write_bytes(named.read_bytes())
        for path in (named, unnamed):
            with open_cloud(path) as reader:
                header = reader.header
                assert (header.format, header.points) == (ext, 250)
                assert "curvature" in header.fields
                crs = header.crs
                assert (crs.to_epsg() if crs is not None else None) == (
                    25832 if ext in ("las", "laz") else None
                )
                chunks = list(reader.chunks(100))
                assert [len(c) for c in chunks] == [100, 100, 50]
                np.testing.assert_allclose(
                    np.concatenate([c.xyz for c in chunks]), reader.read().xyz
                )
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"\x00\x01 not a point cloud" * 10)
    with pytest.raises(PointCloudFormatError, match="unknown point-cloud extension") as info:
        open_cloud(junk)
    assert info.value.path == junk


def test_payload_las_refusals_are_typed_and_name_the_file(tmp_path: Path) -> None:
    """The payload LAS writer is the tile writer's encoder: a fraction in a standard field,
    a NaN GPS time or an unusable CRS is refused naming the file, and nothing is written."""
    from standgrid.errors import CRSError

    xyz = np.zeros((3, 3))
    out = tmp_path / "bad.laz"
    cases = [
        (PointCloud(xyz, {"classification": np.array([1.0, 2.5, 3.0])}), {}, "value 2.5"),
        (PointCloud(xyz, {"gps_time": np.array([1.0, np.nan, 3.0])}), {}, "finite time"),
        (PointCloud(xyz), {"crs": "EPSG:0"}, "unusable CRS"),
    ]
    for cloud, options, text in cases:
        with pytest.raises((PointCloudFormatError, CRSError), match=text) as info:
            write_cloud(cloud, out, **options)
        assert info.value.path == out
        assert not out.exists()
