"""The streaming partition engine: points in (chunk by chunk), points out grouped by cell.

Per chunk: the keys are computed and argsorted once (stable, so arrival order survives
within a cell; a radix sort when the chunk spans few cells); the chunk's own arrays are held
with that order, not copied. No per-cell work happens while adding. When the held blocks
pass the memory budget they are merged (a stable sort by key) into one run of structured
records (``xyz`` + every field) appended to a single spill file per store, with a per-cell
index ``(key, byte offset, count)``. So the cells' spilled data are contiguous
extents of one file: one file is open at a time whatever the number of cells (creating
thousands of per-cell files is what costs most on real file systems, ~2 ms each here).
:meth:`PartitionEngine.finalise` yields the cells in key order, each read back with
``os.preadv`` (runs in spill order), or gathered from the held blocks straight into its
output arrays (arrival order), and checks that every point came out exactly once.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from standgrid.engine.budget import DEFAULT_MEMORY_BUDGET, release_memory
from standgrid.errors import ConservationError, GridError, StandgridError
from standgrid.partition.grid import StandGrid, key_to_index
from standgrid.pointcloud import PointCloud

#: Held points are spilled beyond this fraction of the budget: the rest is for the
#: temporaries of a spill (one slice: see :data:`_SPILL_SLICE`) and of an added chunk (its
#: keys and their order; the chunk's own arrays are counted by whoever loaded it).
_SPILL_AT = 0.8
#: Bytes gathered per write when a run is spilled, as a fraction of the budget.
_SPILL_SLICE = 1 / 64
_XYZ = "xyz"
WITHHELD = "withheld"

KeyFunction = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.integer]]


class ChunkSchemaError(StandgridError, ValueError):
    """A chunk whose field names or dtypes differ from the first chunk's."""


class BufferFunction(Protocol):
    """Which points are copied into which neighbouring cells' buffers."""

    def __call__(
        self, x: NDArray[np.float64], y: NDArray[np.float64], keys: NDArray[np.int64]
    ) -> tuple[NDArray[np.intp], NDArray[np.int64]]:
        """``(point_index, target_key)`` pairs; a target key never equals the point's own key."""
        ...


@dataclass(frozen=True)
class GridBuffer:
    """Buffer rule for a :class:`StandGrid` level: a point within ``distance`` metres
    (Euclidean, to the closed bounds) of one of the 8 neighbouring cells is copied into it."""

    grid: StandGrid
    distance: float
    level: int = 0

    def __post_init__(self) -> None:
        size = self.grid.level_size(self.level)
        if not 0 < self.distance < size:
            raise GridError(f"buffer distance must be in (0, {size}) m, got {self.distance!r}")

    def __call__(
        self, x: NDArray[np.float64], y: NDArray[np.float64], keys: NDArray[np.int64]
    ) -> tuple[NDArray[np.intp], NDArray[np.int64]]:
        s = self.grid.level_size(self.level)
        x0, y0 = self.grid.origin
        ix, iy = key_to_index(keys)
        xmin = x0 + ix.astype(np.float64) * s
        ymin = y0 + iy.astype(np.float64) * s
        gaps_x = {-1: x - xmin, 0: np.zeros_like(x), 1: (xmin + s) - x}
        gaps_y = {-1: y - ymin, 0: np.zeros_like(y), 1: (ymin + s) - y}
        d2 = self.distance * self.distance
        index_parts: list[NDArray[np.intp]] = []
        key_parts: list[NDArray[np.int64]] = []
        for di in (-1, 0, 1):
            near_x = gaps_x[di] <= self.distance
            for dj in (-1, 0, 1):
                if di == 0 and dj == 0:
                    continue
                near = near_x & (gaps_y[dj] <= self.distance)
                if di and dj:
                    near &= gaps_x[di] ** 2 + gaps_y[dj] ** 2 <= d2
                idx = np.flatnonzero(near)
                index_parts.append(idx)
                key_parts.append(keys[idx] + ((di << 32) + dj))
        return np.concatenate(index_parts), np.concatenate(key_parts)


