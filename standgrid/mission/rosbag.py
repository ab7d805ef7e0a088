"""ROS bags (ROS 1 ``.bag``, ROS 2 sqlite3 and MCAP) to a canonical mission, with ``rosbags``.

``sensor_msgs/PointCloud2`` scans become per-node scans in the base frame, selected as the
VILENS logger does: a new node whenever the robot has moved ``node_distance`` (1 m) since
the last node. Poses come from ``nav_msgs/Odometry`` (interpolated at the scan stamp) or,
without odometry, from ``/tf`` (map -> base chain). ``sensor_msgs/NavSatFix`` gives GNSS
fixes with their covariance. The scans are then accumulated into payloads by
:func:`standgrid.mission.build.build_payloads`, exactly as ``payloads build`` does.
``grid_map_msgs/GridMap`` messages (:mod:`standgrid.mission.gridmap`) give each payload the
elevation map nearest its stamp, in its base frame (``payloads/elevation/``).
"""

from __future__ import annotations

import itertools
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import temporary_sibling
from standgrid.errors import OVERWRITE_HINT, BagFormatError, MissionNameError, OutputExistsError
from standgrid.geometry import Matrix4, invert_pose, pose_matrix, relative_pose
from standgrid.mission.gridmap import (
    GRIDMAP_TYPE,
    gridmap_header,
    gridmap_layer,
    register_gridmap_types,
)
from standgrid.mission.sensors import GnssFixes
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOM_TYPE = "nav_msgs/msg/Odometry"
GNSS_TYPE = "sensor_msgs/msg/NavSatFix"
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: The VILENS logger's node spacing (real graphs: every step 1.0-1.4 m).
NODE_DISTANCE = 1.0
#: Largest time (s) between a payload and the GridMap message taken as its elevation map.
MAX_MAP_GAP_S = 5.0
#: PointField datatype -> numpy type code.
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
#: NavSatStatus -> NMEA GGA quality (-1 no fix: 0, fix: 1, SBAS: 2 (DGPS), GBAS: 4 (RTK)).
_QUALITY = {-1: 0, 0: 1, 1: 2, 2: 4}


@dataclass
class BagReport:
    """What was read from the bags and what was left out, with reasons."""

    output: Path
    topics: dict[str, str | None]
    scans: int = 0
    nodes: int = 0
    scans_between_nodes: int = 0
    scans_without_pose: int = 0
    nan_points_dropped: int = 0
    points: int = 0
    gnss_fixes: int = 0
    gnss_without_position: int = 0
    payloads: int = 0
    grid_maps: int = 0
    elevation_maps: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out["output"] = str(self.output)
        return out


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _fail(paths: Sequence[Path], message: str, exc: BaseException | None = None) -> BagFormatError:
    return BagFormatError(message, path=paths[0] if len(paths) == 1 else Path(paths[0]).parent)


def _pick(
    paths: Sequence[Path], by_type: dict[str, list[str]], msgtype: str, given: str | None
) -> str | None:
    """The topic of ``msgtype``: the one given, or the only one in the bags."""
    topics = by_type.get(msgtype, [])
    if given is not None:
        if given not in topics:
            raise _fail(paths, f"no {msgtype} topic {given!r} (have {topics})")
        return given
    if len(topics) > 1:
        raise _fail(paths, f"several {msgtype} topics {topics}: say which one")
    return topics[0] if topics else None


class PoseTrack:
    """Stamped poses ``T_parent_child``, interpolated (lerp + slerp) between samples."""

    def __init__(self, stamps_ns: NDArray[np.int64], poses: Matrix4) -> None:
        from scipy.spatial.transform import Rotation, Slerp

        order = np.argsort(stamps_ns, kind="stable")
        stamps, idx = np.unique(stamps_ns[order], return_index=True)
        self.stamps = stamps
        self.poses = poses[order][idx]
        self._slerp = (
            Slerp(stamps.astype(np.float64), Rotation.from_matrix(self.poses[:, :3, :3]))
            if len(stamps) > 1
            else None
        )

    def at(self, ns: int) -> Matrix4 | None:
        """The pose at ``ns``; exact at a sample stamp; None outside the track."""
        k = int(np.searchsorted(self.stamps, ns))
        if k < len(self.stamps) and self.stamps[k] == ns:
            return np.array(self.poses[k])
        if k == 0 or k == len(self.stamps) or self._slerp is None:
            return None
        t0, t1 = self.stamps[k - 1], self.stamps[k]
        w = (ns - t0) / (t1 - t0)
        pose = np.eye(4)
        pose[:3, :3] = self._slerp([float(ns)]).as_matrix()[0]
        pose[:3, 3] = (1 - w) * self.poses[k - 1][:3, 3] + w * self.poses[k][:3, 3]
        return pose


