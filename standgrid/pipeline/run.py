"""The whole path in one call: missions -> catalog -> enriched -> compared."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from standgrid.engine import SILENT, Progress
from standgrid.errors import MissionNotFoundError
from standgrid.pipeline.enrich import EnrichOptions, enrich_catalog
from standgrid.pipeline.tile import TileOptions, tile_missions


@dataclass
class RunReport:
    tile: dict[str, Any]
    enrich: dict[str, Any]
    compare: dict[str, Any] | None

    def to_dict(self) -> dict[str, Any]:
        return {"tile": self.tile, "enrich": self.enrich, "compare": self.compare}


def expand_missions(paths: Sequence[str | Path]) -> list[Path]:
    """Mission folders and plain scans (:func:`~standgrid.mission.scan.is_scan`) as given; a
    folder that is neither stands for the missions in it."""
    from standgrid.mission.collection import MissionCollection
    from standgrid.mission.layout import discover_layout
    from standgrid.mission.scan import is_scan

    found: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if is_scan(path):
            found.append(path)
            continue
        if not path.is_dir():
            raise MissionNotFoundError("no such folder", path=path)
        if discover_layout(path).is_mission:
            found.append(path)
            continue
        records = MissionCollection(path, strict=True).records
        if not records:
            raise MissionNotFoundError("neither a mission nor a folder of missions", path=path)
        found.extend(sorted(r.path for r in records))
    return found


def run_pipeline(
    paths: Sequence[str | Path],
    catalog: str | Path,
    tile_options: TileOptions | None = None,
    enrich_options: EnrichOptions | None = None,
    *,
    progress: Progress = SILENT,
    workers: int | None = None,
    scheduler: str | None = None,
) -> RunReport:
    """Tile every mission, enrich every epoch, and compare the first epoch with the last
    (enrichment on a dask cluster with ``workers`` or ``scheduler``)."""
    from standgrid.engine import open_executor
    from standgrid.pipeline.compare import compare_epochs

    missions = expand_missions(paths)
    tile_options = tile_options or TileOptions()
    enrich_options = enrich_options or EnrichOptions()
    timeout = tile_options.lock_timeout
    # one cluster (or this process) for both stages
    budget = max(tile_options.memory_budget.bytes, enrich_options.memory_budget.bytes)
    with open_executor(workers, scheduler, memory_budget=budget) as executor:
        tiled = tile_missions(missions, catalog, tile_options, progress=progress, executor=executor)
        enriched = enrich_catalog(
            catalog, enrich_options, progress=progress, executor=executor, lock_timeout=timeout
        )
    compared = None
    if len(enriched.epochs) >= 2:
        compared = compare_epochs(catalog, progress=progress, lock_timeout=timeout).to_dict()
    return RunReport(tiled.to_dict(), enriched.to_dict(), compared)
