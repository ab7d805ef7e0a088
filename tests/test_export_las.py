"""LAS/LAZ tile writer: written with write_tile, checked with laspy directly and read_tile."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyproj
import pytest
from shapely.geometry import box

from standgrid.errors import CRSError, PointCloudFormatError
from standgrid.export.las import read_tile, read_tile_record, rewrite_tile, write_tile
from standgrid.las_fields import LAS_INTEGER_DIMENSIONS
from standgrid.pointcloud import PointCloud
from standgrid.stamps import unix_ns_to_adjusted_gps_time
from tests.conftest import real_file

CRS = "EPSG:32632"


def make_cloud(n: int, seed: int = 0, *, colour: bool = False, source: int = 3) -> PointCloud:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([500_000.0, 6_000_000.0, 100.0], [500_025.0, 6_000_025.0, 130.0], (n, 3))
    fields: dict[str, np.ndarray] = {
        "intensity": rng.uniform(0.0, 1.0, n).astype(np.float32),
        "gps_time": unix_ns_to_adjusted_gps_time(
            1_700_000_000_000_000_000 + rng.integers(0, 10**10, n)
        ),
        "point_source_id": np.full(n, source, np.uint16),
        "payload_id": rng.integers(0, 2**32 - 1, n, dtype=np.uint32),
        "normal_x": rng.normal(size=n).astype(np.float32),
        "ring": rng.integers(0, 128, n).astype(np.uint16),
        "valid": rng.random(n) > 0.5,
    }
    if colour:
        for c in ("red", "green", "blue"):
            fields[c] = rng.integers(0, 65535, n).astype(np.uint16)
    return PointCloud(xyz, fields)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_header_and_points_read_back_with_laspy(tmp_path: Path, suffix: str) -> None:
    core = make_cloud(2000)
    buffer = make_cloud(300, seed=1, source=4)
    path = tmp_path / f"tile{suffix}"
    cell = box(500_000, 6_000_000, 500_025, 6_000_025)
    info = write_tile(path, core, crs=CRS, buffer=buffer, core_bounds=cell)

    las = laspy.read(path)
    h = las.header
    assert (h.version.major, h.version.minor) == (1, 4)
    assert h.point_format.id == 6
    with laspy.open(path) as reader:
        assert reader.header.are_points_compressed == (suffix == ".laz")
    assert h.point_count == 2300
    assert h.global_encoding.wkt
    assert h.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    assert h.parse_crs().to_epsg() == 32632
    assert pyproj.CRS(h.parse_crs()) == pyproj.CRS(CRS)
    np.testing.assert_allclose(h.scales, [0.001] * 3)
    np.testing.assert_array_equal(h.offsets, [500_000.0, 6_000_000.0, 100.0])
    all_xyz = np.concatenate([core.xyz, buffer.xyz])
    np.testing.assert_allclose(h.mins, all_xyz.min(axis=0), atol=5e-4)
    np.testing.assert_allclose(h.maxs, all_xyz.max(axis=0), atol=5e-4)
    assert h.number_of_points_by_return[0] == 2300

    xyz = np.column_stack([las.x, las.y, las.z])
    assert np.abs(xyz - all_xyz).max() <= 0.0005 + 1e-9
    withheld = np.asarray(las.withheld, dtype=bool)
    assert not withheld[:2000].any() and withheld[2000:].all()
    np.testing.assert_array_equal(las.point_source_id, np.r_[np.full(2000, 3), np.full(300, 4)])
    np.testing.assert_array_equal(las.gps_time[:2000], core.fields["gps_time"])
    np.testing.assert_array_equal(las.payload_id[:2000], core.fields["payload_id"])
    assert las.payload_id.dtype == np.uint32
    np.testing.assert_array_equal(las.ring[:2000], core.fields["ring"])
    # float intensity: scaled by intensity_scale (1.0) and clipped into uint16; exact copy kept
    np.testing.assert_array_equal(
        las.intensity[:2000], np.round(core.fields["intensity"]).astype(np.uint16)
    )
    np.testing.assert_array_equal(las.intensity_raw[:2000], core.fields["intensity"])

    assert info.core_count == 2000 and info.buffer_count == 300
    assert info.bounds == pytest.approx((*core.xyz.min(axis=0), *core.xyz.max(axis=0)), abs=1e-12)
    assert info.z_p95 == pytest.approx(np.percentile(core.xyz[:, 2], 95))
    assert info.z_mean == pytest.approx(core.xyz[:, 2].mean())
    assert info.core_bounds is cell
    assert info.points_per_source == {3: 2000}


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_read_tile_round_trip_drops_withheld_exactly(tmp_path: Path, suffix: str) -> None:
    core = make_cloud(1500, colour=True)
    buffer = make_cloud(200, seed=5, colour=True, source=9)
    path = tmp_path / f"tile{suffix}"
    info = write_tile(path, core, crs=CRS, buffer=buffer)
    assert info.point_format == 7

    back = read_tile(path)
    assert len(back) == 1500
    assert np.abs(back.xyz - core.xyz).max() <= 0.0005 + 1e-9
    assert set(back.fields) == set(core.fields)
    for name, values in core.fields.items():
        assert back.fields[name].dtype == values.dtype, name
        np.testing.assert_array_equal(back.fields[name], values, err_msg=name)

    everything = read_tile(path, include_withheld=True)
    assert len(everything) == 1700
    np.testing.assert_array_equal(
        everything.fields["withheld"], np.r_[np.zeros(1500), np.ones(200)]
    )
    np.testing.assert_array_equal(everything.fields["point_source_id"][1500:], 9)


def test_integer_intensity_and_classification_stored_natively(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    n = 500
    cloud = PointCloud(
        rng.uniform(0, 50, (n, 3)) + np.array([300_000, 5_000_000, 0]),
        {
            "intensity": rng.integers(0, 65535, n).astype(np.uint16),
            "classification": rng.choice([1, 2], n).astype(np.uint8),
        },
    )
    write_tile(tmp_path / "t.las", cloud, crs="EPSG:25833")
    las = laspy.read(tmp_path / "t.las")
    assert "intensity_raw" not in set(las.point_format.extra_dimension_names)
    np.testing.assert_array_equal(las.intensity, cloud.fields["intensity"])
    np.testing.assert_array_equal(las.classification, cloud.fields["classification"])
    assert not np.asarray(las.withheld).any()


def test_laz_flag_overrides_suffix_and_multi_component_fields(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 100
    normals = rng.normal(size=(n, 3))
    cloud = PointCloud(rng.uniform(0, 10, (n, 3)), {"normal": normals})
    path = tmp_path / "tile.bin"
    write_tile(path, cloud, crs="EPSG:32632", laz=True)
    with laspy.open(path) as reader:
        assert reader.header.are_points_compressed
    back = read_tile(path)
    np.testing.assert_array_equal(back.fields["normal"], normals)


def test_bad_inputs_raise_typed_errors(tmp_path: Path) -> None:
    cloud = make_cloud(10)
    with pytest.raises(CRSError):
        write_tile(tmp_path / "a.las", cloud, crs="EPSG:999999")
    too_big = cloud.with_fields(point_source_id=np.full(10, 70_000, np.uint32))
    with pytest.raises(PointCloudFormatError, match="point_source_id"):
        write_tile(tmp_path / "b.las", too_big, crs=CRS)
    wide = PointCloud(np.array([[0.0, 0.0, 0.0], [3.0e6, 0.0, 0.0]]))
    with pytest.raises(PointCloudFormatError, match="int32"):
        write_tile(tmp_path / "c.las", wide, crs=CRS)
    with pytest.raises(PointCloudFormatError, match="withheld"):
        flagged = cloud.with_fields(withheld=np.ones(10, bool))
        write_tile(tmp_path / "d.las", flagged, crs=CRS, buffer=cloud)
    with pytest.raises(PointCloudFormatError, match="buffer fields"):
        write_tile(tmp_path / "e.las", cloud, crs=CRS, buffer=PointCloud(cloud.xyz))
    long_name = cloud.with_fields(**{"x" * 33: np.zeros(10)})
    with pytest.raises(PointCloudFormatError, match="32 bytes"):
        write_tile(tmp_path / "f.las", long_name, crs=CRS)
    assert not any(tmp_path.iterdir())  # nothing half-written left behind


def test_combined_cloud_is_split_by_withheld(tmp_path: Path) -> None:
    core, buffer = make_cloud(50), make_cloud(20, seed=8)
    flags = np.r_[np.zeros(50, bool), np.ones(20, bool)]
    combined = PointCloud.concat([core, buffer]).with_fields(withheld=flags)
    info = write_tile(tmp_path / "c.laz", combined, crs=CRS)
    assert (info.core_count, info.buffer_count) == (50, 20)
    las = laspy.read(tmp_path / "c.laz")
    np.testing.assert_array_equal(np.asarray(las.withheld, dtype=bool), flags)
    assert len(read_tile(tmp_path / "c.laz")) == 50


def test_empty_tile(tmp_path: Path) -> None:
    info = write_tile(tmp_path / "e.laz", PointCloud.empty(), crs=CRS)
    assert info.core_count == 0 and np.isnan(info.z_mean)
    assert laspy.read(tmp_path / "e.laz").header.point_count == 0


def test_read_tile_unreadable_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"not a las file at all")
    with pytest.raises(PointCloudFormatError, match=r"bad\.las"):
        read_tile(bad)


@pytest.mark.realdata
def test_real_als_plot_round_trip(tmp_path: Path) -> None:
    source = real_file("als/lidR/MixedConifer.laz")
    original = read_tile(source)  # foreign LAS 1.2 file: common dimensions + extra bytes
    assert len(original) == 37_657
    crs = "EPSG:26912"
    info = write_tile(tmp_path / "mc.laz", original, crs=crs)
    las = laspy.read(tmp_path / "mc.laz")
    assert las.header.parse_crs().to_epsg() == 26912
    assert las.header.point_count == 37_657
    np.testing.assert_array_equal(las.classification, original.fields["classification"])
    back = read_tile(tmp_path / "mc.laz")
    assert np.abs(back.xyz - original.xyz).max() <= 0.0005 + 1e-9
    np.testing.assert_array_equal(back.fields["treeID"], original.fields["treeID"])
    assert info.z_max == pytest.approx(original.xyz[:, 2].max())


def test_stored_coordinates_stay_on_an_off_metre_grid_lattice(tmp_path: Path) -> None:
    """With a grid origin off the metre (0.5 mm, 25 cm), a tile stores exactly the snapped
    coordinates, so a point read back is in the cell it was assigned to."""
    from standgrid.export.las import snap_to_storage
    from standgrid.partition import StandGrid

    grid = StandGrid("EPSG:32630", 20.0, origin=(0.0005, 0.25))
    rng = np.random.default_rng(2)
    edge = 614700.0005
    x = np.concatenate([np.full(200, edge), edge + rng.uniform(-0.003, 0.003, 400)])
    y = 5737140.25 + rng.uniform(0, 19, 600)
    xyz = snap_to_storage(np.column_stack([x, y, rng.uniform(100, 110, 600)]), grid.origin)
    write_tile(tmp_path / "t.las", PointCloud(xyz), crs="EPSG:32630", lattice_origin=grid.origin)
    back = snap_to_storage(read_tile(tmp_path / "t.las").xyz, grid.origin)
    np.testing.assert_array_equal(back, xyz)
    np.testing.assert_array_equal(
        grid.cell_keys(back[:, 0], back[:, 1]), grid.cell_keys(xyz[:, 0], xyz[:, 1])
    )


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_rewrite_tile_equals_writing_the_cloud_with_the_new_fields(
    tmp_path: Path, suffix: str
) -> None:
    core, buffer = make_cloud(1500), make_cloud(200, seed=1, source=4)
    source = tmp_path / f"source{suffix}"
    write_tile(source, core, crs=CRS, buffer=buffer)
    rng = np.random.default_rng(5)
    n = 1700
    new = {
        "classification": rng.integers(1, 3, n).astype(np.uint8),
        "height_above_ground": rng.normal(10.0, 5.0, n).astype(np.float32),
        "ring": rng.integers(0, 2**20, n).astype(np.uint32),  # stored as u2 before: re-typed
    }
    rewritten = tmp_path / f"rewritten{suffix}"
    rewrite_tile(read_tile_record(source), rewritten, new, source=source)

    # the same cloud and fields written from scratch
    def with_new(cloud: PointCloud, rows: slice) -> PointCloud:
        return PointCloud(cloud.xyz, cloud.fields | {k: v[rows] for k, v in new.items()})

    expected = tmp_path / f"expected{suffix}"
    write_tile(
        expected, with_new(core, slice(0, 1500)), crs=CRS, buffer=with_new(buffer, slice(1500, n))
    )
    got, want = (
        read_tile(rewritten, include_withheld=True),
        read_tile(expected, include_withheld=True),
    )
    assert np.array_equal(got.xyz, want.xyz)
    assert list(got.fields) == list(want.fields)
    for name, values in want.fields.items():
        assert got.fields[name].dtype == values.dtype, name
        assert np.array_equal(got.fields[name], values), name
    las = laspy.read(rewritten)  # a second reader: the stored dimensions themselves
    assert np.array_equal(np.asarray(las.classification), new["classification"])
    assert np.array_equal(np.asarray(las["ring"]), new["ring"])
    assert np.array_equal(np.asarray(las["height_above_ground"]), new["height_above_ground"])
    assert las.header.parse_crs().to_epsg() == 32632
    with laspy.open(rewritten) as reader:
        assert reader.header.are_points_compressed == (suffix == ".laz")


def test_rewrite_tile_refuses_wrong_lengths_and_foreign_files(tmp_path: Path) -> None:
    source = tmp_path / "tile.laz"
    write_tile(source, make_cloud(100), crs=CRS)
    record = read_tile_record(source)
    with pytest.raises(PointCloudFormatError, match="99"):
        rewrite_tile(
            record, tmp_path / "out.laz", {"tree_id": np.zeros(99, np.uint32)}, source=source
        )
    with pytest.raises(PointCloudFormatError, match="outside the LAS range"):
        rewrite_tile(
            record,
            tmp_path / "out.laz",
            {"classification": np.full(100, 300, np.uint16)},
            source=source,
        )
    with pytest.raises(PointCloudFormatError, match="cannot be rewritten"):
        rewrite_tile(record, tmp_path / "out.laz", {"x": np.zeros(100)}, source=source)
    foreign = tmp_path / "foreign.las"
    las = laspy.create(point_format=6, file_version="1.4")
    las.x = np.arange(5.0)
    las.write(foreign)
    with pytest.raises(PointCloudFormatError, match="not a standgrid tile"):
        rewrite_tile(read_tile_record(foreign), tmp_path / "o.las", {}, source=foreign)
    assert not (tmp_path / "out.laz").exists() and not (tmp_path / "o.las").exists()


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("returns", [False, True])
def test_tile_bytes_are_what_laspy_writes_for_its_points(
    tmp_path: Path, suffix: str, returns: bool
) -> None:
    """The header write_tile fills in itself (extremes, counts by return, extra bytes'
    extremes) is the one laspy's writer computes from the points: re-writing the read tile
    with laspy gives the same bytes."""
    core, buffer = make_cloud(3000, seed=5), make_cloud(800, seed=6)
    if returns:
        rng = np.random.default_rng(7)
        core, buffer = (
            c.with_fields(
                return_number=rng.integers(1, 4, len(c)).astype(np.uint8),
                number_of_returns=np.full(len(c), 3, np.uint8),
                intensity=np.where(rng.random(len(c)) < 0.1, np.nan, rng.normal(0, 9e4, len(c))),
            )
            for c in (core, buffer)
        )
    path = tmp_path / f"t{suffix}"
    write_tile(path, core, crs=CRS, buffer=buffer)
    rewritten = tmp_path / f"laspy{suffix}"
    with open(rewritten, "wb") as stream:
        laspy.read(path).write(stream, do_compress=suffix == ".laz")
    assert path.read_bytes() == rewritten.read_bytes()
    header = laspy.read(path).header
    assert int(header.number_of_points_by_return.sum()) == 3800


# --- standard LAS fields: stored exactly, or refused with a typed error --------------------

#: Integer LAS dimensions a field is written to (withheld: set from core/buffer).
INTEGER_FIELDS = [name for name in LAS_INTEGER_DIMENSIONS if name != "withheld"]


def _with_standard_field(cloud: PointCloud, name: str, values: np.ndarray) -> PointCloud:
    """``cloud`` with ``values`` as field ``name`` (colours: all three, the others valid)."""
    if name in ("red", "green", "blue"):
        fields = {c: np.zeros(len(cloud), np.uint16) for c in ("red", "green", "blue")}
        fields[name] = values
        return cloud.with_fields(**fields)
    return cloud.with_fields(**{name: values})


def _integral_values(name: str, n: int, seed: int) -> np.ndarray:
    """Random integers over the field's whole LAS range, both ends included."""
    _, lo, hi = LAS_INTEGER_DIMENSIONS[name]
    values = np.random.default_rng(seed).integers(lo, hi + 1, n)
    values[:2] = lo, hi
    return values


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("name", INTEGER_FIELDS)
def test_integral_float_fields_are_stored_exactly(tmp_path: Path, name: str, dtype: type) -> None:
    core_ints, buffer_ints = _integral_values(name, 400, 1), _integral_values(name, 100, 2)
    core = _with_standard_field(make_cloud(400), name, core_ints.astype(dtype))
    buffer = _with_standard_field(make_cloud(100, seed=3), name, buffer_ints.astype(dtype))
    path = tmp_path / "tile.las"
    write_tile(path, core, crs=CRS, buffer=buffer)
    las = laspy.read(path)  # a second reader: the stored integers themselves
    assert name not in las.point_format.extra_dimension_names
    assert np.array_equal(np.asarray(las[name]), np.concatenate([core_ints, buffer_ints]))
    back = read_tile(path, include_withheld=True)  # given back with the dtype written
    assert back.fields[name].dtype == np.dtype(dtype)
    assert np.array_equal(back.fields[name], np.concatenate([core_ints, buffer_ints]))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_float_return_numbers_fill_the_header_counts(tmp_path: Path, suffix: str) -> None:
    """The known case: float32 return numbers (1.0, 2.0) used to fail in laspy's packing."""
    returns = np.tile(np.array([1.0, 2.0, 2.0], np.float32), 100)
    cloud = make_cloud(300).with_fields(
        return_number=returns, number_of_returns=np.full(300, 2.0, np.float32)
    )
    path = tmp_path / f"tile{suffix}"
    write_tile(path, cloud, crs=CRS)
    las = laspy.read(path)
    assert np.array_equal(np.asarray(las.return_number), returns.astype(np.uint8))
    assert np.array_equal(np.asarray(las.number_of_returns), np.full(300, 2))
    assert list(las.header.number_of_points_by_return[:3]) == [100, 200, 0]