def _transform(t: Any) -> Matrix4:
    tr, q = t.translation, t.rotation
    return pose_matrix([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w])


class TfTree:
    """``/tf`` and ``/tf_static``: static edges and interpolated dynamic ones."""

    def __init__(self) -> None:
        self.static: dict[tuple[str, str], Matrix4] = {}
        self.dynamic: dict[tuple[str, str], tuple[list[int], list[Matrix4]]] = {}
        self._tracks: dict[tuple[str, str], PoseTrack] = {}

    def add(self, msg: Any, static: bool) -> None:
        for t in msg.transforms:
            key = (t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/"))
            if static:
                self.static[key] = _transform(t.transform)
            else:
                stamps, poses = self.dynamic.setdefault(key, ([], []))
                stamps.append(_stamp_ns(t.header))
                poses.append(_transform(t.transform))

    def frames(self) -> set[str]:
        return {f for key in (*self.static, *self.dynamic) for f in key}

    def root_of(self, frame: str) -> str:
        parents = {c: p for p, c in (*self.static, *self.dynamic)}
        seen = {frame}
        while frame in parents and parents[frame] not in seen:
            frame = parents[frame]
            seen.add(frame)
        return frame

    def lookup(self, target: str, source: str, ns: int) -> Matrix4 | None:
        """T_target_source at ``ns`` (None when the frames are not connected then)."""
        if target == source:
            return np.eye(4)
        edges: dict[str, list[tuple[str, tuple[str, str], bool]]] = {}
        for p, c in (*self.static, *self.dynamic):
            edges.setdefault(p, []).append((c, (p, c), False))
            edges.setdefault(c, []).append((p, (p, c), True))
        previous: dict[str, tuple[str, tuple[str, str], bool]] = {}
        queue, seen = [target], {target}
        while queue:
            frame = queue.pop(0)
            for nxt, key, inverse in edges.get(frame, []):
                if nxt not in seen:
                    seen.add(nxt)
                    previous[nxt] = (frame, key, inverse)
                    queue.append(nxt)
        if source not in previous:
            return None
        pose, frame = np.eye(4), source
        while frame != target:
            parent, key, inverse = previous[frame]
            step = self._edge(key, ns)
            if step is None:
                return None
            # step is T_parent_child of the tf edge; walking towards target.
            pose = (invert_pose(step) if inverse else step) @ pose
            frame = parent
        return pose

    def _edge(self, key: tuple[str, str], ns: int) -> Matrix4 | None:
        if key in self.static:
            return self.static[key]
        if key not in self._tracks:
            stamps, poses = self.dynamic[key]
            self._tracks[key] = PoseTrack(np.array(stamps, np.int64), np.stack(poses))
        return self._tracks[key].at(ns)


def pointcloud2_xyz(msg: Any) -> tuple[PointCloud, int]:
    """A PointCloud2 as a float64 cloud (other numeric fields kept, first element of each),
    any field layout, organised or not, either byte order; non-finite points dropped and
    counted."""
    fields = {f.name: f for f in msg.fields}
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"PointCloud2 without x/y/z fields (has {sorted(fields)})")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        code = _FIELD_TYPES.get(int(f.datatype))
        if code is None or f.name in names:
            continue
        names.append(f.name)
        formats.append(order + code)
        offsets.append(int(f.offset))
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)}
    )
    width, height, step = int(msg.width), int(msg.height), int(msg.point_step)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    needed = height * int(msg.row_step)
    if data.size < needed or int(msg.row_step) < width * step:
        raise ValueError(f"PointCloud2 data holds {data.size} bytes, header says {needed}")
    rows = data[:needed].reshape(height, int(msg.row_step))[:, : width * step]
    points = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    xyz = np.column_stack([points[a].astype(np.float64) for a in ("x", "y", "z")])
    ok = np.isfinite(xyz).all(axis=1)
    extra = {
        n: np.asarray(points[n][ok]).astype(points[n].dtype.newbyteorder("="))
        for n in names
        if n not in ("x", "y", "z")
    }
    return PointCloud(xyz[ok], extra), int((~ok).sum())


