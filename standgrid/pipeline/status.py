"""What a catalog holds, from ``catalog.json`` alone: epochs, missions, tiles, points, what
is enriched, stale or not enriched, and which comparisons are present or were invalidated."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from standgrid.catalog.invalidate import other_catalog_change
from standgrid.catalog.records import ENRICHED, NOT_ENRICHED, STALE
from standgrid.engine import Execution

__all__ = ["ENRICHED", "NOT_ENRICHED", "STALE", "catalog_status"]


def catalog_status(
    catalog_path: str | Path, *, execution: Execution = Execution()
) -> dict[str, Any]:
    """The status of a catalog (the ``standgrid status --json`` document).

    An epoch is ``enriched``, ``stale`` (it was enriched, then re-tiled: its results were
    removed, ``invalidated`` says when and why) or ``not enriched``. Points are the missions'
    point counts at ingest (no tile is read). A comparison is ``present``, ``invalidated``
    (removed when one of its epochs was re-tiled, and not made again since) or ``stale`` (made
    against another catalog whose epoch changed since: re-tiled, re-enriched or gone; its
    results are still there, ``reason`` says why they are out of date). Reading waits for
    a writer up to ``execution.lock_timeout``.
    """
    from standgrid.catalog import Catalog
    from standgrid.catalog.paths import CATALOG_FILE
    from standgrid.catalog.remote import catalog_at
    from standgrid.storage import is_url

    timeout = execution.lock_timeout
    with catalog_at(catalog_path, write=False, lock_timeout=timeout, only=(CATALOG_FILE,)) as root:
        catalog = Catalog.open(root, lock_timeout=timeout)  # one read
    missions = catalog.mission_records
    epochs: dict[str, Any] = {}
    invalidated: list[dict[str, Any]] = []
    for epoch, record in sorted(catalog.epoch_records.items()):
        state = record.state
        epochs[epoch] = {
            "date": record.date,
            "missions": list(record.missions),
            "tiles": len(catalog.tiles(epoch)),
            "points": sum(missions[n].point_count for n in record.missions if n in missions),
            "state": state,
            "invalidated": dict(record.invalidated or {}) if state == STALE else None,
            "enrichment": dict(record.enrichment or {}) if state == ENRICHED else None,
        }
        for key, lost in record.comparisons_invalidated.items():
            invalidated.append({"comparison": key, **lost})
    comparisons: dict[str, dict[str, Any]] = {}
    others: dict[str, Any] = {}  # each other catalog's catalog.json, read once
    for key, entry in sorted(catalog.comparisons.items()):
        comparisons[key] = {
            "from": entry.get("from"),
            "to": entry.get("to"),
            "other_catalog": entry.get("other_catalog"),
            "state": "present",
        }
        changed = other_catalog_change(entry, others)
        if changed is not None:
            comparisons[key].update(state=STALE, reason=changed)
    for item in sorted(invalidated, key=lambda i: str(i["at"])):  # the latest reason wins
        key = item["comparison"]
        if comparisons.get(key, {}).get("state") not in ("present", STALE):  # else made again
            epoch_from, _, epoch_to = key.partition("__")
            comparisons[key] = {
                "from": epoch_from,
                "to": epoch_to,
                "other_catalog": None,
                "state": "invalidated",
                "reason": item["reason"],
                "at": item["at"],
            }
    return {
        "catalog": str(catalog_path) if is_url(catalog_path) else str(catalog.root),
        "crs": catalog.crs,
        "scheme": catalog.scheme,
        "epochs": epochs,
        "comparisons": comparisons,
    }
