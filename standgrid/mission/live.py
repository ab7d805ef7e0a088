"""A canonical mission folder written piece by piece, as a robot sends it (online ingest).

:class:`LiveMission` adds payload clouds (base frame, with their stamp and node pose), whole
pose-graph updates and GNSS fixes to a folder in the canonical layout
(docs/ARCHITECTURE.md), each one atomically (``standgrid._atomic``) and under the folder's
lock (``flock`` on ``.<name>.lock`` beside it), so concurrent senders are serialised and a
kill leaves the old or the new file. Every call is idempotent: the same piece sent twice is
stored once (``unchanged``); a different piece under the same stamp is refused
(:class:`LiveMissionConflictError`). Received files are read back with the project's readers
before they are kept.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np

from standgrid._atomic import atomic_output
from standgrid.clouds import CLOUD_EXTENSIONS, read_cloud
from standgrid.errors import (
    MissionConsistencyError,
    MissionNotFoundError,
    PointCloudFormatError,
    StandgridError,
)
from standgrid.geometry import Matrix4
from standgrid.mission.metadata import MissionMetadata, read_metadata, write_metadata
from standgrid.mission.posegraph import PoseGraph, Vertex, read_pose_graph, write_pose_graph
from standgrid.mission.sensors import GnssFixes, concat_gnss, read_gnss, write_gnss
from standgrid.mission.writer import GRAPH_FILE, PAYLOAD_DIR
from standgrid.stamps import Stamp

Outcome = Literal["created", "stored", "unchanged"]
METADATA_FILE = "metadata.yaml"
GNSS_FILE = "gnss/fixes.txt"


class LiveMissionConflictError(MissionConsistencyError):
    """A piece differs from the one already stored under the same name or stamp."""


class LiveMission:
    """The mission folder ``path`` (its parent must exist)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.lock_path = self.path.parent / f".{self.path.name}.lock"

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """The folder's lock (exclusive, blocking): one writer at a time, across processes."""
        with open(self.lock_path, "a+b") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    # --- the mission ------------------------------------------------------------------------

    def create(self, metadata: MissionMetadata) -> Outcome:
        """Make the folder with its ``metadata.yaml``; ``unchanged`` when it exists with the
        same metadata, a conflict when it differs."""
        if metadata.name != self.path.name:
            raise LiveMissionConflictError(
                f"metadata names mission {metadata.name!r}", path=self.path
            )
        with self.locked():
            meta_file = self.path / METADATA_FILE
            if meta_file.is_file():
                if read_metadata(meta_file) == self._as_read(metadata):
                    return "unchanged"
                raise LiveMissionConflictError(
                    "the mission exists with other metadata", path=meta_file
                )
            (self.path / PAYLOAD_DIR).mkdir(parents=True, exist_ok=True)
            write_metadata(metadata, meta_file)
            return "created"

    def _as_read(self, metadata: MissionMetadata) -> MissionMetadata:
        """``metadata`` as :func:`read_metadata` gives it back once written here: values it
        lacks derived from the folder name (a unit), times and numbers as YAML keeps them."""
        with tempfile.TemporaryDirectory(prefix="standgrid-live-") as folder:
            probe = Path(folder) / METADATA_FILE
            write_metadata(metadata, probe)
            return read_metadata(probe, folder_name=self.path.name)

    def _require(self) -> None:
        if not (self.path / METADATA_FILE).is_file():
            raise MissionNotFoundError("no such mission: create it first", path=self.path)

    # --- payloads ---------------------------------------------------------------------------

    def add_payload(
        self, stamp: Stamp, data: bytes, extension: str, pose: Matrix4 | None = None
    ) -> Outcome:
        """Keep a payload cloud (file bytes: PCD, PLY, LAS or LAZ) in its node's base frame.

        ``pose`` (T_map_base of the node at ``stamp``) adds the node to the pose graph when the
        graph has none at that stamp; a graph update (:meth:`set_graph`) is authoritative
        and moves payloads when it moves their nodes.
        """
        extension = extension.lower()
        if not extension.startswith("."):
            extension = "." + extension
        if extension not in CLOUD_EXTENSIONS:
            raise PointCloudFormatError(
                f"unknown cloud format {extension!r}; one of {', '.join(CLOUD_EXTENSIONS)}"
            )
        self._require()
        folder = self.path / PAYLOAD_DIR
        target = folder / stamp.filename("cloud", extension.lstrip("."))
        with self.locked():
            others = [p for p in folder.glob(f"cloud_{stamp.sec}_{stamp.nsec:09d}.*")]
            if others:
                same = [p for p in others if p.name == target.name]
                if same and _digest(same[0].read_bytes()) == _digest(data):
                    self._add_vertex(stamp, pose)
                    return "unchanged"
                raise LiveMissionConflictError(
                    f"a different cloud is stored for stamp {stamp}", path=others[0]
                )
            self._check_cloud(data, target)
            folder.mkdir(parents=True, exist_ok=True)
            with atomic_output(target, overwrite=False) as tmp:
                tmp.write_bytes(data)
            self._add_vertex(stamp, pose)
            return "stored"

    @staticmethod
    def _check_cloud(data: bytes, target: Path) -> None:
        """Read the bytes with the project's cloud reader (a bad cloud is refused, typed)."""
        with tempfile.TemporaryDirectory(prefix="standgrid-live-") as folder:
            probe = Path(folder) / target.name
            probe.write_bytes(data)
            try:
                read_cloud(probe)
            except StandgridError as exc:
                raise type(exc)(exc.message, path=target, line=exc.line) from exc

    def _add_vertex(self, stamp: Stamp, pose: Matrix4 | None) -> None:
        if pose is None:
            return
        graph_file = self.path / GRAPH_FILE
        graph = read_pose_graph(graph_file) if graph_file.is_file() else PoseGraph({})
        if any(v.stamp == stamp for v in graph.vertices.values()):
            return
        next_id = max(graph.vertices, default=-1) + 1
        vertices = dict(graph.vertices)
        vertices[next_id] = Vertex(next_id, stamp, np.asarray(pose, dtype=np.float64))
        vertices = dict(sorted(vertices.items(), key=lambda item: item[1].stamp.ns))
        graph.vertices = vertices
        write_pose_graph(graph, graph_file)

    # --- pose graph and GNSS ----------------------------------------------------------------

    def set_graph(self, text: bytes) -> Outcome:
        """Replace the pose graph (g2o text, read back before it is kept)."""
        self._require()
        target = self.path / GRAPH_FILE
        with self.locked():
            if target.is_file() and _digest(target.read_bytes()) == _digest(text):
                return "unchanged"
            with tempfile.TemporaryDirectory(prefix="standgrid-live-") as folder:
                probe = Path(folder) / GRAPH_FILE
                probe.write_bytes(text)
                try:
                    read_pose_graph(probe)
                except StandgridError as exc:
                    raise type(exc)(exc.message, path=target, line=exc.line) from exc
            with atomic_output(target) as tmp:
                tmp.write_bytes(text)
            return "stored"

    def add_gnss(self, text: bytes) -> tuple[Outcome, int]:
        """Merge GNSS fixes (the canonical text log) into ``gnss/fixes.txt``; fixes already
        there are kept once. Returns the outcome and how many fixes were new."""
        self._require()
        target = self.path / GNSS_FILE
        with tempfile.TemporaryDirectory(prefix="standgrid-live-") as folder:
            probe = Path(folder) / "fixes.txt"
            probe.write_bytes(text)
            try:
                incoming = read_gnss(probe)
            except StandgridError as exc:
                raise type(exc)(exc.message, path=target, line=exc.line) from exc
        with self.locked():
            existing = read_gnss(target) if target.is_file() else None
            merged: GnssFixes = concat_gnss([p for p in (existing, incoming) if p is not None])
            new = len(merged) - (0 if existing is None else len(existing))
            if new == 0 and existing is not None:
                return "unchanged", 0
            target.parent.mkdir(parents=True, exist_ok=True)
            write_gnss(merged, target)
            return "stored", new


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
