"""Compare two enriched epochs of a catalog (or of two catalogs on the same grid).

Reads the enrichment outputs (``tables/stand_metrics.parquet``, ``tables/tree_list_<epoch>
.parquet``, ``rasters/<epoch>/chm.tif``), matches trees, computes per-stand change and a CHM
difference, and writes ``compare/<from>__<to>/`` plus the ``stand_changes`` and
``tree_changes`` layers of ``index.gpkg`` — all in one catalog transaction.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths
from standgrid.comparison.coverage import (
    UNOBSERVED,
    CoObserved,
    mark_unobserved,
    stand_change,
)
from standgrid.comparison.options import CompareOptions
from standgrid.engine import Execution
from standgrid.storage import is_url

if TYPE_CHECKING:
    import geopandas as gpd
    import pandas as pd

    from standgrid.catalog import Catalog


@dataclass
class CompareReport:
    """What a comparison found; ``to_dict`` is the CLI's ``--json``."""

    catalog: Path | str  # a folder, or the object-storage URL it was committed to
    epoch_from: str
    epoch_to: str
    years: float
    trees: dict[str, int]
    stands: dict[str, int]
    stands_1ha: dict[str, int] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    headline: dict[str, float | None] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "catalog": str(self.catalog),
            "epoch_from": self.epoch_from,
            "epoch_to": self.epoch_to,
            "years": self.years,
            "trees": self.trees,
            "stands": self.stands,
            "stands_1ha": self.stands_1ha,
            "headline": self.headline,
            "outputs": self.outputs,
        }


def pair_folder(epoch_from: str, epoch_to: str) -> str:
    """Catalog-relative folder of one comparison."""
    return paths.comparison(epoch_from, epoch_to)


def compare_epochs(
    catalog_path: str | Path,
    options: CompareOptions = CompareOptions(),
    *,
    execution: Execution = Execution(),
) -> CompareReport:
    """Change from ``options.epoch_from`` to ``options.epoch_to`` (default: the first and
    last epochs).

    With ``options.other_catalog``, ``epoch_to`` is read from that catalog, which must be on
    the same grid (``GridMismatchError`` otherwise). Outputs go into ``catalog_path``, read
    and written under its writer lock; the other catalog is read as a consistent snapshot
    (:meth:`Catalog.reading`), released before the commit. Tree counts, basal area and
    harvest are compared over the ground both epochs observed only
    (:mod:`standgrid.comparison.coverage`); stands with less than
    ``options.min_observed_fraction`` of it get null changes with a reason. ``execution``
    gives the lock timeout and the progress (a comparison runs in this process).
    """

    from standgrid.catalog.remote import catalog_at

    if is_url(catalog_path):
        lock_timeout = execution.lock_timeout
        with catalog_at(catalog_path, write=True, lock_timeout=lock_timeout) as root:
            report = compare_epochs(root, options, execution=execution)
        return replace(report, catalog=str(catalog_path))
    if is_url(options.other_catalog):  # read from its current generation, recorded by URL
        url = str(options.other_catalog)
        with catalog_at(url, write=False, lock_timeout=execution.lock_timeout) as other:
            local = replace(options, other_catalog=other)
            return _compare_epochs(catalog_path, local, execution, url)
    return _compare_epochs(catalog_path, options, execution, None)


def _compare_epochs(
    catalog_path: str | Path,
    options: CompareOptions,
    execution: Execution,
    other_name: str | None,
) -> CompareReport:
    import os
    import tempfile

    from standgrid.catalog import Catalog

    progress, lock_timeout = execution.progress, execution.lock_timeout
    epoch_from, epoch_to = options.epoch_from, options.epoch_to
    other_catalog = options.other_catalog
    max_distance, min_observed_fraction = options.max_distance, options.min_observed_fraction
    progress.status(f"comparing epochs of {catalog_path}")
    with (
        Catalog.writing(catalog_path, lock_timeout=lock_timeout) as source,
        tempfile.TemporaryDirectory(prefix="standgrid-compare-") as scratch,
    ):
        same = other_catalog is None or os.path.realpath(other_catalog) == os.path.realpath(
            source.root
        )
        if same:
            return _compare(
                source,
                source,
                epoch_from,
                epoch_to,
                other_catalog,
                max_distance,
                min_observed_fraction,
                None,
            )
        with contextlib.ExitStack() as reading:
            assert other_catalog is not None
            target = reading.enter_context(
                Catalog.reading(other_catalog, lock_timeout=lock_timeout)
            )
            return _compare(
                source,
                target,
                epoch_from,
                epoch_to,
                other_name or other_catalog,
                max_distance,
                min_observed_fraction,
                Path(scratch),
                reading.close,
            )


