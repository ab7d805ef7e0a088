"""Build payloads from per-node scans: accumulate scans in the map frame, one payload per
``distance`` metres travelled (or per square tile of ``area`` metres), expressed in the base
frame of the node at the payload's centre and stamped with that node's stamp."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.clouds import read_cloud_header
from standgrid.errors import MissionConsistencyError, MissionNotFoundError, StandgridError
from standgrid.geometry import Matrix4, invert_pose
from standgrid.mission.layout import GRAPH_NAMES, POSES_CSV_NAMES, is_mission_folder
from standgrid.mission.model import Mission
from standgrid.mission.opening import open_mission
from standgrid.mission.payload import Payload
from standgrid.mission.posegraph import PoseGraph
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


def _read_any_graph(path: Path) -> PoseGraph:
    from standgrid.mission.opening import read_pose_graph_file
    from standgrid.mission.poses_csv import read_poses_csv

    if not path.is_file():
        raise MissionNotFoundError("graph file not found", path=path)
    if path.suffix.lower() in (".csv", ".txt") or path.name in POSES_CSV_NAMES:
        graph = read_poses_csv(path).to_pose_graph()
        graph.source = graph.source or path
        return graph
    return read_pose_graph_file(path)


def _graph_hint(mission: Mission, scans: list[Payload]) -> str:
    """Name the graph files seen elsewhere in the folder and how many scans each would pose."""
    stamps = {s.stamp for s in scans}
    seen = []
    for path in mission.layout.stray_graphs:
        rel = path.relative_to(mission.path).as_posix()
        try:
            graph_stamps = {v.stamp for v in _read_any_graph(path).vertices.values()}
        except StandgridError as exc:
            seen.append(f"{rel} (unreadable: {exc.message})")
            continue
        seen.append(f"{rel} (its nodes match {len(stamps & graph_stamps)} of {len(stamps)} scans)")
    if not seen:
        return "no graph file was seen anywhere in the folder"
    return "graph files seen elsewhere: " + "; ".join(seen) + " (pass one with --graph)"


def _check_poseable(mission: Mission, scans: list[Payload]) -> None:
    """Refuse scans that cannot be posed: no graph, and no VIEWPOINTs telling them apart."""
    if mission.graph is not None:
        return
    viewpoints = [read_cloud_header(s.path).viewpoint for s in scans]
    missing = sum(v is None for v in viewpoints)
    distinct = {tuple(np.round(np.asarray(v), 9).ravel()) for v in viewpoints if v is not None}
    if missing == 0 and (len(scans) == 1 or len(distinct) > 1):
        return
    why = (
        f"{missing} of {len(scans)} scans have no VIEWPOINT"
        if missing
        else f"all {len(scans)} scans have the same VIEWPOINT (they would be stacked)"
    )
    raise MissionConsistencyError(
        f"cannot pose the scans: no pose graph ({', '.join(GRAPH_NAMES)}) or pose table "
        f"({', '.join(POSES_CSV_NAMES)}) at the mission root, and {why}; "
        + _graph_hint(mission, scans),
        path=mission.path,
    )


def build_payloads(
    mission_path: str | Path,
    out_path: str | Path,
    *,
    distance: float = 20.0,
    area: float | None = None,
    graph: str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Turn a mission's per-node scans into payloads; write a canonical mission at ``out_path``.

    Grouping is by ``distance`` travelled unless ``area`` (square tile side, metres) is given.
    ``graph`` poses the scans with a graph (or pose table) file from elsewhere; its nodes
    are matched to the scans by stamp. Metadata, graph, GNSS, IMU and images are carried
    over. Returns ``out_path``. Raises :class:`MissionConsistencyError` when there are no
    scans, their fields differ, or they cannot be posed (no graph found and no VIEWPOINTs
    telling them apart: the message names graph files seen elsewhere in the folder).
    """
    mission = open_mission(mission_path, strict=True)
    if graph is not None:
        mission = mission.with_graph(_read_any_graph(Path(graph)), whole=True)
    scans = sorted(mission.scans, key=lambda s: s.stamp)
    if not scans:
        raise MissionConsistencyError(
            "no per-node scans (individual_clouds/, slam_clouds/, undist-clouds/, "
            "raw_data/raw_clouds/)",
            path=mission.path,
        )
    _check_poseable(mission, scans)
    check_fields(scans)
    poses = np.stack([mission.pose_of(s) for s in scans])
    positions = poses[:, :3, 3]
    groups = (
        group_by_area(positions, area)
        if area is not None
        else group_by_distance(positions, distance)
    )
    out = Path(out_path)
    with atomic_output(
        out, overwrite=overwrite, replaces=is_mission_folder, what="a mission folder"
    ) as tmp:
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
