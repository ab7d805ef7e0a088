"""Tile missions into a catalog: georeference -> partition -> LAS/LAZ tiles + GeoPackage index.

One call ingests any number of missions. Missions are grouped into epochs (campaigns; by
default the year of the mission date). For every epoch touched, the epoch's existing tiles
(minus the points of missions being re-ingested) and the new missions' payloads are streamed
through one :class:`~standgrid.partition.engine.PartitionEngine`, so re-ingesting is
idempotent, several robots of one campaign merge into the same tiles, and buffers are right
across mission boundaries. Everything is written inside one catalog transaction: an
interrupted run leaves the previous catalog intact and a re-run completes it.
"""

from __future__ import annotations

import math
import shutil
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from standgrid.catalog import paths
from standgrid.errors import (
    CatalogError,
    CRSError,
    GeoreferenceError,
    GridMismatchError,
    OutputNotWritableError,
    OutputOverlapsInputError,
    out_of_space_error,
)
from standgrid.pointcloud import PointCloud
from standgrid.stamps import unix_ns_to_adjusted_gps_time

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, FileLock, Transaction
    from standgrid.georeference import GeoreferenceFit, MapProjector
    from standgrid.mission.model import Mission, Payload
    from standgrid.partition import StandGrid

T = TypeVar("T")
Wrap = Callable[[Iterable[Any], int, str], Iterable[Any]]

DEFAULT_MEMORY_BUDGET = 2 << 30
#: Payload ids are ``mission_number << 16 | payload index``: stable on re-ingest, no registry.
PAYLOAD_INDEX_BITS = 16
#: Fields the tiler sets on every point.
TILER_FIELDS: dict[str, np.dtype] = {
    "gps_time": np.dtype(np.float64),
    "point_source_id": np.dtype(np.uint16),
    "payload_id": np.dtype(np.uint32),
}


def _no_wrap(items: Iterable[T], total: int, desc: str) -> Iterable[T]:
    return items


@dataclass(frozen=True)
class TileOptions:
    """How to tile. ``cell_size``/``crs`` of ``None``/``"auto"`` take the catalog's own."""

    #: ``None``: the catalog's scheme ("grid" for a new catalog).
    scheme: Literal["grid", "voronoi"] | None = None
    cell_size: float | None = None
    levels: tuple[float, ...] = ()
    origin: tuple[float, float] = (0.0, 0.0)
    crs: str = "auto"
    #: ``None``: the catalog's setting (0 for a new catalog).
    buffer: float | None = None
    #: ``None``: the catalog's setting (LAZ for a new catalog).
    laz: bool | None = None
    method: str = "yaw2d"
    #: ``(lat, lon, alt, yaw_deg)``: place the map frame by hand, no GNSS fit
    #: (:func:`standgrid.georeference.fit_from_anchor`); one mission per run.
    anchor: tuple[float, float, float, float] | None = None
    epoch: str | None = None
    memory_budget: int = DEFAULT_MEMORY_BUDGET
    overwrite: bool = False
    #: Seconds to wait for another writer of the catalog (None: for ever).
    lock_timeout: float | None = 30.0
    #: Tile even when a georeference's residuals are far beyond the fixes' stated accuracy.
    accept_poor_georeference: bool = False


@dataclass
class TileReport:
    """What a tiling run did; ``to_dict`` is the CLI's ``--json``."""

    catalog: Path
    crs: str
    scheme: str
    grid_fingerprint: str
    missions: dict[str, dict[str, Any]] = field(default_factory=dict)
    epochs: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def points_in(self) -> int:
        return sum(e["points_in"] for e in self.epochs.values())

    @property
    def points_out(self) -> int:
        return sum(e["points_out"] for e in self.epochs.values())

    def to_dict(self) -> dict[str, Any]:
        return {
            "catalog": str(self.catalog),
            "crs": self.crs,
            "scheme": self.scheme,
            "grid_fingerprint": self.grid_fingerprint,
            "points_in": self.points_in,
            "points_out": self.points_out,
            "conserved": self.points_in == self.points_out,
            "epochs": self.epochs,
            "missions": self.missions,
        }


@dataclass
class _Ingest:
    """One mission on its way in."""

    mission: Mission
    #: The map -> ENU georeference; None for clouds already in a projected CRS.
    fit: GeoreferenceFit | None
    epoch: str
    date: str
    projector: MapProjector | None = None
    number: int = 0
    #: The projected CRS of a mission whose clouds are already in one (else None).
    source_crs: str | None = None
    #: source CRS -> catalog CRS for such clouds (None: the same CRS).
    to_catalog: Any = None


# --- entry point -------------------------------------------------------------------------


