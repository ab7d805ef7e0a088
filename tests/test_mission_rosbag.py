"""ROS bags written by rosbags' own writers (ROS 1, ROS 2 sqlite3, MCAP) from a simulated
mission read back as the same mission: nodes, GNSS, payloads and points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from standgrid.clouds import write_cloud
from standgrid.errors import BagFormatError
from standgrid.geometry import invert_pose, pose_matrix
from standgrid.mission.build import build_payloads
from standgrid.mission.gridmap import GRIDMAP_MSGS_ROS1, register_gridmap_types
from standgrid.mission.opening import open_mission
from standgrid.mission.posegraph import write_pose_graph
from standgrid.mission.rosbag import bag_to_mission
from standgrid.mission.sensors import write_gnss
from standgrid.simulate import simulate_mission

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

#: GGA quality -> NavSatStatus.
STATUS = {0: -1, 1: 0, 2: 1, 4: 2, 5: 2}
#: A lidar mounted 0.3 m above and 0.1 m ahead of the base, yawed 90 degrees.
T_BASE_LIDAR = pose_matrix([0.1, 0.0, 0.3], Rotation.from_euler("z", 90, degrees=True).as_quat())


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Any:
    root = tmp_path_factory.mktemp("sim")
    return simulate_mission(root, seed=5, epoch=1, area=50.0, points_per_payload=1500)


@pytest.fixture(scope="module")
def scans(sim: Any) -> dict[int, np.ndarray]:
    """Per-node scans (base frame, xyz + intensity): each simulated payload cut into
    contiguous parts, one per node of its span, moved into that node's base frame."""
    mission = open_mission(sim.mission_dir)
    poses = {v.id: v.pose for v in mission.graph.vertices.values()}
    out: dict[int, np.ndarray] = {}
    for span, payload in zip(
        sim.spans, sorted(mission.payloads, key=lambda p: p.stamp), strict=True
    ):
        cloud = mission.load_base(payload)
        members = list(range(span.first, span.last + 1))
        parts = np.array_split(np.arange(len(cloud)), len(members))
        for node, idx in zip(members, parts, strict=True):
            part = cloud.select(idx).transformed(invert_pose(poses[node]) @ poses[span.centre])
            out[node] = np.column_stack([part.xyz, part.fields["intensity"]])
    return out


def _ns_time(ts: Any, ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ts: Any, ns: int, frame: str) -> Any:
    cls = ts.types["std_msgs/msg/Header"]
    extra = {"seq": 0} if "seq" in cls.__dataclass_fields__ else {}
    return cls(stamp=_ns_time(ts, ns), frame_id=frame, **extra)


def _cloud_msg(ts: Any, ns: int, frame: str, pts: np.ndarray, layout: str) -> Any:
    """PointCloud2 in three layouts: float32 flat; float64 organised with padding and a NaN
    row; float64 big-endian with the fields in reverse order."""
    field_t = ts.types["sensor_msgs/msg/PointField"]
    if layout == "f32":
        dt = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4"] * 4})
        rows, height = pts, 1
    elif layout == "f64_organised":
        dt = np.dtype(
            {
                "names": ["x", "y", "z", "intensity"],
                "formats": ["<f8"] * 3 + ["<f4"],
                "offsets": [0, 8, 16, 28],
                "itemsize": 40,
            }
        )
        nan_row = np.full((2 if len(pts) % 2 == 0 else 1, 4), np.nan)
        rows, height = np.vstack([pts, nan_row]), 2
        if len(rows) % 2:
            rows = np.vstack([rows, np.full((1, 4), np.nan)])
    else:
        dt = np.dtype(
            {
                "names": ["intensity", "z", "y", "x"],
                "formats": [">f4"] + [">f8"] * 3,
                "offsets": [0, 4, 12, 20],
                "itemsize": 28,
            }
        )
        rows, height = pts, 1
    arr = np.zeros(len(rows), dtype=dt)
    for k, name in enumerate(("x", "y", "z", "intensity")):
        arr[name] = rows[:, k]
    codes = {"f4": 7, "f8": 8}
    fields = [
        field_t(name=n, offset=dt.fields[n][1], datatype=codes[dt.fields[n][0].str[1:]], count=1)
        for n in dt.names
    ]
    width = len(rows) // height
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, ns, frame),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=layout == "f64_be",
        point_step=dt.itemsize,
        row_step=dt.itemsize * width,
        data=np.frombuffer(arr.tobytes(), np.uint8),
        is_dense=False,
    )


