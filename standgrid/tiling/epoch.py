"""(Re)tile one epoch: its kept points plus new payloads through one partition engine.

The per-item work (reading an old tile, reading and projecting a payload, encoding a cell's
LAS/LAZ tile) runs on the executor, in item order where order matters; this process alone
partitions, and writes the catalog state and the index.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from standgrid.engine import MemoryBudget, Progress
from standgrid.tiling.cells import EpochWork, write_cells

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, TilingSettings, Transaction
    from standgrid.catalog.index import CatalogIndex
    from standgrid.engine import Executor
    from standgrid.export.las import TileInfo
    from standgrid.georeference.placement import Placement, ToCatalog
    from standgrid.mission.model import Mission
    from standgrid.tiling.placement_policy import PlacementChoice


@dataclass
class Ingest:
    """One mission on its way in."""

    mission: Mission
    placement: Placement
    epoch: str
    date: str
    number: int = 0
    to_catalog: ToCatalog | None = None
    #: the placement used and why (under a placement tolerance: maybe the catalog's own)
    choice: PlacementChoice | None = None


@dataclass(frozen=True)
class EpochSettings:
    tiling: TilingSettings
    memory_budget: MemoryBudget
    #: keep a mission's placement while a refit moves it less than this (m); None: exact
    placement_tolerance: float | None = None


@dataclass
class EpochResult:
    """What tiling one epoch produced: the report entry and the tiles written."""

    report: dict[str, Any]
    missions: dict[str, dict[str, Any]] = field(default_factory=dict)
    tiles: list[tuple[str, TileInfo]] = field(default_factory=list)
    #: False when every point stayed where it was (a re-tile of unchanged missions)
    changed: bool = True


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

    from standgrid.catalog.partition import catalog_partition
    from standgrid.errors import CatalogError, ConservationError
    from standgrid.export.gpkg import cell_row
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.partition.chunks import PayloadTask
    from standgrid.tiling.increment import (
        keep_rows,
        kept_tile_info,
        landing_tiles,
        placement_digest,
        plan_increment,
        source_digest,
        tiles_holding,
    )
    from standgrid.tiling.mission_rows import (
        epoch_sites,
        gnss_rows,
        metadata_extra,
        mission_row,
        payload_rows,
        tiling_schema,
        trajectory_rows,
    )
    from standgrid.tiling.retile import KeptTiles

    names = {i.mission.name for i in group}
    previous = sorted(catalog.tiles(epoch)) if epoch in catalog.epochs else []
    schema = tiling_schema(catalog, previous, group)
    stored = index.read("payloads", epoch)
    _choose_placements(catalog, index, epoch, group, stored, schema, settings)
    rows, sources = payload_rows(group, epoch)
    placements = {i.mission.name: placement_digest(i.placement.record()) for i in group}
    for row, source in zip(rows, sources, strict=True):
        row["source_digest"] = source_digest(source, placements[row["mission"]], schema)
    mine = stored["mission"].astype(str).isin(names)
    others = stored[~mine]
    partition = catalog_partition(catalog, payloads=epoch_sites(others, rows), coverage=False)
    origin = partition.lattice_origin
    tasks = [PayloadTask(**given, lattice_origin=origin, schema=schema) for given in sources]
    run_missions = {n for n, r in catalog.mission_records.items() if r.number in renewed}
    increment = plan_increment(
        catalog, epoch, names, rows, stored[mine], settings.tiling, run_missions
    )
    if increment is None:  # the whole epoch
        read = list(range(len(rows)))
        rewrite, drop = previous, {"renewed": tuple(renewed)}
    else:  # in place: the tiles holding dropped payloads or receiving changed ones
        read = [k for k, r in enumerate(rows) if r["payload_id"] not in increment.unchanged]
        landing = landing_tiles(
            [tasks[k] for k in read], partition, epoch, settings.tiling, executor
        )
        holding = tiles_holding(catalog.root, previous, increment.dropped)
        rewrite = sorted((landing | holding) & set(previous))
        drop = {"renewed": (), "dropped_payloads": tuple(sorted(increment.dropped))}
        keep_rows(rows, increment.kept_rows)
        progress.status(
            f"{epoch}: {len(increment.unchanged)} payloads unchanged, {len(read)} to read; "
            f"{len(rewrite)} of {len(previous)} tiles rewritten"
        )

    new_in: dict[str, int] = dict.fromkeys(names, 0)
    withheld_left_out = 0  # source points flagged withheld (deleted), not tiled

    def on_payload(k: int, points: int, footprint: Any, withheld: int) -> None:
        nonlocal withheld_left_out
        row = rows[read[k]]
        row["point_count"] = points
        row["withheld_left_out"] = withheld
        row["geometry"] = footprint
        new_in[row["mission"]] += points
        withheld_left_out += withheld

    work = EpochWork(
        epoch=epoch,
        kept=[
            KeptTiles(catalog.path(rel), lattice_origin=origin, schema=schema, **drop)
            for rel in rewrite
        ],
        payloads=[tasks[k] for k in read],
        partition=partition,
        buffer=partition.buffer(settings.tiling.buffer) if settings.tiling.buffer else None,
        on_payload=on_payload,
        final_partition=lambda: catalog_partition(catalog, payloads=epoch_sites(others, rows)),
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
    untouched, left_in = set(previous) - set(rewrite), 0
    clash = sorted(untouched & {rel for _, rel, _ in done.tiles})
    if clash:  # a payload read twice, changed in between: nothing may be overwritten
        raise ConservationError(
            f"epoch {epoch}: points landed in {clash[0]}, which was to stay as it is (a "
            "payload changed while it was tiled?): nothing was written; tile again",
            path=catalog.root,
        )
    rowless = set(untouched)
    for row in index.read("cells", epoch).to_dict("records"):
        if row["tile_path"] in untouched:  # left as it is, with its row
            rowless.discard(row["tile_path"])
            left_in += int(row["point_count"])
            for name in filter(None, str(row["missions"]).split(",")):
                tiles_of.setdefault(name, set()).add(row["tile_path"])
            cell_rows.append(row)
            result.tiles.append((row["tile_path"], kept_tile_info(
                catalog.path(row["tile_path"]), row, catalog.crs)))  # fmt: skip

    if rowless:
        raise CatalogError(
            f"epoch {epoch}: tiles without a row in the index's cells layer: "
            f"{', '.join(sorted(rowless)[:3])}",
            path=catalog.root,
        )
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
        mine_rows = [r for r in rows if r["mission"] == mission.name]
        record = txn.record_mission(
            mission.name, epoch=epoch, date=ingest.date, path=str(mission.path.resolve()),
            georeference=ingest.placement.record(), placement=_note(ingest),
            payload_count=len(cloud_payloads(mission)),
            point_count=sum(r["point_count"] for r in mine_rows),
            tiles=sorted(tiles_of.get(mission.name, ())), **metadata_extra(mission),
        )  # fmt: skip
        result.missions[mission.name] = {
            "number": record["number"],
            "epoch": epoch,
            "payloads": record["payload_count"],
            "points": record["point_count"],
            "withheld_left_out": sum(r["withheld_left_out"] for r in mine_rows),
            "tiles": len(record["tiles"]),
            "georeference": ingest.placement.summary(),
            "placement": _note(ingest),
            "warnings": list(mission.warnings),
        }
        assert ingest.to_catalog is not None
        trajectories += trajectory_rows(mission, ingest.to_catalog, epoch)
        fixes.append(gnss_rows(mission, ingest.placement, catalog.crs))
        mission_rows.append(mission_row(
            mission, ingest.placement, ingest.number, epoch, ingest.date, catalog,
            placement_offset_m=_note(ingest)["offset_m"],
        ))  # fmt: skip
    index.replace("cells", cell_rows, epochs={epoch})
    index.replace("payloads", rows, missions=names)
    index.replace("trajectories", trajectories, missions=names)
    fixes = [f for f in fixes if len(f)]
    index.replace(
        "gnss_fixes", pd.concat(fixes, ignore_index=True) if fixes else [], missions=names
    )
    index.replace("missions", mission_rows, missions=names)
    result.changed = increment is None or bool(read or rewrite)
    settled = txn.settle_epoch(epoch, settings.tiling, changed=result.changed)
    if not result.changed and settled and before and settled.date != before.date:
        result.changed = True  # the epoch's date moved: what was computed for it is stale
        settled = txn.settle_epoch(epoch, settings.tiling, changed=True)
    result.report = {
        "date": settled.date or "" if settled else "",  # None: every mission moved out
        "points_in": fed + left_in,
        "points_kept_from_catalog": kept_in + left_in,
        "points_new": sum(new_in.values()),
        "withheld_left_out": withheld_left_out,
        "points_out": done.points_out + left_in,
        "points_rewritten": done.points_out,
        "buffer_points": done.buffer_points,
        "cells": len(result.tiles),
        "cells_rewritten": len(done.tiles),
        "cells_removed": len(set(previous) - rels),
        "payloads_unchanged": len(increment.unchanged) if increment else 0,
        "bytes_spilled": done.bytes_spilled,
    }
    return result


def _choose_placements(
    catalog: Catalog,
    index: CatalogIndex,
    epoch: str,
    group: list[Ingest],
    stored: Any,
    schema: Any,
    settings: EpochSettings,
) -> None:
    """Under a placement tolerance, each mission of ``group`` is tiled with the placement
    :func:`~standgrid.tiling.placement_policy.choose_placement` picks (its recipe into the
    catalog CRS renewed when it is the catalog's own)."""
    from standgrid.tiling.placement_policy import PlacementChoice, choose_placement

    if settings.placement_tolerance is None:
        for ingest in group:
            ingest.choice = PlacementChoice(ingest.placement, "fresh")
        return
    cells = index.read("cells", epoch)
    records = catalog.mission_records
    for ingest in group:
        name = ingest.mission.name
        ingest.choice = choose_placement(
            ingest.mission, ingest.number, epoch, ingest.placement, records.get(name), stored,
            cells, schema, catalog.crs, settings.placement_tolerance,
        )  # fmt: skip
        if ingest.choice.placement is not ingest.placement:
            ingest.placement = ingest.choice.placement
            ingest.to_catalog = ingest.placement.to_catalog(catalog.crs, name)


def _note(ingest: Ingest) -> dict[str, Any]:
    """The mission's ``placement`` note (report, record): which placement, how far off."""
    assert ingest.choice is not None
    return ingest.choice.note()
