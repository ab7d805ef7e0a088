"""(Re)tile one epoch: its kept points plus new payloads through one partition engine.

The per-item work (reading an old tile, reading and projecting a payload, encoding a cell's
LAS/LAZ tile) runs on the executor, in item order where order matters; this process alone
partitions, and writes the catalog state and the index.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from standgrid.engine import MemoryBudget, Progress
from standgrid.pipeline.tile_cells import EpochWork, write_cells

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, TilingSettings, Transaction
    from standgrid.catalog.index import CatalogIndex
    from standgrid.engine import Executor
    from standgrid.export.las import TileInfo
    from standgrid.georeference.placement import Placement, ToCatalog
    from standgrid.mission.model import Mission
    from standgrid.partition.schema import Schema


@dataclass
class Ingest:
    """One mission on its way in."""

    mission: Mission
    placement: Placement
    epoch: str
    date: str
    number: int = 0
    to_catalog: ToCatalog | None = None


@dataclass(frozen=True)
class EpochSettings:
    tiling: TilingSettings
    memory_budget: MemoryBudget


@dataclass
class EpochResult:
    """What tiling one epoch produced: the report entry and the tiles written."""

    report: dict[str, Any]
    missions: dict[str, dict[str, Any]] = field(default_factory=dict)
    tiles: list[tuple[str, TileInfo]] = field(default_factory=list)


def tile_epoch(
    catalog: Catalog,
    txn: Transaction,
    index: CatalogIndex,
    epoch: str,
    group: list[Ingest],
    renewed: list[int],
    settings: EpochSettings,
    executor: Executor,
    progress: Progress,
) -> EpochResult:
    """(Re)tile ``epoch``: its kept points plus the payloads of ``group``; the points of every
    mission in ``renewed`` (this run's missions) are taken out of the old tiles first."""
    import pandas as pd

    from standgrid.catalog.mission_rows import (
        gnss_rows,
        metadata_extra,
        mission_row,
        trajectory_rows,
    )
    from standgrid.catalog.partition import catalog_partition
    from standgrid.catalog.retile import KeptTiles
    from standgrid.errors import ConservationError
    from standgrid.export.gpkg import cell_row
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.partition.chunks import PayloadTask

    names = {i.mission.name for i in group}
    previous = sorted(catalog.tiles(epoch)) if epoch in catalog.epochs else []
    schema = _schema(catalog, previous, group)
    rows, sources = _payload_rows(group, epoch)
    others = index.read("payloads", epoch)
    others = others[~others["mission"].astype(str).isin(names)]
    partition = catalog_partition(catalog, payloads=_sites(others, rows), coverage=False)
    origin = partition.lattice_origin
    tasks = [PayloadTask(**given, lattice_origin=origin, schema=schema) for given in sources]

    new_in: dict[str, int] = dict.fromkeys(names, 0)

    def on_payload(k: int, points: int, footprint: Any) -> None:
        rows[k]["point_count"] = points
        rows[k]["geometry"] = footprint
        new_in[rows[k]["mission"]] += points

    work = EpochWork(
        epoch=epoch,
        kept=[KeptTiles(catalog.path(rel), tuple(renewed), origin, schema) for rel in previous],
        payloads=tasks,
        partition=partition,
        buffer=partition.buffer(settings.tiling.buffer) if settings.tiling.buffer else None,
        on_payload=on_payload,
        final_partition=lambda: catalog_partition(catalog, payloads=_sites(others, rows)),
        crs=catalog.crs,
        laz=settings.tiling.laz,
        copc=settings.tiling.copc,
        memory_budget=settings.memory_budget,
    )
    done = write_cells(work, txn, executor, progress)
    kept_in = done.kept_in
    number_to_name = {r.number: n for n, r in txn.mission_records().items()}
    tiles_of: dict[str, set[str]] = {}
    result = EpochResult({})
    cell_rows: list[dict[str, Any]] = []
    for cell_id, rel, info in done.tiles:
        missions = sorted(number_to_name[n] for n in info.points_per_source)
        for name in missions:
            tiles_of.setdefault(name, set()).add(rel)
        size = partition.cell_size(cell_id)
        row = cell_row(cell_id, info, level=0, cell_size=size, epoch=epoch, missions=missions,
                       tile_path=rel)  # fmt: skip
        cell_rows.append(row)
        result.tiles.append((rel, info))

    fed = kept_in + sum(new_in.values())
    if done.points_in != fed or done.points_out != fed:
        raise ConservationError(
            f"epoch {epoch}: {fed} points fed, {done.points_in} partitioned, "
            f"{done.points_out} written",
            path=catalog.root,
        )
    rels = {rel for rel, _ in result.tiles}
    for rel in set(previous) - rels:
        txn.delete(rel)
    before = txn.epoch_record(epoch)
    for name in before.missions if before else ():
        if name not in names:
            txn.set_mission_tiles(name, tiles_of.get(name, ()))
    mission_rows, trajectories, fixes = [], [], []
    for ingest in group:
        mission = ingest.mission
        record = txn.record_mission(
            mission.name, epoch=epoch, date=ingest.date, path=str(mission.path.resolve()),
            georeference=ingest.placement.record(),
            payload_count=len(cloud_payloads(mission)), point_count=new_in[mission.name],
            tiles=sorted(tiles_of.get(mission.name, ())), **metadata_extra(mission),
        )  # fmt: skip
        result.missions[mission.name] = {
            "number": record["number"],
            "epoch": epoch,
            "payloads": record["payload_count"],
            "points": record["point_count"],
            "tiles": len(record["tiles"]),
            "georeference": ingest.placement.summary(),
        }
        assert ingest.to_catalog is not None
        trajectories += trajectory_rows(mission, ingest.to_catalog, epoch)
        fixes.append(gnss_rows(mission, ingest.placement, catalog.crs))
        mission_rows.append(
            mission_row(mission, ingest.placement, ingest.number, epoch, ingest.date, catalog)
        )
    index.replace("cells", cell_rows, epochs={epoch})
    index.replace("payloads", rows, missions=names)
    index.replace("trajectories", trajectories, missions=names)
    fixes = [f for f in fixes if len(f)]
    index.replace(
        "gnss_fixes", pd.concat(fixes, ignore_index=True) if fixes else [], missions=names
    )
    index.replace("missions", mission_rows, missions=names)
    settled = txn.settle_epoch(epoch, settings.tiling)
    result.report = {
        "date": settled.date or "" if settled else "",  # None: every mission moved out
        "points_in": fed,
        "points_kept_from_catalog": kept_in,
        "points_new": sum(new_in.values()),
        "points_out": done.points_out,
        "buffer_points": done.buffer_points,
        "cells": len(result.tiles),
        "cells_removed": len(set(previous) - rels),
        "bytes_spilled": done.bytes_spilled,
    }
    return result


def _sites(others: Any, rows: list[dict[str, Any]]) -> Any:
    """The epoch's payload rows: those of missions not re-ingested, then this run's."""
    import pandas as pd

    new = pd.DataFrame(rows, columns=["mission", "stamp_sec", "stamp_nsec", "x", "y", "geometry"])
    if not len(others):
        return new
    return pd.concat([pd.DataFrame(others[list(new.columns)]), new], ignore_index=True)


def _payload_rows(
    group: list[Ingest], epoch: str
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One ``payloads`` row and one payload task's arguments (but the epoch's lattice origin
    and schema) per cloud payload of the group's missions."""
    from standgrid.catalog.mission_rows import payload_id, payload_row
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.stamps import unix_ns_to_adjusted_gps_time

    rows, sources = [], []
    for ingest in group:
        mission, to_catalog = ingest.mission, ingest.to_catalog
        assert to_catalog is not None
        for k, payload in enumerate(cloud_payloads(mission)):
            ident = payload_id(ingest.number, k, mission)
            row = payload_row(mission, to_catalog, ident, payload, epoch)
            fitted = to_catalog.fit is not None
            sources.append(
                {
                    "path": payload.path,
                    "frame": payload.frame,
                    "file_to_base": mission.file_to_base(payload),
                    "pose": mission.pose_of(payload) if fitted else None,
                    "to_catalog": to_catalog,
                    "gps_time": float(unix_ns_to_adjusted_gps_time(payload.stamp.ns)),
                    "point_source_id": ingest.number,
                    "payload_id": ident,
                    "fallback_footprint": row["geometry"],
                }
            )
            rows.append(row)
    return rows, sources


def _schema(catalog: Catalog, previous: list[str], group: list[Ingest]) -> Schema:
    """The epoch's field schema: from its first existing tile and each mission's first payload."""
    from standgrid.export.las import read_tile
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.partition.schema import epoch_schema

    samples = [read_tile(catalog.path(previous[0]))] if previous else []
    for ingest in group:
        payloads = cloud_payloads(ingest.mission)
        if payloads:
            first = payloads[0]
            mission = ingest.mission
            load = mission.load_projected if first.frame == "utm" else mission.load_base
            samples.append(load(first))
    return epoch_schema(samples, catalog.root)