def _compare(
    source: Catalog,
    target: Catalog,
    epoch_from: str | None,
    epoch_to: str | None,
    other_catalog: str | Path | None,
    max_distance: float,
    min_observed_fraction: float,
    scratch: Path | None,
    release_target: Callable[[], None] = lambda: None,
) -> CompareReport:
    """The comparison; with ``scratch``, ``target`` is another catalog whose files are read
    (or copied into ``scratch``) before this one's transaction commits."""
    import pandas as pd

    from standgrid.catalog.invalidate import other_epoch_read
    from standgrid.catalog.project import write_catalog_project
    from standgrid.comparison import chm_difference, compare_stands, match_trees
    from standgrid.comparison.assemble import (
        forest_metrics,
        headline,
        locate_trees,
        measured_cells,
        presence,
        with_coverage,
    )
    from standgrid.comparison.evidence import MISSED, confirm_change
    from standgrid.comparison.inputs import (
        default_epoch,
        enriched_epoch,
        epoch_metrics,
        read_table,
    )
    from standgrid.comparison.stands import check_same_grid
    from standgrid.enrichment.identity import MAX_DISTANCE_M
    from standgrid.export.styles import raster_style_path

    check_same_grid(source.fingerprint, target.fingerprint, label_a="from", label_b="to")
    one_catalog = target is source
    epoch_from = epoch_from or default_epoch(source, first=True, both_from_it=one_catalog)
    epoch_to = epoch_to or default_epoch(target, first=False, both_from_it=one_catalog)
    _check_pair(source, target, epoch_from, epoch_to)
    date_from = enriched_epoch(source, epoch_from)
    date_to = enriched_epoch(target, epoch_to)

    metrics_from = epoch_metrics(source, epoch_from)
    metrics_to = epoch_metrics(target, epoch_to)
    trees_from = read_table(source, paths.tree_list(epoch_from, "parquet"))
    trees_to = read_table(target, paths.tree_list(epoch_to, "parquet"))
    # one catalog's epochs: the same trees by their tree_uid (paired by this rule, at the
    # default distance, when each was enriched)
    by_uid = (
        one_catalog
        and max_distance == MAX_DISTANCE_M
        and {"tree_uid"} <= set(trees_from.columns) & set(trees_to.columns)
    )
    matches = match_trees(
        trees_from,
        trees_to,
        date_from=date_from,
        date_to=date_to,
        max_distance=max_distance,
        by_uid=by_uid,
    )
    cells = _cell_polygons(source, target, metrics_from, metrics_to)
    co = CoObserved.read(
        source.path(paths.raster(epoch_from, "observed")),
        target.path(paths.raster(epoch_to, "observed")),
    ).within(measured_cells(cells, metrics_from), measured_cells(cells, metrics_to))
    matches = locate_trees(matches, trees_from, trees_to)
    matches = replace(matches, table=mark_unobserved(matches.table, co))
    # removed and new only where the other survey's points show the place empty
    matches = replace(
        matches,
        table=confirm_change(
            matches.table, source, epoch_from, target, epoch_to, trees_from, trees_to
        ),
    )
    per_level = []
    for level in sorted(set(metrics_from["level"]) | set(metrics_to["level"])):
        a = metrics_from[metrics_from["level"] == level]
        b = metrics_to[metrics_to["level"] == level]
        polygons = cells[cells["cell_id"].isin(set(a["cell_id"]) | set(b["cell_id"]))]
        changes = compare_stands(
            forest_metrics(a),
            forest_metrics(b),
            date_from=date_from,
            date_to=date_to,
            epoch_from=epoch_from,
            epoch_to=epoch_to,
        )
        trees = stand_change(
            matches.table,
            "cell_id" if level == 0 else "stand_id",
            polygons.reset_index(drop=True),
            co,
            years=matches.years,
            min_fraction=min_observed_fraction,
        )
        changes = with_coverage(changes, trees, a, b)
        changes.insert(1, "level", int(level))
        per_level.append(changes)
    changes = pd.concat(per_level, ignore_index=True)

    other_read = other_epoch_read(target, epoch_to)  # under the other catalog's reader lock
    chm_to = target.path(paths.raster(epoch_to, "chm"))
    if scratch is not None:  # the other catalog's reader lock is not held across our commit
        chm_to = Path(shutil.copyfile(chm_to, scratch / "chm_to.tif"))
    release_target()  # everything of the other catalog is read
    folder = pair_folder(epoch_from, epoch_to)
    outputs: dict[str, str] = {}
    with source.transaction() as txn:
        chm_rel = paths.comparison(epoch_from, epoch_to, "chm_diff.tif")
        style_rel = raster_style_path(chm_rel).as_posix()
        chm_difference(
            source.path(paths.raster(epoch_from, "chm")),
            chm_to,
            txn.stage(chm_rel),
            extent="union",
            style=txn.stage(style_rel),
        )
        written = _write_outputs(txn, source, folder, changes, matches, epoch_from, epoch_to, cells)
        outputs = {
            "chm_difference": chm_rel,
            "chm_difference_style": style_rel,
            **written,
            "gpkg": paths.INDEX,
        }
        other = (
            (other_catalog if is_url(other_catalog) else str(Path(other_catalog).resolve()))
            if other_catalog is not None and target is not source
            else None
        )
        entry: dict[str, Any] = {"from": epoch_from, "to": epoch_to, "other_catalog": other}
        if other is not None:  # what it read there, to tell when that epoch changes
            entry["other_epoch"] = other_read
        txn.record_comparison(
            paths.comparison_key(epoch_from, epoch_to), {**entry, "outputs": outputs}
        )
        write_catalog_project(txn)  # catalog.qgz shows what this transaction commits
    return CompareReport(
        catalog=source.root,
        epoch_from=epoch_from,
        epoch_to=epoch_to,
        years=matches.years,
        trees={
            status: int((matches.table["status"] == status).sum())
            for status in ("grown", "new", "removed", MISSED, UNOBSERVED)
        },
        stands=presence(changes[changes["level"] == 0]),
        stands_1ha=presence(changes[changes["level"] == 1]),
        outputs=outputs,
        headline=headline(changes, matches),
    )


