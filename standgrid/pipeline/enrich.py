"""Enrich a catalog: ground, terrain rasters, height above ground, trees, stand metrics.

Per epoch, :func:`standgrid.enrichment.apply.catalog_apply` cuts the cells into buffered chunks,
enriches each (here, or on dask workers), rewrites its tiles and merges the chunks' rasters,
trees and samples; this module writes the rasters, fits the height-diameter models, and
writes the stand metrics (all in one catalog transaction; the previous state stays intact
on any error):

- tiles rewritten with ``classification`` (2 = ground, 1 = other), ``height_above_ground``
  and ``tree_id`` (0 = no tree);
- ``rasters/<epoch>/{dtm,chm,density,observed}.tif``: Cloud-Optimized GeoTIFFs
  pixel-aligned to the stand grid, so rasters of different epochs overlay exactly;
- ``tables/stand_metrics.{csv,parquet}`` (keyed by ``cell_id``, ``epoch``) and
  ``tables/tree_list_<epoch>.{csv,parquet}``;
- GeoPackage layers ``stand_metrics`` (cell polygons) and ``trees`` (crown polygons), styled.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from standgrid.catalog import paths
from standgrid.engine import Execution
from standgrid.enrichment.options import EnrichOptions
from standgrid.enrichment.stands import StandSample
from standgrid.errors import EnrichError, EpochNotFoundError, OptionError

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog, Transaction

__all__ = ["EnrichReport", "enrich_catalog"]


@dataclass
class EnrichReport:
    catalog: Path | str  # a folder, or the object-storage URL it was committed to
    epochs: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"catalog": str(self.catalog), "epochs": self.epochs}


def enrich_catalog(
    catalog_path: str | Path,
    options: EnrichOptions = EnrichOptions(),
    *,
    execution: Execution = Execution(),
) -> EnrichReport:
    """Enrich every epoch of the catalog (or ``options.epochs``); returns what was done.

    Chunks run as ``execution`` says (this process, or a dask cluster), each process within
    its memory budget; this process alone writes the catalog, under its writer lock. A
    catalog at an object-storage URL is enriched in a working copy and committed back
    (:mod:`standgrid.catalog.remote`).
    """
    from standgrid.catalog import Catalog
    from standgrid.catalog.remote import catalog_at
    from standgrid.catalog.store import require_catalog
    from standgrid.storage import is_url

    if is_url(catalog_path):
        if not execution.shared_folder:  # workers read tiles from, and put theirs in, the store
            from standgrid.catalog.remote import outbox_url

            execution = replace(execution, outbox=outbox_url(str(catalog_path)))
        with catalog_at(catalog_path, write=True, lock_timeout=execution.lock_timeout) as root:
            report = enrich_catalog(root, options, execution=execution)
        return replace(report, catalog=str(catalog_path))
    if not execution.shared_folder and execution.outbox is None:
        raise OptionError(
            "shared_folder",
            "workers without a shared folder exchange tiles through object storage: give "
            "the catalog as an object-storage URL (s3://bucket/prefix)",
        )
    require_catalog(catalog_path)  # before a cluster starts or a lock file is made
    with contextlib.ExitStack() as stack:
        executor = stack.enter_context(execution.open())
        catalog = stack.enter_context(
            Catalog.writing(catalog_path, lock_timeout=execution.lock_timeout)
        )
        return _enrich(catalog, options, execution.on(executor))


def _enrich(catalog: Catalog, options: EnrichOptions, execution: Execution) -> EnrichReport:
    from standgrid.catalog.invalidate import enrichment_note, invalidate_comparisons
    from standgrid.catalog.project import write_catalog_project
    from standgrid.enrichment.allometry import height_diameter_models, impute_dbh, tree_summary
    from standgrid.enrichment.outputs import metrics_table, write_layers, write_tables
    from standgrid.enrichment.stands import stand_rows

    if not catalog.crs:
        raise EnrichError("the catalog has no CRS (not georeferenced)", path=catalog.root)
    epochs = list(options.epochs) or sorted(catalog.epochs)
    for epoch in epochs:
        if epoch not in catalog.epochs:
            raise EpochNotFoundError(
                f"no epoch {epoch!r} (epochs: {sorted(catalog.epochs)})", path=catalog.root
            )
    if not epochs:
        raise EnrichError(
            "the catalog has no epochs: tile missions into it first", path=catalog.root
        )
    check_pixel_size(catalog, options.pixel_size)
    progress = execution.progress
    rule = options.coverage_rule
    report = EnrichReport(catalog.root)
    metric_tables: dict[str, pd.DataFrame] = {}
    tree_tables: dict[str, pd.DataFrame] = {}
    with catalog.transaction() as txn:
        results = {}
        for epoch in epochs:
            note = enrichment_note(txn.begin_enrichment(epoch))  # says if it was stale
            progress.status(f"enriching epoch {epoch}: {note}")
            results[epoch] = _enrich_epoch(catalog, txn, epoch, options, execution)
        lost = invalidate_comparisons(catalog, txn, set(epochs), "re-enriched")
        if lost:
            progress.status(
                f"comparisons {', '.join(lost)} removed (their inputs change): compare again"
            )
        models = height_diameter_models(catalog, {e: r.trees for e, r in results.items()})
        uids = _tree_uids(catalog, {e: r.trees for e, r in results.items()})
        for epoch, result in results.items():
            trees = impute_dbh(result.trees, models[epoch])
            trees.insert(int(trees.columns.get_loc("tree_id")) + 1, "tree_uid", uids[epoch])
            rows = stand_rows(
                result.samples, result.stands, trees, rule, height_break=options.height_break
            )
            metric_tables[epoch] = metrics_table(rows, epoch)
            tree_tables[epoch] = trees
            summary = result.summary | tree_summary(trees, models[epoch])
            summary["coverage_rule"] = {
                "min_observed_fraction": rule.min_observed_fraction,
                "min_density_pts_m2": rule.min_density_pts_m2,
            }
            report.epochs[epoch] = summary
            txn.mark_enriched(epoch, summary)
        write_tables(catalog, txn, metric_tables, tree_tables)
        write_layers(catalog, txn, metric_tables, tree_tables)
        write_catalog_project(txn)  # catalog.qgz shows what this transaction commits
    return report


def check_pixel_size(catalog: Catalog, pixel_size: float) -> None:
    """Refuse (before any work) a raster pixel that does not divide the lattice the
    catalog's rasters align to: a grid catalog's cell size, or a Voronoi catalog's
    :data:`~standgrid.partition.protocol.VORONOI_RASTER_SIZE` lattice (its cells are
    irregular; rasters of every epoch align to that lattice so they overlay exactly)."""
    import math

    from standgrid.partition.protocol import VORONOI_RASTER_SIZE

    if catalog.scheme == "voronoi":
        size = VORONOI_RASTER_SIZE
        what = f"the {size:g} m lattice a Voronoi catalog's rasters align to"
    else:
        size = float(catalog.grid_definition["cell_size"])
        what = f"the catalog's {size:g} m cell size (rasters align to the cells)"
    ratio = size / pixel_size if pixel_size > 0 and math.isfinite(pixel_size) else math.nan
    if math.isfinite(ratio) and abs(ratio - round(ratio)) <= 1e-6:
        return
    candidates = (0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 2.5, 5.0, 10.0, 20.0, 25.0, 50.0, 100.0)
    fits = [f"{c:g}" for c in candidates if c <= size and abs(size / c - round(size / c)) < 1e-9]
    raise EnrichError(
        f"a raster pixel of {pixel_size:g} m does not divide {what}: give option pixel_size "
        f"as a divisor of {size:g} m ({', '.join(fits)})",
        path=catalog.root,
        option="pixel_size",
    )


@dataclass
class _EpochResult:
    """An epoch after the chunk engine: cells and coarser stands, measured (trees not yet
    attached), and the trees."""

    samples: list[StandSample]
    stands: list[StandSample]
    trees: pd.DataFrame
    summary: dict[str, Any]


def _enrich_epoch(
    catalog: Catalog,
    txn: Transaction,
    epoch: str,
    options: EnrichOptions,
    execution: Execution,
) -> _EpochResult:
    from standgrid.enrichment.apply import catalog_apply
    from standgrid.enrichment.coverage import Coverage, cells_mask
    from standgrid.enrichment.outputs import tree_table, write_coverage, write_raster

    applied = catalog_apply(catalog, txn, epoch, options, execution=execution)
    grid, polygons, samples = applied.grid, applied.polygons, applied.samples
    if all(s.no_ground for s in samples):
        raise EnrichError(
            f"epoch {epoch}: no ground points anywhere, so no terrain model", path=catalog.root
        )
    arrays = applied.rasters
    in_cells = cells_mask(grid, polygons)
    coverage = Coverage(
        grid, arrays["observed"] & in_cells, arrays["near_ground"] & in_cells, in_cells
    )
    trees = tree_table(applied.tree_frames, epoch)

    unseen = ~coverage.near_ground
    for name, description in (
        ("dtm", "digital terrain model: ellipsoidal height of the ground (m)"),
        ("chm", "canopy height model: height above ground (m)"),
    ):
        arrays[name][unseen] = np.nan  # terrain (and heights over it) extrapolated there
        write_raster(txn, paths.raster(epoch, name), arrays[name], grid, description)
    write_raster(
        txn,
        paths.raster(epoch, "density"),
        arrays["density"],
        grid,
        "points per square metre",
    )
    write_coverage(txn, paths.raster(epoch, "observed"), coverage)
    against_dtm = _elevation_map_vs_dtm(txn, epoch, arrays["dtm"], grid)
    observed_m2 = float(sum(s.observed_m2 for s in samples))  # each cell's, clipped to it
    summary: dict[str, Any] = {
        "cells": len(polygons),
        "cells_without_ground": sum(s.no_ground for s in samples),
        "chunks": applied.chunks,
        "raster_pixel_size_m": options.pixel_size,
        "observed_m2": observed_m2,
        "observed_fraction": observed_m2 / float(sum(p.area for p in polygons)),
    }
    if against_dtm is not None:  # said only for an epoch whose payloads carry elevation maps
        summary["elevation_map_minus_dtm"] = against_dtm
    return _EpochResult(samples, applied.stands, trees, summary)


def _elevation_map_vs_dtm(
    txn: Transaction, epoch: str, dtm: Any, grid: Any
) -> dict[str, Any] | None:
    """The epoch's elevation-map mosaic (tiled from its payloads' maps) minus its DTM from
    points, where both hold a value (None: the epoch has no mosaic)."""
    from standgrid.geotiff import read_raster
    from standgrid.tiling.elevation import difference

    current = txn.current(paths.raster(epoch, paths.ELEVATION_MAP))
    if current is None:
        return None
    mosaic = read_raster(current)
    return difference(mosaic.array, mosaic.grid, dtm, grid)


def _tree_uids(catalog: Catalog, trees: dict[str, pd.DataFrame]) -> dict[str, Any]:
    """Each epoch's ``tree_uid``s: its trees paired with those of the catalog's other
    enriched epochs (:func:`standgrid.enrichment.identity.assign_tree_uids`)."""
    import pandas as pd

    from standgrid.enrichment.identity import assign_tree_uids

    others = {}
    for epoch, record in catalog.epoch_records.items():
        path = catalog.path(paths.tree_list(epoch, "parquet"))
        if epoch not in trees and record.state == "enriched" and path.exists():
            others[epoch] = pd.read_parquet(path, columns=None)
    dates = {e: r.date or e for e, r in catalog.epoch_records.items()}
    return assign_tree_uids(trees, dates, others)
