"""The partition engine spread over processes: each chunk partitioned where it is loaded.

For a cluster, points do not travel through the process that writes the catalog. Each item
(a payload, an old tile) is loaded, assigned to cells, stably sorted by cell key and
written, core then buffer copies, to its own run file in a folder every worker reaches
(:func:`spill_chunk`); only the per-cell extents come back. A cell is then read from the
runs of every item in item order (:func:`read_cell`): the same points in the same order as
:class:`~standgrid.partition.engine.PartitionEngine` gives in one process (stable sort per
chunk, then arrival order).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import ConservationError
from standgrid.partition.chunks import PayloadChunk
from standgrid.partition.engine import WITHHELD, BufferFunction, CellPoints, _runs_of
from standgrid.pointcloud import PointCloud

_XYZ = "xyz"


@dataclass(frozen=True)
class SpillTask:
    """Load ``item`` with ``load`` (a module-level function: a PointCloud or a
    PayloadChunk), partition it by ``assign`` (+ ``buffer``) into the run file ``path``."""

    load: Callable[[Any], Any]
    item: Any
    assign: Callable[[Any, Any], NDArray[np.int64]]
    buffer: BufferFunction | None
    path: Path


@dataclass(frozen=True)
class Run:
    """One item's run file: per cell key, the record offset and count of its core points,
    and of the buffer copies it holds for neighbouring cells (after the core records)."""

    path: Path
    descr: list[tuple[Any, ...]]
    points: int
    core: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]
    buffer: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]
    #: What the loader gave besides the points (a payload's footprint and count of source
    #: points left out as withheld), or None.
    extra: Any = None


def spill_chunk(task: SpillTask) -> Run:
    """Load, partition and write one item's run (see the module doc)."""
    got = task.load(task.item)
    if isinstance(got, PayloadChunk):
        cloud, extra = got.cloud, (got.footprint, got.withheld)
    else:
        cloud, extra = got, None
    names = list(cloud.fields)
    descr: list[tuple[Any, ...]] = [(_XYZ, np.dtype(np.float64).str, (3,))]
    descr += [(n, v.dtype.str, v.shape[1:]) for n, v in cloud.fields.items()]
    dtype = np.dtype(descr)
    n = len(cloud)
    records = np.empty(n, dtype=dtype)
    records[_XYZ] = cloud.xyz
    for name in names:
        records[name] = cloud.fields[name]
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    keys = (
        np.asarray(task.assign(x, y)).astype(np.int64, copy=False) if n else np.empty(0, np.int64)
    )
    order = np.argsort(keys, kind="stable")
    core_keys = keys[order]
    if task.buffer is not None and n:
        index, targets = task.buffer(x, y, keys)
        border = np.argsort(targets, kind="stable")
        buffer_records = np.take(records, np.asarray(index)[border])
        buffer_keys = targets[border]
    else:
        buffer_records, buffer_keys = records[:0], np.empty(0, np.int64)
    task.path.parent.mkdir(parents=True, exist_ok=True)
    with open(task.path, "wb") as f:
        np.take(records, order).tofile(f)
        buffer_records.tofile(f)
    ukeys, first, counts = _runs_of(core_keys)
    bkeys, bfirst, bcounts = _runs_of(buffer_keys)
    return Run(task.path, descr, n, (ukeys, first, counts), (bkeys, bfirst + n, bcounts), extra)


@dataclass(frozen=True)
class CellExtents:
    """Where one cell's records are: ``(run path, descr, record offset, count)``, in item
    order, for its core points and its buffer copies."""

    key: int
    core: list[tuple[Path, list[tuple[Any, ...]], int, int]]
    buffer: list[tuple[Path, list[tuple[Any, ...]], int, int]] | None


def cell_extents(runs: Sequence[Run], buffered: bool) -> list[CellExtents]:
    """Every cell with core points, in key order, with its extents in the runs (item order)."""
    core: dict[int, list[tuple[Path, list[tuple[Any, ...]], int, int]]] = {}
    buffer: dict[int, list[tuple[Path, list[tuple[Any, ...]], int, int]]] = {}
    for run in runs:
        for table, part in ((core, run.core), (buffer, run.buffer)):
            for key, start, count in zip(*(a.tolist() for a in part), strict=True):
                table.setdefault(key, []).append((run.path, run.descr, start, count))
    return [
        CellExtents(key, core[key], buffer.get(key, []) if buffered else None)
        for key in sorted(core)
    ]


def read_cell(extents: CellExtents) -> CellPoints:
    """One cell's core points (and buffer copies, flagged withheld) read from the runs."""
    core = _read(extents.core)
    buffer = None
    if extents.buffer is not None:
        buffer = _read(extents.buffer, like=extents.core[0][1])
        buffer = buffer.with_fields(**{WITHHELD: np.ones(len(buffer), dtype=bool)})
    return CellPoints(extents.key, core, buffer)


def _read(
    parts: list[tuple[Path, list[tuple[Any, ...]], int, int]],
    like: list[tuple[Any, ...]] | None = None,
) -> PointCloud:
    descr = parts[0][1] if parts else like
    assert descr is not None
    dtype = np.dtype([tuple(d) for d in descr])
    out = np.empty(sum(p[3] for p in parts), dtype=dtype)
    at = 0
    for path, _, start, count in parts:
        got = np.fromfile(path, dtype=dtype, count=count, offset=start * dtype.itemsize)
        if len(got) != count:
            raise ConservationError(
                f"run file ended early: {count - len(got)} records missing", path=path
            )
        out[at : at + count] = got
        at += count
    names = [n for n in dtype.names or () if n != _XYZ]
    return PointCloud(
        np.ascontiguousarray(out[_XYZ]), {n: np.ascontiguousarray(out[n]) for n in names}
    )