@dataclass(frozen=True)
class CellPoints:
    """One cell's output: its ``core`` points and, when buffering, the ``buffer`` copies of
    neighbours' points (same fields plus ``withheld`` = True; empty when there are none)."""

    key: int
    core: PointCloud
    buffer: PointCloud | None = None

    def combined(self) -> PointCloud:
        """Core then buffer points, with a bool ``withheld`` field (True = buffer copy)."""
        core = self.core.with_fields(**{WITHHELD: np.zeros(len(self.core), dtype=bool)})
        return core if self.buffer is None else PointCloud.concat([core, self.buffer])


@dataclass
class PartitionStats:
    """Counters of one engine run (``peak_buffered_bytes``: held blocks, before a spill)."""

    points_in: int = 0
    points_out: int = 0
    buffer_points: int = 0
    cells: int = 0
    bytes_spilled: int = 0
    spill_flushes: int = 0
    peak_buffered_bytes: int = 0


@dataclass(frozen=True)
class _Block:
    """One chunk's points as held: its arrays (``xyz`` and every field, by name), the rows
    in stable key order (None: the rows as they are) and the keys' runs in that order
    (distinct keys, first position, count)."""

    columns: dict[str, NDArray[Any]]
    order: NDArray[np.integer] | None
    runs: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]
    count: int

    @classmethod
    def of(
        cls, columns: dict[str, NDArray[Any]], order: Any, sorted_keys: NDArray[np.int64]
    ) -> _Block:
        if order is not None and len(order) and int(order.max()) < 2**31:
            order = order.astype(np.int32)  # half the memory of intp
        ukeys, first, counts = _runs_of(sorted_keys)
        return cls(columns, order, (ukeys, first, counts), len(sorted_keys))

    @property
    def nbytes(self) -> int:
        """Bytes of the order and the runs (the columns are counted by the caller)."""
        order = 0 if self.order is None else self.order.nbytes
        return order + sum(a.nbytes for a in self.runs)

    def sorted_keys(self) -> NDArray[np.int64]:
        ukeys, _, counts = self.runs
        return np.repeat(ukeys, counts)

    def rows(self, index: Any) -> Any:
        """Rows of the columns holding the points at ``index`` of the key order."""
        return index if self.order is None else self.order[index]


