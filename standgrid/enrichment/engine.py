"""The chunk engine of enrichment: plan buffered chunks, run :func:`enrich_block` on each
(here or on dask workers), rewrite their tiles, and merge the results in chunk order.

A job carries only plain data (the chunk, where its tiles are and where their new versions
go); the worker reads the tiles, computes, writes the staged tiles and returns rasters,
trees and samples. The caller (the only writer of the catalog) pastes the raster windows
and collects the rest, so one process and a cluster give the same result.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.engine.budget import bounded_map, release_memory
from standgrid.engine.executor import SerialExecutor, run_limited
from standgrid.enrichment.block import RASTERS, BlockContext, BlockResult, enrich_block, paste
from standgrid.errors import EnrichError
from standgrid.storage import file_sha256

if TYPE_CHECKING:
    from standgrid.engine import Executor, Progress
    from standgrid.enrichment.chunks import Chunk
    from standgrid.rastergrid import RasterGrid


#: Shares of a process's memory budget (issue 22: its peak RSS stays within 1.1 x the budget
#: plus the interpreter): the chunks in flight get half, the tiles' coordinates kept for
#: later chunks a sixteenth; the rest is what a process holds besides the chunks (freed
#: arenas not yet returned, the modules the passes load, the merged results: 150-250 MB
#: at 20 M points, more than a quarter of a 512 MB budget).
CHUNK_SHARE = 1 / 2
CACHE_SHARE = 1 / 16


@dataclass(frozen=True)
class BlockJob:
    """One chunk's work: read its tiles under ``root``, enrich, write ``targets``."""

    chunk: Chunk
    root: str
    targets: tuple[str, ...]
    context: BlockContext
    lattice_origin: tuple[float, float]
    #: this process's memory budget (bytes)
    budget_bytes: int = 0

    @property
    def cache_bytes(self) -> int:
        """Bytes of the budget that keep tiles' coordinates for later chunks."""
        return int(self.budget_bytes * CACHE_SHARE)

    @property
    def working_bytes(self) -> int:
        """The peak bytes this job's computation is estimated to hold."""
        from standgrid.enrichment.chunks import BYTES_PER_POINT

        return self.chunk.block_points * BYTES_PER_POINT


def run_block(job: BlockJob) -> BlockResult:
    """Read, enrich and rewrite one chunk's tiles (runs on a worker)."""
    from standgrid.enrichment.chunks import read_chunk, write_chunk_tiles
    from standgrid.enrichment.terrain import ring_bin

    grid = job.context.grid
    points = read_chunk(
        job.root,
        job.chunk,
        job.lattice_origin,
        cache_bytes=job.cache_bytes,
        ring_square=ring_bin(job.context.options.cloth_resolution),
        ring_lattice=(grid.x0, grid.y0),
    )
    result = enrich_block(points, job.context)
    write_chunk_tiles(
        points,
        result.fields,
        {"classification": 1, "height_above_ground": np.nan, "tree_id": 0},
        job.targets,
    )
    result.fields = {}  # written; not shipped back
    del points
    release_memory()  # the block's arrays, freed on this thread's arena, back to the system
    return result


@dataclass
class EpochRasters:
    """The epoch's rasters on ``grid``, pasted from every chunk's owned pixels."""

    grid: RasterGrid
    arrays: dict[str, NDArray[Any]]

    @classmethod
    def empty(cls, grid: RasterGrid) -> EpochRasters:
        arrays = {
            name: np.full(grid.shape, fill, dtype=bool if isinstance(fill, bool) else np.float32)
            for name, fill in RASTERS.items()
        }
        return cls(grid, arrays)

    def paste(self, chunk: Chunk, result: BlockResult) -> None:
        from standgrid.enrichment.coverage import cells_mask

        owned = cells_mask(result.window, [c.polygon for c in chunk.cells])
        for name, values in result.rasters.items():
            paste(self.arrays[name], self.grid, result.window, values, owned)


def apply_blocks(
    jobs: Sequence[BlockJob],
    executor: Executor,
    progress: Progress,
    desc: str,
    remote: tuple[Any, Any, dict[str, str]] | None = None,
) -> Generator[tuple[BlockJob, BlockResult], None, None]:
    """Run every job; yield ``(job, result)`` in the jobs' order (results that finish early
    wait, so merging is deterministic whatever the executor; close it when done, see
    :func:`~standgrid.engine.ordered.ordered_map`). In this process, up to
    :data:`~standgrid.engine.ordered.AHEAD` jobs run at once on threads (see
    :func:`chunks_at_once`), as many as their estimated working sets fit in the share of the
    budget the chunks get (:data:`CHUNK_SHARE`; a chunk cannot be smaller than one cell: a
    dense one runs alone). ``remote``: ``(source, outbox, digests)``: object-storage
    folders and the tiles' digests, for workers that share no folder with this process
    (:class:`RemoteBlockJob`)."""
    from standgrid.engine.ordered import AHEAD, ordered_map

    if isinstance(executor, SerialExecutor):
        limit = jobs[0].budget_bytes * CHUNK_SHARE if jobs else 0
        in_order = bounded_map(
            functools.partial(run_limited, run_block),
            jobs,
            lambda job: job.working_bytes,
            limit,
            threads=AHEAD,
        )
        with contextlib.closing(in_order):
            yield from zip(jobs, progress.track(in_order, len(jobs), desc), strict=True)
        return
    if remote is not None:  # workers without the client's folders
        yield from _through_store(jobs, executor, progress, desc, *remote)
        return
    ordered = ordered_map(executor, run_block, jobs)
    with contextlib.closing(ordered):
        yield from zip(jobs, progress.track(ordered, len(jobs), desc), strict=True)


