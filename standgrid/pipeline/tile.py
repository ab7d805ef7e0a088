"""Tile missions into a catalog: georeference -> partition -> LAS/LAZ tiles + GeoPackage index.

One call ingests any number of missions. Missions are grouped into epochs (campaigns; by
default the year of the mission date). For every epoch touched, the epoch's existing tiles
(minus the points of missions being re-ingested) and the new missions' payloads are streamed
through one :class:`~standgrid.partition.engine.PartitionEngine`, so re-ingesting is
idempotent, several robots of one campaign merge into the same tiles, and buffers are right
across mission boundaries. Everything is written inside one catalog transaction: an
interrupted run leaves the previous catalog intact and a re-run completes it.

The per-payload and per-cell work runs on an executor (this process, or a dask cluster with
``workers``/``scheduler``; :mod:`standgrid.tiling.epoch`); this process alone writes
the catalog, its index and its VPCs.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from standgrid.catalog.index import CatalogIndex
from standgrid.engine import Execution, Progress
from standgrid.errors import (
    CatalogError,
    NotGeoreferencedError,
    OptionError,
    OutputOverlapsInputError,
    out_of_space_error,
)
from standgrid.tiling.epoch import EpochSettings, Ingest, tile_epoch
from standgrid.tiling.options import TileOptions
from standgrid.tiling.setup import (
    GridRequest,
    absolute_output,
    check_area_of_use,
    check_existing,
    create_catalog,
    existing_crs,
    is_catalog,
    refuse_foreign_folder,
    refuse_other_folders,
    refuse_overlap,
    settle_tiling,
)

if TYPE_CHECKING:
    from standgrid.catalog import Catalog
    from standgrid.mission.model import Mission

__all__ = ["TileReport", "realign_catalog", "tile_missions"]


@dataclass
class TileReport:
    """What a tiling run did; ``to_dict`` is the CLI's ``--json``."""

    catalog: Path | str  # a folder, or the object-storage URL it was committed to
    crs: str
    scheme: str
    grid_fingerprint: str
    missions: dict[str, dict[str, Any]] = field(default_factory=dict)
    epochs: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Processes the per-payload and per-cell work ran on (1: this one).
    workers: int = 1
    #: Epochs not tiled whose results were removed too (their DBH imputation pooled the trees
    #: of re-tiled epochs): epoch -> what was removed.
    also_invalidated: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: What alignment did (:meth:`standgrid.alignment.AlignResult.to_dict`); None: not run.
    alignment: dict[str, Any] | None = None

    @property
    def points_in(self) -> int:
        return sum(e["points_in"] for e in self.epochs.values())

    @property
    def points_out(self) -> int:
        return sum(e["points_out"] for e in self.epochs.values())

    @property
    def withheld_left_out(self) -> int:
        """Payload points the source files flag withheld (deleted): not tiled, not in
        :attr:`points_in`."""
        return sum(e.get("withheld_left_out", 0) for e in self.epochs.values())

    def to_dict(self) -> dict[str, Any]:
        return {
            "catalog": str(self.catalog),
            "crs": self.crs,
            "scheme": self.scheme,
            "grid_fingerprint": self.grid_fingerprint,
            "points_in": self.points_in,
            "points_out": self.points_out,
            "conserved": self.points_in == self.points_out,
            "withheld_left_out": self.withheld_left_out,
            "workers": self.workers,
            "epochs": self.epochs,
            "also_invalidated": self.also_invalidated,
            "alignment": self.alignment,
            "missions": self.missions,
        }


def tile_missions(
    mission_paths: Sequence[str | Path | Mission],
    catalog_path: str | Path,
    options: TileOptions = TileOptions(),
    *,
    execution: Execution = Execution(),
) -> TileReport:
    """Georeference and tile missions into the catalog at ``catalog_path`` (made if absent).

    ``mission_paths`` are mission folders (or object-storage URLs of them) or missions
    already opened (``open_mission``); ``catalog_path`` a folder or an object-storage URL
    (:mod:`standgrid.catalog.remote`). The per-payload and per-cell work runs as
    ``execution`` says. Raises a :class:`~standgrid.errors.StandgridError` subclass on any
    bad input, leaving the catalog as it was.
    """
    from standgrid.catalog.remote import catalog_at
    from standgrid.storage import is_url
    from standgrid.storage.objects import fetched_folder

    for m in mission_paths:
        if is_url(m) and is_url(catalog_path) and _nested(str(m), str(catalog_path)):
            raise OutputOverlapsInputError(
                f"the catalog {catalog_path} and the mission {m} overlap: writing one would "
                "destroy the other"
            )
    missions = [fetched_folder(str(m)) if is_url(m) else m for m in mission_paths]
    if not is_url(catalog_path):
        return _tile_missions(missions, catalog_path, options, execution=execution)
    if not execution.shared_folder:
        from standgrid.catalog.remote import outbox_url

        execution = replace(execution, outbox=outbox_url(str(catalog_path)))
    with catalog_at(catalog_path, write=True, lock_timeout=execution.lock_timeout) as root:
        report = _tile_missions(missions, root, options, execution=execution)
    return replace(report, catalog=str(catalog_path))


