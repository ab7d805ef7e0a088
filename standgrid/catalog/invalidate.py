"""No stale results: re-tiling an epoch invalidates its enrichment and its comparisons.

Enrichment and comparisons are computed from an epoch's tiles; once the tiles change (a
mission re-ingested, added, or moved to another epoch) they describe points that are gone.
:func:`invalidate_epochs`, called by the tiler inside its transaction, removes exactly what
was derived from the re-tiled epochs, so a reader never sees old numbers next to new tiles:

- ``rasters/<epoch>/*`` (DTM, CHM, density and their styles; not the elevation-map
  mosaic, which tiling itself remakes) and
  ``tables/tree_list_<epoch>.{csv,parquet}``;
- the epoch's rows of ``tables/stand_metrics.{csv,parquet}`` and of the ``stand_metrics``
  and ``trees`` layers of ``index.gpkg``;
- every comparison involving the epoch: ``compare/<from>__<to>/*``, its rows of the
  ``stand_changes`` and ``tree_changes`` layers and its ``comparisons`` entry.

The points kept from the old tiles lose their per-point enrichment too
(:func:`without_enrichment`: ``height_above_ground`` NaN, ``tree_id`` 0), so a re-tiled tile
never mixes heights and tree ids of the old terrain with new points; ``classification`` is
kept (it may hold the source's classes; ``enrich`` re-derives ground).

The epoch's ``catalog.json`` entry gets ``enriched = false`` and
``invalidated = {"at", "reason", "comparisons"}``; the next ``enrich`` of the epoch clears it
(:meth:`Transaction.begin_enrichment`). ``comparisons_invalidated`` (key -> ``{"at",
"reason"}``) stays, so ``standgrid status`` lists a lost comparison until it is made
again. Other epochs' results are untouched. A comparison made with ``--other`` (its "to"
epoch read from another catalog) is invalidated by its "from" epoch only; comparisons
stored in *other* catalogs that read this one are not known here. Instead such a comparison
records what it read (``other_epoch``: the other epoch's :func:`enrichment_stamp` and the
other catalog's generation), and :func:`other_catalog_change` tells, from one read of the
other catalog's ``catalog.json``, when that epoch is no longer the one compared (re-tiled,
re-enriched, gone): ``standgrid status`` and the served change layers report it as stale.
"""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.catalog import paths
from standgrid.catalog.records import enrichment_stamp
from standgrid.errors import CatalogError
from standgrid.storage import is_url

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, Transaction
    from standgrid.catalog.records import EpochRecord

#: index.gpkg layers of enrichment (keyed by ``epoch``) and of comparisons (keyed by
#: ``epoch_from``, ``epoch_to``).
ENRICH_LAYERS = ("stand_metrics", "trees")
CHANGE_LAYERS = ("stand_changes", "tree_changes")
#: Per-point fields enrich writes into tiles, and their "not computed" value.
ENRICH_POINT_FIELDS: dict[str, float] = {"height_above_ground": np.nan, "tree_id": 0}