class _Store:
    """Key-sorted blocks in memory; spilled as key-sorted runs appended to one spill file.

    Each :meth:`add` keeps one block (a stable key order of a chunk). A :meth:`spill` merges
    every held block into one run — a stable sort by key over the blocks in arrival order,
    written slice by slice so it needs little memory beyond the blocks themselves — appended
    to the store's single spill file with a per-key index ``(key, byte offset, count)``.
    Only one file is ever open, whatever the number of cells.
    """

    def __init__(self, path: Path, dtype: np.dtype, slice_bytes: int) -> None:
        self.path = path
        self.dtype = dtype
        self.slice_records = max(1024, slice_bytes // dtype.itemsize)
        self.blocks: list[_Block] = []
        self.bytes = 0
        self.runs: list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]] = []
        self.file_bytes = 0

    def add(self, block: _Block, held_bytes: int) -> None:
        """Keep a block (``held_bytes``: what it is counted as against the budget)."""
        if block.count:
            self.blocks.append(block)
            self.bytes += held_bytes

    def spill(self) -> int:
        """Write every held block as one key-sorted run; returns the bytes written.

        No order over all the held points is built: the run is the blocks' key runs sorted
        by (key, block), so each slice of it is gathered from the extents it spans, and the
        spill needs memory for one slice beyond the blocks themselves.
        """
        if not self.blocks:
            return 0
        starts = np.cumsum([0] + [b.count for b in self.blocks])
        # every block's key runs: (key, block, position in the blocks' key orders, count)
        ukeys = np.concatenate([b.runs[0] for b in self.blocks])
        which = np.concatenate([np.full(len(b.runs[0]), j) for j, b in enumerate(self.blocks)])
        at = np.concatenate([b.runs[1] + starts[j] for j, b in enumerate(self.blocks)])
        counts = np.concatenate([b.runs[2] for b in self.blocks])
        order = np.lexsort((which, ukeys))  # by key, then arrival order
        ukeys, at, counts = ukeys[order], at[order], counts[order]
        ends = np.cumsum(counts)  # where each extent ends in the run ...
        begins = ends - counts  # ... and begins
        shift = at - begins  # a run position + shift: the position in the blocks' key orders
        total = int(ends[-1])
        start_offset = self.file_bytes
        with open(self.path, "ab") as f:
            for a in range(0, total, self.slice_records):
                b = min(a + self.slice_records, total)
                e0 = int(np.searchsorted(ends, a, side="right"))  # the extents in a..b
                e1 = int(np.searchsorted(begins, b, side="left"))
                lengths = np.minimum(ends[e0:e1], b) - np.maximum(begins[e0:e1], a)
                take = np.arange(a, b, dtype=np.int64)
                take += np.repeat(shift[e0:e1], lengths)
                self._write_slice(f, take, starts)
        written = total * self.dtype.itemsize
        self.file_bytes += written
        first = np.flatnonzero(np.r_[True, ukeys[1:] != ukeys[:-1]])
        offsets = begins[first] * self.dtype.itemsize + start_offset
        self.runs.append((ukeys[first], offsets, np.add.reduceat(counts, first)))
        self.blocks.clear()
        self.bytes = 0
        return written

    def _write_slice(self, f: Any, take: NDArray[np.int64], starts: NDArray[np.int64]) -> None:
        """Gather the records at ``take`` (positions in the blocks' key orders) and write them."""
        which = np.searchsorted(starts, take, side="right") - 1
        by_block = np.argsort(which, kind="stable")
        blocks, first, counts = _runs_of(which[by_block])
        piece = np.empty(len(take), dtype=self.dtype)
        for j, b, m in zip(blocks.tolist(), first.tolist(), counts.tolist(), strict=True):
            at = by_block[b : b + m]
            block = self.blocks[j]
            rows = block.rows(take[at] - starts[j])
            for name, values in block.columns.items():
                piece[name][at] = np.take(values, rows, axis=0)
        piece.tofile(f)

    def extents(self) -> Iterator[tuple[int, list[tuple[int, int, int]]]]:
        """Per key (sorted): its extents ``(source, start, count)`` in arrival order.

        ``source`` -1 is the spill file (``start`` a byte offset); ``j >= 0`` is held block
        ``j`` (``start`` a record index).
        """
        tables = []
        for ukeys, offsets, counts in self.runs:
            tables.append((ukeys, np.full(len(ukeys), -1), offsets, counts))
        for j, block in enumerate(self.blocks):
            ukeys, first, counts = block.runs
            tables.append((ukeys, np.full(len(ukeys), j), first, counts))
        if not tables:
            return
        seq = np.concatenate([np.full(len(t[0]), i) for i, t in enumerate(tables)])
        all_keys, source, start, count = (np.concatenate(c) for c in zip(*tables, strict=True))
        order = np.lexsort((seq, all_keys))  # by key, then arrival order
        all_keys, source, start, count = (a[order] for a in (all_keys, source, start, count))
        ukeys, first, n = _runs_of(all_keys)
        src, st, ct = source.tolist(), start.tolist(), count.tolist()
        for key, a, m in zip(ukeys.tolist(), first.tolist(), n.tolist(), strict=True):
            yield key, [(src[i], st[i], ct[i]) for i in range(a, a + m)]

    def read(self, extents: list[tuple[int, int, int]], fd: int | None) -> dict[str, Any]:
        """One key's points, in arrival order, from its extents: one array per column."""
        names = self.dtype.names or ()
        spilled = [e for e in extents if e[0] < 0]
        if extents and len(spilled) == len(extents):  # all in the spill file: one read
            records = self._read_spilled(spilled, fd)
            return {name: np.ascontiguousarray(records[name]) for name in names}
        total = sum(c for _, _, c in extents)
        out = {
            name: np.empty((total, *self.dtype[name].shape), dtype=self.dtype[name].base)
            for name in names
        }
        at = 0
        for source, start, count in extents:
            if source < 0:
                records = self._read_spilled([(source, start, count)], fd)
                for name in names:
                    out[name][at : at + count] = records[name]
            elif self.blocks[source].order is None:
                block = self.blocks[source]
                for name in names:
                    out[name][at : at + count] = block.columns[name][start : start + count]
            else:
                block = self.blocks[source]
                rows = block.rows(slice(start, start + count))
                for name in names:
                    # take into the output (rows are a permutation's: "clip" never clips; it
                    # spares take's buffer, and is ~4x faster than indexing an (N, 3) array)
                    np.take(
                        block.columns[name],
                        rows,
                        axis=0,
                        out=out[name][at : at + count],
                        mode="clip",
                    )
            at += count
        return out

    def _read_spilled(self, extents: list[tuple[int, int, int]], fd: int | None) -> Any:
        """Records of spill-file extents ``(-1, byte offset, count)``, one after the other."""
        assert fd is not None
        out = np.empty(sum(c for _, _, c in extents), dtype=self.dtype)
        view = out.view(np.uint8).data
        itemsize = self.dtype.itemsize
        at = 0
        for _, start, count in extents:
            lo, hi = at * itemsize, (at + count) * itemsize
            while lo < hi:  # a single read may return less (e.g. > 2 GiB on Linux)
                got = os.preadv(fd, [view[lo:hi]], start + lo - at * itemsize)
                if got <= 0:
                    raise ConservationError(
                        f"spill file ended early: {hi - lo} bytes missing at {start}",
                        path=self.path,
                    )
                lo += got
            at += count
        return out


