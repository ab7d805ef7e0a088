"""One cell's tile as a task: a pure function of plain data, run here or on a dask worker.

The LAS/LAZ encoding (LAZ compression above all) is the expensive, per-cell part of tiling,
so :func:`write_cell` is what an executor spreads over processes; it writes the tile where
the task says (a transaction's staging folder) and returns the :class:`TileInfo`.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from standgrid.export.copc import is_copc, write_copc_tile
from standgrid.export.las import TileInfo, write_tile
from standgrid.partition.spill import CellExtents, read_cell
from standgrid.pointcloud import PointCloud
from standgrid.storage import file_sha256


@dataclass(frozen=True)
class CellTile:
    """What :func:`write_cell` needs: the output file, the points and where they belong."""

    path: Path
    core: PointCloud
    buffer: PointCloud | None
    crs: str
    #: The cell polygon (shapely); None or empty: the core points' bounding box stands in.
    polygon: Any
    lattice_origin: tuple[float, float]


def write_cell(task: CellTile) -> TileInfo:
    """Write one cell's tile (COPC when its name ends ``.copc.laz``); its ``core_bounds`` is
    the cell polygon (or the points' box)."""
    import shapely

    writer = write_copc_tile if is_copc(task.path) else write_tile
    info = writer(
        task.path,
        task.core,
        crs=task.crs,
        buffer=task.buffer,
        core_bounds=task.polygon,
        lattice_origin=task.lattice_origin,
        durable=False,  # staged in a transaction: its commit fsyncs every staged file
    )
    if task.polygon is None or shapely.is_empty(task.polygon):
        xmin, ymin, _, xmax, ymax, _ = info.bounds
        info = TileInfo(**{**info.__dict__, "core_bounds": shapely.box(xmin, ymin, xmax, ymax)})
    return info


@dataclass(frozen=True)
class RunCellTile:
    """A cell to read from the partition's run files (a cluster) and write as a tile."""

    path: Path
    extents: CellExtents
    crs: str
    polygon: Any
    lattice_origin: tuple[float, float]


def write_run_cell(task: RunCellTile) -> TileInfo:
    """Read one cell's points from the runs (:mod:`standgrid.partition.spill`), write its tile."""
    cell = read_cell(task.extents)
    tile = CellTile(task.path, cell.core, cell.buffer, task.crs, task.polygon, task.lattice_origin)
    return write_cell(tile)


@dataclass(frozen=True)
class OutboxTile:
    """A cell to write on a worker that shares no folder with the client: the tile is put
    in object storage (``outbox``, at ``key``); ``tile.path`` names the file (its suffix
    says the format)."""

    tile: CellTile
    outbox: Any  # standgrid.storage.ObjectFolder (sent as its URL)
    key: str


def write_cell_to_outbox(task: OutboxTile) -> tuple[TileInfo, str, int]:
    """Write the tile in a folder of this worker's own, put it at ``task.key``; returns its
    TileInfo, SHA-256 and size (the client checks the copy it fetches against them)."""
    with tempfile.TemporaryDirectory(prefix="standgrid-cell-") as folder:
        local = Path(folder) / task.tile.path.name
        info = write_cell(replace(task.tile, path=local))
        digest, size = file_sha256(local), local.stat().st_size
        task.outbox.upload(local, task.key)
    return info, digest, size
