"""(Re)tile one epoch: its kept points plus new payloads through one partition engine.

The per-item work (reading an old tile, reading and projecting a payload, encoding a cell's
LAS/LAZ tile) runs on the executor, in item order where order matters; this process alone
partitions, and writes the catalog state and the index.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths
from standgrid.engine import MemoryBudget, Progress, SerialExecutor
from standgrid.storage.objects import source_of
from standgrid.tiling.cells import Cells, EpochWork, write_cells

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, TilingSettings, Transaction
    from standgrid.catalog.index import CatalogIndex
    from standgrid.engine import Executor
    from standgrid.export.las import TileInfo
    from standgrid.georeference.placement import Placement, ToCatalog
    from standgrid.mission.model import Mission
    from standgrid.partition.chunks import PayloadTask
    from standgrid.partition.protocol import Partition
    from standgrid.tiling.elevation import PlacedMaps
    from standgrid.tiling.increment import Increment
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
    #: the cluster's workers share no folder with this process: payloads are read here, and
    #: workers put the tiles they encode in this object-storage folder (an ObjectFolder)
    outbox: Any = None


@dataclass
class EpochResult:
    """What tiling one epoch produced: the report entry and the tiles written."""

    report: dict[str, Any]
    missions: dict[str, dict[str, Any]] = field(default_factory=dict)
    tiles: list[tuple[str, TileInfo]] = field(default_factory=list)
    #: False when every point stayed where it was (a re-tile of unchanged missions)
    changed: bool = True
    #: the missions' placed elevation maps staged (``maps/<epoch>/``): the epoch's mosaic
    #: is made of them and those kept (:func:`~standgrid.tiling.elevation.stage_epoch_mosaic`)
    maps_staged: set[str] = field(default_factory=set)


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
    reading = SerialExecutor() if settings.outbox is not None else executor  # paths: here
    plan = _plan_epoch(catalog, index, epoch, group, renewed, settings, reading, progress)
    written = _write_epoch_cells(catalog, txn, epoch, plan, settings, executor, progress)
    tiles = _gather_tiles(catalog, txn, index, epoch, plan, written.cells)
    fed = _check_conservation(catalog, epoch, written)
    removed = sorted(set(plan.previous) - {rel for rel, _ in tiles.result.tiles})
    for rel in removed:
        txn.delete(rel)
    before = txn.epoch_record(epoch)
    for name in before.missions if before else ():
        if name not in plan.names:
            txn.set_mission_tiles(name, tiles.tiles_of.get(name, ()))
    maps = _place_maps(catalog, txn, epoch, group, plan)
    _record_missions(catalog, txn, index, epoch, group, plan, tiles, maps)
    result = tiles.result
    result.maps_staged = {
        paths.mission_elevation_map(epoch, n) for n, m in maps.items() if m.heights is not None
    }
    result.changed = plan.increment is None or bool(plan.read or plan.rewrite)
    settled = txn.settle_epoch(epoch, settings.tiling, changed=result.changed)
    if not result.changed and settled and before and settled.date != before.date:
        result.changed = True  # the epoch's date moved: what was computed for it is stale
        settled = txn.settle_epoch(epoch, settings.tiling, changed=True)
    done, left_in, increment = written.cells, tiles.left_in, plan.increment
    result.report = {
        "date": settled.date or "" if settled else "",  # None: every mission moved out
        "points_in": fed + left_in,
        "points_kept_from_catalog": done.kept_in + left_in,
        "points_new": sum(written.new_in.values()),
        "withheld_left_out": written.withheld_left_out,
        "points_out": done.points_out + left_in,
        "points_rewritten": done.points_out,
        "buffer_points": done.buffer_points,
        "cells": len(result.tiles),
        "cells_rewritten": len(done.tiles),
        "cells_removed": len(removed),
        "payloads_unchanged": len(increment.unchanged) if increment else 0,
        "bytes_spilled": done.bytes_spilled,
    }
    return result


@dataclass
class _EpochPlan:
    """What (re)tiling an epoch reads and rewrites."""

    names: set[str]
    #: the epoch's tiles before (catalog-relative)
    previous: list[str]
    schema: Any
    #: the ``payloads`` rows of ``group``'s missions (in payload order) and their tasks
    rows: list[dict[str, Any]]
    tasks: list[PayloadTask]
    #: the stored ``payloads`` rows of the epoch's other missions
    others: Any
    partition: Partition
    #: None: the whole epoch is re-tiled
    increment: Increment | None
    #: the payloads read (indices into ``rows``), the old tiles rewritten, what they lose
    read: list[int]
    rewrite: list[str]
    drop: dict[str, Any]


def _plan_epoch(
    catalog: Catalog,
    index: CatalogIndex,
    epoch: str,
    group: list[Ingest],
    renewed: list[int],
    settings: EpochSettings,
    executor: Executor,
    progress: Progress,
) -> _EpochPlan:
    """The placements chosen, the payloads' rows and digests, the partition, and what is
    re-tiled: the whole epoch, or in place the tiles holding dropped payloads or receiving
    changed ones (:func:`~standgrid.tiling.increment.plan_increment`)."""
    from standgrid.catalog.partition import catalog_partition
    from standgrid.partition.chunks import PayloadTask
    from standgrid.tiling.increment import (
        keep_rows,
        landing_tiles,
        placement_digest,
        plan_increment,
        source_digest,
        tiles_holding,
    )
    from standgrid.tiling.mission_rows import epoch_sites, payload_rows, tiling_schema

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
    return _EpochPlan(
        names, previous, schema, rows, tasks, others, partition, increment, read, rewrite, drop
    )


@dataclass
class _Written:
    """The cells written, and the new payloads' points per mission."""

    cells: Cells
    new_in: dict[str, int]
    withheld_left_out: int = 0  # source points flagged withheld (deleted), not tiled