def _check_pair(source: Catalog, target: Catalog, epoch_from: str, epoch_to: str) -> None:
    """Refuse, saying why, an epoch compared with itself, a stale epoch (enriched, then
    re-tiled: enrich it again), and an ``epoch_to`` dated before ``epoch_from``."""
    from standgrid.catalog.records import STALE
    from standgrid.comparison.trees import ChangeInputError
    from standgrid.errors import EnrichError

    if target is source and epoch_from == epoch_to:
        raise ChangeInputError(
            f"option epoch_from and option epoch_to are both epoch {epoch_from!r}: compare "
            f"two different epochs (epochs: {', '.join(sorted(source.epochs))})",
            path=source.root,
            option="epoch_to",
        )
    records = {}
    for catalog, epoch in ((source, epoch_from), (target, epoch_to)):
        record = records[epoch, id(catalog)] = catalog.epoch(epoch)  # EpochNotFoundError
        if record.state == STALE:
            why = (record.invalidated or {}).get("reason")
            raise EnrichError(
                f"epoch {epoch!r} is stale: its tiles changed after it was enriched"
                + (f" ({why})" if why else "")
                + f"; re-run `standgrid enrich {catalog.root}`",
                path=catalog.root,
            )
    start, end = records[epoch_from, id(source)].date, records[epoch_to, id(target)].date
    if start and end and end <= start:
        raise ChangeInputError(
            f"epoch {epoch_to!r} ({end}) is not later than epoch {epoch_from!r} ({start}): "
            "option epoch_to must be a later campaign than option epoch_from (swap them?)",
            path=source.root,
            option="epoch_to",
        )


def _write_outputs(
    txn: Any,
    source: Catalog,
    folder: str,
    changes: pd.DataFrame,
    matches: Any,
    epoch_from: str,
    epoch_to: str,
    cells: gpd.GeoDataFrame,
) -> dict[str, str]:
    """Write the change tables into the staging folder and register every file; the change
    layers replace those of the index (:class:`CatalogIndex`, staged in ``txn``)."""
    from standgrid.catalog.index import CatalogIndex
    from standgrid.comparison.report import change_layers

    out_dir = txn.stage(paths.comparison(epoch_from, epoch_to, "stand_changes.csv")).parent
    result, layers = change_layers(
        out_dir,
        changes,
        matches,
        epoch_from=epoch_from,
        epoch_to=epoch_to,
        cells=cells,
        crs=source.crs,
    )
    index = CatalogIndex(source, txn)
    for layer in layers:
        index.replace_all(layer.name, layer.frame, style=layer.style)
    index.save()
    written = {}
    for key in ("stand_csv", "stand_parquet", "tree_csv", "tree_parquet"):
        path = getattr(result, key)
        if path is not None:
            rel = f"{folder}/{Path(path).name}"
            txn.stage(rel)
            written[key] = rel
    return written


def _cell_polygons(
    source: Catalog, target: Catalog, metrics_from: pd.DataFrame, metrics_to: pd.DataFrame
) -> gpd.GeoDataFrame:
    """``cell_id`` + polygon of every stand (tile cells and coarser stands) of either epoch."""
    import geopandas as gpd
    import pandas as pd

    from standgrid.enrichment.outputs import stand_polygons
    from standgrid.export.gpkg import read_index_layer

    cells = pd.concat(
        [
            read_index_layer(c.path(paths.INDEX), "cells")[["cell_id", "geometry"]]
            for c in {id(source): source, id(target): target}.values()
        ],
        ignore_index=True,
    ).drop_duplicates("cell_id")
    ids = sorted(set(metrics_from["cell_id"]) | set(metrics_to["cell_id"]))
    return gpd.GeoDataFrame(
        {"cell_id": ids}, geometry=stand_polygons(source, ids, cells), crs=source.crs
    )
