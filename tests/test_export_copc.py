"""COPC tiles: written with write_copc_tile (lazrs chunks, own COPC VLRs and hierarchy),
read back by laspy (LasReader, CopcReader, also over HTTP from a real standgrid server),
copclib's reader (the independent validator) and read_tile."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import copclib
import laspy
import numpy as np
import pyproj
import pytest

from standgrid.errors import CRSError, OutputExistsError, PointCloudFormatError
from standgrid.export.copc import _stable_order, is_copc, octree_nodes, write_copc_tile
from standgrid.export.las import read_tile, snap_to_storage, write_tile
from standgrid.pointcloud import PointCloud

CRS = "EPSG:32632"
X0, Y0, Z0 = 500_000.0, 6_000_000.0, 100.0


def forest_cloud(n: int, seed: int = 0, *, colour: bool = False, source: int = 3) -> PointCloud:
    """A 20 m x 20 m plot: a sloping ground, ten stems and their crowns (surfaces, as a
    scanner sees them), with the fields tiles carry; coordinates on the 1 mm lattice."""
    rng = np.random.default_rng(seed)
    n_ground, n_stem = n // 2, n // 4
    n_crown = n - n_ground - n_stem
    gx, gy = rng.uniform(0, 20, n_ground), rng.uniform(0, 20, n_ground)
    ground = np.column_stack([gx, gy, 0.05 * gx + rng.normal(0, 0.02, n_ground)])
    stems = rng.uniform(1, 19, (10, 2))
    which = rng.integers(0, 10, n_stem)
    angle = rng.uniform(0, 2 * np.pi, n_stem)
    stem = np.column_stack(
        [
            stems[which, 0] + 0.2 * np.cos(angle),
            stems[which, 1] + 0.2 * np.sin(angle),
            rng.uniform(0, 14, n_stem),
        ]
    )
    which_c = rng.integers(0, 10, n_crown)
    d = rng.normal(size=(n_crown, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    crown = np.column_stack([stems[which_c] + 1.5 * d[:, :2], 16 + 3 * d[:, 2]])
    local = np.clip(np.concatenate([ground, stem, crown]), 0, 20)
    xyz = snap_to_storage(local + np.array([X0, Y0, Z0]))
    fields: dict[str, np.ndarray] = {
        "intensity": rng.uniform(0.0, 1.0, n).astype(np.float32),
        "gps_time": rng.uniform(1.4e9, 1.4e9 + 600, n),
        "point_source_id": np.full(n, source, np.uint16),
        "classification": np.where(np.arange(n) < n_ground, 2, 5).astype(np.uint8),
        "payload_id": rng.integers(0, 2**32 - 1, n, dtype=np.uint32),
        "height_above_ground": (local[:, 2] - 0.05 * local[:, 0]).astype(np.float32),
        "tree_id": np.concatenate([np.full(n_ground, -1), which, which_c]).astype(np.int32),
        "normal": rng.normal(size=(n, 3)).astype(np.float32),
        "valid": rng.random(n) > 0.5,
    }
    if colour:
        for c in ("red", "green", "blue"):
            fields[c] = rng.integers(0, 65535, n).astype(np.uint16)
    return PointCloud(xyz, fields)


def _rows(cloud: PointCloud) -> np.ndarray:
    """One row per point (coordinates in mm and every field), sorted: a multiset to compare."""
    cols = [np.round(cloud.xyz * 1000).astype(np.int64)]
    for name in sorted(set(cloud.fields) - {"withheld"}):
        values = np.asarray(cloud.fields[name])
        cols.append(values.reshape(len(values), -1).astype(np.float64))
    table = np.column_stack(cols).astype(np.float64)
    return table[np.lexsort(table.T[::-1])]


def _record_rows(points: laspy.ScaleAwarePointRecord) -> np.ndarray:
    """Sorted (X, Y, Z, payload_id, withheld) of a laspy point record."""
    table = np.column_stack(
        [
            np.asarray(points.X),
            np.asarray(points.Y),
            np.asarray(points.Z),
            np.asarray(points["payload_id"]),
            np.asarray(points.withheld),
        ]
    ).astype(np.int64)
    return table[np.lexsort(table.T[::-1])]


@pytest.fixture(scope="module")
def tile(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, PointCloud, PointCloud]:
    """A 60k-point tile (with 6k withheld buffer points) written with a deep octree."""
    folder = tmp_path_factory.mktemp("copc")
    core, buffer = forest_cloud(60_000), forest_cloud(6_000, seed=1, source=4)
    path = folder / "cell.copc.laz"
    write_copc_tile(path, core, crs=CRS, buffer=buffer, resolution=32, leaf_points=2_000)
    return path, core, buffer


@pytest.mark.parametrize(
    "n, edge", [(30_000, 20_000), (3_000, 2_000_000)]
)  # Morton codes by table look-up; by bit spreading (finer than 2**16 cells)
def test_octree_puts_every_point_in_one_node_inside_its_voxel(n: int, edge: int) -> None:
    rng = np.random.default_rng(5)
    ijk = rng.integers(0, edge + 1, (n, 3))
    ijk[:100] = edge  # the far faces belong to the last nodes
    keys, node, grouped = octree_nodes(ijk, edge, resolution=8, leaf_points=300)
    np.testing.assert_array_equal(np.sort(grouped), np.arange(len(ijk)))  # a permutation
    assert np.all(np.diff(node[grouped]) >= 0)  # node by node, in key order
    assert node.min() == 0 and node.max() == len(keys) - 1
    assert len({tuple(k) for k in keys}) == len(keys)
    assert np.all(np.diff(keys[:, 0]) >= 0)  # coarse to fine
    d, xyz = keys[node, 0], keys[node, 1:]
    lo, hi = (xyz * edge) >> d[:, None], ((xyz + 1) * edge) >> d[:, None]
    last = xyz == (1 << d[:, None]) - 1
    assert np.all(
        (ijk * (1 << d[:, None]) >= xyz * edge)
        & ((ijk * (1 << d[:, None]) < (xyz + 1) * edge) | last)
    )
    assert np.all((lo <= ijk) & (ijk <= hi))
    key_set = {tuple(k) for k in keys}
    for depth, x, y, z in keys[keys[:, 0] > 0]:  # every node's parent exists
        assert (depth - 1, x // 2, y // 2, z // 2) in key_set
    assert keys[:, 0].max() >= 2
    root = np.flatnonzero(keys[:, 0] == 0)[0]
    # the root holds the first point (in input order) of every occupied cell of its 8^3 grid
    cell = np.minimum(ijk * 8 // edge, 7)
    cell_id = (cell[:, 0] * 8 + cell[:, 1]) * 8 + cell[:, 2]
    first = np.full(8**3, len(ijk))
    np.minimum.at(first, cell_id, np.arange(len(ijk)))
    np.testing.assert_array_equal(np.flatnonzero(node == root), np.sort(first[first < len(ijk)]))
    with pytest.raises(ValueError, match="power of two"):
        octree_nodes(ijk, edge, resolution=12)


@pytest.mark.parametrize(
    "n, bits",
    [(50_000, 30), (50_000, 60), (300_000, 63), (0, 3), (1, 3)],  # one sort, two, argsort
)
def test_stable_order_is_a_stable_argsort(n: int, bits: int) -> None:
    rng = np.random.default_rng(n + bits)
    code = rng.integers(0, 2**bits, n, dtype=np.uint64) if n else np.zeros(0, np.uint64)
    code[: n // 3] = code[n // 3 : 2 * (n // 3)]  # ties
    code[: n // 10] &= np.uint64(2**64 - 256)  # ties in the high bits only
    order, sorted_code = _stable_order(code, bits)
    want = np.argsort(code, kind="stable")
    np.testing.assert_array_equal(order, want)
    np.testing.assert_array_equal(sorted_code, code[want])


def test_hierarchy_entries_are_the_laz_chunks_node_by_node(
    tile: tuple[Path, PointCloud, PointCloud],
) -> None:
    """Each hierarchy entry names one LAZ chunk (variable-size chunks, in entry order): its
    offset, byte size and point count; copclib's and laspy's node lists agree."""
    import lazrs

    path, core, buffer = tile
    with laspy.open(path) as f:
        header = f.header
        laz_vlr = lazrs.LazVlr(header.vlrs.get("LasZipVlr")[0].record_data)
    assert laz_vlr.uses_variable_size_chunks()
    with open(path, "rb") as stream:
        stream.seek(header.offset_to_point_data)
        table = lazrs.read_chunk_table(stream, laz_vlr)
    reader = copclib.FileReader(str(path))
    try:
        nodes = sorted(reader.GetAllNodes(), key=lambda n: n.offset)
    finally:
        reader.Close()
    assert [(n.point_count, n.byte_size) for n in nodes] == [tuple(t) for t in table]
    offsets = header.offset_to_point_data + 8 + np.r_[0, np.cumsum([b for _, b in table])[:-1]]
    assert [n.offset for n in nodes] == offsets.tolist()
    with laspy.CopcReader.open(path) as copc:
        entries = list(copc.root_page.entries.values())  # laspy's reading of the same page
    assert sorted((e.offset, e.byte_size, e.point_count) for e in entries) == [
        (n.offset, n.byte_size, n.point_count) for n in nodes
    ]
    assert sum(n.point_count for n in nodes) == len(core) + len(buffer)


def test_level_and_resolution_queries_return_the_nodes_copclib_reads(
    tile: tuple[Path, PointCloud, PointCloud],
) -> None:
    path, core, buffer = tile
    reader = copclib.FileReader(str(path))
    try:
        by_depth: dict[int, list[np.ndarray]] = {}
        depths = {node.key.d for node in reader.GetAllNodes()}
        for node in reader.GetAllNodes():
            if node.key.d <= 1:
                p = reader.GetPoints(node)
                xyz = np.column_stack([np.asarray(p.x), np.asarray(p.y), np.asarray(p.z)])
                by_depth.setdefault(node.key.d, []).append(xyz)
    finally:
        reader.Close()

    def rows(xyz: Any) -> np.ndarray:
        if not isinstance(xyz, np.ndarray):  # a laspy record
            xyz = np.column_stack([np.asarray(xyz.x), np.asarray(xyz.y), np.asarray(xyz.z)])
        got = np.round(xyz * 1000).astype(np.int64)
        return got[np.lexsort(got.T)]

    with laspy.CopcReader.open(path) as copc:
        spacing = copc.copc_info.spacing
        root = copc.query(level=0)
        coarse = copc.query(resolution=spacing / 2)  # levels 0 and 1
        finest = copc.query(resolution=spacing / 2 ** max(depths))
    np.testing.assert_array_equal(rows(root), rows(np.concatenate(by_depth[0])))
    np.testing.assert_array_equal(rows(coarse), rows(np.concatenate(by_depth[0] + by_depth[1])))
    assert len(root) < len(coarse) < len(finest) == len(core) + len(buffer)


def test_copc_file_is_laz_14_with_the_plain_tiles_vlrs_and_dims(
    tile: tuple[Path, PointCloud, PointCloud], tmp_path: Path
) -> None:
    path, core, buffer = tile
    plain = tmp_path / "plain.laz"
    write_tile(plain, core, crs=CRS, buffer=buffer)
    las, ref = laspy.read(path), laspy.read(plain)
    h = las.header
    with laspy.open(path) as reader:
        assert reader.header.are_points_compressed
    assert (h.version.major, h.version.minor) == (1, 4)
    assert h.point_format.id == ref.header.point_format.id == 6
    assert isinstance(h.vlrs[0], laspy.copc.CopcInfoVlr)  # COPC: the info VLR comes first
    # write_tile's VLRs, no copclib extents VLR (all zeros), the hierarchy the only EVLR
    assert [(v.user_id, v.record_id) for v in h.vlrs] == [("copc", 1)] + [
        (v.user_id, v.record_id) for v in ref.header.vlrs
    ]
    assert [(v.user_id, v.record_id) for v in las.evlrs] == [("copc", 1000)]
    assert h.point_count == len(core) + len(buffer)
    assert h.global_encoding.wkt
    assert h.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    assert pyproj.CRS(h.parse_crs()) == pyproj.CRS(CRS)
    assert h.generating_software == ref.header.generating_software
    assert h.point_format.dtype() == ref.header.point_format.dtype()
    assert list(h.point_format.extra_dimension_names) == list(
        ref.header.point_format.extra_dimension_names
    )
    for uid, rid in (("standgrid", 1), ("LASF_Projection", 2112)):
        mine = [
            bytes(v.record_data_bytes()) for v in h.vlrs if v.user_id == uid and v.record_id == rid
        ]
        theirs = [
            bytes(v.record_data_bytes())
            for v in ref.header.vlrs
            if v.user_id == uid and v.record_id == rid
        ]
        assert mine == theirs and len(mine) == 1, uid
    np.testing.assert_allclose(h.mins, ref.header.mins)
    np.testing.assert_allclose(h.maxs, ref.header.maxs)
    np.testing.assert_array_equal(
        h.number_of_points_by_return, ref.header.number_of_points_by_return
    )
    # Same records, another order: grouped by octree node.
    np.testing.assert_array_equal(
        np.sort(las.points.array, order=["X", "Y", "Z", "gps_time"]),
        np.sort(ref.points.array, order=["X", "Y", "Z", "gps_time"]),
    )
    info = h.vlrs[0]
    assert info.gps_min == las.gps_time.min()
    assert info.gps_max == las.gps_time.max()
    assert info.halfsize * 2 == pytest.approx(np.max(h.maxs - h.mins))


def test_copclib_validates_the_hierarchy_and_every_point_is_in_one_node(
    tile: tuple[Path, PointCloud, PointCloud],
) -> None:
    path, core, buffer = tile
    reader = copclib.FileReader(str(path))
    try:
        assert reader.ValidateSpatialBounds(False)
        nodes = reader.GetAllNodes()
        depths = sorted({n.key.d for n in nodes})
        assert depths[0] == 0 and len(depths) >= 3
        assert sum(n.point_count for n in nodes) == len(core) + len(buffer)
        keys = {(n.key.d, n.key.x, n.key.y, n.key.z) for n in nodes}
        assert all((d - 1, x // 2, y // 2, z // 2) in keys for d, x, y, z in keys if d)
        xyz = np.concatenate(
            [
                np.column_stack([np.asarray(p.x), np.asarray(p.y), np.asarray(p.z)])
                for p in (reader.GetPoints(n) for n in nodes)
            ]
        )
        # a small box reads a few nodes
        box = copclib.Box(X0 + 2, Y0 + 2, Z0 - 1, X0 + 4, Y0 + 4, Z0 + 1)
        assert len(reader.GetNodesIntersectBox(box)) < len(nodes) / 4
    finally:
        reader.Close()
    expected = np.concatenate([core.xyz, buffer.xyz])
    got = np.round(xyz * 1000).astype(np.int64)
    want = np.round(expected * 1000).astype(np.int64)
    np.testing.assert_array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])


@pytest.mark.parametrize(
    "lo, hi",
    [
        ((X0 + 3.25, Y0 + 11.5), (X0 + 9.0, Y0 + 14.0)),  # 2D
        ((X0, Y0, Z0 + 2.0), (X0 + 20.0, Y0 + 20.0, Z0 + 14.5)),  # a slab
        ((X0 + 10.0, Y0 + 0.0, Z0 - 5.0), (X0 + 10.0, Y0 + 20.0, Z0 + 30.0)),  # a node face
        ((X0 - 50, Y0 - 50), (X0 - 10, Y0 - 10)),
    ],  # outside
)
def test_copc_reader_bounds_query_returns_exactly_the_points_inside(
    tile: tuple[Path, PointCloud, PointCloud], lo: tuple[float, ...], hi: tuple[float, ...]
) -> None:
    path, core, buffer = tile
    xyz = np.concatenate([core.xyz, buffer.xyz])
    payload = np.concatenate([core.fields["payload_id"], buffer.fields["payload_id"]])
    withheld = np.r_[np.zeros(len(core), int), np.ones(len(buffer), int)]
    k = len(lo)
    inside = np.all((xyz[:, :k] >= lo) & (xyz[:, :k] <= hi), axis=1)
    with laspy.open(path) as f:
        offsets = f.header.offsets
    stored = np.round((xyz - offsets) * 1000).astype(np.int64)
    want = np.column_stack([stored, payload, withheld])[inside]
    want = want[np.lexsort(want.T[::-1])]
    with laspy.CopcReader.open(path) as reader:
        got = reader.query(laspy.copc.Bounds(mins=np.array(lo), maxs=np.array(hi)))
    assert len(got) == int(inside.sum())
    np.testing.assert_array_equal(_record_rows(got), want)


def test_a_copc_tile_opens_as_a_cloud_by_suffix_or_by_its_bytes(
    tile: tuple[Path, PointCloud, PointCloud], tmp_path: Path
) -> None:
    """The cloud registry reads a COPC file (LAZ 1.4, copc VLR first) as format ``copc``,
    named so or not; it does not write one (the tile writer does)."""
    from standgrid.clouds import open_cloud, write_cloud

    path, core, buffer = tile
    unnamed = tmp_path / "cell.bin"
    shutil.copyfile(path, unnamed)
    for source in (path, unnamed):
        with open_cloud(source) as reader:
            assert reader.header.format == "copc"
            assert reader.header.points == len(core) + len(buffer)
            assert reader.header.crs.to_epsg() == pyproj.CRS.from_user_input(CRS).to_epsg()
            cloud = reader.read(["withheld"])
            assert int(cloud.fields["withheld"].sum()) == len(buffer)
    with pytest.raises(PointCloudFormatError, match="copc files are not written"):
        write_cloud(core, tmp_path / "payload.copc.laz")


@pytest.mark.parametrize("colour", [False, True])
def test_read_tile_round_trip(tmp_path: Path, colour: bool) -> None:
    core = forest_cloud(8_000, seed=7, colour=colour)
    buffer = forest_cloud(900, seed=8, colour=colour, source=4)
    path = tmp_path / "t.copc.laz"
    info = write_copc_tile(path, core, crs=CRS, buffer=buffer, resolution=16, leaf_points=500)
    assert info.path == path and info.compressed
    assert (info.core_count, info.buffer_count) == (8_000, 900)
    assert info.point_format == (7 if colour else 6)
    assert laspy.read(path).header.point_format.id == info.point_format
    back = read_tile(path)
    assert set(back.fields) == set(core.fields)
    for name, values in core.fields.items():
        assert back.fields[name].dtype == values.dtype, name
    np.testing.assert_array_equal(_rows(back), _rows(core))
    everything = read_tile(path, include_withheld=True)
    flags = everything.fields["withheld"]
    assert flags.sum() == len(buffer)
    np.testing.assert_array_equal(_rows(everything.select(flags)), _rows(buffer))
    assert [p.name for p in tmp_path.iterdir()] == ["t.copc.laz"]  # no temporary left


def test_errors_are_typed_and_leave_nothing(tmp_path: Path) -> None:
    core = forest_cloud(500)
    path = tmp_path / "t.copc.laz"
    with pytest.raises(CRSError):
        write_copc_tile(path, core, crs="not a crs")
    with pytest.raises(PointCloudFormatError, match="compressed"):
        write_copc_tile(path, core, crs=CRS, laz=False)
    assert list(tmp_path.iterdir()) == []
    write_copc_tile(path, core, crs=CRS)
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        write_copc_tile(path, forest_cloud(300, seed=3), crs=CRS, overwrite=False)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["t.copc.laz"]
    assert is_copc(path) and not is_copc(tmp_path / "t.laz")


def test_empty_and_single_point_tiles(tmp_path: Path) -> None:
    one = PointCloud(
        np.array([[X0 + 1.0, Y0 + 2.0, Z0 + 3.0]]), {"payload_id": np.array([7], np.uint32)}
    )
    path = tmp_path / "one.copc.laz"
    write_copc_tile(path, one, crs=CRS)
    back = read_tile(path)
    np.testing.assert_array_equal(back.xyz, one.xyz)
    assert back.fields["payload_id"].tolist() == [7]
    with laspy.CopcReader.open(path) as reader:
        assert len(reader.query()) == 1
    empty = PointCloud.empty({"payload_id": np.dtype(np.uint32)})
    path = tmp_path / "empty.copc.laz"
    write_copc_tile(path, empty, crs=CRS)
    assert len(read_tile(path)) == 0
    with laspy.CopcReader.open(path) as reader:
        assert len(reader.query()) == 0


# --- over HTTP from a real standgrid server ------------------------------------------------


class BytesSent:
    """ASGI wrapper counting the response body bytes the server sends (no change to them)."""

    def __init__(self, app: Any) -> None:
        self.app, self.sent = app, 0

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        async def counted(message: Any) -> None:
            if message["type"] == "http.response.body":
                self.sent += len(message.get("body", b""))
            await send(message)

        await self.app(scope, receive, counted)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, str, BytesSent]]:
    """A tiled catalog whose first 2024 tile is rewritten as COPC, served by uvicorn."""
    from standgrid.catalog import Catalog
    from standgrid.serve import create_app
    from standgrid.serve.server import running
    from tests.pipeline_fixtures import tiled_grid25

    folder = tmp_path_factory.mktemp("served") / "catalog"
    shutil.copytree(tiled_grid25(tmp_path_factory), folder)
    rel = max(Catalog.open(folder).tiles("2024"), key=lambda r: (folder / r).stat().st_size)
    las = laspy.read(folder / rel)
    cloud = read_tile(folder / rel, include_withheld=True)
    write_copc_tile(
        folder / rel, cloud, crs=las.header.parse_crs().to_wkt(), resolution=8, leaf_points=200
    )
    app = BytesSent(create_app(folder))
    with running(app) as server:
        assert server.base_url is not None
        yield server.base_url, folder, rel, app


def test_served_copc_tile_is_queried_by_bounds_over_http(
    served: tuple[str, Path, str, BytesSent],
) -> None:
    base, folder, rel, _ = served
    local = laspy.read(folder / rel)
    x, y = np.asarray(local.x), np.asarray(local.y)
    lo = (float(np.quantile(x, 0.3)), float(np.quantile(y, 0.2)))
    hi = (float(np.quantile(x, 0.6)), float(np.quantile(y, 0.7)))
    inside = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])
    assert 0 < inside.sum() < len(x)
    # laspy's query compares stored integers against the bounds rounded to the lattice
    scale, offset = local.header.scales, local.header.offsets
    lo_i = np.round((np.array(lo) - offset[:2]) / scale[:2])
    hi_i = np.round((np.array(hi) - offset[:2]) / scale[:2])
    xy = np.column_stack([local.X, local.Y])
    inside = np.all((xy >= lo_i) & (xy <= hi_i), axis=1)
    with laspy.CopcReader.open(f"{base}/files/{rel}") as reader:
        assert reader.header.point_count == len(x)
        got = reader.query(laspy.copc.Bounds(mins=np.array(lo), maxs=np.array(hi)))
        total_nodes = len(reader.root_page.entries)
    assert total_nodes > 1
    np.testing.assert_array_equal(_record_rows(got), _record_rows(local.points[inside]))


def test_a_small_bounds_query_over_http_fetches_a_part_of_the_tile(
    served: tuple[str, Path, str, BytesSent],
) -> None:
    base, folder, rel, app = served
    local = laspy.read(folder / rel)
    lo = np.array([np.quantile(local.x, 0.45), np.quantile(local.y, 0.45)])
    hi = np.array([np.quantile(local.x, 0.55), np.quantile(local.y, 0.55)])
    before = app.sent
    with laspy.CopcReader.open(f"{base}/files/{rel}") as reader:
        got = reader.query(laspy.copc.Bounds(mins=lo, maxs=hi))
    fetched = app.sent - before
    xy = np.column_stack([local.x, local.y])
    assert len(got) == int(np.all((xy >= lo) & (xy <= hi), axis=1).sum()) > 0
    size = (folder / rel).stat().st_size
    print(f"fetched {fetched} of {size} bytes for {len(got)} of {len(local)} points")
    assert fetched < 0.6 * size
