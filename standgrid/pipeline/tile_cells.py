"""An epoch's points into cells and tiles, in this process or on a cluster.

In this process, the items (old tiles, then payloads) are loaded two ahead on threads and
streamed into one :class:`~standgrid.partition.engine.PartitionEngine` (bounded memory,
spill files beyond the budget); cells are encoded two ahead on threads. On a cluster the
points never travel through this process: each item is loaded and partitioned into a run
file where it runs (:mod:`standgrid.partition.spill`), then each cell is read from the runs
and encoded where it runs. Both give the same cells with the same points in the same order.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from contextlib import closing
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths
from standgrid.engine import MemoryBudget, Progress, SerialExecutor
from standgrid.engine.ordered import ordered_map

if TYPE_CHECKING:
    from standgrid.catalog import Transaction
    from standgrid.catalog.retile import KeptTiles
    from standgrid.engine import Executor
    from standgrid.export.las import TileInfo
    from standgrid.partition.chunks import PayloadTask
    from standgrid.partition.engine import BufferFunction
    from standgrid.partition.protocol import Partition


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
    if isinstance(executor, SerialExecutor):
        return _in_this_process(work, txn, executor, progress)
    return _on_cluster(work, txn, executor, progress)


def _in_this_process(
    work: EpochWork, txn: Transaction, executor: Executor, progress: Progress
) -> Cells:
    from standgrid.catalog.retile import kept_points
    from standgrid.export.tiles import CellTile, write_cell
    from standgrid.partition import PartitionEngine
    from standgrid.partition.chunks import payload_chunk

    done = Cells()
    epoch, origin = work.epoch, work.partition.lattice_origin
    with PartitionEngine(
        work.partition.assign,
        txn.folder / "spill",
        memory_budget_bytes=work.memory_budget.bytes,
        buffer=work.buffer,
    ) as engine:
        with closing(ordered_map(executor, kept_points, work.kept)) as kept:
            for cloud in progress.track(kept, len(work.kept), f"{epoch}: existing tiles"):
                if len(cloud):
                    engine.add(cloud)
                    done.kept_in += len(cloud)
        total = len(work.payloads)
        with closing(ordered_map(executor, payload_chunk, work.payloads)) as chunks:
            for k, chunk in enumerate(progress.track(chunks, total, f"{epoch}: payloads")):
                work.on_payload(k, len(chunk.cloud), chunk.footprint, chunk.withheld)
                engine.add(chunk.cloud)
        partition = work.final_partition()
        names: list[tuple[str, str]] = []

        def cells() -> Any:
            for cell in engine.finalise():
                cell_id = partition.cell_id(cell.key)
                rel = paths.tile(epoch, cell_id, laz=work.laz, copc=work.copc)
                names.append((cell_id, rel))
                polygon = partition.polygon(cell.key)
                yield CellTile(txn.stage(rel), cell.core, cell.buffer, work.crs, polygon, origin)

        with closing(ordered_map(executor, write_cell, cells())) as infos:
            for k, info in enumerate(progress.track(infos, 0, f"{epoch}: tiles")):
                done.tiles.append((*names[k], info))
        stats = engine.stats
    done.points_in, done.points_out = stats.points_in, stats.points_out
    done.buffer_points, done.bytes_spilled = stats.buffer_points, stats.bytes_spilled
    return done


def _on_cluster(work: EpochWork, txn: Transaction, executor: Executor, progress: Progress) -> Cells:
    from standgrid.catalog.retile import kept_points
    from standgrid.export.tiles import RunCellTile, write_run_cell
    from standgrid.partition.chunks import payload_chunk
    from standgrid.partition.spill import SpillTask, cell_extents, spill_chunk

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