def _pose_parts(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()


def _transform_stamped(ts: Any, ns: int, parent: str, child: str, T: np.ndarray) -> Any:
    t, q = _pose_parts(T)
    types = ts.types
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, ns, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def _odometry(ts: Any, ns: int, T: np.ndarray) -> Any:
    t, q = _pose_parts(T)
    types = ts.types
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
        orientation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    zero3 = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return types["nav_msgs/msg/Odometry"](
        header=_header(ts, ns, "odom"),
        child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3),
            covariance=np.zeros(36),
        ),
    )


def _navsat(ts: Any, fixes: Any, k: int) -> Any:
    types = ts.types
    h, v = fixes.h_std[k], fixes.v_std[k]
    cov = np.diag([h * h / 2, h * h / 2, v * v]).ravel()
    status = types["sensor_msgs/msg/NavSatStatus"](status=STATUS[int(fixes.quality[k])], service=1)
    return types["sensor_msgs/msg/NavSatFix"](
        header=_header(ts, int(fixes.stamps_ns[k]), "gps"),
        status=status,
        latitude=fixes.lat[k],
        longitude=fixes.lon[k],
        altitude=fixes.alt[k],
        position_covariance=cov,
        position_covariance_type=2,
    )


def _messages(sim: Any, scans: dict[int, np.ndarray], ts: Any, use_tf: bool, layout: str):
    """(topic, msgtype, stamp, message) in time order: a scan and a pose at every node and
    one more a tenth of the way to the next node (not a node), GNSS fixes."""
    mission = open_mission(sim.mission_dir)
    vertices = sorted(mission.graph.vertices.values(), key=lambda v: v.stamp)
    out = []
    if use_tf:
        static = ts.types["tf2_msgs/msg/TFMessage"](
            transforms=[
                _transform_stamped(ts, vertices[0].stamp.ns, "base_link", "lidar", T_BASE_LIDAR)
            ]
        )
        out.append(("/tf_static", "tf2_msgs/msg/TFMessage", vertices[0].stamp.ns - 1, static))
    for k, v in enumerate(vertices):
        stamps = [(v.stamp.ns, v.pose, scans[v.id])]
        if k + 1 < len(vertices):
            nxt = vertices[k + 1]
            mid_ns = v.stamp.ns + (nxt.stamp.ns - v.stamp.ns) // 10
            mid = v.pose.copy()
            mid[:3, 3] = 0.9 * v.pose[:3, 3] + 0.1 * nxt.pose[:3, 3]
            stamps.append((mid_ns, mid, scans[v.id][:5]))
        for ns, pose, pts in stamps:
            if use_tf:
                tf = ts.types["tf2_msgs/msg/TFMessage"](
                    transforms=[_transform_stamped(ts, ns, "map", "base_link", pose)]
                )
                out.append(("/tf", "tf2_msgs/msg/TFMessage", ns, tf))
                lidar_pts = pts.copy()
                lidar_pts[:, :3] = (
                    invert_pose(T_BASE_LIDAR)[:3, :3] @ pts[:, :3].T
                ).T + invert_pose(T_BASE_LIDAR)[:3, 3]
                msg = _cloud_msg(ts, ns, "lidar", lidar_pts, layout)
            else:
                out.append(("/odom", "nav_msgs/msg/Odometry", ns, _odometry(ts, ns, pose)))
                msg = _cloud_msg(ts, ns, "base_link", pts, layout)
            out.append(("/points", "sensor_msgs/msg/PointCloud2", ns, msg))
    fixes = mission.gnss
    for k in range(len(fixes)):
        ns = int(fixes.stamps_ns[k])
        out.append(("/fix", "sensor_msgs/msg/NavSatFix", ns, _navsat(ts, fixes, k)))
    out.sort(key=lambda m: m[2])
    return out


