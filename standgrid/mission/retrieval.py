"""Retrieve a mission's payloads by data type or by map pose.

Retrieval by GNSS coordinate needs a georeference: it is
:func:`standgrid.georeference.retrieval.retrieve_payload_by_gnss` (the stage after this one).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import OrphanPayloadError, PayloadNotFoundError
from standgrid.geometry import transform_points
from standgrid.mission.model import Mission
from standgrid.mission.opening import open_mission
from standgrid.mission.payload import Payload, PayloadKind
from standgrid.stamps import Stamp

#: data_type aliases -> payload kind.
DATA_TYPES: dict[str, PayloadKind] = {
    "point_cloud": "point_cloud",
    "pointcloud": "point_cloud",
    "cloud": "point_cloud",
    "lidar": "point_cloud",
    "scan": "scan",
    "gnss": "gnss",
    "gps": "gnss",
    "imu": "imu",
    "image": "image",
    "images": "image",
    "camera": "image",
}


def _open(mission: str | Path | Mission) -> Mission:
    return mission if isinstance(mission, Mission) else open_mission(mission, strict=False)


def _node_ids(mission: Mission) -> dict[Stamp, int]:
    return {v.stamp: v.id for v in mission.vertices_by_stamp.values()}


def retrieve_payload_by_type(
    mission_folder_path: str | Path | Mission, data_type: str
) -> list[Payload]:
    """All payload records of one data type, in stamp order.

    ``data_type``: ``point_cloud`` (payload clouds), ``scan`` (per-node scans), ``gnss``,
    ``imu``, ``image``/``camera``. GNSS and IMU records are the per-payload files
    (``payloads/gnss``, ``payloads/imu``), or the full-rate ``gnss/fixes.txt`` as one record.
    Raises :class:`PayloadNotFoundError` for an unknown type.
    """
    kind: PayloadKind | None = DATA_TYPES.get(data_type.lower().replace("-", "_"))
    if kind is None:
        raise PayloadNotFoundError(
            f"unknown data type {data_type!r}; known: {', '.join(sorted(DATA_TYPES))}"
        )
    mission = _open(mission_folder_path)
    layout = mission.layout
    if kind == "point_cloud":
        return list(mission.payloads)
    if kind == "scan":
        return list(mission.scans)
    ids = _node_ids(mission)
    if kind == "image":
        return [
            Payload(i.stamp, ids.get(i.stamp), i.path, "base", {}, "image", i.camera)
            for i in mission.images
        ]
    files = layout.gnss_payloads if kind == "gnss" else layout.imu_payloads
    records = [Payload(f.stamp, ids.get(f.stamp), f.path, "base", {}, kind) for f in files]
    if (
        kind == "gnss"
        and layout.gnss_log is not None
        and mission.gnss is not None
        and len(mission.gnss)
    ):
        first = Stamp.from_ns(int(mission.gnss.stamps_ns[0]))
        records.insert(0, Payload(first, ids.get(first), layout.gnss_log, "base", {}, "gnss"))
    return records


def _query_point(slam_pose: ArrayLike) -> NDArray[np.float64]:
    """``(x, y, z)`` or a 4x4 pose -> a 3-D point; ``(x, y)`` stays 2-D (a horizontal query)."""
    arr = np.asarray(slam_pose, dtype=np.float64)
    if arr.shape == (4, 4):
        return arr[:3, 3].copy()
    if arr.shape in ((3,), (2,)):
        return arr.copy()
    raise ValueError(f"slam_pose must be (x, y, z), (x, y) or a 4x4 pose, got shape {arr.shape}")


def query_distances(query: ArrayLike, positions: ArrayLike) -> NDArray[np.float64]:
    """Distances from a retrieval query to map positions ``(n, 3)``: 3-D for ``(x, y, z)``,
    horizontal (x/y only) for an ``(x, y)`` query."""
    q = np.asarray(query, dtype=np.float64).ravel()
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return np.asarray(np.linalg.norm(pos[:, : len(q)] - q, axis=1), dtype=np.float64)


def footprint(mission: Mission, payload: Payload) -> NDArray[np.float64]:
    """Axis-aligned map-frame box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` of a payload:
    the eight corners of its base-frame bounding box, transformed by its pose (conservative)."""
    xyz = mission.load_base(payload).xyz
    if len(xyz) == 0:
        centre = mission.pose_of(payload)[:3, 3]
        return np.stack([centre, centre])
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    mapped = transform_points(mission.pose_of(payload), corners)
    return np.stack([mapped.min(axis=0), mapped.max(axis=0)])


def _posed(mission: Mission) -> tuple[list[Payload], NDArray[np.float64]]:
    payloads: list[Payload] = []
    positions: list[NDArray[np.float64]] = []
    for p in mission.payloads:
        try:
            positions.append(mission.pose_of(p)[:3, 3])
        except OrphanPayloadError:
            continue  # no pose, cannot be found by pose (listed in mission.problems)
        payloads.append(p)
    return payloads, np.array(positions, dtype=np.float64).reshape(-1, 3)


def retrieve_payload_by_pose(
    mission_folder_path: str | Path | Mission,
    slam_pose: ArrayLike,
    *,
    k: int = 1,
    radius: float | None = None,
    covering: bool = False,
) -> list[Payload]:
    """Payload clouds near a map-frame pose ``(x, y, z)`` or 4x4 T_map_base, nearest first.

    A 2-D point ``(x, y)`` is a horizontal query: nodes are ranked (and ``radius`` measured)
    by their x/y distance alone, whatever their height.

    Default: the ``k`` payloads whose node is nearest. ``radius``: every payload whose node
    lies within ``radius`` metres. ``covering``: every payload whose map-frame footprint
    (x/y of :func:`footprint`) contains the pose. Raises :class:`PayloadNotFoundError` when
    nothing matches.
    """
    from scipy.spatial import cKDTree

    mission = _open(mission_folder_path)
    query = _query_point(slam_pose)
    payloads, positions = _posed(mission)
    if not payloads:
        raise PayloadNotFoundError("mission has no payload with a pose", path=mission.path)
    planar = positions[:, : len(query)]  # x/y only for a 2-D (horizontal) query
    tree = cKDTree(planar)
    if covering:
        dist = query_distances(query, positions)
        hits = []
        for idx in np.argsort(dist, kind="stable"):
            box = footprint(mission, payloads[idx])
            if np.all(box[0, :2] <= query[:2]) and np.all(query[:2] <= box[1, :2]):
                hits.append(int(idx))
    elif radius is not None:
        found = tree.query_ball_point(query, r=radius)
        dist = query_distances(query, positions[found]) if found else np.empty(0)
        hits = [int(found[i]) for i in np.argsort(dist, kind="stable")]
    else:
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        _, idx = tree.query(query, k=min(k, len(payloads)))
        hits = [int(i) for i in np.atleast_1d(idx)]
    if not hits:
        how = "covers" if covering else f"lies within {radius} m of"
        raise PayloadNotFoundError(f"no payload {how} the pose {query.tolist()}", path=mission.path)
    return [payloads[i] for i in hits]


def payload_records(
    payloads: list[Payload],
    query: ArrayLike | None = None,
    mission: Mission | None = None,
) -> list[dict[str, Any]]:
    """Payloads as JSON-ready records (kind, stamp, node, path, frame, sensor, layers); with
    a ``query`` and its ``mission``, also each payload's map position and distance."""
    rows = []
    for p in payloads:
        row: dict[str, Any] = {
            "kind": p.kind,
            "stamp": str(p.stamp),
            "stamp_ns": p.stamp.ns,
            "node_id": p.node_id,
            "path": str(p.path),
            "frame": p.frame,
        }
        if p.sensor is not None:
            row["sensor"] = p.sensor
        if p.layers:
            row["layers"] = {k: str(v) for k, v in p.layers.items()}
        if query is not None and mission is not None:
            position = mission.pose_of(p)[:3, 3]
            row["position_map"] = position.tolist()
            row["distance_m"] = float(query_distances(query, position.reshape(1, 3))[0])
        rows.append(row)
    return rows
