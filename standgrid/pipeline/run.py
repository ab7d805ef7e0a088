"""The whole path in one call: missions -> catalog -> enriched -> compared."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from standgrid.comparison.options import CompareOptions
from standgrid.engine import Execution
from standgrid.enrichment.options import EnrichOptions
from standgrid.errors import MissionNotFoundError
from standgrid.pipeline.enrich import enrich_catalog
from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions


@dataclass
class RunReport:
    tile: dict[str, Any]
    enrich: dict[str, Any]
    compare: dict[str, Any] | None

    def to_dict(self) -> dict[str, Any]:
        return {"tile": self.tile, "enrich": self.enrich, "compare": self.compare}


def expand_missions(paths: Sequence[str | Path]) -> list[Path]:
    """Mission folders and plain scans (:func:`~standgrid.mission.scan.is_scan`) as given; a
    folder that is neither stands for the missions in it; object-storage URLs are fetched
    into a local cache first."""
    from standgrid.mission.collection import MissionCollection
    from standgrid.mission.layout import discover_layout
    from standgrid.mission.scan import is_scan
    from standgrid.storage import is_url
    from standgrid.storage.objects import fetched_folder

    found: list[Path] = []
    for raw in paths:
        path = fetched_folder(str(raw)) if is_url(raw) else Path(raw)
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
    tile_options: TileOptions = TileOptions(),
    enrich_options: EnrichOptions = EnrichOptions(),
    compare_options: CompareOptions = CompareOptions(),
    *,
    execution: Execution = Execution(),
) -> RunReport:
    """Tile every mission, enrich every epoch (or ``enrich_options.epochs``), and compare
    two epochs (``compare_options``; by default the first with the last) when there are
    two; every stage runs as ``execution`` says (one cluster, or this process, for all)."""
    from standgrid.pipeline.compare import compare_epochs

    missions = expand_missions(paths)
    with execution.open() as executor:
        running = execution.on(executor)
        tiled = tile_missions(missions, catalog, tile_options, execution=running)
        enriched = enrich_catalog(catalog, enrich_options, execution=running)
    compared = None
    if len(enriched.epochs) >= 2 or compare_options.other_catalog is not None:
        compared = compare_epochs(catalog, compare_options, execution=execution).to_dict()
    return RunReport(tiled.to_dict(), enriched.to_dict(), compared)
