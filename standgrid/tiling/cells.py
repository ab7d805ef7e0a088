"""An epoch's points into cells and tiles, in this process or on a cluster.

In this process, the items (old tiles, then payloads) are loaded ahead on threads and
streamed into one :class:`~standgrid.partition.engine.PartitionEngine` (bounded memory,
spill files beyond the budget); cells are encoded ahead on threads. Everything in flight
counts against the one budget (:func:`budget_shares`): the engine holds what the loads and
encodes ahead leave, and those go ahead by their estimated bytes, not by count. On a cluster the
points never travel through this process: each item is loaded and partitioned into a run
file where it runs (:mod:`standgrid.partition.spill`), then each cell is read from the runs
and encoded where it runs. Both give the same cells with the same points in the same order.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import closing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths
from standgrid.engine import MemoryBudget, Progress, SerialExecutor
from standgrid.engine.budget import bounded_map, release_memory
from standgrid.errors import TilingError

#: Peak bytes of loading an item (a payload, an old tile) over the bytes of the points it
#: gives: raw fields, converted ones and the projected coordinates coexist for a while
#: (measured: 2-4x on simulated payloads).
LOAD_FACTOR = 3.0
#: Peak bytes of encoding a cell's tile over the bytes of its points (the LAS records, the
#: compressed chunks, snapped coordinates).
ENCODE_FACTOR = 3.0

if TYPE_CHECKING:
    from standgrid.catalog import Transaction
    from standgrid.engine import Executor
    from standgrid.export.las import TileInfo
    from standgrid.partition.chunks import PayloadTask
    from standgrid.partition.engine import BufferFunction
    from standgrid.partition.protocol import Partition
    from standgrid.tiling.cell_task import CellTile
    from standgrid.tiling.retile import KeptTiles


@dataclass(frozen=True)
class EpochWork:
    """What goes into an epoch's cells."""

    epoch: str
    kept: Sequence[KeptTiles]
    payloads: Sequence[PayloadTask]
    partition: Partition
    buffer: BufferFunction | None
    #: Told each payload's point count, footprint and count of source-withheld points left
    #: out, in payload order.
    on_payload: Callable[[int, int, Any, int], None]
    #: The partition whose polygons the cells get (called once every payload is read).
    final_partition: Callable[[], Partition]
    crs: str
    laz: bool
    copc: bool
    memory_budget: MemoryBudget
    #: Workers share no folder with this process: they put tiles here (an ObjectFolder).
    outbox: Any = None


@dataclass
class Cells:
    """The tiles written (cell id, catalog-relative path, TileInfo; in cell key order)."""

    kept_in: int = 0
    tiles: list[tuple[str, str, TileInfo]] = field(default_factory=list)
    points_in: int = 0
    points_out: int = 0
    buffer_points: int = 0
    bytes_spilled: int = 0


def write_cells(work: EpochWork, txn: Transaction, executor: Executor, progress: Progress) -> Cells:
    """Partition the epoch's points and write its tiles into the transaction's staging."""
    if isinstance(executor, SerialExecutor) or work.outbox is not None:
        return _in_this_process(work, txn, executor, progress)
    return _on_cluster(work, txn, executor, progress)


def budget_shares(budget: int) -> tuple[int, int]:
    """``(engine, ahead)`` bytes of a process's budget: ``ahead`` for the items loaded (or
    the cells encoded) ahead on threads, by their estimated peak bytes; an eighth for the
    item being partitioned (its arrays until the engine holds them, its keys and order) and
    the allocator's slack; the engine's buffers get the rest."""
    ahead = budget // 8
    return budget - 2 * ahead, ahead