def _bad_cases() -> list[tuple[str, str, np.ndarray, str]]:
    """(field, what, 10 values with the first bad one at index 6, its text in the message)."""
    cases = []
    for name in INTEGER_FIELDS:
        _, lo, hi = LAS_INTEGER_DIMENSIONS[name]
        good = np.full(10, lo, np.float64)
        for what, bad, text in (
            ("fraction", lo + 0.5, str(lo + 0.5)),
            ("nan", np.nan, "nan"),
            ("infinite", np.inf, "inf"),
            ("below", lo - 1.0, str(lo - 1.0)),
            ("above", hi + 1.0, str(hi + 1.0)),
        ):
            values = good.copy()
            values[6] = values[8] = bad
            cases.append((name, what, values, text))
        ints = np.full(10, lo, np.int64)
        ints[6] = hi + 1
        cases.append((name, "int above", ints, str(hi + 1)))
        ints = np.full(10, lo, np.int32)
        ints[6] = lo - 1
        cases.append((name, "int below", ints, str(lo - 1)))
    times = np.linspace(1e8, 1e8 + 9, 10)
    for what, bad, text in (("nan", np.nan, "nan"), ("infinite", -np.inf, "-inf")):
        values = times.copy()
        values[6] = bad
        cases.append(("gps_time", what, values, text))
    beyond = np.full(10, 2**53, np.uint64)
    beyond[6] = 2**53 + 1
    cases.append(("gps_time", "inexact integer", beyond, str(2**53 + 1)))
    return cases