def write_bag(
    kind: str, path: Path, sim: Any, scans: dict[int, np.ndarray], extra: Any = None
) -> Path:
    """The simulated mission as a bag (``extra(ts, ros1)``: more messages, GridMaps)."""
    if kind == "ros1":
        ts = get_typestore(Stores.ROS1_NOETIC)
        # tf2_msgs is not in rosbags' ROS 1 store: register it from its .msg definition.
        ts.register(
            get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
            )
        )
        register_gridmap_types(ts, GRIDMAP_MSGS_ROS1)
        messages = _messages(sim, scans, ts, True, "f32") + (extra(ts, True) if extra else [])
        with Writer1(path) as writer:
            conns: dict[str, Any] = {}
            for topic, msgtype, ns, msg in sorted(messages, key=lambda m: m[2]):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(conns[topic], ns, ts.serialize_ros1(msg, msgtype))
        return path
    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
    layout = "f64_organised" if kind == "sqlite3" else "f64_be"
    register_gridmap_types(ts)
    messages = _messages(sim, scans, ts, False, layout) + (extra(ts, False) if extra else [])
    with Writer2(path, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, msgtype, ns, msg in sorted(messages, key=lambda m: m[2]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], ns, ts.serialize_cdr(msg, msgtype))
    return path


@pytest.fixture(scope="module")
def reference(sim: Any, scans: dict[int, np.ndarray], tmp_path_factory: pytest.TempPathFactory):
    """The simulator's per-node scans as a folder, through `payloads build`."""
    root = tmp_path_factory.mktemp("ref")
    src = root / "scans"
    mission = open_mission(sim.mission_dir)
    (src / "individual_clouds").mkdir(parents=True)
    for v in mission.graph.vertices.values():
        from standgrid.pointcloud import PointCloud

        pts = scans[v.id]
        write_cloud(
            PointCloud(pts[:, :3], {"intensity": pts[:, 3].astype(np.float32)}),
            src / "individual_clouds" / v.stamp.filename("cloud", "pcd"),
            viewpoint=v.pose,
            xyz_dtype=np.float64,
        )
    write_pose_graph(mission.graph, src / "slam_pose_graph.g2o")
    (src / "gnss").mkdir()
    write_gnss(mission.gnss, src / "gnss" / "fixes.txt")
    return open_mission(build_payloads(src, root / "built"))


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_bag_gives_the_simulated_mission(
    kind: str, sim: Any, scans: dict, reference: Any, tmp_path: Path
) -> None:
    bag = write_bag(kind, tmp_path / ("sim.bag" if kind == "ros1" else "sim_bag"), sim, scans)
    own = open_mission(sim.mission_dir)  # the simulator's own folder
    want_v = sorted(own.graph.vertices.values(), key=lambda v: v.stamp)
    xyz = np.array([v.pose[:3, 3] for v in want_v])
    chords = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    # The simulator's nodes are 1.5 m apart along the path (less in a straight line at the
    # lane ends); a node spacing just below the shortest step keeps exactly those nodes.
    spacing = 0.9 * float(chords.min())
    report = bag_to_mission(
        [bag], tmp_path / "2024-05-14-wytham-anymal-coyote", node_distance=spacing
    )
    got = open_mission(report.output)
    got_v = sorted(got.graph.vertices.values(), key=lambda v: v.stamp)
    assert [v.stamp for v in got_v] == [v.stamp for v in want_v]
    assert report.scans_between_nodes == len(want_v) - 1 and report.scans_without_pose == 0
    pose_err = max(np.abs(a.pose - b.pose).max() for a, b in zip(got_v, want_v, strict=True))
    assert pose_err < 1e-12
    # GNSS: same fixes, covariance back to the same h_std / v_std.
    np.testing.assert_array_equal(got.gnss.stamps_ns, own.gnss.stamps_ns)
    np.testing.assert_allclose(got.gnss.lat, own.gnss.lat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.gnss.h_std, own.gnss.h_std, rtol=1e-12)
    np.testing.assert_allclose(got.gnss.v_std, own.gnss.v_std, rtol=1e-12)
    np.testing.assert_array_equal(got.gnss.quality, own.gnss.quality)
    # Payloads: the same stamps and points as `payloads build` of the same scans.
    assert [p.stamp for p in got.payloads] == [p.stamp for p in reference.payloads]
    tol = 1e-5 if kind == "ros1" else 1e-9  # float32 points in the ROS 1 bag
    worst = 0.0
    for a, b in zip(got.payloads, reference.payloads, strict=True):
        ca, cb = got.load_base(a), reference.load_base(b)
        assert len(ca) == len(cb)
        worst = max(worst, float(np.abs(ca.xyz - cb.xyz).max()))
    assert worst < tol
    if kind == "sqlite3":
        assert report.nan_points_dropped > 0
    # Points: every point of the simulator's own payload folder, in the map frame.
    mine = np.vstack([c.xyz for _, c in got.iter_payload_clouds()])
    theirs = np.vstack([c.xyz for _, c in own.iter_payload_clouds()])
    assert len(mine) == len(theirs)
    dist, _ = cKDTree(mine).query(theirs)
    print(
        f"{kind}: {len(got_v)} nodes, {len(got.payloads)} payloads, {len(mine)} points, "
        f"pose err {pose_err:.1e}, payload err {worst:.1e} m, map NN max {dist.max():.1e} m"
    )
    assert dist.max() < tol