def _nested(a: str, b: str) -> bool:
    """Whether one URL is, or lies inside, the other."""
    a, b = a.rstrip("/") + "/", b.rstrip("/") + "/"
    return a.startswith(b) or b.startswith(a)


def _tile_missions(
    mission_paths: Sequence[str | Path | Mission],
    catalog_path: str | Path,
    options: TileOptions,
    *,
    execution: Execution,
) -> TileReport:
    from standgrid.catalog import Catalog, build_folder, publish, remove_stale_builds, writer_lock
    from standgrid.mission.model import Mission

    if not mission_paths:
        raise CatalogError("no missions given")
    if not execution.shared_folder and execution.outbox is None:
        raise OptionError(
            "shared_folder",
            "workers without a shared folder exchange tiles through object storage: give "
            "the catalog as an object-storage URL (s3://bucket/prefix)",
        )
    if options.anchor is not None and len(mission_paths) > 1:
        raise OptionError("anchor", "an anchor places one mission: tile one mission per anchor")
    progress, timeout = execution.progress, execution.lock_timeout
    auto = options.crs in ("auto", "", None)
    path = absolute_output(catalog_path, options.overwrite)
    # the output before any work (again later: missions opened, under the lock)
    refuse_overlap(path, [g.path if isinstance(g, Mission) else g for g in mission_paths])
    refuse_foreign_folder(path)
    # --crs auto adding to a catalog: the catalog's CRS (also that of clouds naming none)
    held_crs = existing_crs(path, options.overwrite, timeout) if auto else None
    clouds_crs = held_crs or options.crs
    ingests = [_prepare(given, options, progress, clouds_crs) for given in mission_paths]
    names = [i.mission.name for i in ingests]
    if len(set(names)) != len(names):
        raise CatalogError(
            f"a mission is given twice: {sorted(n for n in names if names.count(n) > 1)}"
        )

    refuse_overlap(path, [i.mission.path for i in ingests])
    request = GridRequest(
        options.scheme, options.cell_size, tuple(options.levels), options.origin, options.crs
    )
    placements = [i.placement for i in ingests]
    with contextlib.ExitStack() as stack:
        executor = stack.enter_context(execution.open())
        # One lock, beside the catalog, covers reading it, creating it and replacing it.
        lock = stack.enter_context(writer_lock(path, timeout=timeout))
        remove_stale_builds(path)
        if is_catalog(path) and not options.overwrite:
            with Catalog.writing(path, held=lock, lock_timeout=timeout) as catalog:
                check_existing(catalog, request)
                return _ingest(catalog, ingests, options, execution.on(executor))
        refuse_foreign_folder(path)
        if path.is_dir() and not any(path.iterdir()):
            # an empty folder (maybe the current one) becomes the catalog in place
            try:
                catalog = create_catalog(path, path, lock, placements, request, timeout)
                return _ingest(catalog, ingests, options, execution.on(executor))
            except BaseException:
                for child in path.iterdir():  # back to the empty folder it was
                    shutil.rmtree(child) if child.is_dir() else child.unlink()
                raise
        # A new catalog (or a replacement) is built beside its final place and swapped in
        # only when complete: a failure or a kill leaves nothing, or the old catalog.
        build = build_folder(path)
        try:
            catalog = create_catalog(build, path, lock, placements, request, timeout)
            report = _ingest(catalog, ingests, options, execution.on(executor))
            publish(build, path, timeout=timeout)
        except BaseException as exc:
            shutil.rmtree(build, ignore_errors=True)
            full = out_of_space_error(exc, path)
            if full is not None and full is not exc:
                raise full from exc
            raise
    report.catalog = path
    return report