def _write_epoch_cells(
    catalog: Catalog,
    txn: Transaction,
    epoch: str,
    plan: _EpochPlan,
    settings: EpochSettings,
    executor: Executor,
    progress: Progress,
) -> _Written:
    """The kept points and the payloads read through the partition into the staged tiles;
    each payload's row gets its point count and footprint."""
    from standgrid.catalog.partition import catalog_partition
    from standgrid.tiling.mission_rows import epoch_sites
    from standgrid.tiling.retile import KeptTiles

    rows, read, partition = plan.rows, plan.read, plan.partition
    written = _Written(Cells(), dict.fromkeys(plan.names, 0))

    def on_payload(k: int, points: int, footprint: Any, withheld: int) -> None:
        row = rows[read[k]]
        row["point_count"] = points
        row["withheld_left_out"] = withheld
        row["geometry"] = footprint
        written.new_in[row["mission"]] += points
        written.withheld_left_out += withheld

    origin = partition.lattice_origin
    work = EpochWork(
        epoch=epoch,
        kept=[
            KeptTiles(catalog.path(rel), lattice_origin=origin, schema=plan.schema, **plan.drop)
            for rel in plan.rewrite
        ],
        payloads=[plan.tasks[k] for k in read],
        partition=partition,
        buffer=partition.buffer(settings.tiling.buffer) if settings.tiling.buffer else None,
        on_payload=on_payload,
        final_partition=lambda: catalog_partition(catalog, payloads=epoch_sites(plan.others, rows)),
        crs=catalog.crs,
        laz=settings.tiling.laz,
        copc=settings.tiling.copc,
        memory_budget=settings.memory_budget,
        outbox=settings.outbox,
    )
    written.cells = write_cells(work, txn, executor, progress)
    return written


@dataclass
class _Tiles:
    """The epoch's tiles after the run: written ones and those left as they were."""

    result: EpochResult
    #: the index's ``cells`` rows of every tile
    cell_rows: list[dict[str, Any]]
    #: mission name -> the tiles holding its points
    tiles_of: dict[str, set[str]]
    #: points in the tiles left as they were
    left_in: int


def _gather_tiles(
    catalog: Catalog,
    txn: Transaction,
    index: CatalogIndex,
    epoch: str,
    plan: _EpochPlan,
    done: Cells,
) -> _Tiles:
    """The written tiles' rows, and the untouched tiles' rows as indexed; refuses points
    landed in a tile that was to stay, and an untouched tile without a row."""
    from standgrid.errors import CatalogError, ConservationError
    from standgrid.export.gpkg import cell_row
    from standgrid.tiling.increment import kept_tile_info

    number_to_name = {r.number: n for n, r in txn.mission_records().items()}
    tiles = _Tiles(EpochResult({}), [], {}, 0)
    for cell_id, rel, info in done.tiles:
        missions = sorted(number_to_name[n] for n in info.points_per_source)
        for name in missions:
            tiles.tiles_of.setdefault(name, set()).add(rel)
        size = plan.partition.cell_size(cell_id)
        row = cell_row(
            cell_id, info, level=0, cell_size=size, epoch=epoch, missions=missions, tile_path=rel
        )
        tiles.cell_rows.append(row)
        tiles.result.tiles.append((rel, info))
    untouched = set(plan.previous) - set(plan.rewrite)
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
            tiles.left_in += int(row["point_count"])
            for name in filter(None, str(row["missions"]).split(",")):
                tiles.tiles_of.setdefault(name, set()).add(row["tile_path"])
            tiles.cell_rows.append(row)
            tiles.result.tiles.append(
                (row["tile_path"], kept_tile_info(catalog.path(row["tile_path"]), row, catalog.crs))
            )
    if rowless:
        raise CatalogError(
            f"epoch {epoch}: tiles without a row in the index's cells layer: "
            f"{', '.join(sorted(rowless)[:3])}",
            path=catalog.root,
        )
    return tiles


