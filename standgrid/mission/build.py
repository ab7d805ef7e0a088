"""Build payloads from per-node scans: accumulate scans in the map frame, one payload per
``distance`` metres travelled (or per square tile of ``area`` metres), expressed in the base
frame of the node at the payload's centre and stamped with that node's stamp."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.errors import MissionConsistencyError
from standgrid.geometry import Matrix4, invert_pose
from standgrid.mission.clouds import read_cloud_header
from standgrid.mission.model import Mission, Payload, open_mission
from standgrid.mission.writer import CloudToWrite, own_graph, write_canonical
from standgrid.pointcloud import PointCloud

#: A payload group: indices of its scans (time order) and the index of its centre node.
Group = tuple[list[int], int]


def group_by_distance(positions: NDArray[np.float64], distance: float) -> list[Group]:
    """Consecutive scans per ``distance`` metres travelled; the centre is the scan whose
    travelled distance is nearest the middle of the group's travelled span."""
    if distance <= 0:
        raise ValueError(f"distance must be positive, got {distance}")
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    bins = np.floor(travelled / distance).astype(np.int64)
    groups: list[Group] = []
    for b in np.unique(bins):
        members = np.flatnonzero(bins == b)
        mid = 0.5 * (travelled[members[0]] + travelled[members[-1]])
        centre = int(members[np.argmin(np.abs(travelled[members] - mid))])
        groups.append(([int(m) for m in members], centre))
    return groups


def group_by_area(positions: NDArray[np.float64], area: float) -> list[Group]:
    """Scans whose node lies in the same ``area`` x ``area`` m square tile (map x/y); the
    centre is the member node nearest the tile centre. Groups come in time order of centres."""
    if area <= 0:
        raise ValueError(f"area must be positive, got {area}")
    tiles = np.floor(positions[:, :2] / area).astype(np.int64)
    groups: list[Group] = []
    for tile in np.unique(tiles, axis=0):
        members = np.flatnonzero(np.all(tiles == tile, axis=1))
        centre_xy = (tile + 0.5) * area
        d = np.linalg.norm(positions[members, :2] - centre_xy, axis=1)
        groups.append(([int(m) for m in members], int(members[np.argmin(d)])))
    groups.sort(key=lambda g: g[1])
    return groups


def check_fields(scans: list[Payload]) -> list[str]:
    """The common field set of all scans (headers only); a clear error on the first mismatch."""
    first = list(read_cloud_header(scans[0].path).fields)
    for scan in scans[1:]:
        fields = list(read_cloud_header(scan.path).fields)
        if set(fields) != set(first):
            raise MissionConsistencyError(
                f"scan fields {fields} differ from {first} of {scans[0].path.name}; "
                "all scans of a payload must have the same fields",
                path=scan.path,
            )
    return first


def _accumulate(
    mission: Mission, scans: list[Payload], poses: Matrix4, groups: list[Group]
) -> Iterator[CloudToWrite]:
    for members, centre in groups:
        base_from_map = invert_pose(poses[centre])
        parts = [mission.load_base(scans[i]).transformed(base_from_map @ poses[i]) for i in members]
        layer_names = sorted({name for i in members for name in scans[i].layers})
        layers = {
            name: PointCloud.concat(
                mission.load_base(scans[i], name).transformed(base_from_map @ poses[i])
                for i in members
                if name in scans[i].layers
            )
            for name in layer_names
        }
        yield CloudToWrite(scans[centre].stamp, PointCloud.concat(parts), poses[centre], layers)


def build_payloads(
    mission_path: str | Path,
    out_path: str | Path,
    *,
    distance: float = 20.0,
    area: float | None = None,
    overwrite: bool = False,
) -> Path:
    """Turn a mission's per-node scans into payloads; write a canonical mission at ``out_path``.

    Grouping is by ``distance`` travelled unless ``area`` (square tile side, metres) is given.
    Metadata, graph, GNSS, IMU and images are carried over. Returns ``out_path``.
    Raises :class:`MissionConsistencyError` when there are no scans or their fields differ.
    """
    mission = open_mission(mission_path, strict=True)
    scans = sorted(mission.scans, key=lambda s: s.stamp)
    if not scans:
        raise MissionConsistencyError(
            "no per-node scans (individual_clouds/, slam_clouds/, undist-clouds/, "
            "raw_data/raw_clouds/)",
            path=mission.path,
        )
    check_fields(scans)
    poses = np.stack([mission.pose_of(s) for s in scans])
    positions = poses[:, :3, 3]
    groups = (
        group_by_area(positions, area)
        if area is not None
        else group_by_distance(positions, distance)
    )
    out = Path(out_path)
    with atomic_output(out, overwrite=overwrite) as tmp:
        tmp.mkdir()
        write_canonical(
            tmp,
            metadata=mission.metadata,
            graph=own_graph(mission),
            clouds=_accumulate(mission, scans, poses, groups),
            gnss=mission.gnss,
            imu=mission.imu,
            images=mission.images,
        )
    return out