def test_default_node_spacing_is_the_loggers(sim: Any, scans: dict, tmp_path: Path) -> None:
    """With the real logger's 1 m spacing, every node is at least 1 m from the previous one
    and every scan that is not a node is within 1 m of the last node."""
    bag = write_bag("mcap", tmp_path / "bag", sim, scans)
    report = bag_to_mission([bag], tmp_path / "m")
    vs = sorted(open_mission(report.output).graph.vertices.values(), key=lambda v: v.stamp)
    steps = np.linalg.norm(np.diff([v.pose[:3, 3] for v in vs], axis=0), axis=1)
    assert steps.min() >= 1.0 and report.nodes + report.scans_between_nodes == report.scans
    assert report.scans_between_nodes >= len(scans) - 1


def test_malformed_bag_is_a_typed_error(tmp_path: Path, sim: Any, scans: dict) -> None:
    good = write_bag("ros1", tmp_path / "good.bag", sim, scans)
    bad = tmp_path / "broken.bag"
    bad.write_bytes(good.read_bytes()[:3000])
    with pytest.raises(BagFormatError, match=r"broken\.bag") as info:
        bag_to_mission([bad], tmp_path / "out")
    assert isinstance(info.value, ValueError) and not (tmp_path / "out").exists()
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    with pytest.raises(BagFormatError, match=r"junk\.bag"):
        bag_to_mission([junk], tmp_path / "out")


# --- grid_map_msgs/GridMap: payload elevation maps -----------------------------------------

#: A GridMap's side (m) and cells, and its buffer's start indices (a scrolled circular buffer).
GRID_SIDE, GRID_RES, GRID_START = 12.0, 0.5, (5, 17)


