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

import numpy as np

from standgrid.catalog import paths
from standgrid.compare.coverage import (
    CO_OBSERVED_METRICS,
    UNOBSERVED,
    CoObserved,
    mark_unobserved,
    stand_change,
)
from standgrid.compare.options import CompareOptions
from standgrid.engine import SILENT, Progress
from standgrid.enrich.stands import SAMPLE_COLUMNS, TREE_COUNT_COLUMNS
from standgrid.errors import EnrichError, EpochNotFoundError

if TYPE_CHECKING:
    import geopandas as gpd
    import pandas as pd

    from standgrid.catalog import Catalog


@dataclass
class CompareReport:
    """What a comparison found; ``to_dict`` is the CLI's ``--json``."""

    catalog: Path
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
    options: CompareOptions | None = None,
    *,
    progress: Progress = SILENT,
    lock_timeout: float | None = 30.0,
) -> CompareReport:
    """Change from ``options.epoch_from`` to ``options.epoch_to`` (default: the first and
    last epochs).

    With ``options.other_catalog``, ``epoch_to`` is read from that catalog, which must be on
    the same grid (``GridMismatchError`` otherwise). Outputs go into ``catalog_path``, read
    and written under its writer lock; the other catalog is read as a consistent snapshot
    (:meth:`Catalog.reading`), released before the commit. Tree counts, basal area and
    harvest are compared over the ground both epochs observed only
    (:mod:`standgrid.compare.coverage`); stands with less than
    ``options.min_observed_fraction`` of it get null changes with a reason.
    """
    import os
    import tempfile

    from standgrid.catalog import Catalog

    options = options or CompareOptions()
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
            return _compare(source, source, epoch_from, epoch_to, other_catalog, max_distance,
                            min_observed_fraction, None)  # fmt: skip
        with contextlib.ExitStack() as reading:
            assert other_catalog is not None
            target = reading.enter_context(
                Catalog.reading(other_catalog, lock_timeout=lock_timeout)
            )
            return _compare(
                source, target, epoch_from, epoch_to, other_catalog, max_distance,
                min_observed_fraction, Path(scratch), reading.close,
            )  # fmt: skip


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

    from standgrid.compare import chm_difference, compare_stands, match_trees
    from standgrid.compare.stands import check_same_grid
    from standgrid.export.styles import raster_style_path

    check_same_grid(source.fingerprint, target.fingerprint, label_a="from", label_b="to")
    epoch_from = epoch_from or _default_epoch(source, first=True)
    epoch_to = epoch_to or _default_epoch(target, first=False)
    date_from = _enriched_epoch(source, epoch_from)
    date_to = _enriched_epoch(target, epoch_to)

    metrics_from = _epoch_metrics(source, epoch_from)
    metrics_to = _epoch_metrics(target, epoch_to)
    trees_from = _read_table(source, paths.tree_list(epoch_from, "parquet"))
    trees_to = _read_table(target, paths.tree_list(epoch_to, "parquet"))
    matches = match_trees(
        trees_from, trees_to, date_from=date_from, date_to=date_to, max_distance=max_distance
    )
    cells = _cell_polygons(source, target, metrics_from, metrics_to)
    co = CoObserved.read(
        source.path(paths.raster(epoch_from, "observed")),
        target.path(paths.raster(epoch_to, "observed")),
    ).within(_measured_cells(cells, metrics_from), _measured_cells(cells, metrics_to))
    matches = _locate(matches, trees_from, trees_to)
    matches = replace(matches, table=mark_unobserved(matches.table, co))
    per_level = []
    for level in sorted(set(metrics_from["level"]) | set(metrics_to["level"])):
        a = metrics_from[metrics_from["level"] == level]
        b = metrics_to[metrics_to["level"] == level]
        polygons = cells[cells["cell_id"].isin(set(a["cell_id"]) | set(b["cell_id"]))]
        changes = compare_stands(
            _forest_metrics(a),
            _forest_metrics(b),
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
        changes = _with_coverage(changes, trees, a, b)
        changes.insert(1, "level", int(level))
        per_level.append(changes)
    changes = pd.concat(per_level, ignore_index=True)

    chm_to = target.path(paths.raster(epoch_to, "chm"))
    if scratch is not None:  # the other catalog's reader lock is not held across our commit
        chm_to = Path(shutil.copyfile(chm_to, scratch / "chm_to.tif"))
    release_target()  # everything of the other catalog is read
    folder = pair_folder(epoch_from, epoch_to)
    outputs: dict[str, str] = {}
    with source.transaction() as txn:
        index = txn.stage(paths.INDEX)
        shutil.copyfile(source.path(paths.INDEX), index)
        chm_rel = paths.comparison(epoch_from, epoch_to, "chm_diff.tif")
        style_rel = raster_style_path(chm_rel).as_posix()
        chm_difference(
            source.path(paths.raster(epoch_from, "chm")),
            chm_to,
            txn.stage(chm_rel),
            extent="union",
            style=txn.stage(style_rel),
        )
        written = _write_outputs(
            txn, folder, index, changes, matches, epoch_from, epoch_to, cells, source.crs
        )
        outputs = {
            "chm_difference": chm_rel, "chm_difference_style": style_rel, **written,
            "gpkg": paths.INDEX,
        }  # fmt: skip
        comparisons = txn.state.setdefault("comparisons", {})
        comparisons[paths.comparison_key(epoch_from, epoch_to)] = {
            "from": epoch_from,
            "to": epoch_to,
            "other_catalog": (
                str(Path(other_catalog).resolve())
                if other_catalog is not None and target is not source
                else None
            ),
            "outputs": outputs,
        }
    return CompareReport(
        catalog=source.root,
        epoch_from=epoch_from,
        epoch_to=epoch_to,
        years=matches.years,
        trees={
            status: int((matches.table["status"] == status).sum())
            for status in ("grown", "new", "removed", UNOBSERVED)
        },
        stands=_presence(changes[changes["level"] == 0]),
        stands_1ha=_presence(changes[changes["level"] == 1]),
        outputs=outputs,
        headline=_headline(changes, matches),
    )


def _write_outputs(
    txn: Any,
    folder: str,
    index: Path,
    changes: pd.DataFrame,
    matches: Any,
    epoch_from: str,
    epoch_to: str,
    cells: gpd.GeoDataFrame,
    crs: str,
) -> dict[str, str]:
    """Write the change tables into the staging folder and register every file."""
    from standgrid.compare import write_change_outputs

    out_dir = txn.stage(paths.comparison(epoch_from, epoch_to, "stand_changes.csv")).parent
    result = write_change_outputs(
        out_dir,
        index,
        changes,
        matches,
        epoch_from=epoch_from,
        epoch_to=epoch_to,
        cells=cells,
        crs=crs,
    )
    written = {}
    for key in ("stand_csv", "stand_parquet", "tree_csv", "tree_parquet"):
        path = getattr(result, key)
        if path is not None:
            rel = f"{folder}/{Path(path).name}"
            txn.stage(rel)
            written[key] = rel
    return written


def _read_table(catalog: Catalog, rel: str) -> pd.DataFrame:
    import pandas as pd

    path = catalog.path(rel)
    if not path.exists():
        raise EnrichError(
            f"{rel} is missing: run `standgrid enrich {catalog.root}` first", path=path
        )
    return pd.read_parquet(path)


def _locate(matches: Any, trees_from: pd.DataFrame, trees_to: pd.DataFrame) -> Any:
    """Give every matched tree its cell, 1 ha stand and stem position.

    A tree's stand is where enrich put it (the cell holding its top, half-open), taken from
    the tree lists: the later epoch's for grown and new trees, the earlier one's for removed
    trees; so is its stem position (the fitted stem, or the top without a stem fit).
    """
    table = matches.table.copy()
    removed = (table["status"] == "removed").to_numpy()
    for frame in (trees_from, trees_to):
        for xy in ("x", "y"):
            stem = f"stem_{xy}"
            values = frame[stem] if stem in frame.columns else frame[xy]
            frame[f"_{stem}"] = values.where(values.notna(), frame[xy])
    columns = [c for c in ("cell_id", "stand_id") if c in trees_from.columns]
    columns += ["_stem_x", "_stem_y"]
    by_id_from = trees_from.set_index("tree_id")[columns]
    by_id_to = trees_to.set_index("tree_id")[columns]
    for column in columns:
        later = table["tree_id_to"].map(by_id_to[column])
        earlier = table["tree_id_from"].map(by_id_from[column])
        table[column.lstrip("_")] = later.where(~removed, earlier)
    if "stand_id" not in table.columns:
        table["stand_id"] = None
    return replace(matches, table=table)


#: stand_metrics columns that describe the sample or are recomputed over co-observed ground.
_NOT_COMPARED = frozenset((*SAMPLE_COLUMNS, *TREE_COUNT_COLUMNS, *CO_OBSERVED_METRICS))


#: Shape statistics of the height distribution: their change is given, not as a yearly rate.
_SHAPES = ("zskew", "zkurt", "zentropy", "zpcum")


def _measured_cells(cells: gpd.GeoDataFrame, metrics: pd.DataFrame) -> list[Any]:
    """Polygons of the 20 m cells (or Voronoi cells) whose metrics an epoch reports: ground
    that failed its coverage rule (too few points, no terrain) is not compared either."""
    level0 = metrics[metrics["level"] == 0]
    measured = set(level0.loc[level0["stems_ha"].notna(), "cell_id"])
    return list(cells.loc[cells["cell_id"].isin(measured), "geometry"])


def _forest_metrics(metrics: pd.DataFrame) -> pd.DataFrame:
    """The metric columns whose change means something about the forest."""
    return metrics.drop(columns=[c for c in metrics.columns if c in _NOT_COMPARED])


def _with_coverage(
    changes: pd.DataFrame, trees: pd.DataFrame, a: pd.DataFrame, b: pd.DataFrame
) -> pd.DataFrame:
    """Join the co-observed tree change; null every change of a stand short of coverage."""
    import pandas as pd

    out = changes.merge(trees, on="cell_id", how="left")
    for side, frame in (("from", a), ("to", b)):
        observed = frame.set_index("cell_id")["observed_fraction"]
        out[f"observed_fraction_{side}"] = out["cell_id"].map(observed)
    short = out["coverage_reason"].notna().to_numpy()
    changed = [c for c in out.columns if c.endswith(("_delta", "_per_year"))]
    changed += [c for c in out.columns if c.startswith("trees_") or c.startswith("tree_height")]
    changed += [f"{m}_{side}" for m in CO_OBSERVED_METRICS for side in ("from", "to")]
    out.loc[short, list(dict.fromkeys(changed))] = np.nan
    reason = out["null_reason"].astype("string").fillna("")
    extra = out["coverage_reason"].astype("string").fillna("")
    joined = (extra + "; " + reason).str.strip("; ")
    out["null_reason"] = joined.where(joined != "", pd.NA)
    for column in ("trees_grown", "trees_removed", "trees_new"):
        out[column] = out[column].astype("Int64")
    no_rate = [c for c in out.columns if c.endswith("_per_year") and c.startswith(_SHAPES)]
    return out.drop(columns=["coverage_reason", *no_rate]).copy()


def _default_epoch(catalog: Catalog, *, first: bool) -> str:
    records = catalog.epoch_records
    epochs = sorted(records, key=lambda e: (records[e].date or "", e))
    if len(epochs) < (2 if first else 1):
        raise EpochNotFoundError(
            f"comparing needs two epochs; the catalog has {epochs or 'none'}",
            path=catalog.root,
        )
    return epochs[0] if first else epochs[-1]


def _enriched_epoch(catalog: Catalog, epoch: str) -> str:
    """The epoch's date; raises unless the epoch exists and is enriched."""
    entry = catalog.epoch(epoch)  # EpochNotFoundError naming the epochs
    if not entry.enriched:
        raise EnrichError(
            f"epoch {epoch!r} is not enriched (run `standgrid enrich {catalog.root}` first)",
            path=catalog.root,
        )
    if not entry.date:
        raise EnrichError(f"epoch {epoch!r} has no date to annualise with", path=catalog.root)
    return entry.date


def _epoch_metrics(catalog: Catalog, epoch: str) -> pd.DataFrame:

    table = _read_table(catalog, paths.stand_metrics("parquet"))
    return table[table["epoch"].astype(str) == epoch].drop(columns=["epoch"]).reset_index(drop=True)


def _cell_polygons(
    source: Catalog, target: Catalog, metrics_from: pd.DataFrame, metrics_to: pd.DataFrame
) -> gpd.GeoDataFrame:
    """``cell_id`` + polygon of every stand (tile cells and coarser stands) of either epoch."""
    import geopandas as gpd
    import pandas as pd

    from standgrid.enrich.outputs import stand_polygons
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


def _presence(changes: pd.DataFrame) -> dict[str, int]:
    """How many stands are in both epochs, or in one only."""
    return {
        name: int((changes["presence"] == value).sum())
        for name, value in (("in_both", "both"), ("from_only", "from_only"), ("to_only", "to_only"))
    }


def _headline(changes: pd.DataFrame, matches: Any) -> dict[str, float | None]:
    """A few stand-level averages for the human report."""
    import math

    out: dict[str, float | None] = {}
    cells = changes[changes["level"] == 0]
    for column in ("tree_height_growth_m_per_year", "zq95_per_year", "zmean_per_year"):
        if column in cells.columns:
            value = float(cells[column].mean(skipna=True))
            out[column] = value if math.isfinite(value) else None
    out["trees_removed"] = float(matches.counts().get("removed", 0))
    return out