def _through_store(
    jobs: Sequence[BlockJob],
    executor: Executor,
    progress: Progress,
    desc: str,
    source: Any,
    outbox: Any,
    digests: dict[str, str],
) -> Generator[tuple[BlockJob, BlockResult], None, None]:
    """Run the jobs as :class:`RemoteBlockJob`s; each rewritten tile is fetched from the
    outbox to the path the job stages it at (checked by digest) and noted as already in the
    store, so the commit copies it there instead of uploading it again."""
    from uuid import uuid4

    from standgrid.catalog.remote import note_in_store
    from standgrid.engine.ordered import ordered_map

    tasks = []
    for job in jobs:
        chunk = job.chunk
        rels = {c.tile for c in (*chunk.cells, *chunk.neighbours, *chunk.far)}
        keys = tuple(f"{uuid4().hex}{Path(t).name}" for t in job.targets)
        tasks.append(RemoteBlockJob(job, source, outbox, keys, {r: digests[r] for r in rels}))
    ordered = ordered_map(executor, run_remote_block, tasks)
    with contextlib.closing(ordered):
        tracked = progress.track(ordered, len(tasks), desc)
        for task, (result, written) in zip(tasks, tracked, strict=True):
            for target, key, (sha, size) in zip(task.job.targets, task.keys, written, strict=True):
                outbox.download(key, Path(target))
                if Path(target).stat().st_size != size or file_sha256(Path(target)) != sha:
                    raise EnrichError(f"{outbox.href(key)}: damaged in transfer")
                note_in_store(outbox.href(key), sha)
            yield task.job, result


@dataclass(frozen=True)
class RemoteBlockJob:
    """A :class:`BlockJob` for a worker that shares no folder with the client: it reads the
    chunk's tiles from ``source`` (the catalog generation's folder in object storage),
    checked against ``digests``, and puts the tiles it rewrites in ``outbox`` at ``keys``."""

    job: BlockJob
    source: Any  # standgrid.storage.ObjectFolder (sent as its URL)
    outbox: Any
    keys: tuple[str, ...]
    #: the SHA-256 of each tile the chunk reads (catalog-relative path -> digest)
    digests: dict[str, str]


def _tiles_here(source: Any, digests: dict[str, str]) -> Path:
    """The generation's tiles (relative path -> SHA-256) in this worker's own folder,
    fetched once each and checked (threads fetching one tile at once each write a part of
    their own; a whole one is renamed in place)."""
    import hashlib
    import tempfile

    try:
        from distributed import get_worker

        base = Path(get_worker().local_directory)  # removed with the worker
    except (ImportError, ValueError):
        base = Path(tempfile.gettempdir())
    root = base / "standgrid-tiles" / hashlib.sha256(source.url.encode()).hexdigest()[:16]
    for rel, digest in sorted(digests.items()):
        path = root / rel
        if path.is_file():
            continue
        source.download(rel, path)  # atomic: a part file of this thread's, then renamed
        if file_sha256(path) != digest:
            path.unlink(missing_ok=True)
            raise EnrichError(f"{source.href(rel)}: not the tile its manifest names")
    return root


def run_remote_block(task: RemoteBlockJob) -> tuple[BlockResult, list[tuple[str, int]]]:
    """:func:`run_block` on a worker without the client's folders (see
    :class:`RemoteBlockJob`); returns the result and each rewritten tile's SHA-256 and size."""
    import tempfile
    from dataclasses import replace

    root = _tiles_here(task.source, task.digests)
    with tempfile.TemporaryDirectory(prefix="standgrid-chunk-") as out:
        names = [Path(t).name for t in task.job.targets]
        targets = tuple(str(Path(out) / f"{k}-{name}") for k, name in enumerate(names))
        result = run_block(replace(task.job, root=str(root), targets=targets))
        written = []
        for target, key in zip(targets, task.keys, strict=True):
            written.append((file_sha256(Path(target)), Path(target).stat().st_size))
            task.outbox.upload(Path(target), key)
    return result, written


def chunks_at_once(executor: Executor) -> int:
    """How many chunks one process holds at once: each gets that share of the budget."""
    from standgrid.engine.ordered import AHEAD

    return AHEAD if isinstance(executor, SerialExecutor) else 1
