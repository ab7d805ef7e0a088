"""SLAM pose graphs (``.g2o`` / ``.slam``): vertices with stamps, classified edges, GNSS anchors."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum
from itertools import chain
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
        """Vertices keyed by stamp (check for duplicates with :meth:`duplicate_stamps`)."""
        return {v.stamp: v for v in self.vertices.values()}

    def duplicate_stamps(self) -> dict[Stamp, list[int]]:
        """Stamps carried by more than one vertex -> their vertex ids."""
        seen: dict[Stamp, list[int]] = {}
        for v in self.vertices.values():
            seen.setdefault(v.stamp, []).append(v.id)
        return {s: ids for s, ids in seen.items() if len(ids) > 1}


# --- reading and writing ---------------------------------------------------------------------
#
# Format (docs MISSION_FORMAT.md section 2): whitespace-separated tokens, ``#`` comments.
# Decisions: a plain ``VERTEX_SE3:QUAT`` (no time stamp) is a PoseGraphFormatError, because
# standgrid matches payloads to vertices by stamp and a vertex without one cannot be used;
# tags this reader does not model (TAG_DETECTION, TAG_POSE, IMAGE_POSE, EDGE_POSE_TO_IMAGE, any
# unknown tag) are skipped and counted in ``PoseGraph.skipped_tags``. A second ``PLATFORM_ID``
# with a different value keeps the first and is counted as skipped too.

_VERTEX_TAG = "VERTEX_SE3:QUAT_TIME"
_UNTIMED_VERTEX_TAG = "VERTEX_SE3:QUAT"
_EDGE_TAGS = {
    "EDGE_SE3:QUAT": None,
    "EDGE_SE3_SWITCHABLE": "switchable",
    "EDGE_SE3_MAXMIX": "maxmix",
}
_N_INFO = 21  # upper triangle of the 6x6 information matrix
_TRIU = np.triu_indices(6)


def _pose_error(path: Path, line: int, message: str) -> Exception:
    from standgrid.errors import PoseGraphFormatError

    return PoseGraphFormatError(message, path=path, line=line)


def _numeric_rows(
    rows: list[list[str]], lines: list[int], path: Path, what: str
) -> NDArray[np.float64]:
    """Rows of number tokens -> float array; the first bad row is reported with its line."""
    width = len(rows[0]) if rows else 0
    try:
        flat = np.fromiter(
            map(float, chain.from_iterable(rows)), dtype=np.float64, count=len(rows) * width
        )
    except ValueError:
        for tokens, line in zip(rows, lines, strict=True):
            for tok in tokens:
                try:
                    float(tok)
                except ValueError:
                    raise _pose_error(path, line, f"{what}: non-numeric token {tok!r}") from None
        raise
    arr = flat.reshape(len(rows), width)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise _pose_error(path, lines[k], f"{what}: NaN or infinite value")
    return arr


def _quat_poses(values: NDArray[np.float64], lines: list[int], path: Path, what: str) -> Matrix4:
    """``(N, 7)`` ``x y z qx qy qz qw`` -> ``(N, 4, 4)`` in one batched conversion."""
    from standgrid.geometry import pose_matrix

    norms = np.linalg.norm(values[:, 3:7], axis=1)
    bad = norms < 1e-12
    if bad.any():
        k = int(np.argmax(bad))
        raise _pose_error(path, lines[k], f"{what}: zero quaternion")
    if len(values) == 0:
        return np.zeros((0, 4, 4))
    return pose_matrix(values[:, :3], values[:, 3:7])


def read_pose_graph(path: str | Path) -> PoseGraph:
    """Read a VILENS ``.g2o`` / ``.slam`` pose graph.

    Raises :class:`~standgrid.errors.PoseGraphFormatError` (with file and line) for a known tag
    with the wrong token count, a non-numeric or non-finite number, a zero quaternion, a
    duplicate vertex id, an edge to a missing vertex or an untimed ``VERTEX_SE3:QUAT``; and
    :class:`~standgrid.errors.MissionNotFoundError` when the file does not exist (any other
    OS error, e.g. a folder, is a ``PoseGraphFormatError``). Duplicate
    stamps are not an error here (see :meth:`PoseGraph.duplicate_stamps`).
    """
    from standgrid.errors import MissionNotFoundError, PoseGraphFormatError

    src = Path(path)
    try:
        text = src.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError as exc:
        raise MissionNotFoundError("pose graph not found", path=src) from exc
    except UnicodeDecodeError as exc:
        raise _pose_error(src, 1, f"not a text file ({exc.reason})") from exc
    except OSError as exc:  # a folder, no permission, ...
        msg = f"cannot read pose graph: {exc.strerror or exc}"
        raise PoseGraphFormatError(msg, path=src) from exc
    if not text.strip():
        raise _pose_error(src, 1, "empty pose graph file")

    v_ids: list[int] = []
    v_nums: list[list[str]] = []
    v_stamps: list[tuple[str, str]] = []
    v_lines: list[int] = []
    e_ids: list[tuple[int, int]] = []
    e_nums: list[list[str]] = []
    e_robust: list[tuple[str | None, str | None]] = []
    e_lines: list[int] = []
    platform_id: int | None = None
    lla_ref: tuple[float, float, float] | None = None
    to_map: Matrix4 | None = None
    skipped: Counter[str] = Counter()

    def expect(tokens: list[str], n: int, line: int) -> None:
        if len(tokens) != n:
            raise _pose_error(src, line, f"{tokens[0]} needs {n - 1} values, got {len(tokens) - 1}")

    def to_int(tok: str, line: int, what: str) -> int:
        try:
            return int(tok)
        except ValueError:
            raise _pose_error(src, line, f"{what}: not an integer: {tok!r}") from None

    for lineno, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if tag == _VERTEX_TAG:
            expect(tokens, 11, lineno)
            v_ids.append(to_int(tokens[1], lineno, "vertex id"))
            v_nums.append(tokens[2:9])
            v_stamps.append((tokens[9], tokens[10]))
            v_lines.append(lineno)
        elif tag in _EDGE_TAGS:
            robust = _EDGE_TAGS[tag]
            extra = 0 if robust is None else 1
            expect(tokens, 3 + extra + 7 + _N_INFO, lineno)
            i = to_int(tokens[1], lineno, "edge vertex i")
            j = to_int(tokens[2], lineno, "edge vertex j")
            e_ids.append((i, j))
            e_robust.append((robust, tokens[3] if extra else None))
            e_nums.append(tokens[3 + extra :])  # x y z q(4) + 21 information values
            e_lines.append(lineno)
        elif tag == "PLATFORM_ID":
            expect(tokens, 2, lineno)
            pid = to_int(tokens[1], lineno, "PLATFORM_ID")
            if platform_id is None:
                platform_id = pid
            elif pid != platform_id:
                skipped[tag] += 1
        elif tag == "GNSS_LLA_REF":
            expect(tokens, 4, lineno)
            ref = _numeric_rows([tokens[1:]], [lineno], src, tag)[0]
            if not (-90 <= ref[0] <= 90 and -180 <= ref[1] <= 180):
                raise _pose_error(src, lineno, f"{tag}: latitude/longitude out of range")
            lla_ref = (float(ref[0]), float(ref[1]), float(ref[2]))
        elif tag == "GNSS_LLA_TO_MAP":
            expect(tokens, 8, lineno)
            vals = _numeric_rows([tokens[1:]], [lineno], src, tag)
            to_map = _quat_poses(vals, [lineno], src, tag)[0]
        elif tag == _UNTIMED_VERTEX_TAG:
            raise _pose_error(
                src,
                lineno,
                f"{tag} has no time stamp; standgrid needs {_VERTEX_TAG} "
                "(payloads are matched to vertices by stamp)",
            )
        else:
            skipped[tag] += 1

    # vertices, in one batch
    v_vals = _numeric_rows(v_nums, v_lines, src, _VERTEX_TAG) if v_nums else np.zeros((0, 7))
    v_poses = _quat_poses(v_vals, v_lines, src, _VERTEX_TAG)
    vertices: dict[int, Vertex] = {}
    for k, (vid, (sec, nsec)) in enumerate(zip(v_ids, v_stamps, strict=True)):
        if vid in vertices:
            raise _pose_error(src, v_lines[k], f"duplicate vertex id {vid}")
        try:
            stamp = Stamp.parse(sec, nsec)
        except ValueError as exc:
            raise _pose_error(src, v_lines[k], f"vertex {vid}: invalid stamp {sec} {nsec}") from exc
        vertices[vid] = Vertex(vid, stamp, v_poses[k])

    # edges, in one batch
    edges: list[Edge] = []
    if e_nums:
        e_vals = _numeric_rows(e_nums, e_lines, src, "edge")
        rel = _quat_poses(e_vals[:, :7], e_lines, src, "edge")
        upper = e_vals[:, 7:]
        info = np.empty((len(e_vals), 6, 6))
        info[:, _TRIU[0], _TRIU[1]] = upper
        info[:, _TRIU[1], _TRIU[0]] = upper
        for k, (i, j) in enumerate(e_ids):
            for vid in (i, j):
                if vid not in vertices:
                    raise _pose_error(
                        src, e_lines[k], f"edge {i} {j} refers to missing vertex {vid}"
                    )
            robust, param_token = e_robust[k]
            param = None
            if param_token is not None:
                try:
                    param = float(param_token)
                except ValueError:
                    param = math.nan
                if not math.isfinite(param):
                    raise _pose_error(
                        src, e_lines[k], f"edge {i} {j}: bad robust parameter {param_token!r}"
                    )
            edges.append(
                Edge(i, j, rel[k], info[k], robust=robust, robust_parameter=param)  # type: ignore[arg-type]
            )

    return PoseGraph(
        vertices=vertices,
        edges=edges,
        platform_id=platform_id,
        gnss_lla_ref=lla_ref,
        gnss_lla_to_map=to_map,
        skipped_tags=skipped,
        source=src,
    )


def _fmt(values: NDArray[np.float64]) -> str:
    """Shortest exact (round-trip) text of floats, single-space separated."""
    return " ".join(map(repr, values.tolist()))


def _fmt_number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))


def write_pose_graph(graph: PoseGraph, path: str | Path) -> None:
    """Write ``graph`` in the VILENS format: one space between tokens, exact floats, nsec unpadded.

    Order: a comment line, ``PLATFORM_ID``, ``GNSS_LLA_REF``, ``GNSS_LLA_TO_MAP``, vertices, edges.
    Skipped tags are not written (they were never read).
    """
    from standgrid._atomic import write_text_atomic
    from standgrid.geometry import translation_quat

    out: list[str] = [f"# {_VERTEX_TAG} id x y z qx qy qz qw sec nsec"]
    if graph.platform_id is not None:
        out.append(f"PLATFORM_ID {int(graph.platform_id)}")
    if graph.gnss_lla_ref is not None:
        out.append("GNSS_LLA_REF " + _fmt(np.asarray(graph.gnss_lla_ref, dtype=np.float64)))
    if graph.gnss_lla_to_map is not None:
        t, q = translation_quat(graph.gnss_lla_to_map)
        out.append("GNSS_LLA_TO_MAP " + _fmt(np.concatenate([t, q])))
    if graph.vertices:
        t, q = translation_quat(graph.poses)
        rows = np.concatenate([t, q], axis=1)
        for v, row in zip(graph.vertices.values(), rows, strict=True):
            out.append(f"{_VERTEX_TAG} {v.id} {_fmt(row)} {v.stamp.sec} {v.stamp.nsec}")
    if graph.edges:
        rel = np.stack([e.relative_pose for e in graph.edges])
        t, q = translation_quat(rel)
        rows = np.concatenate([t, q], axis=1)
        for e, row in zip(graph.edges, rows, strict=True):
            info = np.asarray(e.information, dtype=np.float64)[_TRIU]
            if e.robust is None:
                head = f"EDGE_SE3:QUAT {e.i} {e.j}"
            else:
                tag = "EDGE_SE3_SWITCHABLE" if e.robust == "switchable" else "EDGE_SE3_MAXMIX"
                param = e.robust_parameter if e.robust_parameter is not None else 1.0
                head = f"{tag} {e.i} {e.j} {_fmt_number(param)}"
            out.append(f"{head} {_fmt(row)} {_fmt(info)}")
    write_text_atomic(path, "\n".join(out) + "\n")