def tile_missions(
    mission_paths: Sequence[str | Path | Mission],
    catalog_path: str | Path,
    options: TileOptions = TileOptions(),
    *,
    wrap: Wrap = _no_wrap,
    status: Callable[[str], None] = lambda message: None,
) -> TileReport:
    """Georeference and tile missions into the catalog at ``catalog_path`` (made if absent).

    ``mission_paths`` are mission folders or missions already opened (``open_mission``).

    ``wrap(iterable, total, description)`` may add a progress bar; ``status`` gets progress
    lines. Raises a :class:`~standgrid.errors.StandgridError` subclass on any bad input,
    leaving the catalog as it was.
    """
    from standgrid.mission.model import Mission, open_mission

    if not mission_paths:
        raise CatalogError("no missions given")
    if options.anchor is not None and len(mission_paths) > 1:
        raise CatalogError("an anchor places one mission: tile one mission per --anchor")
    ingests: list[_Ingest] = []
    for path in mission_paths:
        # a folder is opened without a point cache: each payload is read once
        mission = path if isinstance(path, Mission) else open_mission(path, cache_points=0)
        status(f"georeferencing {mission.name}")
        ingests.append(_prepare(mission, options))
    names = [i.mission.name for i in ingests]
    if len(set(names)) != len(names):
        raise CatalogError(
            f"a mission is given twice: {sorted(n for n in names if names.count(n) > 1)}"
        )

    path = _absolute_output(catalog_path, options)
    refuse_overlap(path, [i.mission.path for i in ingests])
    from standgrid.catalog import (
        Catalog,
        build_folder,
        publish,
        remove_stale_builds,
        writer_lock,
    )

    # One lock, beside the catalog, covers reading it, creating it and replacing it.
    with writer_lock(path, timeout=options.lock_timeout) as lock:
        remove_stale_builds(path)
        if _is_catalog(path) and not options.overwrite:
            with Catalog.writing(path, held=lock) as catalog:
                _check_existing(catalog, options)
                return _ingest(catalog, ingests, options, wrap, status)
        _refuse_foreign_folder(path, options)
        if path.is_dir() and not any(path.iterdir()):
            # an empty folder (maybe the current one) becomes the catalog in place
            try:
                catalog = _create(path, path, lock, ingests, options)
                return _ingest(catalog, ingests, options, wrap, status)
            except BaseException:
                for child in path.iterdir():  # back to the empty folder it was
                    shutil.rmtree(child) if child.is_dir() else child.unlink()
                raise
        # A new catalog (or a replacement) is built beside its final place and swapped in
        # only when complete: a failure or a kill leaves nothing, or the old catalog.
        build = build_folder(path)
        try:
            catalog = _create(build, path, lock, ingests, options)
            report = _ingest(catalog, ingests, options, wrap, status)
            publish(build, path)
        except BaseException as exc:
            shutil.rmtree(build, ignore_errors=True)
            full = out_of_space_error(exc, path)
            if full is not None and full is not exc:
                raise full from exc
            raise
    report.catalog = path
    return report


def _absolute_output(catalog_path: str | Path, options: TileOptions) -> Path:
    """The catalog path made absolute ("." included); replacing the folder the process
    works in is refused."""
    import os

    path = Path(os.path.abspath(catalog_path))
    if not path.name:
        raise OutputNotWritableError("a catalog cannot be the file-system root", path=path)
    cwd = Path.cwd().resolve()
    if options.overwrite and path.is_dir() and any(path.iterdir()):
        real = path.resolve()
        if cwd == real or cwd.is_relative_to(real):
            raise OutputNotWritableError(
                "is (or holds) the current folder; --overwrite cannot replace it (run from "
                "another folder)",
                path=catalog_path,
            )
    return path


def refuse_overlap(output: Path, inputs: Iterable[str | Path]) -> None:
    """Refuse an output that is, holds or lies inside an input folder (symlinks resolved)."""
    import os

    out = Path(os.path.realpath(output))
    for given in inputs:
        source = Path(os.path.realpath(given))
        if out == source:
            how = "is"
        elif out.is_relative_to(source):
            how = "lies inside"
        elif source.is_relative_to(out):
            how = "holds"
        else:
            continue
        raise OutputOverlapsInputError(
            f"the output {how} the input {given}; outputs never overlap inputs (choose another -o)",
            path=output,
        )


def _ingest(
    catalog: Catalog, ingests: list[_Ingest], options: TileOptions, wrap: Wrap, status: Any
) -> TileReport:
    """Tile the prepared missions into a catalog opened for writing, in one transaction."""
    from standgrid.catalog.invalidate import invalidate_epochs, retile_reason

    grid = _catalog_grid(catalog)
    report = TileReport(catalog.root, catalog.crs, catalog.scheme, catalog.fingerprint)
    layers = _IndexLayers.read(catalog)  # under the writer lock: no commit can intervene
    with catalog.transaction() as txn:
        options = _settle_settings(txn, options)
        for ingest in ingests:
            ingest.number = txn.mission_number(ingest.mission.name)
            if ingest.fit is not None:
                ingest.projector = _projector(ingest.fit, catalog.crs)
            else:
                ingest.to_catalog = _to_catalog(ingest, catalog.crs)
        renewed = [i.number for i in ingests]
        # an epoch a re-ingested mission leaves is re-tiled too (without that mission)
        known = catalog.mission_records
        left = {known[i.mission.name].epoch for i in ingests if i.mission.name in known}
        reasons = {}
        for epoch in sorted({i.epoch for i in ingests} | left):
            group = [i for i in ingests if i.epoch == epoch]
            names = ", ".join(i.mission.name for i in group) or "missions that moved out"
            status(f"tiling epoch {epoch}: {names}")
            _tile_epoch(catalog, txn, grid, epoch, group, renewed, options, layers, report, wrap)
            moved = [
                i.mission.name
                for i in ingests
                if i.epoch != epoch
                and i.mission.name in known
                and known[i.mission.name].epoch == epoch
            ]
            reasons[epoch] = retile_reason([i.mission.name for i in group], moved)
        layers.write(txn, catalog)
        _write_vpcs(txn, catalog, layers)
        # the re-tiled epochs' enrichment and comparisons describe points that are gone
        for epoch, removed in invalidate_epochs(catalog, txn, reasons, status=status).items():
            report.epochs[epoch]["invalidated"] = removed
    status(f"tiled {report.points_out} points into {len(layers.cells)} cells")
    return report


# --- preparing missions and the catalog --------------------------------------------------