def _stable_order(keys: NDArray[np.int64]) -> NDArray[np.intp] | None:
    """The stable argsort of ``keys`` (None when they are all equal: already in order).

    Keys whose high and low 32-bit halves span few values (a chunk covering a few cells)
    are ranked ``(high, low)`` into uint16, which numpy sorts stably by radix: the same
    order as a stable sort of the int64 keys, much faster.
    """
    if len(keys) == 0 or keys.min() == keys.max():
        return None
    high, low = keys >> 32, keys & 0xFFFFFFFF
    high_lo, low_lo = int(high.min()), int(low.min())
    columns = int(low.max()) - low_lo + 1
    if (int(high.max()) - high_lo + 1) * columns <= 1 << 16:
        high -= high_lo  # the rank (high - high_lo) * columns + (low - low_lo), in place
        high *= columns
        low -= low_lo
        high += low
        return np.argsort(high.astype(np.uint16), kind="stable")
    return np.argsort(keys, kind="stable")


def _held(values: NDArray[Any]) -> NDArray[Any]:
    """A chunk's array as the engine holds it: the array itself when it owns its data (made
    read-only: a later change by the caller would silently change the cells), else a copy
    (a view would keep a larger base alive, beyond what the budget counts)."""
    if values.base is not None or not values.flags.c_contiguous:
        return np.array(values)
    values.flags.writeable = False
    return values


def _runs_of(sorted_keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], ...]:
    """Distinct keys of a sorted array, the index of each one's first record, and counts."""
    if len(sorted_keys) == 0:
        empty = np.empty(0, dtype=np.int64)
        return empty, empty, empty
    first = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    counts = np.diff(np.r_[first, len(sorted_keys)])
    return sorted_keys[first], first.astype(np.int64), counts.astype(np.int64)


