"""Standard fields of LAS/LAZ payloads on their way to the tiles: points the source flags
withheld (deleted) are left out and counted, a point-format 0-5 ``scan_angle_rank`` becomes
the LAS 1.4 ``scan_angle``, a PF 6+ ``scan_angle`` passes unchanged, and the source's
``point_source_id`` (flight line) is kept as ``source_point_source_id``. Payloads written
with laspy, tiled with ``tile_missions``, tiles read back with laspy."""

from __future__ import annotations

import os
from pathlib import Path

import laspy
import numpy as np
import pyogrio
import pyproj
import pytest

from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
from tests.conftest import real_file

CRS = "EPSG:32630"
#: Degrees per unit of the LAS 1.4 scan_angle (the specification's, not the code's).
SCAN_ANGLE_UNIT_DEG = 0.006
STAMP = 1717236000


def _mission(root: Path, clouds: list[laspy.LasData | Path], suffix: str = ".las") -> Path:
    """A mission folder whose payloads are the given LAS data (written) or files (linked)."""
    folder = root / "2024-06-01-site-robot"
    (folder / "payload_clouds").mkdir(parents=True)
    (folder / "metadata.yaml").write_text(
        "name: 2024-06-01-site-robot\ndate: 2024-06-01\ntime: 10:00:00\n"
    )
    for k, cloud in enumerate(clouds):
        path = folder / "payload_clouds" / f"cloud_{STAMP + k}_000000000{suffix}"
        if isinstance(cloud, Path):
            os.symlink(cloud, path)
        else:
            cloud.write(path)
    return folder