def _now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def invalidate_epochs(
    catalog: Catalog,
    txn: Transaction,
    reasons: Mapping[str, str],
    *,
    status: Callable[[str], None] = lambda message: None,
) -> dict[str, dict[str, Any]]:
    """Remove the enrichment and comparisons of the epochs in ``reasons`` (epoch -> why).

    Everything goes through ``txn`` (files deleted or rewritten on commit, the catalog state
    edited), so it lands with the new tiles or not at all. Returns, per epoch that had
    results, what was removed: ``files`` (relative paths), ``rows`` (per table and layer) and
    ``comparisons`` (keys); epochs without results are left out.
    """
    reasons = {**pooled_dependents(txn, reasons), **reasons}
    epochs = set(reasons)
    comparisons = _comparisons_of(txn.state, epochs)
    done: dict[str, dict[str, Any]] = {}

    def record(epoch: str) -> dict[str, Any]:
        return done.setdefault(epoch, {"files": [], "rows": {}, "comparisons": []})

    for epoch in sorted(epochs):
        tiled = paths.tiled_rasters(epoch)  # tiling's own (the elevation-map mosaic)
        rels = _files_under(catalog.root, paths.rasters_folder(epoch))
        rels = [rel for rel in rels if rel not in tiled]
        rels += [
            rel
            for rel in (paths.tree_list(epoch, ext) for ext in paths.TABLE_FORMATS)
            if txn.current(rel) is not None
        ]
        for rel in rels:
            txn.delete(rel)
        if rels:
            record(epoch)["files"].extend(rels)
    for key, (epoch_from, epoch_to) in comparisons.items():
        rels = _files_under(catalog.root, paths.comparison_folder(key))
        for rel in rels:
            txn.delete(rel)
        for epoch in {epoch_from, epoch_to} & epochs:
            record(epoch)["comparisons"].append(key)
            record(epoch)["files"].extend(rels)
        del txn.state["comparisons"][key]

    for epoch, count in _drop_metric_rows(txn, epochs).items():
        record(epoch)["rows"][paths.METRICS_TABLE] = count
    for (layer, epoch), count in _drop_layer_rows(txn, epochs, comparisons).items():
        record(epoch)["rows"][layer] = record(epoch)["rows"].get(layer, 0) + count

    before = catalog.epochs  # the state this transaction started from
    for epoch in sorted(epochs):
        entry = txn.state["epochs"].get(epoch)
        if entry is None:  # the epoch is gone (every mission moved out): nothing to mark
            continue
        if before.get(epoch, {}).get("enriched") or entry.get("invalidated"):
            record(epoch)
        entry["enriched"] = False
        entry.pop("enrichment", None)
        entry.pop("enrichment_id", None)
        if epoch not in done:
            continue
        earlier = entry.get("invalidated") or {}
        now = _now()
        entry["invalidated"] = {
            "at": now,
            "reason": reasons[epoch],
            "comparisons": sorted({*earlier.get("comparisons", []), *done[epoch]["comparisons"]}),
        }
        # kept after the next enrich, so `status` lists them until they are compared again
        lost = entry.setdefault("comparisons_invalidated", {})
        for key in done[epoch]["comparisons"]:
            lost[key] = {"at": now, "reason": f"epoch {epoch} {reasons[epoch]}"}
    for epoch, what in sorted(done.items()):
        what["files"] = sorted(set(what["files"]))
        what["comparisons"] = sorted(set(what["comparisons"]))
        compared = ", ".join(what["comparisons"]) or "none"
        status(
            f"epoch {epoch} re-tiled: its enrichment ({len(what['files'])} files, "
            f"{sum(what['rows'].values())} table and layer rows) and comparisons ({compared}) "
            "are removed; run `standgrid enrich` again"
        )
    if done and txn.current(paths.QGIS_PROJECT) is not None:
        from standgrid.catalog.project import write_catalog_project

        write_catalog_project(txn)  # so no layer of catalog.qgz names a removed file
    return done


def invalidate_comparisons(
    catalog: Catalog, txn: Transaction, epochs: set[str], reason: str
) -> list[str]:
    """Remove every comparison that read one of ``epochs`` (their inputs are being
    recomputed): its files, its change-layer rows and its catalog entry; each epoch lists it
    under ``comparisons_invalidated`` until it is compared again. Returns the keys."""
    comparisons = _comparisons_of(txn.state, epochs)
    now = _now()
    for key, (epoch_from, epoch_to) in comparisons.items():
        for rel in _files_under(catalog.root, paths.comparison_folder(key)):
            txn.delete(rel)
        del txn.state["comparisons"][key]
        for epoch in {epoch_from, epoch_to} & epochs:
            entry = txn.state["epochs"].get(epoch)
            if entry is not None:
                lost = entry.setdefault("comparisons_invalidated", {})
                lost[key] = {"at": now, "reason": f"epoch {epoch} {reason}"}
    if comparisons:
        _drop_layer_rows(txn, set(), comparisons)
    return sorted(comparisons)