def _prepare(
    given: str | Path | Mission, options: TileOptions, progress: Progress, crs: str
) -> Ingest:
    """Open (a folder, without a point cache: each payload is read once) and place a mission
    (``crs``: of clouds already projected that name none)."""
    from standgrid.georeference.placement import place_mission
    from standgrid.mission.model import Mission
    from standgrid.mission.opening import open_mission
    from standgrid.mission.scan import ScanOptions, is_scan, open_scan

    if isinstance(given, Mission):
        mission = given
    elif is_scan(given):
        scan = ScanOptions(crs=crs, date=options.scan_date, trajectory=options.trajectory)
        mission = open_scan(given, scan)
    else:
        if options.trajectory is not None:
            raise CatalogError(
                "option trajectory is for plain scans (LAS/LAZ files or "
                "folders of them); a mission has its pose graph",
                path=Path(given),
                option="trajectory",
            )
        mission = open_mission(given, cache_points=0)
    progress.status(f"georeferencing {mission.name}")
    try:
        placement = place_mission(
            mission,
            crs=crs,
            anchor=options.anchor,
            method=options.method,
            accept_poor=options.accept_poor_georeference,
        )
    except NotGeoreferencedError as exc:
        # no GNSS and no anchor: the catalog (or the missions given with it) may place it
        if not options.align or mission.graph is None or mission.is_projected:
            raise
        from standgrid.alignment.stage import provisional_placement

        try:
            placement = provisional_placement(mission)
        except NotGeoreferencedError:
            raise exc from None
    meta = mission.metadata
    labels = dict(options.epochs)
    if mission.name in labels:
        epoch = labels[mission.name]
    elif options.epoch is not None:
        epoch = options.epoch
    elif meta is not None:
        epoch = str(meta.date.year)
    else:
        raise CatalogError(
            "no metadata.yaml and no conventional folder name: cannot tell the epoch "
            "(give one with option epoch)",
            path=mission.path,
            option="epoch",
        )
    date = meta.date.isoformat() if meta is not None else ""
    return Ingest(mission, placement, epoch, date)


def _ingest(
    catalog: Catalog, ingests: list[Ingest], options: TileOptions, execution: Execution
) -> TileReport:
    """Tile the prepared missions into a catalog opened for writing, in one transaction
    (``execution.executor``: open)."""
    from standgrid.catalog.invalidate import invalidate_epochs, retile_reason
    from standgrid.tiling.elevation import stage_epoch_mosaic
    from standgrid.tiling.vpcs import stage_epoch_vpc

    executor, progress = execution.executor, execution.progress
    assert executor is not None
    report = TileReport(catalog.root, catalog.crs, catalog.scheme, catalog.fingerprint)
    report.workers = executor.workers
    with catalog.transaction() as txn:
        index = CatalogIndex(catalog, txn)  # under the writer lock: no commit can intervene
        tiling = settle_tiling(txn, options.buffer, options.laz, options.copc)
        # a placement given by hand (an anchor, a fit method) is applied exactly
        by_hand = options.anchor is not None or options.method != TileOptions.method
        tolerance = None if by_hand else options.placement_tolerance
        outbox = None
        if execution.outbox is not None:
            from standgrid.storage import ObjectFolder

            outbox = ObjectFolder.open(execution.outbox)
        settings = EpochSettings(tiling, execution.memory_budget, tolerance, outbox)
        if options.align and not by_hand and _alignable(catalog, ingests):
            from standgrid.pipeline.align import align_ingests

            report.alignment = align_ingests(catalog, txn, ingests, progress)
        for ingest in ingests:  # a mission without GNSS that nothing registered with
            if ingest.placement.alignment and _is_provisional(ingest.placement):
                raise NotGeoreferencedError(
                    "no GNSS fixes and no pose-graph anchor, and no other mission (given, or "
                    "in the catalog) registers with it: give option anchor",
                    path=ingest.mission.path,
                    option="anchor",
                )
        for ingest in ingests:
            ingest.number = txn.mission_number(ingest.mission.name)
            ingest.to_catalog = ingest.placement.to_catalog(catalog.crs, ingest.mission.name)
        renewed = [i.number for i in ingests]
        if not options.replace_missions:
            refuse_other_folders(catalog, [(i.mission.name, i.mission.path) for i in ingests])
        if options.crs in ("auto", "", None):  # the catalog's CRS must suit every mission
            check_area_of_use(catalog, [(i.mission.name, i.placement) for i in ingests])
        # an epoch a re-ingested mission leaves is re-tiled too (without that mission)
        known = catalog.mission_records
        left = {known[i.mission.name].epoch for i in ingests if i.mission.name in known}
        reasons = {}
        maps_staged: set[str] = set()
        for epoch in sorted({i.epoch for i in ingests} | left):
            group = [i for i in ingests if i.epoch == epoch]
            names = ", ".join(i.mission.name for i in group) or "missions that moved out"
            progress.status(f"tiling epoch {epoch}: {names}")
            done = tile_epoch(
                catalog, txn, index, epoch, group, renewed, settings, executor, progress
            )
            report.epochs[epoch] = done.report
            report.missions.update(done.missions)
            maps_staged |= done.maps_staged
            stage_epoch_vpc(txn, epoch, done.tiles, catalog.crs)
            moved = [
                i.mission.name
                for i in ingests
                if i.epoch != epoch
                and i.mission.name in known
                and known[i.mission.name].epoch == epoch
            ]
            if done.changed:  # else its enrichment and comparisons still hold
                reasons[epoch] = retile_reason([i.mission.name for i in group], moved)
        index.save()
        cells = len(index.read("cells"))
        # the re-tiled epochs' enrichment and comparisons describe points that are gone
        removed_by_epoch = invalidate_epochs(catalog, txn, reasons, status=progress.status)
        # the epochs' elevation-map mosaics, of their missions' maps (kept and new)
        for epoch in sorted({*report.epochs, *removed_by_epoch}):
            mosaic = stage_epoch_mosaic(catalog, txn, epoch, maps_staged)
            if mosaic is not None and epoch in report.epochs:
                report.epochs[epoch]["elevation_map"] = mosaic
        for epoch, removed in removed_by_epoch.items():
            if epoch in report.epochs:
                report.epochs[epoch]["invalidated"] = removed
            else:  # not tiled, but computed from the re-tiled epochs' trees
                report.also_invalidated[epoch] = removed
    progress.status(f"tiled {report.points_out} points into {cells} cells")
    return report