def _check_conservation(catalog: Catalog, epoch: str, written: _Written) -> int:
    """The points fed (kept and new); :class:`ConservationError` unless every one was
    partitioned and written."""
    from standgrid.errors import ConservationError

    done = written.cells
    fed = done.kept_in + sum(written.new_in.values())
    if done.points_in != fed or done.points_out != fed:
        raise ConservationError(
            f"epoch {epoch}: {fed} points fed, {done.points_in} partitioned, "
            f"{done.points_out} written",
            path=catalog.root,
        )
    return fed


def _place_maps(
    catalog: Catalog, txn: Transaction, epoch: str, group: list[Ingest], plan: _EpochPlan
) -> dict[str, PlacedMaps]:
    """The derived maps of the group's missions placed into the catalog CRS (missions that
    carry some), their elevation maps staged into ``maps/<epoch>/`` (earlier ones gone)."""
    from standgrid.tiling.elevation import has_maps, place_mission_maps, stage_mission_maps

    origin, _ = plan.partition.raster_alignment()
    out = {}
    for ingest in group:
        mission = ingest.mission
        placed = None
        if has_maps(mission):
            assert ingest.to_catalog is not None
            placed = place_mission_maps(mission, ingest.to_catalog, catalog.crs, origin)
            out[mission.name] = placed
        stage_mission_maps(catalog, txn, epoch, mission.name, placed)
    return out


def _record_missions(
    catalog: Catalog,
    txn: Transaction,
    index: CatalogIndex,
    epoch: str,
    group: list[Ingest],
    plan: _EpochPlan,
    tiles: _Tiles,
    maps: dict[str, PlacedMaps],
) -> None:
    """Each mission of ``group`` recorded in the catalog state and the report; the epoch's
    cells, payloads and the missions' trajectories, GNSS fixes and rows into the index."""
    import pandas as pd

    from standgrid.georeference.placement import cloud_payloads
    from standgrid.tiling.mission_rows import (
        gnss_rows,
        metadata_extra,
        mission_row,
        trajectory_rows,
    )

    rows, names, tiles_of = plan.rows, plan.names, tiles.tiles_of
    mission_rows, trajectories, fixes = [], [], []
    for ingest in group:
        mission = ingest.mission
        mine_rows = [r for r in rows if r["mission"] == mission.name]
        placed = maps.get(mission.name)
        extra = {} if placed is None else {"derived_maps": placed.record()}
        record = txn.record_mission(
            mission.name,
            epoch=epoch,
            date=ingest.date,
            path=source_of(mission.path),  # its URL when fetched from object storage
            georeference=ingest.placement.record(),
            placement=_note(ingest),
            payload_count=len(cloud_payloads(mission)),
            point_count=sum(r["point_count"] for r in mine_rows),
            tiles=sorted(tiles_of.get(mission.name, ())),
            **metadata_extra(mission),
            **extra,
        )
        tiles.result.missions[mission.name] = {
            "number": record["number"],
            "epoch": epoch,
            "payloads": record["payload_count"],
            "points": record["point_count"],
            "withheld_left_out": sum(r["withheld_left_out"] for r in mine_rows),
            "tiles": len(record["tiles"]),
            "georeference": ingest.placement.summary(),
            "placement": _note(ingest),
            "warnings": list(mission.warnings),
            **extra,
        }
        assert ingest.to_catalog is not None
        trajectories += trajectory_rows(mission, ingest.to_catalog, epoch)
        fixes.append(gnss_rows(mission, ingest.placement, catalog.crs))
        mission_rows.append(
            mission_row(
                mission,
                ingest.placement,
                ingest.number,
                epoch,
                ingest.date,
                catalog,
                placement_offset_m=_note(ingest)["offset_m"],
            )
        )
    index.replace("cells", tiles.cell_rows, epochs={epoch})
    index.replace("payloads", rows, missions=names)
    index.replace("trajectories", trajectories, missions=names)
    fixes = [f for f in fixes if len(f)]
    index.replace(
        "gnss_fixes", pd.concat(fixes, ignore_index=True) if fixes else [], missions=names
    )
    index.replace("missions", mission_rows, missions=names)


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
            ingest.mission,
            ingest.number,
            epoch,
            ingest.placement,
            records.get(name),
            stored,
            cells,
            schema,
            catalog.crs,
            settings.placement_tolerance,
        )
        if ingest.choice.placement is not ingest.placement:
            ingest.placement = ingest.choice.placement
            ingest.to_catalog = ingest.placement.to_catalog(catalog.crs, name)


def _note(ingest: Ingest) -> dict[str, Any]:
    """The mission's ``placement`` note (report, record): which placement, how far off."""
    assert ingest.choice is not None
    return ingest.choice.note()