@pytest.mark.parametrize(
    ("name", "values", "text"),
    [pytest.param(n, v, t, id=f"{n}-{w}") for n, w, v, t in _bad_cases()],
)
def test_bad_standard_field_values_are_refused_before_any_file(
    tmp_path: Path, name: str, values: np.ndarray, text: str
) -> None:
    # the bad value (index 6) lies in the buffer: points are counted core first
    cloud = _with_standard_field(make_cloud(10), name, values)
    core, buffer = cloud.select(np.arange(4)), cloud.select(np.arange(4, 10))
    path = tmp_path / "tile.laz"
    with pytest.raises(PointCloudFormatError) as info:
        write_tile(path, core, crs=CRS, buffer=buffer)
    message = str(info.value)
    assert info.value.path == path and message.startswith(f"{path}: ")
    assert f"field {name!r} value {text} (point 6)" in message
    assert list(tmp_path.iterdir()) == []  # no tile, no temporary file


@pytest.mark.parametrize("name", ["return_number", "classification", "gps_time", "red"])
@pytest.mark.parametrize(
    "values",
    [np.ones((10, 2), np.uint8), np.ones(10, np.complex64), np.array(["1"] * 10)],
    ids=["two-values-per-point", "complex", "text"],
)
def test_standard_fields_of_the_wrong_shape_or_kind_are_refused(
    tmp_path: Path, name: str, values: np.ndarray
) -> None:
    path = tmp_path / "tile.las"
    with pytest.raises(PointCloudFormatError, match=f"field {name!r}") as info:
        write_tile(path, _with_standard_field(make_cloud(10), name, values), crs=CRS)
    assert info.value.path == path
    assert list(tmp_path.iterdir()) == []


