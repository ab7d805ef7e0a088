"""Pose tables (``slam_poses.csv`` and variants) and the shared text-table reader.

Pose CSV variants (MISSION_FORMAT.md section 3)::

    # counter, sec, nsec, x, y, z, qx, qy, qz, qw      (canonical, what the writer writes)
    #counter,sec,nsec,x,y,z,qx,qy,qz,qw
    #sec,nsec,x,y,z,qx,qy,qz,qw                       (no counter)

Columns are taken from the header line; without a header, from the column count (10 ->
with counter, 9 -> without). Commas and/or whitespace separate values.

:func:`read_text_table` is the one tokenizer behind the pose CSV and the GNSS / IMU text logs
(:mod:`standgrid.mission.sensors`): it reports the exact line of a bad row.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import FormatError, MissionNotFoundError, PoseGraphFormatError
from standgrid.geometry import Matrix4
from standgrid.mission.posegraph import PoseGraph, Vertex
from standgrid.stamps import NS_PER_S, Stamp

_SPLIT = re.compile(r"[,\s]+")


@dataclass(frozen=True)
class TextTable:
    """Rows of tokens from a text log, with the canonical column names and each row's line."""

    path: Path
    columns: tuple[str, ...]
    rows: list[list[str]]
    lines: list[int]
    error: type[FormatError]

    def __len__(self) -> int:
        return len(self.rows)

    def _column_tokens(self, name: str) -> list[str]:
        k = self.columns.index(name)
        return [row[k] for row in self.rows]

    def _first_bad(self, tokens: list[str], convert: type, what: str) -> FormatError:
        for tok, line in zip(tokens, self.lines, strict=True):
            try:
                convert(tok)
            except ValueError:
                kind = "an integer" if convert is int else "a number"
                return self.error(f"{what}: not {kind}: {tok!r}", path=self.path, line=line)
        return self.error(f"{what}: cannot convert column", path=self.path)

    def ints(self, name: str) -> NDArray[np.int64]:
        """Column ``name`` as int64 (a non-integer token raises with its line)."""
        tokens = self._column_tokens(name)
        try:
            return (
                np.array(tokens, dtype=np.str_).astype(np.int64)
                if tokens
                else np.zeros(0, np.int64)
            )
        except (ValueError, OverflowError):
            raise self._first_bad(tokens, int, name) from None

    def floats(self, name: str) -> NDArray[np.float64]:
        """Column ``name`` as float64, or all-NaN when the file lacks the (optional) column."""
        if name not in self.columns:
            return np.full(len(self.rows), np.nan)
        tokens = self._column_tokens(name)
        try:
            return np.array(tokens, dtype=np.str_).astype(np.float64) if tokens else np.zeros(0)
        except ValueError:
            raise self._first_bad(tokens, float, name) from None

    def fail(self, mask: ArrayLike, message: str) -> None:
        """Raise ``message`` naming the line of the first row where ``mask`` is true."""
        mask = np.asarray(mask, dtype=bool)
        if mask.any():
            k = int(np.argmax(mask))
            raise self.error(f"{message} (row {k + 1})", path=self.path, line=self.lines[k])

    def stamps_ns(self) -> NDArray[np.int64]:
        """``sec``/``nsec`` columns -> int64 nanoseconds, checking ``0 <= nsec < 1e9``."""
        sec = self.ints("sec")
        nsec = self.ints("nsec")
        self.fail((sec < 0) | (nsec < 0) | (nsec >= NS_PER_S), "invalid stamp (sec, nsec)")
        return sec * NS_PER_S + nsec


def read_text_table(
    path: str | Path,
    *,
    aliases: Mapping[str, str],
    layouts: Mapping[int, Sequence[str]],
    required: Sequence[str],
    error: type[FormatError],
    what: str,
) -> TextTable:
    """Tokenize a comma- or whitespace-separated text log.

    ``aliases`` maps lower-case header names to canonical column names; a ``#`` line (or a
    first non-numeric line) whose names all map is the header, other ``#`` lines are comments.
    Without a header the column count picks one of ``layouts``. A row with the wrong number
    of values raises ``error`` with its line; so does a file with no content at all. A missing
    file raises :class:`MissionNotFoundError`, any other OS error (a folder) ``error``.
    """
    src = Path(path)
    try:
        text = src.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise MissionNotFoundError(f"{what} not found", path=src) from exc
    except UnicodeDecodeError as exc:
        raise error(f"{what} is not a text file ({exc.reason})", path=src, line=1) from exc
    except OSError as exc:  # a folder, no permission, ...
        raise error(f"cannot read {what}: {exc.strerror or exc}", path=src) from exc
    if not text.strip():
        raise error(f"empty {what} file", path=src, line=1)

    columns: tuple[str, ...] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        is_comment = line.startswith("#")
        if columns is None and not rows and (is_comment or not _looks_numeric(line)):
            names = [n for n in _SPLIT.split(line.lstrip("#").strip().lower()) if n]
            if names and all(n in aliases for n in names):
                columns = tuple(aliases[n] for n in names)
                missing = [c for c in required if c not in columns]
                if missing:
                    raise error(f"header lacks column(s) {missing}", path=src, line=lineno)
                continue
            if not is_comment:
                raise error(f"unrecognised header {line!r}", path=src, line=lineno)
        if is_comment:
            continue
        tokens = line.replace(",", " ").split()
        if columns is None:
            layout = layouts.get(len(tokens))
            if layout is None:
                counts = " or ".join(str(n) for n in sorted(layouts))
                raise error(
                    f"{len(tokens)} values in a row without a header; expected {counts}",
                    path=src,
                    line=lineno,
                )
            columns = tuple(layout)
        if len(tokens) != len(columns):
            raise error(
                f"{len(tokens)} values in a row, the header has {len(columns)}",
                path=src,
                line=lineno,
            )
        rows.append(tokens)
        lines.append(lineno)
    if columns is None:
        raise error(f"{what} has no header and no rows", path=src, line=1)
    return TextTable(src, columns, rows, lines, error)