def _alignable(catalog: Catalog, ingests: list[Ingest]) -> bool:
    """Two missions at least (given, or in the catalog besides them): else alignment has
    nothing to do, and :mod:`standgrid.alignment` (stems: pandas, scipy) is not even imported."""
    given = {i.mission.name for i in ingests}
    return len(ingests) > 1 or any(name not in given for name in catalog.mission_records)


def _is_provisional(placement: Any) -> bool:
    from standgrid.alignment.stage import is_provisional  # only placements with an alignment

    return is_provisional(placement)


def realign_catalog(
    catalog_path: str | Path,
    options: TileOptions = TileOptions(),
    *,
    execution: Execution = Execution(),
) -> TileReport:
    """Re-tile every mission of a catalog from the folder it was tiled from, in its own
    epoch, aligned all together (``standgrid align``). Raises
    :class:`~standgrid.errors.CatalogError` when a mission's folder is gone."""
    from standgrid.catalog.remote import catalog_at
    from standgrid.storage import is_url

    if not is_url(catalog_path):
        return _realign_catalog(Path(catalog_path), options, execution=execution)
    with catalog_at(catalog_path, write=True, lock_timeout=execution.lock_timeout) as root:
        report = _realign_catalog(root, options, execution=execution)
    return replace(report, catalog=str(catalog_path))


def _realign_catalog(path: Path, options: TileOptions, *, execution: Execution) -> TileReport:
    from standgrid.catalog import Catalog
    from standgrid.storage import is_url
    from standgrid.storage.objects import local_copy

    records = Catalog.open(path, lock_timeout=execution.lock_timeout).mission_records
    if not records:
        raise CatalogError("no missions in the catalog: nothing to align", path=path)
    gone = sorted(
        n
        for n, r in records.items()
        if not r.path or (not is_url(r.path) and not Path(r.path).exists())
    )
    if gone:
        raise CatalogError(
            f"cannot re-align: the folders of {', '.join(gone)} are gone (tile them again "
            "from where they are now, with option replace_missions)",
            path=path,
            option="replace_missions",
        )
    missions = [local_copy(str(r.path)) for _, r in sorted(records.items())]  # URLs fetched
    epochs = tuple(sorted((n, r.epoch) for n, r in records.items()))
    settings = replace(options, align=True, epochs=epochs, overwrite=False)
    return tile_missions(missions, path, settings, execution=execution)