def _slope(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Heights of the maps published in the map frame: not symmetric in x and y."""
    return 100.0 + 0.3 * x - 0.1 * y + 0.5 * np.sin(0.4 * x)


def _gridmap(ts: Any, ns: int, frame: str, heights: np.ndarray, centre: Any, ros1: bool) -> Any:
    """A GridMap as grid_map writes it: layer matrices with the row index along -x and the
    column index along -y, column-major, scrolled by GRID_START; an extra layer first."""
    types = ts.types
    matrix = heights.T[::-1, ::-1]
    rows, cols = matrix.shape
    buffer = np.roll(matrix, GRID_START, axis=(0, 1))
    dim = types["std_msgs/msg/MultiArrayDimension"]
    layout = types["std_msgs/msg/MultiArrayLayout"](
        dim=[
            dim(label="column_index", size=cols, stride=rows * cols),
            dim(label="row_index", size=rows, stride=rows),
        ],
        data_offset=0,
    )
    array = types["std_msgs/msg/Float32MultiArray"]
    data = [
        array(layout=layout, data=np.zeros(rows * cols, np.float32)),
        array(layout=layout, data=buffer.ravel(order="F").astype(np.float32)),
    ]
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=centre[0], y=centre[1], z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    info = {
        "resolution": GRID_RES,
        "length_x": rows * GRID_RES,
        "length_y": cols * GRID_RES,
        "pose": pose,
    }
    common = {
        "layers": ["variance", "elevation"],
        "basic_layers": ["elevation"],
        "data": data,
        "outer_start_index": GRID_START[0],
        "inner_start_index": GRID_START[1],
    }
    info_t, map_t = types["grid_map_msgs/msg/GridMapInfo"], types["grid_map_msgs/msg/GridMap"]
    if ros1:
        return map_t(info=info_t(header=_header(ts, ns, frame), **info), **common)
    return map_t(header=_header(ts, ns, frame), info=info_t(**info), **common)


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_gridmaps_in_a_bag_become_the_payloads_elevation_maps(
    kind: str, sim: Any, scans: dict, tmp_path: Path
) -> None:
    """One GridMap per node: ROS 1 in the map frame (heights of a known surface), ROS 2 in
    the base frame (known arrays). Each payload gets the one of its stamp, in its base frame:
    placed with the payload's pose it is the surface, or the very array published."""
    vertices = sorted(open_mission(sim.mission_dir).graph.vertices.values(), key=lambda v: v.stamp)
    n = round(GRID_SIDE / GRID_RES)
    centres = -GRID_SIDE / 2 + (np.arange(n) + 0.5) * GRID_RES
    published: dict[int, np.ndarray] = {}

    def gridmaps(ts: Any, ros1: bool) -> list[Any]:
        out = []
        for v in vertices:
            if ros1:  # in the map frame, around the node (cell edges on the 0.5 m lattice)
                centre = np.round(v.pose[:2, 3] / GRID_RES) * GRID_RES
                x, y = np.meshgrid(centre[0] + centres, centre[1] + centres)
                heights, frame = _slope(x, y).astype(np.float32), "map"
            else:  # in the base frame, a known array (not symmetric)
                centre = np.array([0.5, -0.25])
                heights = np.arange(n * n, dtype=np.float32).reshape(n, n) + v.id * 1e3
                frame = "base_link"
            published[v.stamp.ns] = heights
            msg = _gridmap(ts, v.stamp.ns, frame, heights, centre, ros1)
            out.append(("/elevation_map", "grid_map_msgs/msg/GridMap", v.stamp.ns, msg))
        return out

    bag = write_bag(kind, tmp_path / ("m.bag" if kind == "ros1" else "m"), sim, scans, gridmaps)
    xyz = np.array([v.pose[:3, 3] for v in vertices])
    spacing = 0.9 * float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).min())
    report = bag_to_mission(
        [bag], tmp_path / "2024-05-14-wytham-anymal-coyote", node_distance=spacing
    )
    got = open_mission(report.output)
    assert report.topics["grid_map"] == "/elevation_map" and report.grid_maps == len(vertices)
    assert report.elevation_maps == len(got.payloads) > 1
    for payload in got.payloads:
        emap = got.load_elevation_map(payload)
        assert emap.heights.shape == (n, n) and emap.resolution == GRID_RES
        if kind == "ros1":
            pts = emap.cell_points() @ got.pose_of(payload)[:3, :3].T + got.pose_of(payload)[:3, 3]
            np.testing.assert_allclose(pts[:, 2], _slope(pts[:, 0], pts[:, 1]), atol=1e-4)
        else:
            np.testing.assert_array_equal(emap.heights, published[payload.stamp.ns])
            assert emap.origin == (-GRID_SIDE / 2, -GRID_SIDE / 2)
            np.testing.assert_allclose(emap.pose[:3, 3], [0.5, -0.25, 0.0], atol=1e-9)


def test_a_gridmap_without_the_layer_is_a_bag_format_error(
    sim: Any, scans: dict, tmp_path: Path
) -> None:
    stamp = min(v.stamp.ns for v in open_mission(sim.mission_dir).graph.vertices.values())

    def one(ts: Any, ros1: bool) -> list[Any]:
        msg = _gridmap(ts, stamp, "base_link", np.zeros((4, 4), np.float32), (0, 0), ros1)
        return [("/elevation_map", "grid_map_msgs/msg/GridMap", stamp, msg)]

    bag = write_bag("mcap", tmp_path / "bag", sim, scans, one)
    with pytest.raises(BagFormatError, match="no GridMap layer 'height'"):
        bag_to_mission([bag], tmp_path / "m", elevation_layer="height")