def _looks_numeric(line: str) -> bool:
    token = line.replace(",", " ").split()[0]
    try:
        float(token)
    except ValueError:
        return False
    return True


# --- pose tables ---------------------------------------------------------------------------

_POSE_COLUMNS = ("sec", "nsec", "x", "y", "z", "qx", "qy", "qz", "qw")
_POSE_ALIASES = {
    "counter": "counter",
    "id": "counter",
    "index": "counter",
    "sec": "sec",
    "secs": "sec",
    "nsec": "nsec",
    "nsecs": "nsec",
    **{c: c for c in ("x", "y", "z", "qx", "qy", "qz", "qw")},
}
_POSE_LAYOUTS = {10: ("counter", *_POSE_COLUMNS), 9: _POSE_COLUMNS}
CSV_HEADER = "# counter, sec, nsec, x, y, z, qx, qy, qz, qw"


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Timed poses from a CSV: ``poses`` (N, 4, 4) float64 T_map_base, stamps two ways."""

    stamps: list[Stamp]
    stamps_ns: NDArray[np.int64]
    poses: Matrix4
    counters: NDArray[np.int64] | None = None
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @classmethod
    def from_arrays(
        cls,
        stamps_ns: NDArray[np.int64],
        poses: Matrix4,
        counters: NDArray[np.int64] | None = None,
        source: Path | None = None,
    ) -> PoseTable:
        ns = np.asarray(stamps_ns, dtype=np.int64)
        return cls(
            stamps=[Stamp.from_ns(int(n)) for n in ns],
            stamps_ns=ns,
            poses=np.asarray(poses, dtype=np.float64).reshape(len(ns), 4, 4),
            counters=None if counters is None else np.asarray(counters, dtype=np.int64),
            source=source,
        )

    @classmethod
    def from_pose_graph(cls, graph: PoseGraph) -> PoseTable:
        """The vertices of a graph as a table (counter = vertex id)."""
        return cls.from_arrays(graph.stamps_ns, graph.poses, graph.ids, graph.source)

    def to_pose_graph(self) -> PoseGraph:
        """A graph with these poses as vertices and no edges (ids = counter, else row index)."""
        ids = self.counters if self.counters is not None else np.arange(len(self))
        vertices: dict[int, Vertex] = {}
        for k, vid in enumerate(ids.tolist()):
            if vid in vertices:
                raise PoseGraphFormatError(f"duplicate counter {vid}", path=self.source)
            vertices[vid] = Vertex(vid, self.stamps[k], self.poses[k])
        return PoseGraph(vertices=vertices, source=self.source)


def read_poses_csv(path: str | Path) -> PoseTable:
    """Read a pose CSV in any of the known variants (see the module docstring)."""
    from standgrid.geometry import pose_matrix

    table = read_text_table(
        path,
        aliases=_POSE_ALIASES,
        layouts=_POSE_LAYOUTS,
        required=_POSE_COLUMNS,
        error=PoseGraphFormatError,
        what="pose CSV",
    )
    stamps_ns = table.stamps_ns()
    values = np.stack([table.floats(c) for c in _POSE_COLUMNS[2:]], axis=1).reshape(len(table), 7)
    table.fail(~np.isfinite(values).all(axis=1), "NaN or infinite pose value")
    table.fail(np.linalg.norm(values[:, 3:], axis=1) < 1e-12, "zero quaternion")
    poses = pose_matrix(values[:, :3], values[:, 3:]) if len(table) else np.zeros((0, 4, 4))
    counters = table.ints("counter") if "counter" in table.columns else None
    return PoseTable.from_arrays(stamps_ns, poses, counters, table.path)


def write_poses_csv(table: PoseTable, path: str | Path) -> None:
    """Write the canonical variant ``# counter, sec, nsec, x, y, z, qx, qy, qz, qw``.

    Counters are the table's, or the row index when it has none. Floats are written exactly
    (shortest round-trip text).
    """
    from standgrid._atomic import write_text_atomic
    from standgrid.geometry import translation_quat

    counters = table.counters if table.counters is not None else np.arange(len(table))
    out = [CSV_HEADER]
    if len(table):
        t, q = translation_quat(table.poses)
        values = np.concatenate([t, q], axis=1).tolist()
        sec, nsec = np.divmod(table.stamps_ns, NS_PER_S)
        for c, s, n, row in zip(
            counters.tolist(), sec.tolist(), nsec.tolist(), values, strict=True
        ):
            out.append(f"{c}, {s}, {n}, " + ", ".join(map(repr, row)))
    write_text_atomic(path, "\n".join(out) + "\n")
