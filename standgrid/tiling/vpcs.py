"""One virtual point cloud per epoch (``tiles_<epoch>.vpc``): one QGIS layer each."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from standgrid.catalog import paths

if TYPE_CHECKING:
    from standgrid.catalog.transaction import Transaction
    from standgrid.export.las import TileInfo


def stage_epoch_vpc(
    txn: Transaction, epoch: str, tiles: Sequence[tuple[str, TileInfo]], crs: str
) -> None:
    """Stage the epoch's VPC over its tiles (``(catalog-relative path, TileInfo)`` as
    written: counts and bounds of the files, buffer points included), or delete it when the
    epoch has no tiles left."""
    from standgrid.export.gpkg import VpcTile, write_vpc

    rel = paths.vpc(epoch)
    if not tiles:
        if txn.current(rel) is not None:
            txn.delete(rel)
        return
    record = txn.epoch_record(epoch)
    date = record.date if record else None
    stamp = f"{date}T00:00:00Z" if date else None
    entries = sorted(
        (VpcTile(path, info.file_bounds, crs, info.point_count, stamp) for path, info in tiles),
        key=lambda tile: str(tile.path),
    )
    write_vpc(txn.stage(rel), entries, durable=False)  # the commit fsyncs it