def test_intensity_of_two_values_per_point_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "tile.las"
    cloud = make_cloud(10).with_fields(intensity=np.ones((10, 2), np.uint16))
    with pytest.raises(PointCloudFormatError, match="'intensity' has shape") as info:
        write_tile(path, cloud, crs=CRS)
    assert info.value.path == path and list(tmp_path.iterdir()) == []


def test_float_withheld_flags_split_exactly_or_are_refused(tmp_path: Path) -> None:
    flags = np.array([0, 1, 0, 1, 1, 0, 0, 0], np.float32)
    path = tmp_path / "tile.las"
    write_tile(path, make_cloud(8).with_fields(withheld=flags), crs=CRS)
    assert np.array_equal(np.asarray(laspy.read(path).withheld), [0, 0, 0, 0, 0, 1, 1, 1])
    flags[2] = 0.5
    other = tmp_path / "other.las"
    with pytest.raises(PointCloudFormatError, match=r"'withheld' value 0.5 \(point 2\)"):
        write_tile(other, make_cloud(8).with_fields(withheld=flags), crs=CRS)
    assert not other.exists()


def test_copc_tile_refusal_names_the_tile_and_leaves_nothing(tmp_path: Path) -> None:
    from standgrid.export.copc import write_copc_tile

    path = tmp_path / "tile.copc.laz"
    cloud = make_cloud(50).with_fields(classification=np.full(50, 2.5, np.float32))
    with pytest.raises(PointCloudFormatError, match=r"'classification' value 2\.5") as info:
        write_copc_tile(path, cloud, crs=CRS)
    assert info.value.path == path
    assert list(tmp_path.iterdir()) == []


