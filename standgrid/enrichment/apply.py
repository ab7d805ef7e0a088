"""``catalog_apply`` for enrichment (lidR's layout), one entry point for an epoch.

The epoch's cells are cut into buffered chunks (:mod:`standgrid.enrichment.chunks`);
:func:`~standgrid.enrichment.engine.run_block`, a pure function of one chunk (read its tiles and
its neighbours' points in the buffer, :func:`~standgrid.enrichment.block.enrich_block`, rewrite
its tiles where the transaction staged them), runs on each, here or on dask workers; the
engine (:func:`~standgrid.enrichment.engine.apply_blocks`) gives the results back in chunk order
and they are merged here: the raster windows pasted, the stand samples and trees collected.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from standgrid.engine import SerialExecutor
from standgrid.enrichment.stands import StandAggregator, StandSample
from standgrid.errors import EnrichError

if TYPE_CHECKING:
    import pandas as pd
    from numpy.typing import NDArray

    from standgrid.catalog import Catalog, Transaction
    from standgrid.engine import Execution
    from standgrid.enrichment.chunks import ChunkCell
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.partition.protocol import Partition
    from standgrid.rastergrid import RasterGrid


@dataclass
class AppliedEpoch:
    """An epoch's chunks, enriched and merged (trees not yet attached to the stands)."""

    grid: RasterGrid
    #: the cells' polygons (in cell id order)
    polygons: list[Any]
    #: the epoch's rasters on ``grid`` (:data:`~standgrid.enrichment.block.RASTERS`)
    rasters: dict[str, NDArray[Any]]
    #: every cell's sample and every coarser stand's
    samples: list[StandSample]
    stands: list[StandSample]
    tree_frames: list[pd.DataFrame]
    chunks: int


def catalog_apply(
    catalog: Catalog,
    txn: Transaction,
    epoch: str,
    options: EnrichOptions,
    *,
    execution: Execution,
) -> AppliedEpoch:
    """Enrich ``epoch`` chunk by chunk on ``execution``'s executor (open) and within its
    memory budget: its tiles rewritten into ``txn``'s staging, the chunks' rasters, samples
    and trees merged in chunk order."""
    import shapely

    from standgrid.catalog.partition import catalog_partition
    from standgrid.enrichment.block import BlockContext
    from standgrid.enrichment.chunks import BYTES_PER_POINT, chunk_side, plan_chunks
    from standgrid.enrichment.engine import (
        CHUNK_SHARE,
        BlockJob,
        EpochRasters,
        apply_blocks,
        chunks_at_once,
    )
    from standgrid.enrichment.terrain import GROUND_HALO_M, ground_reach
    from standgrid.rastergrid import RasterGrid

    executor, progress = execution.executor, execution.progress
    if executor is None:
        raise EnrichError("catalog_apply needs an open executor (Execution.executor)")

    partition = catalog_partition(catalog, epoch, coverage=False)
    cells = _epoch_cells(catalog, epoch, partition)
    if not cells:
        raise EnrichError(f"epoch {epoch} has no tiles", path=catalog.root)
    origin, cell_size = partition.raster_alignment()
    polygons = [c.polygon for c in cells]
    grid = RasterGrid.covering(
        tuple(shapely.bounds(shapely.union_all(polygons))),
        origin=origin,
        cell_size=cell_size,
        pixel_size=options.pixel_size,
        closed=True,
        crs=catalog.crs,
    )
    # the buffer must reach every copy a tile holds, so those get heights and ids too; and
    # be wider than the coverage closing (2 x radius), so chunks agree with the whole epoch
    tiling_buffer = txn.tiling_settings().buffer
    # and hold every point CSF sees around the ground squares of the cells it owns
    halo = max(
        options.halo,
        tiling_buffer,
        2 * options.coverage_closing_m + 2 * grid.pixel_size,
        GROUND_HALO_M,
    )
    # a share of the budget for the chunks a process holds at once (enrich.engine.CHUNK_SHARE)
    budget = execution.memory_budget
    block_points = int(budget.bytes * CHUNK_SHARE) // chunks_at_once(executor) // BYTES_PER_POINT
    side = chunk_side(cells, cell_size, halo, block_points)
    reach = functools.partial(ground_reach, lattice=(grid.x0, grid.y0))
    chunks = plan_chunks(cells, side=side, origin=origin, buffer=halo, reach=reach)
    size = partition.cell_size(cells[0].cell_id)
    context = BlockContext(grid, options, half_open=partition.half_open, cell_size=size)
    jobs = [
        BlockJob(
            chunk,
            str(catalog.root),
            tuple(str(txn.stage(c.tile)) for c in chunk.cells),
            context,
            origin,
            budget_bytes=budget.bytes,
        )
        for chunk in chunks
    ]
    progress.status(
        f"{epoch}: {len(cells)} cells in {len(chunks)} chunks of up to {side:g} m "
        f"(+{halo:g} m buffer) on {executor.workers} worker(s)"
    )
    densest = max(c.block_points for c in chunks)
    if densest > block_points * chunks_at_once(executor):  # one cell and its buffer: no less
        progress.status(
            f"{epoch}: the densest chunk ({densest:,} points with its buffer) needs about "
            f"{densest * BYTES_PER_POINT >> 20} MB, more than the budget's share for chunks "
            f"({int(budget.bytes * CHUNK_SHARE) >> 20} MB of {budget.bytes >> 20}): the peak "
            "will exceed the memory budget (a chunk holds at least one cell)"
        )
    stand_of = {c.cell_id: c.stand_id for c in cells}
    stand_ids = sorted({s for s in stand_of.values() if s is not None})
    # side of the coarser stands (1 ha: 100 m) the cells aggregate into
    stand_size = partition.cell_size(stand_ids[0]) if stand_ids else None
    stands = StandAggregator(
        stand_of, stand_size, options.coverage_rule, height_break=options.height_break
    )
    rasters = EpochRasters.empty(grid)
    samples: list[StandSample] = []
    tree_frames = []
    remote = _remote(catalog, execution) if not isinstance(executor, SerialExecutor) else None
    blocks = apply_blocks(jobs, executor, progress, f"{epoch}: chunks", remote)
    with contextlib.closing(blocks) as done:
        for job, result in done:
            rasters.paste(job.chunk, result)
            stands.add(result.samples)
            samples.extend(result.samples)
            tree_frames.append(result.trees)
    return AppliedEpoch(
        grid, polygons, rasters.arrays, samples, stands.result(), tree_frames, len(chunks)
    )


def _remote(catalog: Catalog, execution: Execution) -> tuple[Any, Any, dict[str, str]] | None:
    """Workers without a shared folder: the catalog generation's folder they read the tiles
    from, the outbox they put theirs in, and the tiles' digests they check (None: workers
    share this process's folders)."""
    if execution.outbox is None:
        return None
    from standgrid.catalog.remote import generation_of
    from standgrid.storage import ObjectFolder

    found = generation_of(catalog.root)
    if found is None:
        raise EnrichError("workers without a shared folder need the catalog in object storage")
    url, files = found
    digests = {rel: str(entry["sha256"]) for rel, entry in files.items()}
    return ObjectFolder.open(url), ObjectFolder.open(execution.outbox), digests


def _epoch_cells(catalog: Catalog, epoch: str, partition: Partition) -> list[ChunkCell]:
    """The epoch's cells (in cell id order) from the index's ``cells`` layer."""
    from standgrid.catalog.index import CatalogIndex
    from standgrid.enrichment.chunks import cells_of

    cells = CatalogIndex(catalog).read("cells", epoch).sort_values("cell_id")
    return cells_of(cells, partition.stand_of)