def _prepare(mission: Mission, options: TileOptions) -> _Ingest:
    """How the mission gets into the catalog's CRS: clouds already projected (no fit), an
    explicit anchor, or its own georeference (pose-graph anchor or GNSS fit)."""
    from standgrid.georeference import fit_from_anchor, georeference_mission
    from standgrid.georeference.fit import check_fit_quality

    fit: GeoreferenceFit | None = None
    source_crs = None
    if mission.is_projected:
        if options.anchor is not None:
            raise CatalogError(
                "the clouds are already in a projected CRS: an anchor would not be used",
                path=mission.path,
            )
        source_crs = _projected_crs(mission, options)
    elif options.anchor is not None:
        fit = fit_from_anchor(*options.anchor)
    else:
        try:
            fit = georeference_mission(mission, method=options.method)
        except GeoreferenceError as exc:
            raise type(exc)(
                f"{exc.message} (tiling needs a georeference: GNSS fixes, GNSS_LLA_REF/"
                "GNSS_LLA_TO_MAP in the pose graph, an explicit --anchor LAT LON ALT YAW, "
                "or clouds already in a projected CRS: payload_clouds_in_utm/ or LAS/LAZ "
                "with a CRS)",
                path=exc.path or mission.path,
                line=exc.line,
            ) from exc
    meta = mission.metadata
    if options.epoch is not None:
        epoch = options.epoch
    elif meta is not None:
        epoch = str(meta.date.year)
    else:
        raise CatalogError(
            "no metadata.yaml and no conventional folder name: cannot tell the epoch "
            "(give one with --epoch)",
            path=mission.path,
        )
    if fit is not None and not options.accept_poor_georeference:
        check_fit_quality(fit, source=_gnss_file(mission))
    date = meta.date.isoformat() if meta is not None else ""
    return _Ingest(mission, fit, epoch, date, source_crs=source_crs)


def _projected_crs(mission: Mission, options: TileOptions) -> str:
    """The one projected CRS of a mission's projected clouds: their files' own (LAS/LAZ),
    else ``options.crs`` (PCD/PLY in ``payload_clouds_in_utm/`` carry none)."""
    from standgrid.georeference import crs_to_text, resolve_crs

    clouds = _cloud_payloads(mission)
    own = {p.crs for p in clouds if p.crs is not None}
    if len(own) > 1:
        raise CRSError(
            f"the mission's clouds are in several CRSs: {sorted(own)}", path=mission.path
        )
    if own and len(own) == 1 and all(p.crs is not None for p in clouds):
        return own.pop()
    given = options.crs not in ("auto", "", None)
    if not given:
        folder = clouds[0].path.parent.name
        raise CRSError(
            f"the clouds in {folder}/ are in a projected CRS their files do not name: give it "
            "with --crs EPSG:XXXX (it is also the catalog's CRS)",
            path=mission.path,
        )
    text = crs_to_text(resolve_crs(options.crs))
    if own and own != {text}:
        raise CRSError(
            f"some clouds carry the CRS {own.pop()}, --crs says {text}", path=mission.path
        )
    return text


def _to_catalog(ingest: _Ingest, crs: str) -> Any:
    """A source -> catalog CRS transformer for projected clouds (None: the same CRS).

    Only x/y are transformed (2-D); heights are kept as the clouds have them."""
    import pyproj

    if ingest.source_crs == crs:
        return None
    return pyproj.Transformer.from_crs(ingest.source_crs, crs, always_xy=True)


def _gnss_file(mission: Mission) -> Path:
    """The file the mission's GNSS fixes came from (for messages)."""
    gnss = mission.path / "gnss" / "fixes.txt"
    return gnss if gnss.is_file() else mission.path


def _requested_grid(crs: str, options: TileOptions) -> dict[str, Any]:
    from standgrid.partition import StandGrid

    if options.scheme == "voronoi":
        return {"scheme": "voronoi", "crs": crs}  # cells come from the payloads
    grid = StandGrid(
        crs, options.cell_size or 20.0, origin=options.origin, levels=tuple(options.levels)
    )
    return grid.to_dict()


def _is_catalog(path: Path) -> bool:
    from standgrid.catalog import CATALOG_FILE

    return (path / CATALOG_FILE).is_file()


def _refuse_foreign_folder(path: Path, options: TileOptions) -> None:
    """A folder with other files is not silently turned into (or replaced by) a catalog."""
    from standgrid.errors import OutputExistsError

    if path.exists() and not path.is_dir():
        raise OutputExistsError("exists and is not a folder", path=path)
    if path.is_dir() and any(path.iterdir()) and not options.overwrite:
        raise OutputExistsError(
            "is a folder with files but not a catalog (use overwrite to replace it)", path=path
        )


def _check_existing(catalog: Catalog, options: TileOptions) -> None:
    """Refuse adding missions in another CRS, scheme or grid than the catalog's."""
    from standgrid.catalog import CATALOG_FILE
    from standgrid.georeference import crs_to_text, resolve_crs

    path = catalog.root
    if options.crs not in ("auto", "", None):
        wanted = crs_to_text(resolve_crs(options.crs))
        if wanted != catalog.crs:
            raise CRSError(
                f"the catalog is in {catalog.crs}; cannot add missions in {wanted}",
                path=path / CATALOG_FILE,
            )
    if options.scheme is not None and options.scheme != catalog.scheme:
        raise GridMismatchError(
            f"the catalog uses the {catalog.scheme} scheme, not {options.scheme}",
            path=path / CATALOG_FILE,
        )
    if catalog.scheme == "grid" and options.cell_size is not None:
        stored = catalog.grid_definition
        if not options.levels and float(options.cell_size) == float(stored["cell_size"]):
            # an unspecified --levels means "the catalog's", not the default levels
            options = replace(options, levels=tuple(float(v) for v in stored["levels"]))
        catalog.check_grid(_requested_grid(catalog.crs, options))


