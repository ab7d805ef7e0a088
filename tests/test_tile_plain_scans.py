"""Plain scans in: a LAS/LAZ/COPC file, a folder of tiles or a VPC tiled by one command.

Points are compared with the source read by laspy (the tiles by a second reader: every
tile read back), the CRS is the file's, the date and epoch come from the header or --date.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import laspy
import numpy as np
import pytest
from click.testing import CliRunner

from standgrid.cli import cli
from standgrid.errors import CRSError, MetadataError, SensorLogFormatError
from standgrid.mission.scan import (
    ScanOptions,
    adjusted_gps_to_date,
    open_scan,
    week_start,
)
from standgrid.mission.scan_trajectory import read_trajectory, segment_times
from standgrid.pipeline.tile import tile_missions
from standgrid.stamps import unix_ns_to_adjusted_gps_time
from standgrid.tiling.options import TileOptions

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "als"


def _real(name: str) -> Path:
    path = REAL / name
    if not path.exists():
        pytest.skip(f"{path} absent")
    return path


def _tiles_xyz(catalog: Path) -> np.ndarray:
    """Every core point of every tile (buffer copies are flagged withheld), read by laspy."""
    parts = []
    for tile in sorted((catalog / "tiles").rglob("*.la[sz]")):
        las = laspy.read(tile)
        keep = ~np.asarray(las.withheld, dtype=bool)
        parts.append(np.column_stack([las.x, las.y, las.z])[keep])
    return np.concatenate(parts)


def _source_xyz(files: list[Path]) -> np.ndarray:
    return np.concatenate(
        [np.column_stack([las.x, las.y, las.z]) for las in (laspy.read(f) for f in files)]
    )


def _same_points(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape
    order_a = np.lexsort(np.round(a, 3).T[::-1])
    order_b = np.lexsort(np.round(b, 3).T[::-1])
    assert np.max(np.abs(a[order_a] - b[order_b])) <= 0.0005 + 1e-9


def test_one_file_is_tiled_directly_by_the_cli(tmp_path: Path) -> None:
    scan = _real("las_chablais3.laz")
    result = CliRunner().invoke(
        cli,
        ["tile", str(scan), "-o", str(tmp_path / "cat"), "--date", "2019-07-01", "--json", "-q"],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["crs"] == "EPSG:2154"
    assert report["conserved"] and report["points_in"] == 92_097
    assert list(report["missions"]) == ["las_chablais3"]
    assert list(report["epochs"]) == ["2019"]
    assert report["epochs"]["2019"]["date"] == "2019-07-01"
    _same_points(_tiles_xyz(tmp_path / "cat"), _source_xyz([scan]))
    tile = next((tmp_path / "cat" / "tiles").rglob("*.laz"))
    assert laspy.read(tile).header.parse_crs().to_epsg() == 2154
    # the scan's GPS week seconds are stored as the adjusted standard time the tiles flag
    assert "week seconds" in report["missions"]["las_chablais3"]["warnings"][0]
    times = np.concatenate(
        [laspy.read(t).gps_time for t in (tmp_path / "cat" / "tiles").rglob("*.laz")]
    )
    source = np.asarray(laspy.read(scan).gps_time)
    offset = week_start(dt.date(2019, 7, 1), float(source.min()))
    assert np.allclose(np.sort(times) - np.sort(source), offset, atol=1e-6)
    # 29,216 s into a GPS week is Sunday 08:06: the Sunday nearest to Monday 1 July
    assert adjusted_gps_to_date(float(times.min())) == dt.date(2019, 6, 30)
    assert adjusted_gps_to_date(week_start(dt.date(2019, 7, 6), 29_216.0) + 29_216.0) == (
        dt.date(2019, 7, 7)
    )


def test_a_scan_without_a_date_says_how_to_give_one(tmp_path: Path) -> None:
    scan = _real("las_chablais3.laz")
    result = CliRunner().invoke(cli, ["tile", str(scan), "-o", str(tmp_path / "cat")])
    assert result.exit_code != 0
    assert "--date" in result.output and "las_chablais3.laz" in result.output
    assert "Traceback" not in result.output


@pytest.mark.slow
def test_a_folder_of_tiles_is_one_mission_its_edge_points_once(tmp_path: Path) -> None:
    """The four edge-matched bcts tiles, read in parts of 400,000 points (seeks in LAZ)."""
    folder = _real("lasR_bcts")
    files = sorted(folder.glob("*.laz"))
    scan = open_scan(folder, ScanOptions(date=dt.date(2018, 5, 1), part_points=400_000))
    assert scan.name == "lasR_bcts"
    assert len(scan.payloads) == sum(-(-laspy.open(f).header.point_count // 400_000) for f in files)
    report = tile_missions([scan], tmp_path / "cat", TileOptions(cell_size=50.0))
    assert report.crs == "EPSG:3005"
    assert report.points_in == report.points_out == 2_834_350
    _same_points(_tiles_xyz(tmp_path / "cat"), _source_xyz(files))


def test_a_vpc_names_the_tiles(tmp_path: Path) -> None:
    folder = _real("lasR_bcts")
    files = sorted(folder.glob("*.laz"))[:2]
    overview = tmp_path / "overview.copc.laz"  # thinned copies: never read
    features = [
        {
            "type": "Feature",
            "properties": {},
            "assets": {
                "data": {"href": str(f), "roles": ["data"]},
                "overview": {"href": str(overview), "roles": ["overview"]},
            },
        }
        for f in files
    ]
    vpc = tmp_path / "two.vpc"
    vpc.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    report = tile_missions(
        [vpc], tmp_path / "cat", TileOptions(cell_size=50.0, scan_date=dt.date(2018, 5, 1))
    )
    assert list(report.missions) == ["two"]
    assert report.points_out == sum(laspy.open(f).header.point_count for f in files)


def test_a_file_without_a_crs_needs_crs(tmp_path: Path) -> None:
    scan = _real("TreeLS/pine_plot.laz")
    with pytest.raises(CRSError, match="option crs"):
        open_scan(scan, ScanOptions(date=dt.date(2020, 1, 1)))
    report = tile_missions(
        [scan],
        tmp_path / "cat",
        TileOptions(crs="EPSG:32633", scan_date=dt.date(2020, 1, 1), cell_size=5.0),
    )
    assert report.crs == "EPSG:32633" and report.points_in == report.points_out


def _walk_scan(tmp_path: Path, standard: bool = True) -> tuple[Path, Path, np.ndarray]:
    """A scanner walking an L-shaped 120 m path for 240 s, 200 points a second within 8 m
    of it, GPS times adjusted standard (2023-06-14); its trajectory file at 10 Hz."""
    rng = np.random.default_rng(7)
    noon = dt.datetime(2023, 6, 14, 12, tzinfo=dt.UTC).timestamp()
    t0 = float(unix_ns_to_adjusted_gps_time(int(noon) * 10**9))  # adjusted standard GPS
    times = np.arange(0.0, 240.0, 0.1)
    path = np.where(
        times[:, None] < 120,
        [[0.0, 0.0]] + times[:, None] * [[0.5, 0.0]],
        [[60.0, 0.0]] + (times[:, None] - 120) * [[0.0, 0.5]],
    )
    xyz0 = np.array([500_000.0, 5_200_000.0, 300.0])
    traj = np.column_stack([t0 + times, path + xyz0[:2], np.full(len(times), xyz0[2])])
    pt = np.sort(rng.uniform(0, 240, 48_000))
    centre = np.column_stack([np.interp(pt, times, path[:, 0]), np.interp(pt, times, path[:, 1])])
    offset = rng.uniform(-8, 8, (len(pt), 2))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.001] * 3
    header.offsets = xyz0
    header.add_crs(__import__("pyproj").CRS.from_epsg(32632))
    if standard:
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    las = laspy.LasData(header)
    las.x = xyz0[0] + centre[:, 0] + offset[:, 0]
    las.y = xyz0[1] + centre[:, 1] + offset[:, 1]
    las.z = xyz0[2] + rng.uniform(0, 20, len(pt))
    las.gps_time = t0 + pt
    scan = tmp_path / "walk.laz"
    las.write(scan)
    trajectory = tmp_path / "walk_traj.txt"
    lines = ["Time X Y Z"] + [f"{t:.3f} {x:.3f} {y:.3f} {z:.3f}" for t, x, y, z in traj]
    trajectory.write_text("\n".join(lines) + "\n")
    return scan, trajectory, traj


def test_a_scan_with_its_trajectory_tiles_into_voronoi_cells(tmp_path: Path) -> None:
    scan, trajectory, traj = _walk_scan(tmp_path)
    mission = open_scan(scan, ScanOptions(trajectory=trajectory))
    assert mission.metadata.date == dt.date(2023, 6, 14)  # from the adjusted GPS time
    assert len(mission.payloads) == 6  # 120 m of travel in 20 m segments
    report = tile_missions(
        [scan], tmp_path / "cat", TileOptions(scheme="voronoi", trajectory=trajectory)
    )
    assert report.points_in == report.points_out == 48_000
    import geopandas as gpd

    payloads = gpd.read_file(tmp_path / "cat" / "index.gpkg", layer="payloads")
    cells = gpd.read_file(tmp_path / "cat" / "index.gpkg", layer="cells")
    assert len(payloads) == 6 and len(cells) == 6
    line = gpd.read_file(tmp_path / "cat" / "index.gpkg", layer="trajectories").geometry[0]
    assert np.allclose(np.asarray(line.coords), traj[:, 1:3], atol=1e-6)
    # every payload's site is on the trajectory and its footprint around that site
    d = np.min(
        np.hypot(
            payloads.x.values[:, None] - traj[None, :, 1],
            payloads.y.values[:, None] - traj[None, :, 2],
        ),
        axis=1,
    )
    assert np.all(d < 0.06)
    assert payloads.point_count.sum() == 48_000
    assert all(
        g.contains(p) for g, p in zip(payloads.geometry, payloads.geometry.centroid, strict=False)
    )


def test_trajectory_errors_name_the_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "t.csv"
    bad.write_text("time,x,y,z\n1,0,0,0\n2,1,0,nope\n")
    with pytest.raises(SensorLogFormatError, match=r"t\.csv:3: "):
        read_trajectory(bad)
    noted = tmp_path / "noted.txt"  # an exporter's comment before the header, a bare "#"
    noted.write_text("# exported by a scanner\n#\n%time x y z\n1 0 0 0\n2 1 0 0\n")
    assert read_trajectory(noted)[1].tolist() == [[0, 0, 0], [1, 0, 0]]
    bad.write_text("time,x,y,z\n2,0,0,0\n1,1,0,0\n")
    with pytest.raises(SensorLogFormatError, match="does not increase"):
        read_trajectory(bad)
    scan, _trajectory, _ = _walk_scan(tmp_path, standard=False)
    far = tmp_path / "far.txt"
    far.write_text("0 0 0 0\n10 20 0 0\n")
    with pytest.raises(SensorLogFormatError, match="do not meet"):
        open_scan(scan, ScanOptions(trajectory=far, date=dt.date(2023, 6, 14)))
    # adjusted standard times under a header flag saying week seconds: read as what they are
    flagged = open_scan(scan)
    assert flagged.metadata.sources["date"] == "GPS time"
    assert flagged.metadata.date == dt.date(2023, 6, 14)
    assert "values are standard time" in flagged.warnings[0]


def test_segments_cut_the_travel_evenly() -> None:
    times = np.arange(11.0)
    xyz = np.column_stack([np.arange(11.0) * 10, np.zeros(11), np.zeros(11)])
    cuts, sites = segment_times(times, xyz, 20.0)
    assert np.allclose(cuts, [0, 2, 4, 6, 8, 10])
    assert np.allclose(sites[:, 0], [10, 30, 50, 70, 90])


def _scan_of_mission(root: Path, name: str) -> Path:
    """A commercial scanner's export of a simulated mission: its points at their true CRS
    coordinates, one LAZ with the CRS (as a georeferenced handheld scan is delivered)."""

    from standgrid.mission.opening import open_mission
    from standgrid.simulate import load_truth

    chain = load_truth(root / "truth" / name).chain()
    mission = open_mission(root / "missions" / name)
    xyz = chain.map_to_crs(np.concatenate([c.xyz for _, c in mission.iter_payload_clouds("map")]))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.001] * 3
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(chain.crs.pyproj_crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    scan = root / "handheld_scan.laz"
    las.write(scan)
    return scan


def _placement_error(root: Path, catalog: Path, name: str) -> np.ndarray:
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.project import MapProjector
    from standgrid.mission.opening import open_mission
    from standgrid.simulate import load_truth

    state = json.loads((catalog / "catalog.json").read_text())
    geo = state["missions"][name]["georeference"]
    fit = GeoreferenceFit.without_fixes(
        tuple(geo["lla_ref"]), np.array(geo["T_enu_map"]), geo["method"]
    )
    nodes = open_mission(root / "missions" / name).trajectory()[1]
    truth = load_truth(root / "truth" / name).chain().map_to_crs(nodes)
    return np.hypot(*(MapProjector(fit, state["crs"]).exact(nodes) - truth)[:, :2].T)


@pytest.mark.slow
def test_a_robot_mission_aligns_to_a_georeferenced_scan(tmp_path: Path) -> None:
    """A handheld scan delivered georeferenced (true coordinates) and a robot's mission of the
    same stand with canopy GNSS (biased, walking, stating 0.5 m): the robot registers onto
    the scan, given together or with the scan already in the catalog."""
    from tests.align_scenarios import simulate

    simulate(tmp_path, 3, epochs=(1, 3))
    ref, robot = sorted(p.name for p in (tmp_path / "missions").iterdir())
    scan = _scan_of_mission(tmp_path, ref)
    day = dt.date(2024, 5, 14)
    alone = tmp_path / "alone"
    tile_missions(
        [scan, tmp_path / "missions" / robot], alone, TileOptions(align=False, scan_date=day)
    )
    gnss_error = _placement_error(tmp_path, alone, robot)
    together = tmp_path / "together"
    report = tile_missions(
        [scan, tmp_path / "missions" / robot], together, TileOptions(scan_date=day)
    )
    assert report.alignment is not None
    assert any(r["accepted"] for r in report.alignment["registrations"])
    aligned = _placement_error(tmp_path, together, robot)
    sigma = report.alignment["missions"][robot]["sigma_h_m"]
    # the catalog holds the scan first; the robot's mission comes later
    later = tmp_path / "later"
    tile_missions([scan], later, TileOptions(scan_date=day))
    tile_missions([tmp_path / "missions" / robot], later, TileOptions())
    added = _placement_error(tmp_path, later, robot)
    print(
        f"robot's horizontal error: GNSS alone median {np.median(gnss_error):.3f} m "
        f"(max {gnss_error.max():.3f}); aligned to the scan median {np.median(aligned):.3f} "
        f"m (max {aligned.max():.3f}), stated 1-sigma {sigma:.3f} m; added later median "
        f"{np.median(added):.3f} m"
    )
    assert np.median(gnss_error) > 0.5  # the canopy GNSS alone is off
    assert aligned.max() < 0.1 and added.max() < 0.1
    assert sigma is not None and aligned.max() < 3 * sigma + 0.02


def test_dense_segments_are_read_in_parts_every_point_once(tmp_path: Path) -> None:
    scan, trajectory, _ = _walk_scan(tmp_path)
    mission = open_scan(scan, ScanOptions(trajectory=trajectory, part_points=5_000))
    assert len(mission.payloads) > 6
    report = tile_missions([mission], tmp_path / "cat", TileOptions(scheme="voronoi"))
    assert report.points_in == report.points_out == 48_000
    import geopandas as gpd

    assert len(gpd.read_file(tmp_path / "cat" / "index.gpkg", layer="cells")) == 6
    _same_points(_tiles_xyz(tmp_path / "cat"), _source_xyz([scan]))


@pytest.mark.slow
def test_a_folder_of_copc_tiles_is_one_scan(tmp_path: Path) -> None:
    """COPC tiles (a catalog's own, cut on a 20 m grid) tiled again as one plain scan on
    another grid: every point once, edge points included, CRS kept."""
    scan = _real("las_chablais3.laz")
    day = dt.date(2019, 7, 1)
    tile_missions([scan], tmp_path / "a", TileOptions(copc=True, scan_date=day))
    folder = tmp_path / "a" / "tiles" / "2019"
    assert all(p.name.endswith(".copc.laz") for p in folder.iterdir())
    report = tile_missions([folder], tmp_path / "b", TileOptions(cell_size=15.0, scan_date=day))
    assert report.crs == "EPSG:2154" and report.points_out == 92_097
    _same_points(_tiles_xyz(tmp_path / "b"), _source_xyz([scan]))
    # the flight lines of the first source survive both tilings
    lines = np.concatenate(
        [laspy.read(t).source_point_source_id for t in (tmp_path / "b" / "tiles").rglob("*.laz")]
    )
    source = np.asarray(laspy.read(scan).point_source_id)
    assert np.array_equal(np.bincount(lines), np.bincount(source))


def test_info_describes_a_scan_and_what_tiling_it_needs() -> None:
    scan = _real("las_chablais3.laz")
    result = CliRunner().invoke(cli, ["info", str(scan), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    assert info["points"] == 92_097 and info["crs"] == "EPSG:2154"
    assert info["date"] is None and "--date" in info["needs"][0]
    assert info["gps_time"] == "week seconds"


def test_week_seconds_need_the_date_and_cross_the_rollover(tmp_path: Path) -> None:
    """GPS week seconds from Saturday 23:55 to Sunday 00:05 GPS (the rollover, 604,800 ->
    0): a date is required, and every time becomes adjusted standard time, in order."""
    import pyproj

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.001] * 3
    header.offsets = [500_000.0, 5_200_000.0, 0.0]
    header.add_crs(pyproj.CRS.from_epsg(32632))
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.WEEK_TIME
    true = np.linspace(604_500.0, 605_100.0, 3000)  # seconds since the week's start
    las = laspy.LasData(header)
    las.x = 500_000.0 + np.linspace(0, 50, 3000)
    las.y = np.full(3000, 5_200_010.0)
    las.z = np.zeros(3000)
    las.gps_time = np.mod(true, 604_800.0)
    scan = tmp_path / "rollover.laz"
    las.write(scan)
    with pytest.raises(MetadataError, match="week seconds: give its date"):
        open_scan(scan)
    day = dt.date(2023, 6, 17)  # the Saturday
    report = tile_missions([scan], tmp_path / "cat", TileOptions(scan_date=day))
    assert report.points_out == 3000
    tiles = sorted((tmp_path / "cat" / "tiles").rglob("*.laz"))
    got = np.concatenate([laspy.read(t).gps_time for t in tiles])
    start = week_start(day, float(true[0]))
    assert np.allclose(np.sort(got), true + start, atol=1e-6)
    assert adjusted_gps_to_date(float(got.min())) == day