def other_epoch_read(target: Catalog, epoch: str) -> dict[str, Any]:
    """What a comparison read from another catalog's ``epoch`` (its ``other_epoch`` record)."""
    return {
        "epoch": epoch,
        "enrichment": enrichment_stamp(target.epochs[epoch]),
        "generation": target.generation,
    }


def other_catalog_change(
    entry: Mapping[str, Any], states: dict[str, dict[str, Any] | None] | None = None
) -> str | None:
    """Why a comparison read from another catalog is stale (None: it is not, or it is not
    against another catalog): that catalog or its "to" epoch is gone, or the epoch is no
    longer the enrichment compared (re-tiled, re-enriched). Reads the other catalog's
    ``catalog.json`` once (``states`` caches it per catalog; commits rename it in whole)."""
    import json

    other = entry.get("other_catalog")
    if not other:
        return None
    states = {} if states is None else states
    if other not in states:
        try:
            if is_url(other):  # its current generation's catalog.json
                from standgrid.catalog.remote import current_state

                states[other] = current_state(other)
            else:
                text = (Path(other) / paths.CATALOG_FILE).read_text("utf-8")
                states[other] = json.loads(text)
        except (OSError, ValueError):  # StorageError is an OSError
            states[other] = None
    state = states[other]
    epoch_to = str(entry.get("to"))
    if state is None:
        return f"catalog {other} is gone or unreadable"
    epoch = (state.get("epochs") or {}).get(epoch_to)
    if epoch is None:
        return f"epoch {epoch_to} of {other} is gone"
    now = enrichment_stamp(epoch)
    if now is None:
        stale = epoch.get("invalidated") or {}
        if stale:
            return f"epoch {epoch_to} of {other} {stale.get('reason')} at {stale.get('at')}"
        return f"epoch {epoch_to} of {other} is no longer enriched"
    compared = (entry.get("other_epoch") or {}).get("enrichment")
    if compared is not None and compared != now:
        return f"epoch {epoch_to} of {other} was enriched again since it was compared"
    return None


def without_enrichment(fields: Mapping[str, NDArray[Any]]) -> dict[str, NDArray[Any]]:
    """Per-point fields with enrich's values reset to "not computed" (same dtypes)."""
    return {
        name: np.full_like(values, ENRICH_POINT_FIELDS[name])
        if name in ENRICH_POINT_FIELDS
        else values
        for name, values in fields.items()
    }


def retile_reason(tiled: list[str], moved_out: list[str]) -> str:
    """Why an epoch was re-tiled: the missions (re-)ingested into it and those that left it."""
    parts = [f"missions {', '.join(tiled)}"] if tiled else []
    if moved_out:
        parts.append(f"missions moved to another epoch: {', '.join(moved_out)}")
    return "re-tiled: " + "; ".join(parts)


#: The ``source`` of a height-diameter model fitted to every epoch's measured trees.
POOLED_MODEL = "catalog (all epochs)"


def pooled_dependents(txn: Transaction, reasons: Mapping[str, str]) -> dict[str, str]:
    """Other enriched epochs whose DBH imputation used a height-diameter model pooled over
    the catalog's epochs, so over the trees of the epochs in ``reasons`` too (epoch -> why)."""
    changed = sorted(reasons)
    found = {}
    for epoch, entry in txn.state["epochs"].items():
        model = ((entry.get("enrichment") or {}).get("height_diameter_model")) or {}
        if epoch not in reasons and entry.get("enriched") and model.get("source") == POOLED_MODEL:
            found[epoch] = (
                "its height-diameter model pooled the trees of re-tiled epochs "
                + ", ".join(changed)
            )
    return found


def enrichment_note(before: EpochRecord) -> str:
    """What enriching an epoch does, from its record before (the line to say so)."""
    stale = before.invalidated
    if stale:
        redo = ", ".join(stale.get("comparisons", []))
        again = f"; compare again: {redo}" if redo else ""
        return f"refreshing stale epoch ({stale.get('reason')}, {stale.get('at')}){again}"
    return "recomputing (was enriched)" if before.enriched else "computing (not enriched)"