def _create(
    path: Path, final: Path, lock: FileLock, ingests: list[_Ingest], options: TileOptions
) -> Catalog:
    """A new, empty catalog at ``path`` (to be published at ``final``) in the requested (or
    the missions' UTM) CRS."""
    from standgrid.catalog import Catalog
    from standgrid.georeference import crs_to_text, resolve_crs

    first = ingests[0]
    if first.fit is None and options.crs in ("auto", "", None):
        assert first.source_crs is not None
        crs = first.source_crs  # projected clouds: their own CRS
    else:
        fit = next((i.fit for i in ingests if i.fit is not None), None)
        lat, lon = (fit.lla_ref[0], fit.lla_ref[1]) if fit is not None else (None, None)
        crs = crs_to_text(resolve_crs(options.crs, lon=lon, lat=lat))
    scheme = options.scheme or "grid"
    return Catalog.build(path, _requested_grid(crs, options), crs, scheme, final=final, held=lock)


def _settle_settings(txn: Transaction, options: TileOptions) -> TileOptions:
    """Unset buffer/compression options take the catalog's defaults (the last ones given);
    each epoch records the settings it was tiled with (``epochs[e]["tiling"]``)."""
    stored = txn.state.setdefault("tiling", {"buffer": 0.0, "laz": True})
    buffer = stored["buffer"] if options.buffer is None else float(options.buffer)
    laz = stored["laz"] if options.laz is None else bool(options.laz)
    stored.update(buffer=buffer, laz=laz)
    return replace(options, buffer=buffer, laz=laz)


def _catalog_grid(catalog: Catalog) -> StandGrid | None:
    from standgrid.partition import StandGrid

    return StandGrid.from_dict(catalog.grid_definition) if catalog.scheme == "grid" else None


def _projector(fit: GeoreferenceFit, crs: str) -> MapProjector:
    from standgrid.georeference import MapProjector

    return MapProjector(fit, crs)


# --- one epoch ---------------------------------------------------------------------------


def _cloud_payloads(mission: Mission) -> list[Payload]:
    """The point-cloud payloads (a strict mission attaches every one to a node)."""
    return [p for p in mission.payloads if p.kind == "point_cloud"]


def _payload_id(number: int, index: int, mission: Mission) -> int:
    if index >= 1 << PAYLOAD_INDEX_BITS:
        raise CatalogError(
            f"more than {1 << PAYLOAD_INDEX_BITS} payloads in one mission", path=mission.path
        )
    return (number << PAYLOAD_INDEX_BITS) | index


