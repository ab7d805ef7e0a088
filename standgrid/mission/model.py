"""A mission in memory: payloads attached to graph nodes, sensor logs, images, its cloud cache.

Clouds are read lazily. Base-frame clouds are kept in a bounded LRU cache shared by every
re-aligned view (:meth:`Mission.with_graph`), so re-aligning after a re-optimised or merged
graph never reads a cloud file again. Opening a mission folder is
:mod:`standgrid.mission.opening`.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from standgrid.clouds import read_cloud, read_cloud_header
from standgrid.errors import (
    DuplicateStampError,
    MissionConsistencyError,
    OrphanPayloadError,
    PointCloudFormatError,
)
from standgrid.geometry import Matrix4, invert_pose
from standgrid.mission.derived_maps import ElevationMap, OctreeMap, VoxelGrid
from standgrid.mission.layout import MissionLayout
from standgrid.mission.metadata import MissionMetadata
from standgrid.mission.payload import Payload, _attach, _vertices_by_stamp
from standgrid.mission.posegraph import PoseGraph, Vertex
from standgrid.mission.sensors import (
    GnssFixes,
    ImageRef,
    ImuSamples,
)
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp

#: Default bound of the base-frame cloud cache, in points (~24 bytes each for xyz).
DEFAULT_CACHE_POINTS = 20_000_000


class CloudCache:
    """A least-recently-used cache of base-frame clouds, bounded by a total point count."""

    def __init__(self, max_points: int = DEFAULT_CACHE_POINTS) -> None:
        self.max_points = max_points
        self._items: OrderedDict[tuple[Path, str | None], PointCloud] = OrderedDict()
        self._points = 0

    def get(self, key: tuple[Path, str | None]) -> PointCloud | None:
        cloud = self._items.get(key)
        if cloud is not None:
            self._items.move_to_end(key)
        return cloud

    def put(self, key: tuple[Path, str | None], cloud: PointCloud) -> None:
        if key in self._items:
            self._points -= len(self._items.pop(key))
        self._items[key] = cloud
        self._points += len(cloud)
        while self._points > self.max_points and len(self._items) > 1:
            _, old = self._items.popitem(last=False)
            self._points -= len(old)

    def __len__(self) -> int:
        return len(self._items)


class Mission:
    """An opened mission. Build it with :func:`~standgrid.mission.opening.open_mission`."""

    def __init__(
        self,
        *,
        layout: MissionLayout,
        metadata: MissionMetadata | None,
        graph: PoseGraph | None,
        payloads: list[Payload],
        scans: list[Payload],
        gnss: GnssFixes | None,
        imu: ImuSamples | None,
        images: list[ImageRef],
        problems: list[str],
        strict: bool,
        source_poses: dict[Path, Matrix4],
        cache: CloudCache,
        read_cloud_fn: Callable[[Path], PointCloud] = read_cloud,
        warnings: list[str] | None = None,
    ) -> None:
        self.layout = layout
        self.path: Path = layout.root
        self.name: str = layout.root.name
        self.metadata = metadata
        self.graph = graph
        self.payloads = payloads
        #: Per-node scans (``individual_clouds`` etc.), the input of ``payloads build``.
        self.scans = scans
        #: A plain scan's trajectory in its CRS ``(N, 3)``, when one was given.
        self.scan_path: NDArray[np.float64] | None = None
        self.gnss = gnss
        self.imu = imu
        self.images = images
        #: Inconsistencies found by a non-strict open (a strict open raises on the first).
        self.problems = problems
        #: Notes that are never an error, in both modes (a graph file present but not used).
        self.warnings: list[str] = [] if warnings is None else warnings
        self.strict = strict
        #: The function every cloud file is read with (wrap it to count or trace reads).
        self.read_cloud: Callable[[Path], PointCloud] = read_cloud_fn
        # Pose each map-frame file was written with (to bring it back to base), by path.
        self._source_poses = source_poses
        self._cache = cache
        self._by_stamp: dict[Stamp, Vertex] = _vertices_by_stamp(graph)
        self._viewpoints: dict[Path, Matrix4] = {}

    def __repr__(self) -> str:
        nodes = len(self.graph) if self.graph is not None else 0
        return f"Mission({self.name!r}, nodes={nodes}, payloads={len(self.payloads)})"

    # --- poses ---------------------------------------------------------------------------

    @property
    def vertices_by_stamp(self) -> dict[Stamp, Vertex]:
        """This mission's graph vertices by stamp (in a merged graph: only its own)."""
        return dict(self._by_stamp)

    def vertex_of(self, payload: Payload) -> Vertex | None:
        """The graph node with the payload's stamp (None without a graph or match)."""
        return self._by_stamp.get(payload.stamp)

    def pose_of(self, payload: Payload) -> Matrix4:
        """T_map_base of the payload: the graph vertex pose, or (no graph) the PCD VIEWPOINT.

        A cloud without a graph and without a VIEWPOINT has the identity pose (PCD default).
        """
        if self.graph is not None:
            vertex = self.vertex_of(payload)
            if vertex is None:
                raise OrphanPayloadError(
                    f"no pose-graph node has the stamp {payload.stamp}", path=payload.path
                )
            return vertex.pose
        pose = self._viewpoints.get(payload.path)
        if pose is None:
            header = read_cloud_header(payload.path)
            pose = np.eye(4) if header.viewpoint is None else np.asarray(header.viewpoint, float)
            self._viewpoints[payload.path] = pose
        return pose

    def trajectory(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Node stamps (ns, int64) and map positions ``(N, 3)``, in time order.

        Without a graph, the payload (or scan) poses stand in for the nodes.
        """
        if self.graph is not None and self._by_stamp:
            vertices = sorted(self._by_stamp.values(), key=lambda v: v.stamp)
            stamps = np.array([v.stamp.ns for v in vertices], dtype=np.int64)
            return stamps, np.array([v.pose[:3, 3] for v in vertices], dtype=np.float64).reshape(
                -1, 3
            )
        items = self.payloads or self.scans
        if items and all(p.site is not None for p in items):  # a plain scan: in its CRS
            stamps = np.array([p.stamp.ns for p in items], dtype=np.int64)
            return stamps, np.array([p.site for p in items], dtype=np.float64).reshape(-1, 3)
        stamps = np.array([p.stamp.ns for p in items], dtype=np.int64)
        positions = np.array([self.pose_of(p)[:3, 3] for p in items], dtype=np.float64)
        return stamps, positions.reshape(-1, 3)

    # --- clouds --------------------------------------------------------------------------

    def load_base(self, payload: Payload, layer: str | None = None) -> PointCloud:
        """The payload (or one of its layers) in its node's base frame, float64, cached."""
        path = payload.path if layer is None else self._layer_path(payload, layer)
        key = (path, layer)
        cloud = self._cache.get(key)
        if cloud is not None:
            return cloud
        cloud = self.read_cloud(path)
        frame = payload.frame if layer is None else "base"
        if frame == "map":
            cloud = cloud.transformed(invert_pose(self._source_poses[path]))
        elif frame == "utm":
            raise MissionConsistencyError(
                "a UTM-frame cloud cannot be brought to the base frame without a georeference",
                path=path,
            )
        self._cache.put(key, cloud)
        return cloud

    def file_to_base(self, payload: Payload) -> Matrix4 | None:
        """T_base_file of the payload's own file: :meth:`load_base` reads the file and applies
        it (None: the file is in the base frame already, or in a projected CRS)."""
        if payload.frame != "map":
            return None
        return invert_pose(self._source_poses[payload.path])

    @property
    def is_projected(self) -> bool:
        """True when the payloads are clouds already in a projected CRS (frame ``utm``)."""
        clouds = [p for p in self.payloads if p.kind == "point_cloud"]
        return bool(clouds) and all(p.frame == "utm" for p in clouds)

    def load_projected(self, payload: Payload) -> PointCloud:
        """A ``utm``-frame payload as stored: float64 coordinates in its projected CRS."""
        if payload.frame != "utm":
            raise MissionConsistencyError(
                f"a {payload.frame}-frame cloud is not in a projected CRS", path=payload.path
            )
        if payload.span is not None:
            from standgrid.clouds.las import read_las_part

            return read_las_part(payload.path, payload.span, payload.window)
        return self.read_cloud(payload.path)

    def load_payload(
        self,
        payload: Payload,
        frame: Literal["map", "base"] = "map",
        layer: str | None = None,
    ) -> PointCloud:
        """The payload cloud (or a layer of it) as float64, in the map or its base frame."""
        if frame not in ("map", "base"):
            raise ValueError(f"frame must be 'map' or 'base', not {frame!r}")
        base = self.load_base(payload, layer)
        if frame == "base":
            return base
        return base.transformed(self.pose_of(payload))

    def iter_payload_clouds(
        self, frame: Literal["map", "base"] = "map", layer: str | None = None
    ) -> Iterator[tuple[Payload, PointCloud]]:
        """``(payload, cloud)`` one payload at a time (payloads without a pose are skipped
        only when the mission was opened non-strict; they are listed in ``problems``)."""
        for payload in self.payloads:
            if layer is not None and layer not in payload.layers:
                continue
            if frame == "map" and self.graph is not None and self.vertex_of(payload) is None:
                if self.strict:
                    self.pose_of(payload)  # raises OrphanPayloadError
                continue
            yield payload, self.load_payload(payload, frame, layer)

    # --- derived maps ----------------------------------------------------------------------

    def load_elevation_map(self, payload: Payload) -> ElevationMap:
        """The payload's elevation map (its grid placed in the base frame by its ``pose``)."""
        from standgrid.mission.derived_maps import read_elevation_map

        if payload.elevation_map is None:
            raise MissionConsistencyError("payload has no elevation map", path=payload.path)
        return read_elevation_map(payload.elevation_map)

    def load_volumetric_map(self, payload: Payload) -> VoxelGrid | OctreeMap:
        """The payload's volumetric map (a voxel grid, or an OctoMap read with octomap-python)."""
        from standgrid.mission.derived_maps import read_voxel_grid

        if payload.volumetric_map is None:
            raise MissionConsistencyError("payload has no volumetric map", path=payload.path)
        return read_voxel_grid(payload.volumetric_map)

    def _layer_path(self, payload: Payload, layer: str) -> Path:
        try:
            return payload.layers[layer]
        except KeyError:
            raise MissionConsistencyError(
                f"payload has no layer {layer!r} (has {sorted(payload.layers)})", path=payload.path
            ) from None

    # --- re-alignment --------------------------------------------------------------------

    def with_graph(self, graph: PoseGraph, *, whole: bool = False) -> Mission:
        """A view of this mission re-aligned on ``graph`` (re-optimised, or a merged graph
        whose vertices are matched to this mission's payloads by stamp). No cloud is re-read:
        the base-frame cache is shared. ``whole``: every vertex of ``graph`` belongs to this
        mission (a graph file given for it), not only those matching its own stamps."""
        problems = list(self.problems)
        by_stamp = _vertices_by_stamp(graph)
        dups = graph.duplicate_stamps()
        own = {p.stamp for p in self.payloads} | {p.stamp for p in self.scans}
        if self.graph is not None:
            own |= set(_vertices_by_stamp(self.graph))
        clashing = {s: ids for s, ids in dups.items() if s in own}
        if clashing:
            stamp, ids = next(iter(clashing.items()))
            msg = f"vertices {ids} share the stamp {stamp}"
            if self.strict:
                raise DuplicateStampError(msg, path=graph.source)
            problems.append(f"{graph.source}: {msg}")

        view = Mission(
            layout=self.layout,
            metadata=self.metadata,
            graph=graph,
            payloads=_attach(self.payloads, by_stamp, graph, self.strict, problems),
            scans=_attach(self.scans, by_stamp, graph, self.strict, problems),
            gnss=self.gnss,
            imu=self.imu,
            images=self.images,
            problems=problems,
            strict=self.strict,
            source_poses=self._source_poses,
            cache=self._cache,
            read_cloud_fn=self.read_cloud,
            warnings=list(self.warnings),
        )
        # Keep only this mission's vertices when matching (merged graphs hold others too).
        if own and not whole:
            view._by_stamp = {s: v for s, v in by_stamp.items() if s in own}
        else:
            view._by_stamp = by_stamp
        return view

    # --- summary -------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        """Counts, time span and map extent, from headers only (no point is read)."""
        graph = self.graph
        edges: dict[str, int] = {}
        if graph is not None:
            edges = {str(kind): n for kind, n in sorted(graph.edge_counts().items())}
        problems = list(self.problems)
        points, bad_payloads = _counted_points(self.payloads, problems, self.strict)
        scan_points, bad_scans = _counted_points(self.scans, problems, self.strict)
        stamps, positions = self.trajectory()
        all_ns = [int(s) for s in stamps]
        all_ns += [p.stamp.ns for p in self.payloads + self.scans]
        all_ns += [i.stamp.ns for i in self.images]
        for log in (self.gnss, self.imu):
            if log is not None and len(log):
                all_ns += [int(log.stamps_ns.min()), int(log.stamps_ns.max())]
        span = None
        if all_ns:
            first, last = Stamp.from_ns(min(all_ns)), Stamp.from_ns(max(all_ns))
            span = {"start": str(first), "end": str(last), "seconds": (last.ns - first.ns) / 1e9}
        extent = None
        if len(positions):
            extent = {"min": positions.min(axis=0).tolist(), "max": positions.max(axis=0).tolist()}
        summary = {
            "name": self.name,
            "path": str(self.path),
            "metadata": None if self.metadata is None else _metadata_dict(self.metadata),
            "graph": None if graph is None or graph.source is None else str(graph.source),
            "nodes": 0 if graph is None else len(graph),
            "edges": edges,
            "payloads": len(self.payloads),
            "payload_folder": None
            if self.layout.payload_source is None
            else self.layout.payload_source.name,
            "points": points,
            "payloads_truncated": bad_payloads,
            "scans": len(self.scans),
            "scan_points": scan_points,
            "scans_truncated": bad_scans,
            "cloud_folders": {
                f.name: len(f.files)
                for f in (
                    *self.layout.payload_folders,
                    *self.layout.scan_folders,
                    *self.layout.layer_folders,
                )
            },
            "gnss_fixes": 0 if self.gnss is None else len(self.gnss),
            "imu_samples": 0 if self.imu is None else len(self.imu),
            "images": len(self.images),
            "cameras": sorted({i.camera for i in self.images}),
            "time_span": span,
            "extent_map": extent,
            "problems": problems,
            "warnings": list(self.warnings),
        }
        elevation = sum(p.elevation_map is not None for p in self.payloads)
        volumetric = sum(p.volumetric_map is not None for p in self.payloads)
        if elevation or volumetric:  # said only when there are some (summaries stay as they were)
            summary["elevation_maps"], summary["volumetric_maps"] = elevation, volumetric
        return summary


def _counted_points(items: list[Payload], problems: list[str], strict: bool) -> tuple[int, int]:
    """Points the clouds' headers announce; files too short for their header, or whose header
    cannot be read, left out (and reported in ``problems``; a strict mission raises).
    Returns ``(points, truncated or unreadable files)``."""
    total = bad = 0
    for item in items:
        try:
            header = read_cloud_header(item.path)
        except PointCloudFormatError as exc:  # empty, a bad header, a cut LAZ chunk table
            if strict:
                raise
            bad += 1
            where = f"{item.path}:{exc.line}" if exc.line is not None else str(item.path)
            problems.append(f"{where}: {exc.message}; not counted")
            continue
        problem = header.size_problem()
        if problem is None:
            total += header.points
            continue
        if strict:
            raise PointCloudFormatError(problem, path=item.path)
        bad += 1
        problems.append(f"{item.path}: {problem}; not counted")
    return total, bad


def _metadata_dict(meta: MissionMetadata) -> dict[str, Any]:
    to_dict = getattr(meta, "to_dict", None)
    if callable(to_dict):
        return dict(to_dict())
    import dataclasses

    return dataclasses.asdict(meta) if dataclasses.is_dataclass(meta) else {"value": str(meta)}