def test_rewrite_tile_stores_integral_floats_and_refuses_the_rest(tmp_path: Path) -> None:
    source = tmp_path / "tile.laz"
    write_tile(source, make_cloud(100), crs=CRS)
    record = read_tile_record(source)
    out = tmp_path / "out.laz"
    for fields, text in (
        ({"return_number": np.full(100, 1.5, np.float32)}, "'return_number' value 1.5 (point 0)"),
        ({"classification": np.full(100, np.nan)}, "'classification' value nan (point 0)"),
        ({"gps_time": np.full(100, np.inf)}, "'gps_time' value inf (point 0)"),
        # a valid extra field first: nothing of it is applied when a later field is refused
        ({"tree_id": np.arange(100.0), "user_data": np.full(100, -1)}, "'user_data' value -1"),
    ):
        with pytest.raises(PointCloudFormatError) as info:
            rewrite_tile(record, out, fields, source=source)
        assert info.value.path == source and text in str(info.value)
        assert not out.exists()
    assert "tree_id" not in record.point_format.extra_dimension_names
    classes = np.arange(100) % 7
    rewrite_tile(
        record,
        out,
        {"classification": classes.astype(np.float64), "return_number": np.full(100, 2.0)},
        source=source,
    )
    las = laspy.read(out)
    assert np.array_equal(np.asarray(las.classification), classes)
    assert np.array_equal(np.asarray(las.return_number), np.full(100, 2))
    assert read_tile(out).fields["classification"].dtype == np.float64