def _tile_epoch(
    catalog: Catalog,
    txn: Transaction,
    grid: StandGrid | None,
    epoch: str,
    group: list[_Ingest],
    renewed: list[int],
    options: TileOptions,
    layers: _IndexLayers,
    report: TileReport,
    wrap: Wrap,
) -> None:
    """(Re)tile one epoch: its kept points plus the payloads of ``group``; the points of every
    mission in ``renewed`` (this run's missions) are taken out of the old tiles first."""
    from standgrid.catalog.invalidate import without_enrichment
    from standgrid.errors import ConservationError
    from standgrid.export.las import read_tile, snap_to_storage
    from standgrid.partition import GridBuffer, PartitionEngine

    origin = grid.origin if grid is not None else (0.0, 0.0)
    group_names = {i.mission.name for i in group}
    previous_tiles = sorted(catalog.tiles(epoch)) if epoch in catalog.epochs else []
    layers.drop_missions(group_names)
    layers.cells = [row for row in layers.cells if row["epoch"] != epoch]

    work = [
        (ingest, index, payload)
        for ingest in group
        for index, payload in enumerate(_cloud_payloads(ingest.mission))
    ]
    rows = {}
    for ingest, index, payload in work:
        row = _payload_row(ingest, index, payload, epoch)
        rows[row["payload_id"]] = row
    layers.payloads.extend(rows.values())
    schema = _schema(catalog, previous_tiles, group)

    voronoi = None
    buffer = None
    if grid is not None:
        assign: Callable[[Any, Any], NDArray[np.int64]] = grid.cell_keys
        if options.buffer:
            buffer = GridBuffer(grid, options.buffer)
    else:
        if options.buffer:
            raise CatalogError("buffers are available for the grid scheme only", path=catalog.root)
        voronoi = _voronoi(layers.payloads_of_epoch(epoch), coverage=None)
        assign = voronoi.assign

    kept_in = 0
    new_in: dict[str, int] = dict.fromkeys(group_names, 0)
    number_to_name = {int(r["number"]): n for n, r in txn.state["missions"].items()}
    tiles_of: dict[str, set[str]] = {}
    written: set[str] = set()
    with PartitionEngine(
        assign, txn.folder / "spill", memory_budget_bytes=options.memory_budget, buffer=buffer
    ) as engine:
        for rel in wrap(previous_tiles, len(previous_tiles), f"{epoch}: existing tiles"):
            cloud = read_tile(catalog.path(rel))
            keep = ~np.isin(cloud.fields["point_source_id"], renewed)
            if keep.any():
                kept = cloud.select(keep)
                # heights and tree ids of the old enrichment do not survive a re-tile
                kept = PointCloud(
                    snap_to_storage(kept.xyz, origin), without_enrichment(kept.fields)
                )
                engine.add(_conform(kept, schema, catalog.path(rel)))
                kept_in += int(keep.sum())

        def prepare(item: tuple[_Ingest, int, Payload]) -> tuple[_Ingest, int, PointCloud, Any]:
            ingest, index, payload = item
            chunk = _payload_chunk(ingest, index, payload, schema, origin)
            row = rows[_payload_id(ingest.number, index, ingest.mission)]
            return ingest, index, chunk, _footprint(chunk.xyz, row["geometry"])

        # payloads are read and projected on a second thread while this one partitions
        prepared = _prefetch(prepare, wrap(work, len(work), f"{epoch}: payloads"))
        for ingest, index, chunk, footprint in prepared:
            row = rows[_payload_id(ingest.number, index, ingest.mission)]
            row["point_count"] = len(chunk)
            row["geometry"] = footprint
            engine.add(chunk)
            new_in[ingest.mission.name] += len(chunk)
        polygons: dict[str, Any] = {}
        if voronoi is not None:
            final = _voronoi(layers.payloads_of_epoch(epoch), coverage="footprints")
            polygons = final.polygons()
        for cell in wrap(engine.finalise(), 0, f"{epoch}: tiles"):
            cell_id, polygon, size = _cell_geometry(cell.key, grid, voronoi, polygons)
            rel = paths.tile(epoch, cell_id, laz=bool(options.laz))
            info = _write_cell(txn, rel, cell, catalog.crs, polygon, origin)
            names = sorted(number_to_name[n] for n in info.points_per_source)
            for name in names:
                tiles_of.setdefault(name, set()).add(rel)
            layers.cells.append(_cell_row(cell_id, info, size, epoch, names, rel))
            written.add(rel)
        stats = engine.stats

    fed = kept_in + sum(new_in.values())
    if stats.points_in != fed or stats.points_out != fed:
        raise ConservationError(
            f"epoch {epoch}: {fed} points fed, {stats.points_in} partitioned, "
            f"{stats.points_out} written",
            path=catalog.root,
        )
    for rel in set(previous_tiles) - written:
        txn.delete(rel)
    for name in txn.state["epochs"].get(epoch, {}).get("missions", []):
        if name not in group_names:
            txn.state["missions"][name]["tiles"] = sorted(tiles_of.get(name, ()))
    for ingest in group:
        mission = ingest.mission
        record = txn.record_mission(
            mission.name,
            epoch=epoch,
            date=ingest.date,
            path=str(mission.path.resolve()),
            georeference=_georeference_record(ingest),
            payload_count=len(_cloud_payloads(mission)),
            point_count=new_in[mission.name],
            tiles=sorted(tiles_of.get(mission.name, ())),
            **_metadata_extra(mission),
        )
        report.missions[mission.name] = {
            "number": record["number"],
            "epoch": epoch,
            "payloads": record["payload_count"],
            "points": record["point_count"],
            "tiles": len(record["tiles"]),
            "georeference": _georeference_summary(ingest),
        }
        layers.add_mission(ingest, epoch, catalog)
    entry = txn.state["epochs"].get(epoch)
    if entry is None:  # every mission moved out: the epoch is gone
        entry = {"date": "", "missions": []}
    else:
        dates = [txn.state["missions"][n]["date"] for n in entry["missions"]]
        entry["date"] = min(d for d in dates if d) if any(dates) else ""
        entry["enriched"] = False
        entry["tiling"] = {"buffer": options.buffer, "laz": options.laz}
    report.epochs[epoch] = {
        "date": entry["date"],
        "points_in": fed,
        "points_kept_from_catalog": kept_in,
        "points_new": sum(new_in.values()),
        "points_out": stats.points_out,
        "buffer_points": stats.buffer_points,
        "cells": len(written),
        "cells_removed": len(set(previous_tiles) - written),
        "bytes_spilled": stats.bytes_spilled,
    }


# --- points ------------------------------------------------------------------------------


def _schema(
    catalog: Catalog, previous_tiles: list[str], group: list[_Ingest]
) -> dict[str, np.dtype]:
    """The field set and dtypes every chunk of an epoch is brought to (union, promoted)."""
    from standgrid.export.las import read_tile

    samples: list[PointCloud] = []
    if previous_tiles:
        samples.append(read_tile(catalog.path(previous_tiles[0])))
    for ingest in group:
        payloads = _cloud_payloads(ingest.mission)
        if payloads:
            samples.append(_load_source(ingest.mission, payloads[0]))
    schema: dict[str, np.dtype] = {}
    for cloud in samples:
        for name, values in cloud.fields.items():
            if name == "withheld":
                continue
            # (N, k) fields (PCD COUNT > 1) keep their k: a sub-array dtype
            dtype = np.dtype((values.dtype, values.shape[1:])) if values.ndim > 1 else values.dtype
            if name in schema and schema[name].shape != dtype.shape:
                raise CatalogError(
                    f"field {name!r} has shape {dtype.shape} here and {schema[name].shape} "
                    "in another payload of the epoch",
                    path=catalog.root,
                )
            if name in schema:
                base = np.result_type(schema[name].base, dtype.base)
                dtype = np.dtype((base, dtype.shape)) if dtype.shape else base
            schema[name] = dtype
    for name, dtype in TILER_FIELDS.items():
        schema[name] = dtype
    return schema