def _in_this_process(
    work: EpochWork, txn: Transaction, executor: Executor, progress: Progress
) -> Cells:
    from standgrid.partition import PartitionEngine
    from standgrid.partition.chunks import payload_chunk
    from standgrid.tiling.cell_task import CellTile, write_cell
    from standgrid.tiling.retile import kept_points

    done = Cells()
    epoch, origin = work.epoch, work.partition.lattice_origin
    engine_bytes, ahead_bytes = budget_shares(work.memory_budget.bytes)
    with PartitionEngine(
        work.partition.assign,
        txn.folder / "spill",
        memory_budget_bytes=engine_bytes,
        buffer=work.buffer,
    ) as engine:
        loads = _LoadCost()
        kept = bounded_map(kept_points, work.kept, loads.cost, ahead_bytes, loads.learn)
        with closing(kept):
            for cloud in progress.track(kept, len(work.kept), f"{epoch}: existing tiles"):
                if len(cloud):
                    engine.add(cloud)
                    done.kept_in += len(cloud)
                del cloud
        total = len(work.payloads)
        loads = _LoadCost()
        chunks = bounded_map(payload_chunk, work.payloads, loads.cost, ahead_bytes, loads.learn)
        with closing(chunks):
            for k, chunk in enumerate(progress.track(chunks, total, f"{epoch}: payloads")):
                work.on_payload(k, len(chunk.cloud), chunk.footprint, chunk.withheld)
                engine.add(chunk.cloud)
                del chunk
        release_memory()
        partition = work.final_partition()
        names: list[tuple[str, str]] = []

        def cells() -> Any:
            for cell in engine.finalise():
                cell_id = partition.cell_id(cell.key)
                rel = paths.tile(epoch, cell_id, laz=work.laz, copc=work.copc)
                names.append((cell_id, rel))
                polygon = partition.polygon(cell.key)
                yield CellTile(txn.stage(rel), cell.core, cell.buffer, work.crs, polygon, origin)

        def encode_cost(tile: CellTile) -> float:
            return ENCODE_FACTOR * (_cloud_bytes(tile.core) + _cloud_bytes(tile.buffer))

        if work.outbox is None or isinstance(executor, SerialExecutor):
            infos = bounded_map(write_cell, cells(), encode_cost, ahead_bytes)
        else:  # workers without a shared folder: points there, tiles back via the store
            infos = _through_outbox(cells(), encode_cost, ahead_bytes, executor, work.outbox)
        with closing(infos):
            for k, info in enumerate(progress.track(infos, 0, f"{epoch}: tiles")):
                done.tiles.append((*names[k], info))
        stats = engine.stats
    release_memory()
    done.points_in, done.points_out = stats.points_in, stats.points_out
    done.buffer_points, done.bytes_spilled = stats.buffer_points, stats.bytes_spilled
    return done


def _through_outbox(
    tiles: Iterator[CellTile],
    cost: Callable[[CellTile], float],
    budget: int,
    executor: Executor,
    outbox: Any,
) -> Generator[TileInfo, None, None]:
    """Each cell's tile written on a worker that shares no folder with this process: its
    points go with the task, the worker puts the tile in ``outbox``; here it is fetched to
    its staged path (checked by digest) and noted as already in the store, so the commit
    copies it there instead of uploading it again. Cells go in batches of at most
    ``budget`` estimated bytes (one at least); results come back in cell order."""
    from uuid import uuid4

    from standgrid.catalog.remote import note_in_store
    from standgrid.storage import file_sha256
    from standgrid.tiling.cell_task import OutboxTile, write_cell_to_outbox

    batch: list[CellTile] = []
    held = 0.0
    done = False
    while not done:
        tile = next(tiles, None)
        done = tile is None
        if tile is not None:
            batch.append(tile)
            held += cost(tile)
        if not batch or (not done and held < budget):
            continue
        tasks = [
            OutboxTile(replace(t, path=Path(t.path.name)), outbox, f"{uuid4().hex}{t.path.name}")
            for t in batch  # a key of its own: cells of two epochs share names
        ]
        results = dict(executor.map(write_cell_to_outbox, tasks))
        for k, staged in enumerate(batch):
            info, sha, size = results[k]
            outbox.download(tasks[k].key, staged.path)
            if file_sha256(staged.path) != sha or staged.path.stat().st_size != size:
                raise TilingError(f"{outbox.href(tasks[k].key)}: damaged in transfer")
            note_in_store(outbox.href(tasks[k].key), sha)
            yield replace(info, path=staged.path)
        batch, held = [], 0.0