# --- through the pipeline: a payload's bad field is named with the payload file -----------


def _mission_with_fields(root: Path, fields_of: Any) -> tuple[Path, list[Path]]:
    """A copy of a bundled mission with its first 3 payloads, ``fields_of(k, n)`` added to
    payload ``k`` (of ``n`` points)."""
    import shutil

    from standgrid.clouds import read_cloud, write_cloud
    from tests.conftest import BUNDLED_MISSIONS

    mission = shutil.copytree(
        BUNDLED_MISSIONS / "2024-05-14-wytham-anymal-coyote",
        root / "2024-05-14-wytham-anymal-coyote",
    )
    payloads = sorted((mission / "payload_clouds").glob("*.pcd"))
    for extra in payloads[3:]:
        extra.unlink()
    for k, payload in enumerate(payloads[:3]):
        cloud = read_cloud(payload)
        write_cloud(cloud.with_fields(**fields_of(k, len(cloud))), payload)
    return mission, payloads[:3]


def test_tiling_payloads_with_float_return_numbers(tmp_path: Path) -> None:
    from standgrid.clouds import read_cloud
    from standgrid.pipeline.tile import tile_missions

    def returns(k: int, n: int) -> dict[str, np.ndarray]:
        return {"return_number": (np.arange(n) % 3 + 1).astype(np.float32)}

    mission, payloads = _mission_with_fields(tmp_path / "good", returns)
    assert read_cloud(payloads[0]).fields["return_number"].dtype == np.float32
    catalog = tmp_path / "good" / "catalog"
    report = tile_missions([mission], catalog)
    tiles = sorted((catalog / "tiles").rglob("*.la[sz]"))
    assert tiles and report.points_out == sum(len(read_cloud(p)) for p in payloads)
    for tile in tiles:
        las = laspy.read(tile)
        stored = np.asarray(las.return_number)
        assert set(np.unique(stored)) <= {1, 2, 3}
        assert np.array_equal(
            np.bincount(stored, minlength=16)[1:16], las.header.number_of_points_by_return
        )

    def one_fraction(k: int, n: int) -> dict[str, np.ndarray]:
        values = returns(k, n)
        if k == 1:
            values["return_number"][5] = 1.5
        return values

    mission, payloads = _mission_with_fields(tmp_path / "bad", one_fraction)
    catalog = tmp_path / "bad" / "catalog"
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions([mission], catalog)
    assert info.value.path == payloads[1]
    assert "field 'return_number' value 1.5 (point 5)" in str(info.value)
    assert not catalog.exists()