def _conform(cloud: PointCloud, schema: dict[str, np.dtype], source: Path) -> PointCloud:
    """Bring a chunk to the epoch's schema: cast, fill absent fields (NaN or 0)."""
    unknown = sorted(set(cloud.fields) - set(schema) - {"withheld"})
    if unknown:
        raise CatalogError(
            f"fields {unknown} appear here but not in the epoch's first payload; "
            "every payload of a mission must carry the same fields",
            path=source,
        )
    n = len(cloud)
    fields = {}
    for name, dtype in schema.items():
        values = cloud.fields.get(name)
        base, shape = dtype.base, dtype.shape
        if values is None:
            fill = np.nan if np.issubdtype(base, np.floating) else 0
            fields[name] = np.full((n, *shape), fill, dtype=base)
        elif values.shape[1:] != shape:
            raise CatalogError(
                f"field {name!r} has shape {values.shape[1:]}, the epoch's is {shape}",
                path=source,
            )
        else:
            fields[name] = values.astype(base, copy=False)
    return PointCloud(cloud.xyz, fields)


def _payload_chunk(
    ingest: _Ingest,
    index: int,
    payload: Payload,
    schema: dict[str, np.dtype],
    origin: tuple[float, float],
) -> PointCloud:
    """One payload in the output CRS (snapped to the tiles' 1 mm lattice) with tiler fields."""
    from standgrid.export.las import snap_to_storage

    if ingest.fit is None:  # already in a projected CRS
        with _MISSION_LOCK:
            cloud = ingest.mission.load_projected(payload)
        xyz = snap_to_storage(_reproject(ingest, cloud.xyz), origin)
    else:
        assert ingest.projector is not None
        with _MISSION_LOCK:  # the mission's reader and caches are not shared across threads
            cloud = ingest.mission.load_base(payload)
            pose = ingest.mission.pose_of(payload)
        xyz = snap_to_storage(ingest.projector.fast(cloud.xyz, pose=pose), origin)
    n = len(xyz)
    fields = dict(cloud.fields)
    if "gps_time" not in fields:  # per-point times of the source win over the payload stamp
        fields["gps_time"] = np.full(n, unix_ns_to_adjusted_gps_time(payload.stamp.ns))
    fields["point_source_id"] = np.full(n, ingest.number, dtype=np.uint16)
    fields["payload_id"] = np.full(
        n, _payload_id(ingest.number, index, ingest.mission), dtype=np.uint32
    )
    return _conform(PointCloud(xyz, fields), schema, payload.path)


def _load_source(mission: Mission, payload: Payload) -> PointCloud:
    return mission.load_projected(payload) if payload.frame == "utm" else mission.load_base(payload)