def _comparisons_of(state: Mapping[str, Any], epochs: set[str]) -> dict[str, tuple[str, str]]:
    """Comparisons (key -> (from, to)) that read one of ``epochs`` of this catalog."""
    found = {}
    for key, entry in state.get("comparisons", {}).items():
        epoch_from, epoch_to = str(entry.get("from")), str(entry.get("to"))
        to_is_here = not entry.get("other_catalog")
        if epoch_from in epochs or (to_is_here and epoch_to in epochs):
            found[key] = (epoch_from, epoch_to)
    return found


def _files_under(root: Path, folder: str) -> list[str]:
    """Catalog-relative paths of the files under ``folder`` (none when it does not exist)."""
    base = root / folder
    if not base.is_dir():
        return []
    return sorted(p.relative_to(root).as_posix() for p in base.rglob("*") if p.is_file())


def _drop_metric_rows(txn: Transaction, epochs: set[str]) -> dict[str, int]:
    """Remove the epochs' rows of ``tables/stand_metrics.{csv,parquet}``; rows per epoch."""
    import pandas as pd

    current = txn.current(paths.stand_metrics("parquet"))
    if current is None:
        return {}
    table = pd.read_parquet(current)
    epoch_of = table["epoch"].astype(str)
    gone = epoch_of.isin(epochs)
    if not gone.any():
        return {}
    counts = {str(e): int(n) for e, n in epoch_of[gone].value_counts().items()}
    kept = table[~gone].reset_index(drop=True)
    if len(kept) == 0:
        txn.delete(paths.stand_metrics("parquet"))
        txn.delete(paths.stand_metrics("csv"))
    else:
        kept.to_parquet(txn.stage(paths.stand_metrics("parquet")), index=False)
        kept.to_csv(txn.stage(paths.stand_metrics("csv")), index=False)
    return counts


def _drop_layer_rows(
    txn: Transaction, epochs: set[str], comparisons: Mapping[str, tuple[str, str]]
) -> dict[tuple[str, str], int]:
    """Delete the epochs' enrichment rows and the comparisons' change rows from the staged
    ``index.gpkg``; rows per (layer, epoch). SQL deletes keep every other row, the layers'
    schemas and their QGIS styles; GeoPackage triggers keep the R-tree index in step."""
    current = txn.current(paths.INDEX)
    if current is None:
        return {}
    staged = txn.stage(paths.INDEX)
    if current != staged:
        shutil.copyfile(current, staged)
    counts: dict[tuple[str, str], int] = {}
    try:
        with contextlib.closing(sqlite3.connect(staged)) as db, db:
            present = {row[0] for row in db.execute("SELECT table_name FROM gpkg_contents")}
            for layer in ENRICH_LAYERS:
                if layer not in present:
                    continue
                for epoch in sorted(epochs):
                    n = db.execute(
                        f'DELETE FROM "{layer}" WHERE CAST("epoch" AS TEXT) = ?', (epoch,)
                    ).rowcount
                    if n:
                        counts[layer, epoch] = n
            for layer in CHANGE_LAYERS:
                if layer not in present:
                    continue
                for epoch_from, epoch_to in comparisons.values():
                    n = db.execute(
                        f'DELETE FROM "{layer}" WHERE CAST("epoch_from" AS TEXT) = ? '
                        'AND CAST("epoch_to" AS TEXT) = ?',
                        (epoch_from, epoch_to),
                    ).rowcount
                    for epoch in {epoch_from, epoch_to} & epochs:
                        if n:
                            counts[layer, epoch] = counts.get((layer, epoch), 0) + n
            touched = sorted({layer for layer, _ in counts})
            db.executemany(
                "UPDATE gpkg_contents SET last_change = strftime('%Y-%m-%dT%H:%M:%fZ','now') "
                "WHERE table_name = ?",
                [(layer,) for layer in touched],
            )
    except sqlite3.DatabaseError as exc:
        raise CatalogError(f"cannot remove stale rows: {exc}", path=current) from exc
    return counts
