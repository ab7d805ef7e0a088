"""Write a mission in the canonical layout of docs/ARCHITECTURE.md, atomically.

```
<mission>/
  metadata.yaml
  slam_pose_graph.g2o
  slam_poses.csv
  payload_clouds/cloud_<sec>_<nsec:09d>.pcd    # base frame, VIEWPOINT = the node pose
  <layer>_clouds/cloud_<sec>_<nsec:09d>.pcd    # layers (e.g. ground_clouds), base frame
  gnss/fixes.txt
  payloads/gnss/gnss_<sec>_<nsec:09d>.txt       # the GNSS log cut into one window per payload
  payloads/imu/imu_<sec>_<nsec:09d>.txt         # the IMU log cut into one window per payload
  payloads/cameras/<cam>/image_<sec>_<nsec:09d>.<ext>
```
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.clouds import write_cloud
from standgrid.errors import OrphanPayloadError
from standgrid.geometry import Matrix4
from standgrid.mission.layout import is_mission_folder
from standgrid.mission.metadata import MissionMetadata, write_metadata
from standgrid.mission.model import Mission
from standgrid.mission.posegraph import PoseGraph, write_pose_graph
from standgrid.mission.poses_csv import PoseTable, write_poses_csv
from standgrid.mission.sensors import GnssFixes, ImageRef, ImuSamples, write_gnss, write_imu
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp

GRAPH_FILE = "slam_pose_graph.g2o"
POSES_FILE = "slam_poses.csv"
PAYLOAD_DIR = "payload_clouds"


@dataclass
class CloudToWrite:
    """One payload for the canonical writer: base-frame cloud, its node pose, its layers."""

    stamp: Stamp
    cloud: PointCloud
    pose: Matrix4 | None
    layers: Mapping[str, PointCloud] = field(default_factory=dict)


def own_graph(mission: Mission) -> PoseGraph | None:
    """The mission's graph restricted to its own vertices (a merged graph holds others)."""
    graph = mission.graph
    if graph is None:
        return None
    own_ids = {v.id for v in mission.vertices_by_stamp.values()}
    if len(own_ids) == len(graph.vertices):
        return graph
    return PoseGraph(
        vertices={i: v for i, v in graph.vertices.items() if i in own_ids},
        edges=[e for e in graph.edges if e.i in own_ids and e.j in own_ids],
        platform_id=graph.platform_id,
        gnss_lla_ref=graph.gnss_lla_ref,
        gnss_lla_to_map=graph.gnss_lla_to_map,
    )


def _mission_clouds(mission: Mission) -> Iterable[CloudToWrite]:
    for payload in mission.payloads:
        try:
            pose: Matrix4 | None = mission.pose_of(payload)
        except OrphanPayloadError:
            pose = None  # kept, written without a VIEWPOINT: it stays an orphan when read back
        layers = {name: mission.load_base(payload, name) for name in payload.layers}
        yield CloudToWrite(payload.stamp, mission.load_base(payload), pose, layers)


def payload_windows(sample_ns: NDArray[np.int64], payload_ns: Sequence[int]) -> NDArray[np.intp]:
    """Window index (into the sorted unique ``payload_ns``) of each sample stamp.

    Window boundaries lie at the midpoints between consecutive payload stamps; the first and
    last windows are open-ended, so every sample lands in exactly one window.
    """
    stamps = np.unique(np.asarray(payload_ns, dtype=np.int64))
    mids = stamps[:-1] + (stamps[1:] - stamps[:-1]) // 2
    return np.searchsorted(mids, np.asarray(sample_ns, dtype=np.int64), side="right")


def _window_groups(sample_ns: NDArray[np.int64], payload_ns: list[int]) -> list[NDArray[np.intp]]:
    which = payload_windows(sample_ns, payload_ns)
    return [np.flatnonzero(which == k) for k in range(len(payload_ns))]