def bag_to_mission(
    bags: Sequence[str | Path],
    out: str | Path,
    *,
    cloud_topic: str | None = None,
    odom_topic: str | None = None,
    gnss_topic: str | None = None,
    base_frame: str | None = None,
    map_frame: str | None = None,
    node_distance: float = NODE_DISTANCE,
    distance: float = 20.0,
    area: float | None = None,
    overwrite: bool = False,
    grid_map_topic: str | None = None,
    elevation_layer: str = "elevation",
    max_map_gap: float = MAX_MAP_GAP_S,
) -> BagReport:
    """Read ``bags`` (ROS 1 files, or one ROS 2 folder) and write a canonical mission.

    A ``grid_map_msgs/GridMap`` topic (``grid_map_topic``, or the only one) gives each
    payload the ``elevation_layer`` of the message nearest its stamp (within
    ``max_map_gap`` seconds), written as its elevation map.

    Raises :class:`BagFormatError` (naming the bag) when a bag cannot be read or lacks
    clouds or poses.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from standgrid.clouds import write_cloud
    from standgrid.mission.build import build_payloads
    from standgrid.mission.metadata import metadata_from_folder_name, write_metadata
    from standgrid.mission.posegraph import Edge, PoseGraph, Vertex, write_pose_graph
    from standgrid.mission.sensors import write_gnss

    paths = [Path(b) for b in bags]
    out_path = Path(out)
    if out_path.exists() and not overwrite:
        raise OutputExistsError(f"exists ({OVERWRITE_HINT})", path=out_path)
    if node_distance < 0:
        raise ValueError(f"node_distance must be >= 0, got {node_distance}")
    report = BagReport(out_path, topics={})
    try:
        typestore = get_typestore(Stores.LATEST)
        register_gridmap_types(typestore)
        reader = AnyReader(paths, default_typestore=typestore)
        reader.open()
    except Exception as exc:  # rosbags raises its own, ValueError, KeyError... on bad files
        raise BagFormatError(f"not a readable ROS bag: {exc}", path=paths[0]) from exc
    try:
        by_type: dict[str, list[str]] = {}
        for conn in reader.connections:
            topics = by_type.setdefault(conn.msgtype, [])
            if conn.topic not in topics:
                topics.append(conn.topic)
        clouds = _pick(paths, by_type, CLOUD_TYPE, cloud_topic)
        odom = _pick(paths, by_type, ODOM_TYPE, odom_topic)
        gnss = _pick(paths, by_type, GNSS_TYPE, gnss_topic)
        grid_map = _pick(paths, by_type, GRIDMAP_TYPE, grid_map_topic)
        report.topics = {
            "clouds": clouds,
            "odometry": odom,
            "gnss": gnss,
            "tf": "/tf" if TF_TYPE in by_type else None,
        }
        if grid_map is not None:
            report.topics["grid_map"] = grid_map
        if clouds is None:
            raise _fail(paths, f"no {CLOUD_TYPE} topic (topics: {sorted(by_type)})")
        tf = TfTree()
        odo_ns: list[int] = []
        odo_poses: list[Matrix4] = []
        odo_frames: set[tuple[str, str]] = set()
        fixes: list[tuple[int, float, float, float, int, float, float]] = []
        wanted = [c for c in reader.connections if c.topic in {odom, gnss} or c.msgtype == TF_TYPE]
        for conn, _, raw in reader.messages(connections=wanted):
            msg = _decode(reader, raw, conn, paths)
            if conn.msgtype == TF_TYPE:
                tf.add(msg, static=conn.topic.endswith("tf_static"))
            elif conn.topic == odom:
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                odo_ns.append(_stamp_ns(msg.header))
                odo_poses.append(pose_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w]))
                odo_frames.add((msg.header.frame_id.lstrip("/"), msg.child_frame_id.lstrip("/")))
            else:
                fixes.append(_fix(msg))
        if odom is not None and odo_ns:
            if len(odo_frames) > 1:
                raise _fail(paths, f"odometry {odom} changes frames: {sorted(odo_frames)}")
            parent, child = next(iter(odo_frames))
            base = base_frame or child
            track = PoseTrack(np.array(odo_ns, np.int64), np.stack(odo_poses))

            def pose_at(ns: int) -> Matrix4 | None:
                pose = track.at(ns)
                if pose is None or base == child:
                    return pose
                extra = tf.lookup(child, base, ns)
                return None if extra is None else pose @ extra

            map_name = parent
        else:
            frames = tf.frames()
            base = base_frame or next(
                (f for f in ("base_link", "base", "base_footprint") if f in frames), ""
            )
            if not base:
                raise _fail(paths, "no odometry and no tf base frame (give base_frame)")
            map_name = map_frame or tf.root_of(base)

            def pose_at(ns: int) -> Matrix4 | None:
                return tf.lookup(map_name, base, ns)

        tmp = temporary_sibling(out_path)
        try:
            scan_dir = tmp / "individual_clouds"
            scan_dir.mkdir(parents=True)
            vertices: list[Vertex] = []
            cloud_conns = [c for c in reader.connections if c.topic == clouds]
            for conn, _, raw in reader.messages(connections=cloud_conns):
                msg = _decode(reader, raw, conn, paths)
                report.scans += 1
                ns = _stamp_ns(msg.header)
                pose = pose_at(ns)
                if pose is None:
                    report.scans_without_pose += 1
                    continue
                if vertices and np.linalg.norm(pose[:3, 3] - vertices[-1].pose[:3, 3]) < (
                    node_distance
                ):
                    report.scans_between_nodes += 1
                    continue
                try:
                    cloud, dropped = pointcloud2_xyz(msg)
                except ValueError as exc:
                    raise _fail(paths, f"{clouds} at {Stamp.from_ns(ns)}: {exc}") from exc
                frame = msg.header.frame_id.lstrip("/")
                if frame == map_name:
                    to_base: Matrix4 | None = invert_pose(pose)
                else:
                    to_base = tf.lookup(base, frame, ns) if frame != base else np.eye(4)
                if to_base is None:
                    raise _fail(paths, f"no transform from cloud frame {frame!r} to {base!r}")
                if not np.array_equal(to_base, np.eye(4)):
                    cloud = cloud.transformed(to_base)
                report.nan_points_dropped += dropped
                report.points += len(cloud)
                stamp = Stamp.from_ns(ns)
                vertices.append(Vertex(len(vertices), stamp, pose))
                write_cloud(
                    cloud,
                    scan_dir / stamp.filename("cloud", "pcd"),
                    viewpoint=pose,
                    xyz_dtype=np.float64,
                )
            if not vertices:
                raise _fail(
                    paths, f"no scan of {clouds} has a pose (map {map_name!r}, base {base!r})"
                )
            report.nodes = len(vertices)
            edges = [
                Edge(a.id, b.id, relative_pose(a.pose, b.pose), np.eye(6))
                for a, b in itertools.pairwise(vertices)
            ]
            graph = PoseGraph({v.id: v for v in vertices}, edges, platform_id=0)
            write_pose_graph(graph, tmp / "slam_pose_graph.g2o")
            good = [f for f in fixes if np.isfinite(f[1]) and np.isfinite(f[2])]
            report.gnss_without_position = len(fixes) - len(good)
            report.gnss_fixes = len(good)
            if good:
                cols = list(zip(*sorted(good), strict=True))
                (tmp / "gnss").mkdir()
                write_gnss(
                    GnssFixes(
                        np.array(cols[0], np.int64),
                        np.array(cols[1]),
                        np.array(cols[2]),
                        np.array(cols[3]),
                        np.array(cols[4], np.int8),
                        np.array(cols[5]),
                        np.array(cols[6]),
                    ),
                    tmp / "gnss" / "fixes.txt",
                )
            try:
                write_metadata(metadata_from_folder_name(out_path.name), tmp / "metadata.yaml")
            except MissionNameError:
                report.notes.append(f"{out_path.name}: not a conventional name, no metadata.yaml")
            build_payloads(tmp, out_path, distance=distance, area=area, overwrite=overwrite)
            if grid_map is not None:

                def frame_pose(frame: str, ns: int) -> Matrix4 | None:
                    """T_map_frame of a GridMap's frame at its stamp."""
                    if frame == map_name:
                        return np.eye(4)
                    return pose_at(ns) if frame == base else tf.lookup(map_name, frame, ns)

                maps = _GridMaps(grid_map, elevation_layer, max_map_gap, frame_pose)
                maps.write(reader, out_path, paths, report)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    finally:
        reader.close()
    from standgrid.mission.opening import open_mission

    report.payloads = len(open_mission(out_path).payloads)
    return report


