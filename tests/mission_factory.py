"""Small synthetic missions with known poses and clouds, written with the format writers."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from standgrid.clouds import write_cloud
from standgrid.geometry import Matrix4, pose_matrix, relative_pose
from standgrid.mission.posegraph import Edge, PoseGraph, Vertex, write_pose_graph
from standgrid.mission.poses_csv import PoseTable, write_poses_csv
from standgrid.mission.sensors import GnssFixes, ImuSamples, write_gnss, write_imu
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp

BASE_SEC = 1_700_000_000


@dataclass
class Synthetic:
    """What was written: the mission folder and its ground truth."""

    path: Path
    stamps: list[Stamp]
    poses: Matrix4  # (N, 4, 4) T_map_base of the nodes
    clouds: dict[Stamp, PointCloud] = field(default_factory=dict)  # base frame, by stamp
    graph: PoseGraph | None = None
    gnss: GnssFixes | None = None
    imu: ImuSamples | None = None


def node_stamps(n: int) -> list[Stamp]:
    """Stamps with small nsec values, so the graph's unpadded nsec differs from file names."""
    return [Stamp(BASE_SEC + 2 * i, 39_995 * i + 7) for i in range(n)]


def node_poses(n: int, spacing: float = 1.5, seed: int = 0) -> Matrix4:
    """A gently curving, slightly tilted path with ``spacing`` metres between nodes."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(np.full(n, 0.08)) + 0.3
    steps = np.stack([np.cos(yaw), np.sin(yaw), 0.02 * rng.standard_normal(n)], axis=1) * spacing
    xyz = np.cumsum(steps, axis=0) + np.array([100.0, -50.0, 3.0])
    half = 0.5 * yaw
    roll = 0.02 * rng.standard_normal(n)
    q = np.stack([0.5 * roll, 0.5 * roll, np.sin(half), np.cos(half)], axis=1)
    return pose_matrix(xyz, q / np.linalg.norm(q, axis=1, keepdims=True))


def random_cloud(
    rng: np.random.Generator, n: int, fields: tuple[str, ...] = ("intensity",)
) -> PointCloud:
    xyz = rng.uniform(-8.0, 8.0, size=(n, 3))
    return PointCloud(xyz, {f: rng.uniform(0, 100, n).astype(np.float32) for f in fields})


def make_graph(stamps: list[Stamp], poses: Matrix4, id_offset: int = 0) -> PoseGraph:
    vertices = {id_offset + i: Vertex(id_offset + i, s, poses[i]) for i, s in enumerate(stamps)}
    edges = [
        Edge(
            id_offset + i,
            id_offset + i + 1,
            relative_pose(poses[i], poses[i + 1]),
            np.eye(6) * 100.0,
        )
        for i in range(len(stamps) - 1)
    ]
    if len(stamps) > 3:
        edges.append(Edge(id_offset, id_offset + 3, relative_pose(poses[0], poses[3]), np.eye(6)))
    return PoseGraph(vertices=vertices, edges=edges, platform_id=0)


def make_mission(
    root: Path,
    name: str = "2024-05-14-wytham-anymal-coyote",
    *,
    n_nodes: int = 5,
    points: int = 200,
    cloud_folder: str = "payload_clouds",
    cloud_nodes: list[int] | None = None,
    graph_name: str | None = "slam_pose_graph.g2o",
    csv_name: str | None = "slam_poses.csv",
    spacing: float = 1.5,
    fields: tuple[str, ...] = ("intensity",),
    gnss: bool = False,
    imu: bool = False,
    cameras: tuple[str, ...] = (),
    viewpoints: bool = False,
    seed: int = 1,
) -> Synthetic:
    """Write a mission folder ``root/name`` with ``n_nodes`` nodes and a cloud at each node
    in ``cloud_nodes`` (default: all) inside ``cloud_folder`` (``*_in_map`` folders get
    map-frame points)."""
    rng = np.random.default_rng(seed)
    path = root / name
    path.mkdir(parents=True)
    stamps = node_stamps(n_nodes)
    poses = node_poses(n_nodes, spacing, seed)
    graph = make_graph(stamps, poses)
    if graph_name is not None:
        write_pose_graph(graph, path / graph_name)
    if csv_name is not None:
        write_poses_csv(PoseTable.from_pose_graph(graph), path / csv_name)
    out = Synthetic(path, stamps, poses, graph=graph)
    folder = path / cloud_folder
    folder.mkdir(parents=True)
    for i in range(n_nodes) if cloud_nodes is None else cloud_nodes:
        cloud = random_cloud(rng, points, fields)
        out.clouds[stamps[i]] = cloud
        written = cloud.transformed(poses[i]) if cloud_folder.endswith("_in_map") else cloud
        target = folder / stamps[i].filename("cloud", "pcd")
        write_cloud(
            written, target, viewpoint=poses[i] if viewpoints else None, xyz_dtype=np.float64
        )
    if gnss:
        k = 3 * n_nodes
        ns = np.array([stamps[0].ns + j * 700_000_000 for j in range(k)], dtype=np.int64)
        out.gnss = GnssFixes(
            ns,
            51.77 + rng.uniform(0, 1e-4, k),
            -1.33 + rng.uniform(0, 1e-4, k),
            100 + rng.uniform(0, 1, k),
            np.full(k, 4, np.int8),
            np.full(k, 0.02),
            np.full(k, 0.05),
        )
        (path / "gnss").mkdir()
        write_gnss(out.gnss, path / "gnss" / "fixes.txt")
    if imu:
        k = 10 * n_nodes
        ns = np.array([stamps[0].ns + j * 200_000_000 for j in range(k)], dtype=np.int64)
        out.imu = ImuSamples(ns, rng.normal(size=(k, 3)), rng.normal(size=(k, 3)))
        (path / "payloads" / "imu").mkdir(parents=True)
        half = k // 2
        for a, b in ((0, half), (half, k)):
            part = ImuSamples(ns[a:b], out.imu.accel[a:b], out.imu.gyro[a:b])
            write_imu(
                part, path / "payloads" / "imu" / Stamp.from_ns(int(ns[a])).filename("imu", "txt")
            )
    for cam in cameras:
        from PIL import Image

        cam_dir = path / "payloads" / "cameras" / cam
        cam_dir.mkdir(parents=True)
        for s in stamps[:2]:
            Image.fromarray(rng.integers(0, 255, (4, 6, 3), dtype=np.uint8)).save(
                cam_dir / s.filename("image", "png")
            )
    return out