def test_tiling_refuses_a_payload_field_that_would_wrap_in_the_epochs_dtype(
    tmp_path: Path,
) -> None:
    """The epoch's field dtypes come from its first payload: a later payload's value that
    does not fit (300 in a uint8 field) is refused, not wrapped to 44."""
    from standgrid.pipeline.tile import tile_missions

    def rings(k: int, n: int) -> dict[str, np.ndarray]:
        if k == 0:
            return {"ring": np.arange(n).astype(np.uint8)}
        values = np.arange(n, dtype=np.uint16) % 200
        if k == 2:
            values[7] = 300
        return {"ring": values}

    mission, payloads = _mission_with_fields(tmp_path, rings)
    catalog = tmp_path / "catalog"
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions([mission], catalog)
    assert info.value.path == payloads[2]
    assert "field 'ring' value 300 (point 7)" in str(info.value)
    assert not catalog.exists()


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_a_payload_without_return_numbers_gets_return_one_of_one(
    tmp_path: Path, dtype: Any
) -> None:
    """A payload that lacks the return fields others of its epoch carry gets what a tile
    without them holds, return 1 of 1 (not 0, nor a NaN the writer would refuse)."""
    from standgrid.pipeline.tile import tile_missions

    def returns(k: int, n: int) -> dict[str, np.ndarray]:
        if k == 1:
            return {}
        return {"return_number": np.full(n, 2, dtype), "number_of_returns": np.full(n, 3, dtype)}

    mission, _ = _mission_with_fields(tmp_path, returns)
    catalog = tmp_path / "catalog"
    tile_missions([mission], catalog)
    seen = {}
    for tile in sorted((catalog / "tiles").rglob("*.la[sz]")):
        las = laspy.read(tile)
        for payload in np.unique(np.asarray(las.payload_id)).tolist():
            mine = np.asarray(las.payload_id) == payload
            pairs = set(
                zip(
                    np.asarray(las.return_number)[mine].tolist(),
                    np.asarray(las.number_of_returns)[mine].tolist(),
                    strict=True,
                )
            )
            seen.setdefault(payload, set()).update(pairs)
    assert len(seen) == 3
    first, second, third = (seen[k] for k in sorted(seen))
    assert first == third == {(2, 3)} and second == {(1, 1)}


