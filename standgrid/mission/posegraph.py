"""SLAM pose graphs (``.g2o`` / ``.slam``): vertices with stamps, classified edges, GNSS anchors."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from standgrid.geometry import Matrix4
from standgrid.stamps import Stamp

#: Merged multi-mission graphs offset vertex ids by this much per mission.
MISSION_ID_OFFSET = 10_000


class EdgeKind(StrEnum):
    ODOMETRY = "odometry"
    LOOP_CLOSURE = "loop_closure"
    PRIOR = "prior"


@dataclass(frozen=True, eq=False)
class Vertex:
    """A pose-graph node: ``pose`` is T_map_base (maps base-frame points into the map)."""

    id: int
    stamp: Stamp
    pose: Matrix4

    @property
    def mission_index(self) -> int:
        """Index of the source mission in a merged graph (``id // 10000``)."""
        return self.id // MISSION_ID_OFFSET


@dataclass(frozen=True, eq=False)
class Edge:
    """A relative-pose constraint ``T_i^-1 * T_j`` with its 6x6 information matrix."""

    i: int
    j: int
    relative_pose: Matrix4
    information: NDArray[np.float64]
    robust: Literal["switchable", "maxmix"] | None = None
    robust_parameter: float | None = None

    @property
    def kind(self) -> EdgeKind:
        if self.i == self.j:
            return EdgeKind.PRIOR
        if self.j == self.i + 1:
            return EdgeKind.ODOMETRY
        return EdgeKind.LOOP_CLOSURE


@dataclass(eq=False)
class PoseGraph:
    """A whole pose graph. ``vertices`` is keyed by id, in file order."""

    vertices: dict[int, Vertex]
    edges: list[Edge] = field(default_factory=list)
    platform_id: int | None = None
    #: ENU origin ``(lat, lon, alt)`` (WGS84 degrees, ellipsoidal metres), if the graph has one.
    gnss_lla_ref: tuple[float, float, float] | None = None
    #: T_map_enu: ``p_map = R * p_enu + t``, if the graph has one.
    gnss_lla_to_map: Matrix4 | None = None
    #: Tags that were present but skipped (tag -> count), so nothing vanishes unreported.
    skipped_tags: Counter[str] = field(default_factory=Counter)
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.vertices)

    @property
    def ids(self) -> NDArray[np.int64]:
        return np.fromiter(self.vertices, dtype=np.int64, count=len(self.vertices))

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        return np.array([v.stamp.ns for v in self.vertices.values()], dtype=np.int64)

    @property
    def poses(self) -> Matrix4:
        """All vertex poses, ``(N, 4, 4)`` float64, in ``vertices`` order."""
        if not self.vertices:
            return np.zeros((0, 4, 4))
        return np.stack([v.pose for v in self.vertices.values()])

    @property
    def positions(self) -> NDArray[np.float64]:
        return self.poses[:, :3, 3]

    def edge_counts(self) -> Counter[EdgeKind]:
        return Counter(e.kind for e in self.edges)

    def by_stamp(self) -> dict[Stamp, Vertex]:
        """Vertices keyed by stamp (the caller checks for duplicates via :func:`duplicate_stamps`)."""
        return {v.stamp: v for v in self.vertices.values()}

    def duplicate_stamps(self) -> dict[Stamp, list[int]]:
        """Stamps carried by more than one vertex -> their vertex ids."""
        seen: dict[Stamp, list[int]] = {}
        for v in self.vertices.values():
            seen.setdefault(v.stamp, []).append(v.id)
        return {s: ids for s, ids in seen.items() if len(ids) > 1}