class PartitionEngine:
    """Group streamed points by ``assign(x, y) -> int64 keys`` within a memory budget.

    Use as a context manager (or call :meth:`close`) so the spill folder is removed even when
    :meth:`finalise` is not run to the end.
    """

    def __init__(
        self,
        assign: KeyFunction,
        workdir: str | PathLike[str],
        *,
        memory_budget_bytes: int = DEFAULT_MEMORY_BUDGET,
        buffer: BufferFunction | None = None,
    ) -> None:
        if memory_budget_bytes <= 0:
            raise ValueError(f"memory budget must be positive, got {memory_budget_bytes}")
        self.assign = assign
        self.buffer = buffer
        self.memory_budget_bytes = int(memory_budget_bytes)
        Path(workdir).mkdir(parents=True, exist_ok=True)
        self._dir = Path(tempfile.mkdtemp(prefix="partition-", dir=workdir))
        self._names: tuple[str, ...] | None = None
        self._dtype: np.dtype | None = None
        self._core: _Store | None = None
        self._buf: _Store | None = None
        self._state = "open"
        self.stats = PartitionStats()

    # -- input ----------------------------------------------------------------------------

    def _schema(self, chunk: PointCloud) -> np.dtype:
        """The record dtype (fixed by the first chunk); field order may differ between chunks."""
        names = tuple(self._names or chunk.fields)
        descr: list[tuple[str, np.dtype, tuple[int, ...]]] = [(_XYZ, np.dtype(np.float64), (3,))]
        for name in names:
            if name in (_XYZ, WITHHELD):
                raise ChunkSchemaError(f"field name {name!r} is reserved by the partition engine")
            values = chunk.fields.get(name)
            if values is None:
                break
            descr.append((name, values.dtype, values.shape[1:]))
        dtype = np.dtype(descr)
        if self._dtype is None:
            self._names, self._dtype = names, dtype
            slice_bytes = int(self.memory_budget_bytes * _SPILL_SLICE)
            self._core = _Store(self._dir / "core.bin", dtype, slice_bytes)
            if self.buffer is not None:
                self._buf = _Store(self._dir / "buffer.bin", dtype, slice_bytes)
        elif dtype != self._dtype or set(chunk.fields) != set(names):
            raise ChunkSchemaError(
                f"chunk fields {_describe_fields(chunk)} differ from the first chunk's "
                f"{_describe(self._dtype)}"
            )
        return self._dtype

    def add(self, chunk: PointCloud) -> None:
        """Partition one chunk (in the output CRS; any fields, the same for every chunk).

        The chunk's arrays are held as they are, not copied, and made read-only (views of
        larger arrays are copied): change them after adding and numpy raises.
        """
        if self._state != "open":
            raise RuntimeError(f"cannot add points: the engine is {self._state}")
        dtype = self._schema(chunk)
        n = len(chunk)
        if n == 0:
            return
        x, y = chunk.xyz[:, 0], chunk.xyz[:, 1]
        raw = np.asarray(self.assign(x, y))
        if raw.shape != (n,) or not np.issubdtype(raw.dtype, np.integer):
            raise GridError(
                f"assign returned {raw.dtype} {raw.shape}, expected ({n},) integer keys"
            )
        keys: NDArray[np.int64] = raw.astype(np.int64, copy=False)
        columns = {_XYZ: _held(chunk.xyz)}
        columns.update((name, _held(chunk.fields[name])) for name in self._names or ())
        held = sum(v.nbytes for v in columns.values())
        assert self._core is not None
        order = _stable_order(keys)
        block = _Block.of(columns, order, keys if order is None else keys[order])
        self._core.add(block, held + block.nbytes)
        self.stats.points_in += n
        if self.buffer is not None:
            assert self._buf is not None
            index, targets = self.buffer(x, y, keys)
            index, targets = np.asarray(index, dtype=np.intp), np.asarray(targets, np.int64)
            border = _stable_order(targets)
            if border is not None:
                index, targets = index[border], targets[border]
            copies = _Block.of(columns, index, targets)
            # counted as the records the copies become when read or spilled
            self._buf.add(copies, copies.count * dtype.itemsize + copies.nbytes)
        self._balance()

    def _stores(self) -> list[_Store]:
        return [s for s in (self._core, self._buf) if s is not None]

    def _balance(self) -> None:
        held = sum(s.bytes for s in self._stores())
        self.stats.peak_buffered_bytes = max(self.stats.peak_buffered_bytes, held)
        if held > self.memory_budget_bytes * _SPILL_AT:
            self._spill()

    def _spill(self) -> None:
        for store in self._stores():
            self.stats.bytes_spilled += store.spill()
        self.stats.spill_flushes += 1
        release_memory()

    # -- output ---------------------------------------------------------------------------

    def finalise(self) -> Iterator[CellPoints]:
        """Yield every cell with core points, in sorted key order; then check conservation.

        A cell's points come in arrival order. Once anything was spilled, what is still held
        is spilled too, so every cell is read back as a few contiguous extents.
        """
        if self._state != "open":
            raise RuntimeError(f"cannot finalise: the engine is {self._state}")
        self._state = "finalising"
        fds: dict[str, int] = {}
        try:
            if self._core is not None:
                if self._core.runs or (self._buf is not None and self._buf.runs):
                    self._spill()
                for name, store in (("core", self._core), ("buffer", self._buf)):
                    if store is not None and store.runs:
                        fds[name] = _open_spill(store)
                yield from self._cells(fds)
            if self.stats.points_out != self.stats.points_in:
                raise ConservationError(
                    f"{self.stats.points_in} points went in, {self.stats.points_out} came out"
                )
        finally:
            for fd in fds.values():
                os.close(fd)
            self.close()
        self._state = "finalised"

    def _cells(self, fds: dict[str, int]) -> Iterator[CellPoints]:
        assert self._core is not None
        buffer_extents = self._buf.extents() if self._buf is not None else iter(())
        pending = next(buffer_extents, None)
        for key, extents in self._core.extents():
            core = self._cloud(self._core.read(extents, fds.get("core")))
            buffer = None
            if self._buf is not None:
                while pending is not None and pending[0] < key:
                    pending = next(buffer_extents, None)  # buffer copies for an empty cell
                if pending is not None and pending[0] == key:
                    columns = self._buf.read(pending[1], fds.get("buffer"))
                else:
                    columns = self._buf.read([], None)
                buffer = self._cloud(columns)
                buffer = buffer.with_fields(**{WITHHELD: np.ones(len(buffer), dtype=bool)})
                self.stats.buffer_points += len(buffer)
            self.stats.points_out += len(core)
            self.stats.cells += 1
            yield CellPoints(int(key), core, buffer)

    def _cloud(self, columns: dict[str, Any]) -> PointCloud:
        return PointCloud(columns[_XYZ], {name: columns[name] for name in self._names or ()})

    def close(self) -> None:
        """Drop all held points and remove the spill folder."""
        self._core = self._buf = None
        if self._state == "open":
            self._state = "closed"
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> PartitionEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_spill(store: _Store) -> int:
    fd = os.open(store.path, os.O_RDONLY)
    size = os.fstat(fd).st_size
    if size != store.file_bytes:
        os.close(fd)
        raise ConservationError(
            f"spill file holds {size} bytes, {store.file_bytes} were written", path=store.path
        )
    return fd


def _describe_fields(chunk: PointCloud) -> str:
    return (
        "{" + ", ".join(f"{n}: {v.dtype}{v.shape[1:] or ''}" for n, v in chunk.fields.items()) + "}"
    )


def _describe(dtype: np.dtype | None) -> str:
    if dtype is None or dtype.names is None:
        return "{}"
    fields: dict[str, Any] = dict(dtype.fields or {})
    return "{" + ", ".join(f"{n}: {fields[n][0]}" for n in dtype.names if n != _XYZ) + "}"