@dataclass
class _GridMaps:
    """The GridMap topic's messages into the payloads' elevation maps."""

    topic: str
    layer: str
    max_gap_s: float
    frame_pose: Any  # (frame, ns) -> T_map_frame or None

    def write(
        self, reader: Any, mission_dir: Path, paths: Sequence[Path], report: BagReport
    ) -> None:
        """Each payload of the written mission gets the layer of the message nearest its
        stamp (within ``max_gap_s``), in its base frame (``pose``: T_base_grid)."""
        from standgrid.mission.derived_maps import (
            ELEVATION_FOLDER,
            ELEVATION_PREFIX,
            write_elevation_npz,
        )
        from standgrid.mission.opening import open_mission

        mission = open_mission(mission_dir)
        stamps = np.array([p.stamp.ns for p in mission.payloads], np.int64)
        best: dict[int, tuple[int, Any]] = {}  # payload index -> (gap ns, message)
        conns = [c for c in reader.connections if c.topic == self.topic]
        for conn, _, raw in reader.messages(connections=conns):
            msg = _decode(reader, raw, conn, paths)
            report.grid_maps += 1
            ns = _stamp_ns(gridmap_header(msg))
            if self.layer not in msg.layers:  # a wrong layer name: said at once
                where = f"{self.topic} at {Stamp.from_ns(ns)}"
                raise BagFormatError(
                    f"{where}: no GridMap layer {self.layer!r} (layers: {list(msg.layers)})",
                    path=paths[0],
                )
            if not len(stamps):
                continue
            k = int(np.argmin(np.abs(stamps - ns)))
            gap = abs(int(stamps[k]) - ns)
            if gap <= self.max_gap_s * 1e9 and (k not in best or gap < best[k][0]):
                best[k] = (gap, msg)
        for k, (_, msg) in sorted(best.items()):
            payload = mission.payloads[k]
            header = gridmap_header(msg)
            ns, frame = _stamp_ns(header), header.frame_id.lstrip("/")
            where = f"{self.topic} at {Stamp.from_ns(ns)}"
            try:
                heights, res, corner, centre = gridmap_layer(msg, self.layer, where)
            except BagFormatError as exc:  # said of the bag
                raise BagFormatError(exc.message, path=paths[0]) from exc
            to_map = self.frame_pose(frame, ns)
            if to_map is None:
                report.notes.append(f"{where}: no pose of frame {frame!r}: map left out")
                continue
            at_centre = np.eye(4)
            at_centre[:2, 3] = centre
            pose = invert_pose(mission.pose_of(payload)) @ to_map @ at_centre
            name = payload.stamp.filename(ELEVATION_PREFIX, "npz")
            write_elevation_npz(mission_dir / ELEVATION_FOLDER / name, heights, res, corner, pose)
            report.elevation_maps += 1


def _decode(reader: Any, raw: bytes, conn: Any, paths: Sequence[Path]) -> Any:
    try:
        return reader.deserialize(raw, conn.msgtype)
    except Exception as exc:  # the deserialisers raise assorted errors on bad bytes
        raise _fail(
            paths,
            f"cannot decode a {conn.msgtype} message on {conn.topic}: {type(exc).__name__}: {exc}",
        ) from exc


def _fix(msg: Any) -> tuple[int, float, float, float, int, float, float]:
    """One NavSatFix: stamp, lat, lon, alt, GGA quality, horizontal RMS and vertical std
    from the ENU covariance (NaN when its type is unknown)."""
    cov = np.asarray(msg.position_covariance, dtype=np.float64)
    known = int(msg.position_covariance_type) != 0
    h_std = float(np.sqrt(cov[0] + cov[4])) if known else float("nan")
    v_std = float(np.sqrt(cov[8])) if known else float("nan")
    quality = _QUALITY.get(int(msg.status.status), 0)
    return (
        _stamp_ns(msg.header),
        float(msg.latitude),
        float(msg.longitude),
        float(msg.altitude),
        quality,
        h_std,
        v_std,
    )