@pytest.mark.parametrize(
    ("name", "dtype", "fill"),
    [("classification", np.float32, 0), ("user_data", np.float64, 0), ("scan_angle", np.int16, 0)],
)
def test_a_payload_without_a_standard_field_gets_the_blank_records_value(
    tmp_path: Path, name: str, dtype: Any, fill: int
) -> None:
    """Fields stored in standard LAS dimensions are filled as a tile without the field holds
    them, whatever their dtype (a float one used to get NaN, which the writer refuses)."""
    from standgrid.pipeline.tile import tile_missions

    def fields(k: int, n: int) -> dict[str, np.ndarray]:
        return {} if k == 1 else {name: np.full(n, 7, dtype)}

    mission, _ = _mission_with_fields(tmp_path, fields)
    catalog = tmp_path / "catalog"
    tile_missions([mission], catalog)
    seen: dict[int, set[int]] = {}
    for tile in sorted((catalog / "tiles").rglob("*.la[sz]")):
        las = laspy.read(tile)
        payloads = np.asarray(las.payload_id)
        for payload in np.unique(payloads).tolist():
            values = np.asarray(las[name])[payloads == payload].tolist()
            seen.setdefault(payload, set()).update(values)
    first, second, third = (seen[k] for k in sorted(seen))
    assert first == third == {7} and second == {fill}


@pytest.mark.parametrize(
    ("fields_of_bad", "text"),
    [
        (
            lambda n: {"return_number": np.where(np.arange(n) == 4, 20, 1).astype(np.uint8)},
            "field 'return_number' value 20 (point 4) is outside the LAS range [0, 15]",
        ),
        (
            lambda n: {"gps_time": np.where(np.arange(n) == 9, np.nan, 1e9)},
            "field 'gps_time' value nan (point 9) is not a finite time",
        ),
    ],
)
def test_a_bad_value_of_the_fields_own_dtype_names_the_payload(
    tmp_path: Path, fields_of_bad: Any, text: str
) -> None:
    """Values a field's own dtype can hold but its LAS dimension cannot (a uint8 return number
    of 20, a NaN time) are refused when the payload is read: the error names the payload and
    its own point, not a staging tile."""
    from standgrid.pipeline.tile import tile_missions

    def fields(k: int, n: int) -> dict[str, np.ndarray]:
        good = {
            key: np.ones(n, v.dtype) * (1e9 if key == "gps_time" else 1)
            for key, v in fields_of_bad(n).items()
        }
        return fields_of_bad(n) if k == 1 else good

    mission, payloads = _mission_with_fields(tmp_path, fields)
    catalog = tmp_path / "catalog"
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions([mission], catalog)
    assert info.value.path == payloads[1] and text in str(info.value)
    assert not catalog.exists()


def test_a_later_payloads_value_the_epochs_float_dtype_would_round_is_refused(
    tmp_path: Path,
) -> None:
    """The epoch's dtypes come from the mission's first payload (float32 here): a later
    float64 value float32 cannot hold is refused, naming the payload, not rounded; float64
    values float32 holds exactly pass."""
    from standgrid.clouds import read_cloud
    from standgrid.pipeline.tile import tile_missions

    def ranges(exact: bool) -> Any:
        def fields(k: int, n: int) -> dict[str, np.ndarray]:
            if k == 0:
                return {"range_m": np.full(n, 12.5, np.float32)}
            values = np.full(n, 12.25)
            if k == 2 and not exact:
                values[3] = 12.345678901234
            return {"range_m": values}

        return fields

    mission, payloads = _mission_with_fields(tmp_path / "bad", ranges(exact=False))
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions([mission], tmp_path / "bad" / "catalog")
    assert info.value.path == payloads[2]
    assert "field 'range_m' value 12.345678901234 (point 3)" in str(info.value)
    mission, payloads = _mission_with_fields(tmp_path / "good", ranges(exact=True))
    assert read_cloud(payloads[1]).fields["range_m"].dtype == np.float64
    report = tile_missions([mission], tmp_path / "good" / "catalog")
    assert report.points_out == sum(len(read_cloud(p)) for p in payloads)
