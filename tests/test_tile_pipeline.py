"""Acceptance tests of ``tile_missions``: conservation, stable cells, buffers, headers, index,
catalog behaviour, Voronoi cells and bad input.

Every output is read back with a second reader: laspy for tiles, pyogrio and sqlite3 for the
GeoPackage, json for catalog.json and the VPCs, pypcd4 for the missions' payloads.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyogrio
import pypcd4
import pyproj
import pytest
import shapely
from scipy.spatial import cKDTree

from standgrid.clouds import write_cloud
from standgrid.engine import CallbackProgress, Execution
from standgrid.errors import (
    CRSError,
    GeoreferenceError,
    GridMismatchError,
    MissionFolderConflictError,
    OutputExistsError,
    OutputNotWritableError,
    PointCloudFormatError,
)
from standgrid.geometry import invert_pose, transform_points
from standgrid.georeference import MapProjector
from standgrid.georeference.fit import fit_from_pose_graph
from standgrid.mission.posegraph import write_pose_graph
from standgrid.partition import CellId, StandGrid
from standgrid.pipeline.tile import tile_missions
from standgrid.stamps import Stamp, stamp_from_filename, unix_ns_to_adjusted_gps_time
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS
from tests.mission_factory import make_mission

M1 = BUNDLED_MISSIONS / "2024-05-14-wytham-anymal-coyote"
M2 = BUNDLED_MISSIONS / "2028-05-20-wytham-frontier-v15"
SCALE = 0.001


# --- helpers -----------------------------------------------------------------------------


def payload_counts(mission: Path) -> dict[Stamp, int]:
    """Points per payload stamp, read with pypcd4 (not standgrid's reader)."""
    counts = {}
    for path in sorted((mission / "payload_clouds").glob("*.pcd")):
        parsed = stamp_from_filename(path.name)
        assert parsed is not None
        counts[parsed[1]] = pypcd4.PointCloud.from_path(path).points
    return counts


def tile_files(catalog: Path, epoch: str | None = None) -> list[Path]:
    pattern = f"tiles/{epoch}/*.la[sz]" if epoch else "tiles/*/*.la[sz]"
    return sorted(catalog.glob(pattern))


def core(las: Any) -> np.ndarray:
    return ~np.asarray(las.withheld, dtype=bool)


def records(las: Any, mask: np.ndarray | None = None) -> np.ndarray:
    """(x, y, z, gps_time, point_source_id, payload_id) rows (xyz at 1 mm), sorted."""
    cols = [
        np.asarray(las.x),
        np.asarray(las.y),
        np.asarray(las.z),
        np.asarray(las.gps_time),
        np.asarray(las.point_source_id, dtype=np.float64),
        np.asarray(las.payload_id, dtype=np.float64),
    ]
    rows = np.column_stack(cols)
    if mask is not None:
        rows = rows[mask]
    rows[:, :3] = np.round(rows[:, :3] / SCALE) * SCALE
    return rows[np.lexsort(rows.T[::-1])]


def snapshot(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``folder``."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def catalog_json(catalog: Path) -> dict[str, Any]:
    return json.loads((catalog / "catalog.json").read_text())


def grid_of(catalog: Path) -> StandGrid:
    return StandGrid.from_dict(catalog_json(catalog)["grid"])


def tile(missions: list[Path], catalog: Path, **options: Any) -> Any:
    return tile_missions(missions, catalog, TileOptions(**options))


# --- catalogs shared by the tests (each built once) ---------------------------------------


@pytest.fixture(scope="module")
def pair_catalog(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    """The bundled pair, 20 m grid, LAS, no buffer: one catalog, two epochs."""
    root = tmp_path_factory.mktemp("pair") / "catalog"
    report = tile([M1, M2], root, cell_size=20.0, laz=False)
    return root, report


@pytest.fixture(scope="module")
def buffer_catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("buffer") / "catalog"
    tile([M1, M2], root, cell_size=20.0, laz=False, buffer=2.0)
    return root


# --- conservation and stable cells ---------------------------------------------------------


def test_points_in_equal_points_out(pair_catalog: tuple[Path, Any]) -> None:
    root, report = pair_catalog
    expected = sum(payload_counts(M1).values()) + sum(payload_counts(M2).values())
    written = sum(int(core(laspy.read(p)).sum()) for p in tile_files(root))
    assert written == expected
    assert report.points_in == report.points_out == expected
    assert report.to_dict()["conserved"] is True
    missions = catalog_json(root)["missions"]
    assert missions[M1.name]["point_count"] == sum(payload_counts(M1).values())
    assert missions[M2.name]["point_count"] == sum(payload_counts(M2).values())


def test_every_point_is_in_exactly_one_tile(pair_catalog: tuple[Path, Any]) -> None:
    root, _ = pair_catalog
    for epoch in ("2024", "2028"):
        rows = np.concatenate([records(laspy.read(p)) for p in tile_files(root, epoch)])
        unique = np.unique(rows[:, :4], axis=0)
        assert len(unique) == len(rows), f"{len(rows) - len(unique)} duplicated points"


def test_stored_coordinates_lie_in_their_tile_cell(pair_catalog: tuple[Path, Any]) -> None:
    """Read back at 1 mm, every core point lies in the half-open cell its tile is named by
    (cells are assigned on coordinates snapped to the stored 1 mm lattice)."""
    root, _ = pair_catalog
    grid = grid_of(root)
    outside = 0
    for path in tile_files(root):
        las = laspy.read(path)
        keys = grid.cell_keys(np.asarray(las.x), np.asarray(las.y))
        outside += int((keys != CellId.parse(path.stem).key).sum())
    assert outside == 0


def test_two_missions_over_the_same_ground_share_cell_ids(pair_catalog: tuple[Path, Any]) -> None:
    root, _ = pair_catalog
    grid = grid_of(root)
    first = {p.stem for p in tile_files(root, "2024")}
    second = {p.stem for p in tile_files(root, "2028")}
    shared = first & second
    # the same 80 m stand seen twice: nearly all cells in common, with the same ids
    assert len(shared) >= 0.8 * min(len(first), len(second))
    # and the ids are the grid's cells of the ground: the stand (x 614700-614780,
    # y 5737110-5737190) centre cell is in both epochs
    centre = str(grid.cell(614740.0, 5737150.0))
    assert centre in shared


def _anchored_mission(root: Path, crs: str = "EPSG:32630") -> tuple[Path, np.ndarray]:
    """A small mission with a GNSS_LLA_REF/GNSS_LLA_TO_MAP anchor whose payload holds points
    that project exactly onto 20 m cell edges and corners. Returns (mission, edge points)."""
    synthetic = make_mission(root, n_nodes=5, points=50, seed=4)
    yaw = 0.7
    T_map_enu = np.eye(4)
    T_map_enu[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T_map_enu[:3, 3] = [3.0, -2.0, 0.5]
    assert synthetic.graph is not None
    graph = dataclasses.replace(
        synthetic.graph, gnss_lla_ref=(51.7735, -1.337, 150.0), gnss_lla_to_map=T_map_enu
    )
    write_pose_graph(graph, synthetic.path / "slam_pose_graph.g2o")
    fit = fit_from_pose_graph(graph)
    assert fit is not None
    projector = MapProjector(fit, crs)
    stamp = synthetic.stamps[2]
    pose = synthetic.poses[2]
    centre = projector.exact(pose[:3, 3][None])[0]
    kx, ky = np.floor(centre[:2] / 20.0) * 20.0
    edge = []
    for dx, dy in itertools.product((-20.0, 0.0, 20.0), repeat=2):
        edge.append([kx + dx, ky + dy, centre[2]])  # corners
        edge.append([kx + dx, ky + dy + 7.25, centre[2] + 1.0])  # on a vertical edge
        edge.append([kx + dx + 3.5, ky + dy, centre[2] - 1.0])  # on a horizontal edge
    edge_crs = np.array(edge)
    base = transform_points(invert_pose(pose), projector.to_map(edge_crs))
    cloud = synthetic.clouds[stamp]
    from standgrid.pointcloud import PointCloud

    extra = PointCloud(base, {"intensity": np.full(len(base), 42.0, dtype=np.float32)})
    write_cloud(
        PointCloud.concat([cloud, extra]),
        synthetic.path / "payload_clouds" / stamp.filename("cloud", "pcd"),
        xyz_dtype=np.float64,
    )
    return synthetic.path, edge_crs


def test_points_on_cell_edges_land_in_exactly_one_cell(tmp_path: Path) -> None:
    mission, edge = _anchored_mission(tmp_path / "m")
    catalog = tmp_path / "catalog"
    report = tile([mission], catalog, cell_size=20.0, laz=False, crs="EPSG:32630")
    assert report.missions[mission.name]["georeference"]["method"] == "pose_graph"
    tree = cKDTree(edge[:, :2])
    found = np.zeros(len(edge), dtype=np.int64)
    for path in tile_files(catalog):
        las = laspy.read(path)
        xy = np.column_stack([np.asarray(las.x), np.asarray(las.y)])
        dist, idx = tree.query(xy)
        hits = dist < 0.002
        np.add.at(found, idx[hits], 1)
    assert found.tolist() == [1] * len(edge)


def test_edge_points_are_in_the_cell_of_their_stored_coordinates(tmp_path: Path) -> None:
    mission, edge = _anchored_mission(tmp_path / "m")
    catalog = tmp_path / "catalog"
    tile([mission], catalog, cell_size=20.0, laz=False, crs="EPSG:32630")
    grid = grid_of(catalog)
    tree = cKDTree(edge[:, :2])
    for path in tile_files(catalog):
        las = laspy.read(path)
        xy = np.column_stack([np.asarray(las.x), np.asarray(las.y)])
        dist, idx = tree.query(xy)
        on_edge = dist < 0.002
        keys = grid.cell_keys(xy[on_edge, 0], xy[on_edge, 1])
        cell = CellId.parse(path.stem)
        assert np.all(keys == cell.key), path.name
        # half-open cells: a point on the edge x = k * 20 is in column k (likewise rows)
        for (x, y), target in zip(xy[on_edge], edge[idx[on_edge]], strict=True):
            if target[0] % 20.0 == 0.0:
                assert x == target[0] and cell.ix == int(target[0] // 20.0), path.name
            if target[1] % 20.0 == 0.0:
                assert y == target[1] and cell.iy == int(target[1] // 20.0), path.name


# --- buffers -------------------------------------------------------------------------------


def test_buffer_points_are_withheld_copies_within_the_buffer(
    buffer_catalog: Path, pair_catalog: tuple[Path, Any]
) -> None:
    plain, _ = pair_catalog
    grid = grid_of(buffer_catalog)
    buffered_tiles = tile_files(buffer_catalog)
    assert [p.relative_to(buffer_catalog) for p in buffered_tiles] == [
        p.relative_to(plain) for p in tile_files(plain)
    ]
    total_withheld = 0
    for path in buffered_tiles:
        las = laspy.read(path)
        held = ~core(las)
        total_withheld += int(held.sum())
        xmin, ymin, xmax, ymax = grid.bounds(CellId.parse(path.stem))
        x, y = np.asarray(las.x)[held], np.asarray(las.y)[held]
        dx = np.maximum.reduce([xmin - x, x - xmax, np.zeros_like(x)])
        dy = np.maximum.reduce([ymin - y, y - ymax, np.zeros_like(y)])
        outside = (x < xmin) | (x >= xmax) | (y < ymin) | (y >= ymax)
        assert np.all(outside), path.name
        assert np.all(np.hypot(dx, dy) <= 2.0 + 1e-9), path.name
        # dropping the withheld points gives exactly the no-buffer tile
        plain_las = laspy.read(plain / path.relative_to(buffer_catalog))
        assert np.array_equal(records(las, core(las)), records(plain_las))
    assert total_withheld > 0


def test_buffer_holds_every_neighbour_point_within_the_distance(buffer_catalog: Path) -> None:
    """Completeness: a tile's withheld points are all other tiles' core points within 2 m."""
    grid = grid_of(buffer_catalog)
    for epoch in ("2024", "2028"):
        paths = tile_files(buffer_catalog, epoch)
        cores = {p.stem: records(las, core(las)) for p in paths for las in [laspy.read(p)]}
        for path in paths[::3]:
            others = np.concatenate([rows for stem, rows in cores.items() if stem != path.stem])
            xmin, ymin, xmax, ymax = grid.bounds(CellId.parse(path.stem))
            x, y = others[:, 0], others[:, 1]
            dx = np.maximum.reduce([xmin - x, x - xmax, np.zeros_like(x)])
            dy = np.maximum.reduce([ymin - y, y - ymax, np.zeros_like(y)])
            expected = others[np.hypot(dx, dy) <= 2.0 - SCALE]
            las = laspy.read(path)
            held = records(las, ~core(las))
            assert len(held) >= len(expected)
            held_set = {tuple(r) for r in held}
            missing = sum(tuple(r) not in held_set for r in expected)
            assert missing == 0, f"{path.name}: {missing} neighbour points missing"


# --- headers -------------------------------------------------------------------------------


def test_tile_headers(pair_catalog: tuple[Path, Any]) -> None:
    root, _ = pair_catalog
    state = catalog_json(root)
    crs = pyproj.CRS.from_user_input(state["crs"])
    numbers = {name: m["number"] for name, m in state["missions"].items()}
    layer = pyogrio.read_dataframe(root / "index.gpkg", layer="payloads")
    by_id = {int(r.payload_id): r for r in layer.itertuples()}
    stamps_gps = {
        int(r.payload_id): float(unix_ns_to_adjusted_gps_time(Stamp(r.stamp_sec, r.stamp_nsec).ns))
        for r in layer.itertuples()
    }
    for path in tile_files(root):
        las = laspy.read(path)
        header = las.header
        assert str(header.version) == "1.4"
        assert header.point_format.id == 6
        assert np.allclose(header.scales, SCALE)
        assert header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
        wkt_vlrs = [
            v for v in header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)
        ]
        assert len(wkt_vlrs) == 1
        assert pyproj.CRS.from_wkt(wkt_vlrs[0].string).equals(crs)
        assert header.parse_crs().to_epsg() == crs.to_epsg()
        xyz = np.column_stack([las.x, las.y, las.z])
        assert np.allclose(header.mins, xyz.min(axis=0), atol=SCALE / 2)
        assert np.allclose(header.maxs, xyz.max(axis=0), atol=SCALE / 2)
        assert header.point_count == len(las.points)
        assert "payload_id" in las.point_format.extra_dimension_names
        epoch = path.parent.name
        pids = np.asarray(las.payload_id)
        sources = np.asarray(las.point_source_id)
        for pid in np.unique(pids):
            row = by_id[int(pid)]  # every payload_id is a row of the payloads layer
            mask = pids == pid
            assert np.all(sources[mask] == numbers[row.mission])
            assert str(row.epoch) == epoch
            # gps_time: the payload stamp as adjusted standard GPS time
            assert np.allclose(np.asarray(las.gps_time)[mask], stamps_gps[int(pid)], atol=1e-6)
        assert set(np.unique(sources)) <= {numbers[n] for n in state["epochs"][epoch]["missions"]}


# --- GeoPackage and VPC ----------------------------------------------------------------------


def test_geopackage_layers(pair_catalog: tuple[Path, Any]) -> None:
    root, _ = pair_catalog
    gpkg = root / "index.gpkg"
    state = catalog_json(root)
    layers = {name for name, _ in pyogrio.list_layers(gpkg)}
    assert {"cells", "payloads", "trajectories", "gnss_fixes", "missions"} <= layers
    crs = pyproj.CRS.from_user_input(state["crs"])
    for name in ("cells", "payloads", "trajectories", "gnss_fixes"):
        info = pyogrio.read_info(gpkg, layer=name)
        assert pyproj.CRS.from_user_input(info["crs"]).equals(crs), name
    cells = pyogrio.read_dataframe(gpkg, layer="cells")
    on_disk = {p.relative_to(root).as_posix() for p in tile_files(root)}
    assert len(cells) == len(on_disk)
    assert set(cells["tile_path"]) == on_disk
    for row in cells.itertuples():
        las = laspy.read(root / row.tile_path)
        assert row.point_count == int(core(las).sum())
        assert row.cell_id == Path(row.tile_path).stem
    payloads = pyogrio.read_dataframe(gpkg, layer="payloads")
    for mission in (M1, M2):
        counts = payload_counts(mission)
        rows = payloads[payloads["mission"] == mission.name]
        assert len(rows) == len(counts)
        got = {
            Stamp(int(r.stamp_sec), int(r.stamp_nsec)): int(r.point_count)
            for r in rows.itertuples()
        }
        assert got == counts
    missions = pyogrio.read_dataframe(gpkg, layer="missions", read_geometry=False)
    assert sorted(missions["mission"]) == sorted(state["missions"])
    trajectories = pyogrio.read_dataframe(gpkg, layer="trajectories")
    assert sorted(trajectories["mission"]) == sorted(state["missions"])
    fixes = pyogrio.read_dataframe(gpkg, layer="gnss_fixes")
    assert set(fixes["mission"]) == set(state["missions"])
    with sqlite3.connect(gpkg) as db:
        styles = db.execute(
            "SELECT f_table_name FROM layer_styles WHERE useAsDefault = 1"
        ).fetchall()
    assert {"cells", "payloads", "trajectories", "gnss_fixes"} <= {s[0] for s in styles}


def test_vpc_per_epoch_lists_every_tile(pair_catalog: tuple[Path, Any]) -> None:
    root, _ = pair_catalog
    for epoch in ("2024", "2028"):
        vpc = json.loads((root / f"tiles_{epoch}.vpc").read_text())
        assert vpc["type"] == "FeatureCollection"
        hrefs = {}
        for feature in vpc["features"]:
            href = feature["assets"]["data"]["href"]
            hrefs[(root / href).resolve()] = feature["properties"]["pc:count"]
        tiles = tile_files(root, epoch)
        assert set(hrefs) == {p.resolve() for p in tiles}
        for path in tiles:
            assert hrefs[path.resolve()] == laspy.read(path).header.point_count


def test_vpc_describes_the_files_of_a_buffered_catalog(buffer_catalog: Path) -> None:
    vpc = json.loads((buffer_catalog / "tiles_2024.vpc").read_text())
    for feature in vpc["features"]:
        header = laspy.open(buffer_catalog / feature["assets"]["data"]["href"]).header
        assert feature["properties"]["pc:count"] == header.point_count
        xmin, ymin, zmin, xmax, ymax, zmax = feature["properties"]["proj:bbox"]
        assert xmin <= header.mins[0] and ymin <= header.mins[1] and zmin <= header.mins[2]
        assert xmax >= header.maxs[0] and ymax >= header.maxs[1] and zmax >= header.maxs[2]


# --- catalog behaviour ----------------------------------------------------------------------


def test_reingest_is_idempotent(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0, laz=False)
    before = {p.name: laspy.read(p) for p in tile_files(catalog)}
    number = catalog_json(catalog)["missions"][M1.name]["number"]
    report = tile([M1], catalog)
    after = {p.name: laspy.read(p) for p in tile_files(catalog)}
    assert sorted(after) == sorted(before)
    assert catalog_json(catalog)["missions"][M1.name]["number"] == number
    assert report.points_out == sum(payload_counts(M1).values())
    for name, las in after.items():
        assert len(las.points) == len(before[name].points)
        assert np.array_equal(records(las), records(before[name]))
        # in practice even the point records are the same bytes, in the same order
        assert las.points.array.tobytes() == before[name].points.array.tobytes(), name
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    payloads = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    assert len(cells) == len(after)
    assert len(payloads) == len(payload_counts(M1))  # no duplicated payload rows


def test_adding_an_epoch_leaves_the_first_untouched(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0)
    first = {k: v for k, v in snapshot(catalog).items() if k.startswith("tiles/2024/")}
    vpc_first = (catalog / "tiles_2024.vpc").read_bytes()
    tile([M2], catalog)
    now = snapshot(catalog)
    assert {k: v for k, v in now.items() if k.startswith("tiles/2024/")} == first
    assert any(k.startswith("tiles/2028/") for k in now)
    assert (catalog / "tiles_2024.vpc").read_bytes() == vpc_first
    assert sorted(catalog_json(catalog)["epochs"]) == ["2024", "2028"]


def test_two_missions_of_one_epoch_merge_into_shared_tiles(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    report = tile([M1, M2], catalog, cell_size=20.0, laz=False, epoch="campaign")
    state = catalog_json(catalog)
    assert list(state["epochs"]) == ["campaign"]
    numbers = {state["missions"][m.name]["number"] for m in (M1, M2)}
    shared = 0
    for path in tile_files(catalog, "campaign"):
        sources = set(np.unique(laspy.read(path).point_source_id).tolist())
        assert sources <= numbers
        shared += sources == numbers
    assert shared >= 10
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    both = ",".join(sorted(m.name for m in (M1, M2)))
    assert (cells["missions"] == both).sum() == shared
    assert report.points_out == sum(payload_counts(M1).values()) + sum(payload_counts(M2).values())


def test_reingest_keeps_the_other_missions_points_in_place(tmp_path: Path) -> None:
    """Re-ingesting M1 alone: M2's points stay exactly where they were; M1 is registered
    to M2 (held where the catalog has it) and lands within a centimetre of where the joint
    alignment of both put it. Without alignment, every point is where it was."""
    for align in (True, False):
        catalog = tmp_path / f"catalog_{align}"
        tile([M1, M2], catalog, cell_size=20.0, laz=False, epoch="campaign", align=align)
        before = {p.name: records(laspy.read(p)) for p in tile_files(catalog)}
        report = tile([M1], catalog, epoch="campaign", align=align)
        after = {p.name: records(laspy.read(p)) for p in tile_files(catalog)}
        if not align:
            assert report.alignment is None
            assert sorted(after) == sorted(before)
            for name in before:
                assert np.array_equal(after[name], before[name]), name
            continue
        assert report.alignment is not None
        assert report.alignment["references"] == [M2.name]
        assert report.alignment["missions"][M1.name]["registered_with"] == [M2.name]
        number = {"m1": 1.0, "m2": 2.0}
        for key, keep in (("m2", True), ("m1", False)):
            was = np.concatenate([r[r[:, 4] == number[key]] for r in before.values()])
            now = np.concatenate([r[r[:, 4] == number[key]] for r in after.values()])
            assert len(was) == len(now)
            if keep:
                was, now = was[np.lexsort(was.T[::-1])], now[np.lexsort(now.T[::-1])]
                assert np.array_equal(was, now)
                continue
            # each payload's points, moved rigidly by less than a centimetre
            for payload in np.unique(was[:, 5]):
                a, b = was[was[:, 5] == payload, :3], now[now[:, 5] == payload, :3]
                assert len(a) == len(b)
                assert np.abs(a.mean(axis=0) - b.mean(axis=0)).max() < 0.01


def test_voronoi_cells(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    tile([M1], catalog, scheme="voronoi", laz=False)
    payloads = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    site_of = {
        f"V_{r.mission}_{int(r.stamp_sec)}_{int(r.stamp_nsec):09d}": int(r.payload_id)
        for r in payloads.itertuples()
    }
    paths = tile_files(catalog)
    assert paths and {p.stem for p in paths} <= set(site_of)
    ids = list(site_of)
    tree = cKDTree(
        np.array([[payloads.set_index("payload_id").loc[site_of[s], c] for c in "xy"] for s in ids])
    )
    total = 0
    for path in paths:
        las = laspy.read(path)
        xy = np.column_stack([np.asarray(las.x), np.asarray(las.y)])
        dist, idx = tree.query(xy, k=2)
        clear = dist[:, 1] - dist[:, 0] > 0.01  # not within rounding of a Voronoi edge
        assert np.all(np.array(ids)[idx[clear, 0]] == path.stem), path.name
        total += len(xy)
    assert total == sum(payload_counts(M1).values())
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    polygons = list(cells.geometry)
    assert all(p.is_valid and not p.is_empty for p in polygons)
    for a, b in itertools.combinations(polygons, 2):
        assert a.intersection(b).area < 1e-6
    coverage = shapely.union_all(list(payloads.geometry))
    union = shapely.union_all(polygons)
    assert union.difference(coverage).area < 1e-3 * coverage.area


# --- bad input -------------------------------------------------------------------------------


def test_mission_without_georeference_raises_and_writes_nothing(tmp_path: Path) -> None:
    mission = make_mission(tmp_path / "m").path
    catalog = tmp_path / "catalog"
    with pytest.raises(GeoreferenceError) as info:
        tile([mission], catalog)
    assert mission.name in str(info.value)
    assert not catalog.exists()


def test_unknown_crs(tmp_path: Path) -> None:
    with pytest.raises(CRSError):
        tile([M1], tmp_path / "catalog", crs="EPSG:999999")
    assert not (tmp_path / "catalog" / "catalog.json").exists()


def test_grid_mismatch_leaves_the_catalog_unchanged(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0)
    before = snapshot(catalog)
    with pytest.raises(GridMismatchError):
        tile([M2], catalog, cell_size=50.0)
    assert snapshot(catalog) == before


def test_same_cell_size_without_levels_adds_to_a_catalog_with_levels(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0, levels=(20.0, 60.0))
    tile([M2], catalog, cell_size=20.0)
    assert grid_of(catalog).levels == (20.0, 60.0)
    assert sorted(catalog_json(catalog)["epochs"]) == ["2024", "2028"]


def test_unwritable_output(tmp_path: Path) -> None:
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder\n")
    with pytest.raises(OutputNotWritableError):
        tile([M1], blocker / "catalog")


def test_existing_folder_needs_overwrite(tmp_path: Path) -> None:
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine\n")
    with pytest.raises(OutputExistsError):
        tile([M1], folder)
    assert (folder / "notes.txt").read_text() == "mine\n"
    with pytest.raises(OutputExistsError, match="overwriting replaces only a catalog"):
        tile([M1], folder, overwrite=True)  # never deletes a folder of other things
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]
    (folder / "notes.txt").unlink()
    tile([M1], folder)  # an empty folder becomes the catalog
    tile([M1], folder, overwrite=True)  # a catalog is replaced
    assert (folder / "catalog.json").is_file()
    # another tool's catalog.json (a STAC catalog) does not make a folder a catalog
    stac = tmp_path / "stac"
    (stac / "items").mkdir(parents=True)
    (stac / "catalog.json").write_text('{"type": "Catalog", "id": "mine"}')
    (stac / "items" / "a.json").write_text("{}")
    with pytest.raises(OutputExistsError, match="overwriting replaces only a catalog"):
        tile([M1], stac, overwrite=True)
    assert (stac / "items" / "a.json").is_file()
    # a symbolic link is not replaced by the catalog (nor is what it points to)
    link = tmp_path / "link"
    link.symlink_to(stac)
    with pytest.raises(OutputExistsError, match="symbolic link"):
        tile([M1], link, overwrite=True)
    assert link.is_symlink() and (stac / "items" / "a.json").is_file()


def test_interrupted_run_leaves_the_catalog_intact(tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0)
    before = snapshot(catalog)
    broken = tmp_path / "missions" / M2.name
    shutil.copytree(M2, broken)
    clouds = sorted((broken / "payload_clouds").glob("*.pcd"))
    victim = clouds[len(clouds) // 2]
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) - 5000])  # header intact, points cut short
    messages: list[str] = []
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions(
            [broken],
            catalog,
            TileOptions(),
            execution=Execution(progress=CallbackProgress(on_status=messages.append)),
        )
    assert victim.name in str(info.value)
    # it failed midway: inside the catalog transaction, while aligning the mission to the
    # catalog's (reading its payloads for stems) or tiling the epoch
    assert any(m.startswith(("tiling epoch 2028", "aligning: landmarks of")) for m in messages)
    assert snapshot(catalog) == before
    assert not (catalog / ".staging").exists()
    victim.write_bytes(data)
    report = tile([broken], catalog)
    assert report.points_out == sum(payload_counts(M2).values())
    assert sorted(catalog_json(catalog)["epochs"]) == ["2024", "2028"]


def test_reingest_into_another_epoch_moves_the_points(tmp_path: Path) -> None:
    mission = M1
    catalog = tmp_path / "cat"
    tile([mission], catalog, epoch="e1")
    tile([mission], catalog, epoch="e2")
    state = catalog_json(catalog)
    assert sorted(state["epochs"]) == ["e2"]
    assert tile_files(catalog, "e1") == []
    on_disk = sum(int(core(laspy.read(f)).sum()) for f in tile_files(catalog))
    assert on_disk == sum(payload_counts(mission).values())
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    assert set(cells["epoch"]) == {"e2"}
    assert not (catalog / "tiles_e1.vpc").exists() and (catalog / "tiles_e2.vpc").exists()


def test_the_fused_base_frame_path_matches_the_exact_chain() -> None:
    from standgrid.georeference import georeference_mission
    from standgrid.mission.opening import open_mission

    opened = open_mission(M1)
    projector = MapProjector(georeference_mission(opened), "auto")
    payload = opened.payloads[3]
    base = opened.load_base(payload)
    pose = opened.pose_of(payload)
    exact = projector.exact(transform_points(pose, base.xyz))
    fused = projector.fast(base.xyz, pose=pose)
    assert np.abs(fused - exact).max() < 1e-3
    assert projector.fast_chunks == 1


def test_a_half_built_catalog_of_a_killed_run_is_removed(tmp_path: Path) -> None:
    stale = tmp_path / ".cat.999999-deadbeef.tmp"  # no process 999999
    (stale / "tiles").mkdir(parents=True)
    tile([M1], tmp_path / "cat")
    assert not stale.exists()
    assert (tmp_path / "cat" / "catalog.json").is_file()


def test_a_same_name_mission_from_another_folder_is_refused_unless_replaced(
    tmp_path: Path,
) -> None:
    """Missions are keyed by name: one of the same name from another folder (here a copy
    with 6 payloads fewer) would silently replace the catalog's mission. It is refused,
    naming both folders, leaving the catalog as it was; ``replace_missions`` replaces it."""
    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0)
    other = tmp_path / "elsewhere" / M1.name
    shutil.copytree(M1, other)
    for cloud in sorted((other / "payload_clouds").iterdir())[:6]:
        cloud.unlink()
    before = snapshot(catalog)
    with pytest.raises(MissionFolderConflictError) as caught:
        tile([other], catalog)
    assert isinstance(caught.value, FileExistsError)
    assert str(M1.resolve()) in str(caught.value) and str(other.resolve()) in str(caught.value)
    assert snapshot(catalog) == before

    report = tile([other], catalog, replace_missions=True)
    entry = catalog_json(catalog)["missions"][M1.name]
    assert entry["path"] == str(other.resolve())
    assert (
        report.points_out == sum(payload_counts(other).values()) < sum(payload_counts(M1).values())
    )
    again = tile([other], catalog)  # from its own folder now: re-ingesting needs no leave
    assert again.points_out == report.points_out


def test_cli_tile_refuses_a_same_name_mission_from_another_folder(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from standgrid.cli import cli

    catalog = tmp_path / "catalog"
    tile([M1], catalog, cell_size=20.0)
    other = tmp_path / "elsewhere" / M1.name
    shutil.copytree(M1, other)
    result = CliRunner().invoke(cli, ["tile", str(other), "-o", str(catalog), "-q"])
    assert result.exit_code == 1
    assert "MissionFolderConflictError" in result.output and "--replace" in result.output
    result = CliRunner().invoke(cli, ["tile", str(other), "-o", str(catalog), "-q", "--replace"])
    assert result.exit_code == 0, result.output
    assert catalog_json(catalog)["missions"][M1.name]["path"] == str(other.resolve())


def test_crs_auto_adding_to_a_catalog_of_another_continent_is_refused(tmp_path: Path) -> None:
    """``--crs auto`` adding to a catalog means its CRS; a Wytham (UK) mission lies far
    outside EPSG:3005 (British Columbia): refused, naming the CRS and where the mission is."""
    catalog = tmp_path / "bc"
    tile([M2], catalog, cell_size=20.0, crs="EPSG:3005")  # placed there by an explicit --crs
    before = snapshot(catalog)
    with pytest.raises(CRSError) as caught:
        tile([M1], catalog)
    message = str(caught.value)
    assert "EPSG:3005" in message and "area of use" in message, message
    assert "lat 51.7" in message and "lon -1.3" in message, message
    assert snapshot(catalog) == before
    # a catalog in the mission's own UTM zone takes it, with --crs auto
    utm = tmp_path / "utm"
    tile([M2], utm, cell_size=20.0)
    report = tile([M1], utm)
    assert report.crs == catalog_json(utm)["crs"] == "EPSG:32630"