def _las(point_format: int, version: str, n: int, seed: int, first_time: float) -> laspy.LasData:
    """``n`` points over 30 m x 30 m (several 20 m cells) with unique GPS times."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.add_crs(pyproj.CRS(CRS))
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500000.0, 5000000.0, 0.0])
    las = laspy.LasData(header)
    las.x = rng.uniform(500000, 500030, n)
    las.y = rng.uniform(5000000, 5000030, n)
    las.z = rng.uniform(100, 120, n)
    las.gps_time = first_time + np.arange(n, dtype=np.float64)
    return las


def _tiles(catalog: Path) -> dict[str, np.ndarray]:
    """Every field of every tile point (laspy), concatenated; ``extra``: extra dim names."""
    parts: dict[str, list[np.ndarray]] = {}
    extra: set[str] = set()
    for path in sorted(catalog.glob("tiles/*/*.la[sz]")):
        las = laspy.read(path)
        extra |= set(las.point_format.extra_dimension_names)
        for name in las.point_format.dimension_names:
            parts.setdefault(name, []).append(np.asarray(las[name]))
    out = {name: np.concatenate(values) for name, values in parts.items()}
    out["extra"] = np.array(sorted(extra))
    return out


def _by_time(times: np.ndarray, values: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """``values`` of the points with GPS times ``wanted`` (each present exactly once)."""
    order = np.argsort(times)
    where = np.searchsorted(times[order], wanted)
    assert np.array_equal(times[order][where], wanted)
    return values[order][where]


@pytest.mark.parametrize("buffer", [0.0, 2.0])
def test_point_format_1_source_withheld_scan_angle_rank_and_flight_lines(
    tmp_path: Path, buffer: float
) -> None:
    n, withheld = 3000, 100
    rng = np.random.default_rng(1)
    first = _las(1, "1.2", n, seed=2, first_time=1e5)
    first.scan_angle_rank = rng.integers(-20, 21, n).astype(np.int8)
    flags = np.zeros(n, np.uint8)
    flags[rng.choice(n, withheld, replace=False)] = 1
    first.withheld = flags
    synthetic = np.zeros(n, np.uint8)
    synthetic[np.flatnonzero(flags == 0)[:50]] = 1  # 50 kept synthetic points
    synthetic[np.flatnonzero(flags)[:30]] = 1  # and 30 deleted ones
    first.synthetic = synthetic
    first.point_source_id = (24025 + rng.integers(0, 4, n)).astype(np.uint16)
    second = _las(1, "1.2", 500, seed=3, first_time=2e5)  # no withheld, rank 0, one line
    second.point_source_id = np.full(500, 7, np.uint16)
    mission = _mission(tmp_path, [first, second])

    report = tile_missions(
        [mission], tmp_path / "cat", TileOptions(laz=False, buffer=buffer)
    ).to_dict()

    tiled = n + 500 - withheld
    assert report["withheld_left_out"] == withheld
    assert report["points_in"] == report["points_out"] == tiled and report["conserved"]
    (epoch,) = report["epochs"].values()
    assert epoch["withheld_left_out"] == withheld and epoch["points_new"] == tiled
    (summary,) = report["missions"].values()
    assert summary["withheld_left_out"] == withheld and summary["points"] == tiled
    payloads = pyogrio.read_dataframe(tmp_path / "cat" / "index.gpkg", layer="payloads")
    payloads = payloads.sort_values("stamp_sec")
    assert payloads["withheld_left_out"].tolist() == [withheld, 0]
    assert payloads["point_count"].tolist() == [n - withheld, 500]
    cells = pyogrio.read_dataframe(tmp_path / "cat" / "index.gpkg", layer="cells")
    assert int(cells["point_count"].sum()) == tiled

    got = _tiles(tmp_path / "cat")
    core = got["withheld"] == 0  # the tiles' withheld flag: buffer copies only
    assert int(core.sum()) == tiled
    if buffer:
        assert (~core).any()
    times = got["gps_time"][core]
    source_times = np.concatenate([np.asarray(first.gps_time), np.asarray(second.gps_time)])
    kept = np.concatenate([flags == 0, np.ones(500, bool)])
    assert np.array_equal(np.sort(times), source_times[kept])
    # no copy of a deleted point anywhere, buffers included
    assert not np.isin(got["gps_time"], np.asarray(first.gps_time)[flags == 1]).any()
    assert int(got["synthetic"][core].sum()) == 50

    # scan_angle_rank -> scan_angle (0.006 degree units), no scan_angle_rank extra dimension
    assert "scan_angle_rank" not in got["extra"]
    rank = np.concatenate([np.asarray(first.scan_angle_rank), np.zeros(500, np.int8)])[kept]
    angle = _by_time(times, got["scan_angle"][core], source_times[kept])
    assert angle.dtype == np.int16
    assert np.abs(angle * SCAN_ANGLE_UNIT_DEG - rank).max() <= 0.003 + 1e-12
    assert np.all(angle[rank == 15] == 2500) and np.all(angle[rank == -15] == -2500)
    assert np.ptp(angle) > 6000  # -20..20 degrees, not nadir everywhere

    # the flight lines kept beside the mission number
    lines = np.concatenate([np.asarray(first.point_source_id), np.full(500, 7)])[kept]
    assert "source_point_source_id" in got["extra"]
    stored = _by_time(times, got["source_point_source_id"][core], source_times[kept])
    assert stored.dtype == np.uint16 and np.array_equal(stored, lines)
    assert set(np.unique(got["point_source_id"]).tolist()) == {summary["number"]}


def test_point_format_6_scan_angle_passes_unchanged_and_zero_lines_are_kept(
    tmp_path: Path,
) -> None:
    n = 2000
    las = _las(6, "1.4", n, seed=4, first_time=3e5)
    angles = np.random.default_rng(5).integers(-30000, 30001, n).astype(np.int16)
    las.scan_angle = angles  # laspy: the raw int16, 0.006 degree units
    mission = _mission(tmp_path, [las], suffix=".laz")

    report = tile_missions([mission], tmp_path / "cat", TileOptions(laz=True)).to_dict()

    assert report["withheld_left_out"] == 0 and report["points_in"] == n
    got = _tiles(tmp_path / "cat")
    stored = _by_time(got["gps_time"], got["scan_angle"], np.asarray(las.gps_time))
    assert np.array_equal(stored, angles)
    # the source's point_source_id (0 everywhere here) is kept as it is
    assert np.array_equal(got["source_point_source_id"], np.zeros(n, np.uint16))


def test_flight_lines_after_a_first_payload_without_any_are_kept(tmp_path: Path) -> None:
    """Every LAS payload carries its point_source_id: a first payload of 0s does not decide
    for the others (their flight lines used to be refused)."""
    first = _las(1, "1.2", 300, seed=6, first_time=1e5)
    second = _las(1, "1.2", 300, seed=7, first_time=2e5)
    second.point_source_id = np.full(300, 12, np.uint16)
    mission = _mission(tmp_path, [first, second])
    tile_missions([mission], tmp_path / "cat", TileOptions(laz=False))
    got = _tiles(tmp_path / "cat")
    times = np.concatenate([np.asarray(first.gps_time), np.asarray(second.gps_time)])
    lines = np.r_[np.zeros(300, np.uint16), np.full(300, 12, np.uint16)]
    assert np.array_equal(_by_time(got["gps_time"], got["source_point_source_id"], times), lines)


@pytest.mark.parametrize("relative", ["lidR/MixedConifer.laz", "las_chablais3.laz"])
def test_real_als_scan_angles_and_flight_lines_reach_the_tiles(
    tmp_path: Path, relative: str
) -> None:
    source_path = real_file(f"als/{relative}")
    source = laspy.read(source_path)
    mission = _mission(tmp_path, [source_path], suffix=".laz")

    report = tile_missions([mission], tmp_path / "cat", TileOptions(laz=True)).to_dict()

    n = len(source.points)
    assert report["points_in"] == report["points_out"] == n
    got = _tiles(tmp_path / "cat")
    rank = np.asarray(source.scan_angle_rank)
    lines = np.asarray(source.point_source_id)
    # the same points, matched by (GPS time, angle, flight line) as multisets
    want = np.rec.fromarrays(
        [np.asarray(source.gps_time), np.rint(rank / SCAN_ANGLE_UNIT_DEG).astype(np.int16)],
        names="t,a",
    )
    have = np.rec.fromarrays([got["gps_time"], got["scan_angle"]], names="t,a")
    assert np.array_equal(np.sort(want, order=["t", "a"]), np.sort(have, order=["t", "a"]))
    assert np.abs(got["scan_angle"] * SCAN_ANGLE_UNIT_DEG).max() == pytest.approx(
        np.abs(rank).max(), abs=0.003
    )
    assert np.array_equal(np.sort(got["source_point_source_id"]), np.sort(lines))
    print(f"\n{relative}: flight lines {lines.min()}..{lines.max()} kept")
    print(
        f"\n{relative}: scan_angle_rank {rank.min()}..{rank.max()} -> scan_angle "
        f"{got['scan_angle'].min()}..{got['scan_angle'].max()} (0.006 degree units)"
    )


def test_tiles_written_with_the_rank_as_extra_bytes_get_scan_angle_when_retiled(
    tmp_path: Path,
) -> None:
    """Tiles of a catalog written before the rank became ``scan_angle`` (the rank as an
    extra dimension, ``scan_angle`` absent) re-tiled with a new mission: their points get
    the ``scan_angle`` too, and no tile keeps a ``scan_angle_rank`` dimension."""
    from standgrid.export.las import read_tile, write_tile
    from standgrid.pointcloud import PointCloud

    old = _las(1, "1.2", 1500, seed=8, first_time=1e5)
    old.scan_angle_rank = np.random.default_rng(9).integers(-25, 26, 1500).astype(np.int8)
    catalog = tmp_path / "cat"
    report = tile_missions([_mission(tmp_path / "a", [old])], catalog, TileOptions(laz=False))
    for path in catalog.glob("tiles/*/*.las"):  # as the tiler wrote them before
        tile = read_tile(path)
        fields = dict(tile.fields)
        units = fields.pop("scan_angle")
        fields["scan_angle_rank"] = np.rint(units * SCAN_ANGLE_UNIT_DEG).astype(np.int8)
        write_tile(path, PointCloud(tile.xyz, fields), crs=report.crs, laz=False)
    assert "scan_angle_rank" in _tiles(catalog)["extra"]

    new = _las(1, "1.2", 700, seed=10, first_time=5e5)
    new.scan_angle_rank = np.full(700, -7, np.int8)
    root = tmp_path / "b"
    folder = _mission(root, [new]).rename(root / "2024-06-02-site-robot")
    (folder / "metadata.yaml").write_text(
        "name: 2024-06-02-site-robot\ndate: 2024-06-02\ntime: 10:00:00\n"
    )
    again = tile_missions([folder], catalog, TileOptions())

    assert again.points_in == again.points_out == 2200
    got = _tiles(catalog)
    assert "scan_angle_rank" not in got["extra"]
    times = np.concatenate([np.asarray(old.gps_time), np.asarray(new.gps_time)])
    rank = np.concatenate([np.asarray(old.scan_angle_rank), np.asarray(new.scan_angle_rank)])
    angle = _by_time(got["gps_time"], got["scan_angle"], times)
    assert np.array_equal(angle, np.rint(rank / SCAN_ANGLE_UNIT_DEG).astype(np.int16))
