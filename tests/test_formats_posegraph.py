"""Pose graphs (.g2o/.slam) and pose CSVs: real files, generated graphs, exact round trips."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from standgrid.geometry import pose_matrix, relative_pose
from standgrid.mission.posegraph import (
    Edge,
    EdgeKind,
    PoseGraph,
    Vertex,
    read_pose_graph,
    write_pose_graph,
)
from standgrid.mission.poses_csv import PoseTable, read_poses_csv, write_poses_csv
from standgrid.stamps import Stamp
from tests.conftest import real_file

GRAPHS = "vilens/slam_tutorial/graphs"


def assert_same_graph(a: PoseGraph, b: PoseGraph) -> None:
    assert list(a.vertices) == list(b.vertices)
    assert [v.stamp for v in a.vertices.values()] == [v.stamp for v in b.vertices.values()]
    np.testing.assert_allclose(a.poses, b.poses, rtol=0, atol=1e-12)
    assert len(a.edges) == len(b.edges)
    for ea, eb in zip(a.edges, b.edges, strict=True):
        assert (ea.i, ea.j, ea.kind, ea.robust) == (eb.i, eb.j, eb.kind, eb.robust)
        assert ea.robust_parameter == eb.robust_parameter
        np.testing.assert_allclose(ea.relative_pose, eb.relative_pose, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ea.information, eb.information)
    assert a.platform_id == b.platform_id


@pytest.mark.realdata
def test_real_slam_pose_graph_counts() -> None:
    graph = read_pose_graph(real_file(f"{GRAPHS}/slam_pose_graph.slam"))
    assert len(graph) == 178
    assert len(graph.edges) == 189
    assert graph.edge_counts() == Counter({EdgeKind.ODOMETRY: 177, EdgeKind.LOOP_CLOSURE: 12})
    assert graph.platform_id == 0
    assert not graph.skipped_tags
    # first vertex as printed in the file: nsec unpadded, quaternion x y z w
    v0 = graph.vertices[0]
    assert v0.stamp == Stamp(1696592849, 114957094)
    np.testing.assert_allclose(v0.pose[:3, 3], [-0.247094, -0.00731443, -0.0496486])
    info = graph.edges[0].information
    np.testing.assert_array_equal(info, info.T)
    np.testing.assert_array_equal(np.diag(info), [1e6, 1e6, 1e6, 1e4, 1e4, 1e4])


@pytest.mark.realdata
def test_real_graph_edges_match_vertex_poses() -> None:
    graph = read_pose_graph(real_file(f"{GRAPHS}/ground_truth.slam"))
    assert (len(graph), len(graph.edges)) == (50, 49)
    # odometry edges are T_i^-1 T_j of the ground-truth vertices (6-digit file precision)
    for e in graph.edges:
        expected = relative_pose(graph.vertices[e.i].pose, graph.vertices[e.j].pose)
        np.testing.assert_allclose(e.relative_pose, expected, atol=2e-4)


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["slam_pose_graph.slam", "ground_truth.slam"])
def test_real_graph_round_trip(name: str, tmp_path: Path) -> None:
    graph = read_pose_graph(real_file(f"{GRAPHS}/{name}"))
    out = tmp_path / "graph.g2o"
    write_pose_graph(graph, out)
    again = read_pose_graph(out)
    assert_same_graph(graph, again)
    for line in out.read_text().splitlines():
        assert "  " not in line and "\t" not in line  # single-space separated
    # nsec written unpadded, as in the source
    first = next(v for v in graph.vertices.values())
    assert f" {first.stamp.sec} {first.stamp.nsec}\n" in out.read_text()


@pytest.mark.realdata
def test_real_csv_agrees_with_graph() -> None:
    table = read_poses_csv(real_file(f"{GRAPHS}/ground_truth.csv"))
    graph = read_pose_graph(real_file(f"{GRAPHS}/ground_truth.slam"))
    assert len(table) == 50
    assert table.counters is None  # the "#sec,nsec,..." variant
    np.testing.assert_array_equal(table.stamps_ns, graph.stamps_ns)
    assert table.stamps == [v.stamp for v in graph.vertices.values()]
    np.testing.assert_allclose(table.poses, graph.poses, atol=1e-5)
    as_graph = table.to_pose_graph()
    assert list(as_graph.vertices) == list(range(50))
    assert as_graph.edges == []


def _synthetic_graph(n: int, seed: int = 1) -> PoseGraph:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    poses = pose_matrix(rng.uniform(-1e3, 1e3, (n, 3)), q)
    ids = np.arange(n) + 10_000  # a second mission in a merged graph
    vertices = {
        int(i): Vertex(int(i), Stamp(1_700_000_000 + k, int(rng.integers(0, 10**9))), poses[k])
        for k, i in enumerate(ids)
    }
    info = np.diag([1e6, 1e6, 1e6, 1e4, 1e4, 1e4])
    info[0, 4] = info[4, 0] = 12.5
    edges = [
        Edge(int(ids[k]), int(ids[k + 1]), relative_pose(poses[k], poses[k + 1]), info)
        for k in range(n - 1)
    ]
    edges.append(
        Edge(int(ids[0]), int(ids[-1]), relative_pose(poses[0], poses[-1]), info, "switchable", 7.0)
    )
    edges.append(
        Edge(int(ids[1]), int(ids[5]), relative_pose(poses[1], poses[5]), info, "maxmix", 0.25)
    )
    edges.append(Edge(int(ids[2]), int(ids[2]), np.eye(4), info))
    return PoseGraph(
        vertices,
        edges,
        platform_id=3,
        gnss_lla_ref=(51.7734, -1.3386, 123.456),
        gnss_lla_to_map=pose_matrix(
            [1.5, -2.0, 0.25], [0, 0, 0.3826834323650898, 0.9238795325112867]
        ),
    )


def test_synthetic_round_trip_all_edge_kinds(tmp_path: Path) -> None:
    graph = _synthetic_graph(40)
    out = tmp_path / "g.slam"
    write_pose_graph(graph, out)
    again = read_pose_graph(out)
    assert_same_graph(graph, again)
    assert again.gnss_lla_ref == graph.gnss_lla_ref
    assert again.gnss_lla_to_map is not None and graph.gnss_lla_to_map is not None
    np.testing.assert_allclose(again.gnss_lla_to_map, graph.gnss_lla_to_map, atol=1e-15)
    kinds = again.edge_counts()
    assert kinds[EdgeKind.PRIOR] == 1 and kinds[EdgeKind.LOOP_CLOSURE] == 2
    assert [e.robust for e in again.edges[-3:]] == ["switchable", "maxmix", None]
    assert again.edges[-2].robust_parameter == 0.25
    assert {v.mission_index for v in again.vertices.values()} == {1}
    text = out.read_text()
    assert "EDGE_SE3_SWITCHABLE 10000 10039 7 " in text


def test_whitespace_comments_and_skipped_tags(tmp_path: Path) -> None:
    path = tmp_path / "mixed.g2o"
    path.write_text(
        "# header comment\n"
        "PLATFORM_ID\t2\n"
        "VERTEX_SE3:QUAT_TIME   0 0 0 0  0 0 0 1   100 5\n"
        "   VERTEX_SE3:QUAT_TIME 1 1 0 0 0 0 0 1 100 500000000\n"
        "\n"
        "TAG_DETECTION 1 2 3\n"
        "TAG_POSE 4 5\nTAG_POSE 4 6\n"
        "IMAGE_POSE 9\nEDGE_POSE_TO_IMAGE 1 2\nSOMETHING_NEW a b c\n"
        "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + " ".join(["1"] * 21) + "\n"
    )
    graph = read_pose_graph(path)
    assert graph.platform_id == 2
    assert graph.vertices[0].stamp == Stamp(100, 5)
    assert graph.vertices[1].stamp.nsec == 500_000_000
    assert graph.skipped_tags == Counter(
        {
            "TAG_DETECTION": 1,
            "TAG_POSE": 2,
            "IMAGE_POSE": 1,
            "EDGE_POSE_TO_IMAGE": 1,
            "SOMETHING_NEW": 1,
        }
    )
    assert np.all(graph.edges[0].information == 1.0)


def test_duplicate_stamps_are_not_a_parse_error(tmp_path: Path) -> None:
    path = tmp_path / "dup.g2o"
    path.write_text(
        "VERTEX_SE3:QUAT_TIME 0 0 0 0 0 0 0 1 100 5\nVERTEX_SE3:QUAT_TIME 1 1 0 0 0 0 0 1 100 5\n"
    )
    graph = read_pose_graph(path)
    assert graph.duplicate_stamps() == {Stamp(100, 5): [0, 1]}


def test_large_graph_parses(tmp_path: Path) -> None:
    graph = _synthetic_graph(20_000, seed=3)
    out = tmp_path / "big.g2o"
    write_pose_graph(graph, out)
    again = read_pose_graph(out)
    assert len(again) == 20_000 and len(again.edges) == 20_002
    np.testing.assert_allclose(again.poses, graph.poses, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "header, sep",
    [
        ("# counter, sec, nsec, x, y, z, qx, qy, qz, qw", ", "),
        ("#counter,sec,nsec,x,y,z,qx,qy,qz,qw", ","),
        (None, " "),
    ],
)
def test_pose_csv_variants_with_counter(tmp_path: Path, header: str | None, sep: str) -> None:
    rows: list[list[float]] = [
        [5, 1769886345, 745156160, 0, 0, 0, 0, 0, 0, 1],
        [6, 1769886346, 5, 1.5, 2, 3, 0, 0, 1, 0],
    ]
    text = ([header] if header else []) + [sep.join(map(str, r)) for r in rows]
    path = tmp_path / "slam-poses.csv"
    path.write_text("\n".join(text) + "\n")
    table = read_poses_csv(path)
    np.testing.assert_array_equal(table.counters, [5, 6])
    assert table.stamps[1] == Stamp(1769886346, 5)
    np.testing.assert_allclose(table.poses[1][:3, 3], [1.5, 2, 3])
    np.testing.assert_allclose(table.poses[1][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-15)
    assert list(table.to_pose_graph().vertices) == [5, 6]


def test_pose_csv_without_header_nine_columns(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    path.write_text("10 20 1 2 3 0 0 0 1\n11 0 4 5 6 0 0 0 1\n")
    table = read_poses_csv(path)
    assert table.counters is None
    np.testing.assert_array_equal(table.stamps_ns, [10 * 10**9 + 20, 11 * 10**9])


def test_pose_csv_round_trip(tmp_path: Path) -> None:
    graph = _synthetic_graph(100)
    table = PoseTable.from_pose_graph(graph)
    out = tmp_path / "slam_poses.csv"
    write_poses_csv(table, out)
    assert out.read_text().splitlines()[0] == "# counter, sec, nsec, x, y, z, qx, qy, qz, qw"
    again = read_poses_csv(out)
    np.testing.assert_array_equal(again.counters, graph.ids)
    np.testing.assert_array_equal(again.stamps_ns, graph.stamps_ns)
    np.testing.assert_allclose(again.poses, graph.poses, rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    xyz=st.lists(
        st.tuples(*[st.floats(-1e7, 1e7, allow_nan=False, allow_subnormal=False)] * 3),
        min_size=1,
        max_size=5,
    ),
    nsec=st.integers(0, 999_999_999),
    info=st.floats(1e-9, 1e12),
)
def test_round_trip_property(xyz: list[tuple[float, float, float]], nsec: int, info: float) -> None:
    import tempfile

    n = len(xyz)
    poses = pose_matrix(np.array(xyz), np.tile([0.3, -0.1, 0.7, 0.5], (n, 1)))
    vertices = {k: Vertex(k, Stamp(1_600_000_000 + k, nsec), poses[k]) for k in range(n)}
    edges = [
        Edge(k, k + 1, relative_pose(poses[k], poses[k + 1]), np.eye(6) * info)
        for k in range(n - 1)
    ]
    graph = PoseGraph(vertices, edges)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "g.g2o"
        write_pose_graph(graph, out)
        again = read_pose_graph(out)
    assert [v.stamp for v in again.vertices.values()] == [v.stamp for v in vertices.values()]
    np.testing.assert_array_equal(again.positions, graph.positions)  # translations are exact
    np.testing.assert_allclose(again.poses[:, :3, :3], graph.poses[:, :3, :3], atol=1e-15)
    for e in again.edges:
        np.testing.assert_array_equal(e.information, np.eye(6) * info)