def write_payload_logs(
    folder: Path, payload_stamps: Iterable[Stamp], gnss: GnssFixes | None, imu: ImuSamples | None
) -> None:
    """Cut the GNSS and IMU logs into one window per payload (see :func:`payload_windows`)
    and write ``payloads/gnss/gnss_<stamp>.txt`` and ``payloads/imu/imu_<stamp>.txt``, each
    named with its payload's stamp (a window without samples is a header-only file).

    Without payloads, a non-empty log is written as one file named after its first sample.
    """
    stamps = sorted({s.ns for s in payload_stamps})
    if gnss is not None and len(gnss):
        gnss_dir = folder / "payloads" / "gnss"
        gnss_dir.mkdir(parents=True, exist_ok=True)
        if not stamps:
            first = Stamp.from_ns(int(gnss.stamps_ns[0]))
            write_gnss(gnss, gnss_dir / first.filename("gnss", "txt"))
        for ns, idx in zip(stamps, _window_groups(gnss.stamps_ns, stamps), strict=True):
            part = GnssFixes(
                gnss.stamps_ns[idx],
                gnss.lat[idx],
                gnss.lon[idx],
                gnss.alt[idx],
                gnss.quality[idx],
                gnss.h_std[idx],
                gnss.v_std[idx],
            )
            write_gnss(part, gnss_dir / Stamp.from_ns(ns).filename("gnss", "txt"))
    if imu is not None and len(imu):
        imu_dir = folder / "payloads" / "imu"
        imu_dir.mkdir(parents=True, exist_ok=True)
        if not stamps:
            write_imu(imu, imu_dir / Stamp.from_ns(int(imu.stamps_ns[0])).filename("imu", "txt"))
        for ns, idx in zip(stamps, _window_groups(imu.stamps_ns, stamps), strict=True):
            part_imu = ImuSamples(imu.stamps_ns[idx], imu.accel[idx], imu.gyro[idx])
            write_imu(part_imu, imu_dir / Stamp.from_ns(ns).filename("imu", "txt"))


def write_canonical(
    folder: Path,
    *,
    metadata: MissionMetadata | None,
    graph: PoseGraph | None,
    clouds: Iterable[CloudToWrite],
    gnss: GnssFixes | None,
    imu: ImuSamples | None,
    images: Iterable[ImageRef],
) -> None:
    """Write the parts of a mission into an existing (temporary) ``folder``."""
    if metadata is not None:
        write_metadata(metadata, folder / "metadata.yaml")
    if graph is not None:
        write_pose_graph(graph, folder / GRAPH_FILE)
        write_poses_csv(PoseTable.from_pose_graph(graph), folder / POSES_FILE)
    stamps: list[Stamp] = []
    for item in clouds:
        stamps.append(item.stamp)
        target = folder / PAYLOAD_DIR / item.stamp.filename("cloud", "pcd")
        target.parent.mkdir(parents=True, exist_ok=True)
        write_cloud(item.cloud, target, viewpoint=item.pose, xyz_dtype=np.float64)
        for name, layer in item.layers.items():
            layer_path = folder / f"{name}_clouds" / item.stamp.filename("cloud", "pcd")
            layer_path.parent.mkdir(parents=True, exist_ok=True)
            write_cloud(layer, layer_path, viewpoint=item.pose, xyz_dtype=np.float64)
    if gnss is not None and len(gnss):
        (folder / "gnss").mkdir()
        write_gnss(gnss, folder / "gnss" / "fixes.txt")
    write_payload_logs(folder, stamps, gnss, imu)
    for ref in images:
        ext = ref.path.suffix.lstrip(".").lower()
        target = folder / "payloads" / "cameras" / ref.camera / ref.stamp.filename("image", ext)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(ref.path, target)


def write_mission(
    mission: Mission,
    out_path: str | Path,
    *,
    overwrite: bool = False,
    include_scans: bool = False,
) -> Path:
    """Write ``mission`` (any layout, or a re-aligned view) in the canonical layout.

    Payloads are written in their node's base frame with the node pose as VIEWPOINT, as
    float64 PCD (lossless: reading back gives the same points);
    layers go to ``<layer>_clouds/``; with ``include_scans`` the per-node scans go to
    ``individual_clouds/`` (the canonical layout has none). Written to a temporary folder,
    then renamed.
    Raises :class:`OutputExistsError` if ``out_path`` exists and not ``overwrite``.
    """
    out = Path(out_path)
    with atomic_output(
        out, overwrite=overwrite, replaces=is_mission_folder, what="a mission folder"
    ) as tmp:
        tmp.mkdir()
        write_canonical(
            tmp,
            metadata=mission.metadata,
            graph=own_graph(mission),
            clouds=_mission_clouds(mission),
            gnss=mission.gnss,
            imu=mission.imu,
            images=mission.images,
        )
        if include_scans and mission.scans:
            scan_dir = tmp / "individual_clouds"
            scan_dir.mkdir()
            for scan in mission.scans:
                try:
                    pose: Matrix4 | None = mission.pose_of(scan)
                except OrphanPayloadError:
                    pose = None
                target = scan_dir / scan.stamp.filename("cloud", "pcd")
                write_cloud(mission.load_base(scan), target, viewpoint=pose, xyz_dtype=np.float64)
    return out