def _reproject(ingest: _Ingest, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
    """Projected clouds into the catalog CRS (x/y only; heights as the clouds have them)."""
    if ingest.to_catalog is None:
        return xyz
    x, y = ingest.to_catalog.transform(xyz[:, 0], xyz[:, 1], errcheck=True)
    return np.column_stack([np.asarray(x), np.asarray(y), xyz[:, 2]])


_MISSION_LOCK = threading.Lock()
#: Payloads being prepared ahead of the partition engine (bounds the extra memory).
PREFETCH = 2


def _prefetch(fn: Callable[[Any], T], items: Iterable[Any], depth: int = PREFETCH) -> Iterator[T]:
    """``fn`` over ``items`` in order, computed up to ``depth`` items ahead on worker threads.

    numpy, laspy and pyproj release the GIL in their inner loops, so on two cores the next
    payload is read and projected while the current one is partitioned.
    """
    from collections import deque
    from concurrent.futures import Future, ThreadPoolExecutor

    iterator = iter(items)
    with ThreadPoolExecutor(max_workers=depth) as pool:
        pending: deque[Future[T]] = deque()
        for item in iterator:
            pending.append(pool.submit(fn, item))
            if len(pending) >= depth:
                break
        while pending:
            result = pending.popleft().result()
            following = next(iterator, None)
            if following is not None:
                pending.append(pool.submit(fn, following))
            yield result


#: Footprint hulls are taken over at most this many points of a payload (display geometry).
FOOTPRINT_POINTS = 20_000


def _footprint(xyz: NDArray[np.float64], fallback: Any) -> Any:
    """The convex hull of a payload's projected points (a polygon; the pose point if < 3)."""
    import shapely
    from scipy.spatial import ConvexHull, QhullError

    stride = max(1, len(xyz) // FOOTPRINT_POINTS)
    xy = xyz[::stride, :2]
    if len(xy) < 3:
        return fallback
    try:
        hull = ConvexHull(xy)
    except QhullError:  # collinear points
        return shapely.MultiPoint(xy[:: max(1, len(xy) // 1000)]).convex_hull
    return shapely.Polygon(xy[hull.vertices])


# --- cells -------------------------------------------------------------------------------


def _voronoi(payload_rows: list[dict[str, Any]], coverage: str | None) -> Any:
    """Voronoi cells around an epoch's projected payload poses (ids from mission + stamp)."""
    import shapely

    from standgrid.partition import VoronoiPartition
    from standgrid.partition.voronoi import site_id
    from standgrid.stamps import Stamp

    if not payload_rows:
        raise CatalogError("no payloads to build Voronoi cells around")
    xy = np.array([[r["x"], r["y"]] for r in payload_rows], dtype=np.float64)
    ids = [
        site_id(r["mission"], Stamp(int(r["stamp_sec"]), int(r["stamp_nsec"])))
        for r in payload_rows
    ]
    if coverage == "footprints":
        area = shapely.union_all([r["geometry"] for r in payload_rows])
    else:  # assignment covers the whole plane; polygons need the real coverage later
        area = shapely.MultiPoint(xy).convex_hull.buffer(1.0)
    return VoronoiPartition(xy, ids, area)


def _cell_geometry(
    key: int, grid: StandGrid | None, voronoi: Any, polygons: dict[str, Any]
) -> tuple[str, Any, float]:
    if grid is not None:
        cell = grid.key_to_cell(key)
        return str(cell), grid.polygon(cell), grid.cell_size
    site = voronoi.ids[int(key)]
    return site, polygons.get(site), math.nan


def _write_cell(
    txn: Transaction, rel: str, cell: Any, crs: str, polygon: Any, origin: tuple[float, float]
) -> Any:
    import shapely

    from standgrid.export.las import write_tile

    info = write_tile(
        txn.stage(rel),
        cell.core,
        crs=crs,
        buffer=cell.buffer,
        core_bounds=polygon,
        lattice_origin=origin,
    )
    if polygon is None or shapely.is_empty(polygon):
        xmin, ymin, _, xmax, ymax, _ = info.bounds
        info = type(info)(**{**info.__dict__, "core_bounds": shapely.box(xmin, ymin, xmax, ymax)})
    return info


def _cell_row(
    cell_id: str, info: Any, size: float, epoch: str, missions: list[str], rel: str
) -> dict[str, Any]:
    from standgrid.export.gpkg import cell_row

    return cell_row(
        cell_id, info, level=0, cell_size=size, epoch=epoch, missions=missions, tile_path=rel
    )


# --- index layers ------------------------------------------------------------------------


def _payload_row(ingest: _Ingest, index: int, payload: Payload, epoch: str) -> dict[str, Any]:
    import shapely

    from standgrid.export.gpkg import iso_time

    if ingest.fit is None:  # projected clouds: the centre of their box, no heading
        x, y, z = _projected_centre(ingest, payload)
        heading = math.nan
    else:
        assert ingest.projector is not None
        pose = ingest.mission.pose_of(payload)
        ends = ingest.projector.exact(np.array([pose[:3, 3], pose[:3, 3] + pose[:3, 0]]))
        x, y, z = ends[0]
        heading = math.degrees(math.atan2(ends[1, 1] - y, ends[1, 0] - x))
    return {
        "payload_id": _payload_id(ingest.number, index, ingest.mission),
        "mission": ingest.mission.name,
        "stamp_sec": payload.stamp.sec,
        "stamp_nsec": payload.stamp.nsec,
        "time": iso_time(payload.stamp.sec, payload.stamp.nsec),
        "node_id": payload.node_id,
        "point_count": 0,
        "x": float(x),
        "y": float(y),
        "z": float(z),
        "yaw": heading,
        "epoch": epoch,
        "geometry": shapely.Point(x, y),
    }


def _projected_centre(ingest: _Ingest, payload: Payload) -> tuple[float, float, float]:
    """Centre of a projected cloud's bounding box, in the catalog CRS (LAS: from the header)."""
    from standgrid.mission.clouds import read_cloud_header

    header = read_cloud_header(payload.path)
    if header.bounds is not None:
        lo, hi = header.bounds
    else:
        with _MISSION_LOCK:
            xyz = ingest.mission.load_projected(payload).xyz
        lo = np.array([xyz[:, k].min() for k in range(3)])
        hi = np.array([xyz[:, k].max() for k in range(3)])
    centre = _reproject(ingest, (0.5 * (np.asarray(lo) + np.asarray(hi)))[None, :])[0]
    return float(centre[0]), float(centre[1]), float(centre[2])


def _georeference_record(ingest: _Ingest) -> dict[str, Any]:
    """What the catalog stores about how the mission was placed."""
    if ingest.fit is None:
        return {"format": "standgrid.georeference/1", "method": "projected",
                "source_crs": ingest.source_crs}  # fmt: skip
    return ingest.fit.to_dict()


def _georeference_summary(ingest: _Ingest) -> dict[str, Any]:
    if ingest.fit is None:
        return {"method": "projected", "source_crs": ingest.source_crs, "fixes_used": 0,
                "fixes_rejected": 0, "rmse_horizontal_m": None, "uncertainty": None}  # fmt: skip
    return fit_summary(ingest.fit)


def fit_summary(fit: GeoreferenceFit) -> dict[str, Any]:
    """The headline figures of a georeference fit."""
    return {
        "method": fit.method,
        "fixes_used": int(fit.n_used),
        "fixes_rejected": int(fit.n_rejected),
        "rejected_by_reason": fit.rejected_by_reason,
        "rmse_horizontal_m": _finite(fit.rmse_m),
        "rmse_vertical_m": _finite(fit.rmse_vertical_m),
        "yaw_deg": fit.yaw_deg,
        "lla_ref": list(fit.lla_ref),
        "uncertainty": None if fit.uncertainty is None else fit.uncertainty.to_dict(),
    }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _metadata_extra(mission: Mission) -> dict[str, Any]:
    meta = mission.metadata
    if meta is None:
        return {"robot": "", "place": "", "unit": "", "sensors": []}
    return {
        "robot": meta.robot or "",
        "place": meta.place or "",
        "unit": meta.unit or "",
        "sensors": list(meta.sensors),
    }


@dataclass
class _IndexLayers:
    """The catalog's standard index layers as row lists, edited then written in one go."""

    cells: list[dict[str, Any]] = field(default_factory=list)
    payloads: list[dict[str, Any]] = field(default_factory=list)
    trajectories: list[dict[str, Any]] = field(default_factory=list)
    gnss_fixes: list[dict[str, Any]] = field(default_factory=list)
    missions: list[dict[str, Any]] = field(default_factory=list)

    NAMES = ("cells", "payloads", "trajectories", "gnss_fixes", "missions")

    @classmethod
    def read(cls, catalog: Catalog) -> _IndexLayers:
        from standgrid.export.gpkg import index_layer_names, read_index_layer

        layers = cls()
        path = catalog.path(paths.INDEX)
        if not path.exists():
            return layers
        present = index_layer_names(path)
        for name in cls.NAMES:
            if name in present:
                frame = read_index_layer(path, name)
                setattr(layers, name, frame.to_dict("records"))
        return layers

    def drop_missions(self, names: set[str]) -> None:
        for name in ("payloads", "trajectories", "gnss_fixes", "missions"):
            setattr(self, name, [r for r in getattr(self, name) if r["mission"] not in names])

    def payloads_of_epoch(self, epoch: str) -> list[dict[str, Any]]:
        return [r for r in self.payloads if str(r.get("epoch")) == epoch]

    def add_mission(self, ingest: _Ingest, epoch: str, catalog: Catalog) -> None:
        import shapely

        mission, fit = ingest.mission, ingest.fit
        if ingest.projector is not None and mission.graph is not None and len(mission.graph) >= 2:
            xyz = ingest.projector.exact(mission.graph.positions)
            self.trajectories.append(
                {
                    "mission": mission.name,
                    "epoch": epoch,
                    "geometry": shapely.LineString(xyz[:, :2]),
                }
            )
        if fit is not None:
            self.gnss_fixes.extend(_gnss_rows(ingest, catalog.crs))
        meta = _metadata_extra(mission)
        self.missions.append(
            {
                "mission": mission.name,
                "number": ingest.number,
                "epoch": epoch,
                "date": ingest.date,
                "robot": meta["robot"],
                "place": meta["place"],
                "unit": meta["unit"],
                "sensors": ",".join(meta["sensors"]),
                "fit_method": "projected" if fit is None else fit.method,
                "rmse_m": None if fit is None else _finite(fit.rmse_m),
                "n_used": 0 if fit is None else int(fit.n_used),
                "n_rejected": 0 if fit is None else int(fit.n_rejected),
                "grid_fingerprint": catalog.fingerprint,
                "crs": catalog.crs,
            }
        )

    def write(self, txn: Transaction, catalog: Catalog) -> None:
        from standgrid.export.gpkg import write_index

        write_index(
            txn.stage(paths.INDEX),
            crs=catalog.crs,
            base=txn.current(paths.INDEX) if (catalog.root / paths.INDEX).exists() else None,
            cells=self.cells,
            payloads=self.payloads,
            trajectories=self.trajectories,
            gnss_fixes=self.gnss_fixes,
            missions=self.missions,
        )


def _gnss_rows(ingest: _Ingest, crs: str) -> list[dict[str, Any]]:
    """One row per GNSS fix: projected position, residuals of the fit, inlier flag."""
    import pyproj
    import shapely

    gnss, fit = ingest.mission.gnss, ingest.fit
    assert fit is not None
    if gnss is None or len(gnss) == 0 or len(fit.fix_stamps_ns) == 0:
        return []
    if len(fit.fix_stamps_ns) != len(gnss) or not np.array_equal(fit.fix_stamps_ns, gnss.stamps_ns):
        raise GeoreferenceError(
            "the georeference fit does not list the mission's GNSS fixes in order",
            path=ingest.mission.path,
        )
    to_crs = pyproj.Transformer.from_crs("EPSG:4979", crs, always_xy=True)
    rows = []
    status_names = fit.status_names
    valid = np.isfinite(gnss.lat) & np.isfinite(gnss.lon)
    x, y = np.full(len(gnss), np.nan), np.full(len(gnss), np.nan)
    x[valid], y[valid] = to_crs.transform(gnss.lon[valid], gnss.lat[valid])
    for k, stamp in enumerate(fit.fix_stamps_ns):
        i = k
        if not valid[i]:
            continue
        e, n, u = (float(v) for v in fit.residuals_m[k])
        rows.append(
            {
                "mission": ingest.mission.name,
                "stamp_sec": int(stamp) // 1_000_000_000,
                "stamp_nsec": int(stamp) % 1_000_000_000,
                "quality": int(gnss.quality[i]),
                "residual_e": e,
                "residual_n": n,
                "residual_u": u,
                "residual_h": math.hypot(e, n),
                "inlier": bool(fit.inliers[k]),
                "status": status_names[k],
                "geometry": shapely.Point(float(x[i]), float(y[i])),
            }
        )
    return rows


def _write_vpcs(txn: Transaction, catalog: Catalog, layers: _IndexLayers) -> None:
    """One virtual point cloud per epoch (``tiles_<epoch>.vpc``): one QGIS layer each.

    Counts and bounds come from each tile's own LAS header, buffer points included, so the
    VPC describes the files as they are.
    """
    import laspy

    from standgrid.export.gpkg import VpcTile, write_vpc

    by_epoch: dict[str, list[VpcTile]] = {}
    for row in layers.cells:
        epoch = str(row["epoch"])
        rel = str(row["tile_path"])
        current = txn.current(rel)
        if current is None:
            raise CatalogError(f"tile {rel} is indexed but missing", path=catalog.root)
        with laspy.open(current) as reader:
            header = reader.header
            bounds = (*header.mins[:2], header.mins[2], *header.maxs[:2], header.maxs[2])
            count = int(header.point_count)
        date = txn.state["epochs"].get(epoch, {}).get("date") or None
        by_epoch.setdefault(epoch, []).append(
            VpcTile(rel, bounds, catalog.crs, count, f"{date}T00:00:00Z" if date else None)
        )
    for epoch, tiles in by_epoch.items():
        tiles.sort(key=lambda tile: str(tile.path))
        write_vpc(txn.stage(paths.vpc(epoch)), tiles)
    for epoch in catalog.epochs:
        if epoch not in by_epoch and (catalog.root / paths.vpc(epoch)).exists():
            txn.delete(paths.vpc(epoch))
