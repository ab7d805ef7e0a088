"""A payload: one stamped piece of mission data, and its attachment to graph nodes by stamp."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from standgrid.crs import CRS
from standgrid.errors import OrphanPayloadError
from standgrid.mission.layout import Frame
from standgrid.mission.posegraph import PoseGraph, Vertex
from standgrid.stamps import Stamp

PayloadKind = Literal["point_cloud", "scan", "gnss", "imu", "image"]


@dataclass(frozen=True)
class Payload:
    """One stamped piece of mission data, attached to the graph node of the same stamp.

    ``node_id`` is None when no node has the stamp (reported in ``Mission.problems``).
    ``frame`` is the frame of the file's coordinates (``utm``: any projected CRS, for
    clouds in a ``*_in_utm`` folder and LAS/LAZ files carrying a projected CRS, which
    wins over the folder's frame); ``layers`` maps a layer name
    (``ground``) to a cloud file of the same stamp. ``sensor`` names the camera of an image.
    """

    stamp: Stamp
    node_id: int | None
    path: Path
    frame: Frame = "base"
    layers: dict[str, Path] = field(default_factory=dict, hash=False, compare=False)
    kind: PayloadKind = "point_cloud"
    sensor: str | None = None
    #: The projected CRS of a ``utm``-frame cloud, when its file says (LAS/LAZ CRS VLR).
    crs: CRS | None = field(default=None, hash=False, compare=False)
    #: A plain scan's payload is a part of a LAS/LAZ file: its points ``[start, stop)`` ...
    span: tuple[int, int] | None = field(default=None, hash=False, compare=False)
    #: ... of GPS times in ``[lo, hi)`` (a trajectory segment); None: all of them.
    window: tuple[float, float] | None = field(default=None, hash=False, compare=False)
    #: Where a plain scan's payload was taken from, in its CRS (the trajectory's position),
    #: if known; else the centre of the file's box stands in.
    site: tuple[float, float, float] | None = field(default=None, hash=False, compare=False)
    #: Seconds added to the file's GPS times (a plain scan's GPS week seconds made adjusted
    #: standard GPS time with the week of its date).
    time_offset: float = field(default=0.0, hash=False, compare=False)
    #: ... and a week (604,800 s) more for a file time below this (after the rollover).
    time_wrap: float | None = field(default=None, hash=False, compare=False)
    #: The elevation map and the volumetric map computed on board for this payload, if any
    #: (:mod:`standgrid.mission.derived_maps`; read by
    #: :meth:`~standgrid.mission.model.Mission.load_elevation_map`).
    elevation_map: Path | None = field(default=None, hash=False, compare=False)
    volumetric_map: Path | None = field(default=None, hash=False, compare=False)

    def __post_init__(self) -> None:
        if self.crs is not None:  # the text a file or record gives: the value
            object.__setattr__(self, "crs", CRS.of(self.crs))


def _vertices_by_stamp(graph: PoseGraph | None) -> dict[Stamp, Vertex]:
    """Stamp -> vertex, keeping the first vertex of a duplicated stamp."""
    out: dict[Stamp, Vertex] = {}
    if graph is not None:
        for v in graph.vertices.values():
            out.setdefault(v.stamp, v)
    return out


def _orphan(payload: Payload, graph_path: Path | None, strict: bool, problems: list[str]) -> None:
    msg = f"no pose-graph node has the stamp {payload.stamp}"
    if graph_path is not None:
        msg += f" (graph {graph_path})"
    if strict:
        raise OrphanPayloadError(msg, path=payload.path)
    problems.append(f"{payload.path}: {msg}")


def _attach(
    items: list[Payload],
    by_stamp: dict[Stamp, Vertex],
    graph: PoseGraph | None,
    strict: bool,
    problems: list[str],
) -> list[Payload]:
    if graph is None:
        return items
    out = []
    for p in items:
        vertex = by_stamp.get(p.stamp)
        if vertex is None:
            _orphan(p, graph.source, strict, problems)
        out.append(replace(p, node_id=None if vertex is None else vertex.id))
    return out