class _LoadCost:
    """Estimated peak bytes of loading an item: its source's size (points of a scan's part,
    else the file's bytes) times the most bytes per unit of source seen so far, times
    :data:`LOAD_FACTOR`; unknown (infinite: loaded alone) until an item was loaded."""

    def __init__(self) -> None:
        self.per_unit = math.inf

    def cost(self, item: Any) -> float:
        item_size = _source_size(item)
        return math.inf if math.isinf(self.per_unit) else LOAD_FACTOR * self.per_unit * item_size

    def learn(self, item: Any, result: Any) -> None:
        cloud = getattr(result, "cloud", result)
        per_unit = _cloud_bytes(cloud) / max(1, _source_size(item)) if item is not None else 0
        self.per_unit = per_unit if math.isinf(self.per_unit) else max(self.per_unit, per_unit)


def _source_size(item: Any) -> int:
    span = getattr(item, "span", None)
    if span is not None:
        return max(1, int(span[1]) - int(span[0]))
    try:
        return max(1, os.stat(item.path).st_size)
    except (AttributeError, OSError):
        return 1


def _cloud_bytes(cloud: Any) -> int:
    if cloud is None:
        return 0
    return int(cloud.xyz.nbytes) + sum(int(v.nbytes) for v in cloud.fields.values())


def _on_cluster(work: EpochWork, txn: Transaction, executor: Executor, progress: Progress) -> Cells:
    from standgrid.partition.chunks import payload_chunk
    from standgrid.partition.spill import SpillTask, cell_extents, spill_chunk
    from standgrid.tiling.cell_task import RunCellTile, write_run_cell
    from standgrid.tiling.retile import kept_points

    done = Cells()
    epoch, origin = work.epoch, work.partition.lattice_origin
    folder = txn.folder / "spill" / f"runs-{epoch}"
    assign, buffer = work.partition.assign, work.buffer
    try:
        tasks = [
            SpillTask(kept_points, item, assign, buffer, folder / f"kept-{k}.bin")
            for k, item in enumerate(work.kept)
        ] + [
            SpillTask(payload_chunk, item, assign, buffer, folder / f"payload-{k}.bin")
            for k, item in enumerate(work.payloads)
        ]
        found = dict(
            progress.track(executor.map(spill_chunk, tasks), len(tasks), f"{epoch}: points")
        )
        runs = [found[k] for k in range(len(tasks))]
        for k, run in enumerate(runs[len(work.kept) :]):
            work.on_payload(k, run.points, *run.extra)
        done.kept_in = sum(run.points for run in runs[: len(work.kept)])
        done.points_in = sum(run.points for run in runs)
        done.bytes_spilled = sum(run.path.stat().st_size for run in runs)
        partition = work.final_partition()
        cells = []
        for extents in cell_extents(runs, buffered=buffer is not None):
            cell_id = partition.cell_id(extents.key)
            rel = paths.tile(epoch, cell_id, laz=work.laz, copc=work.copc)
            polygon = partition.polygon(extents.key)
            cells.append(
                (cell_id, rel, RunCellTile(txn.stage(rel), extents, work.crs, polygon, origin))
            )
        written = dict(
            progress.track(
                executor.map(write_run_cell, [c[2] for c in cells]), len(cells), f"{epoch}: tiles"
            )
        )
        for k, (cell_id, rel, _) in enumerate(cells):
            info = written[k]
            done.tiles.append((cell_id, rel, info))
            done.points_out += info.core_count
            done.buffer_points += info.buffer_count
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return done
