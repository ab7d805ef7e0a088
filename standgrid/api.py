"""The front door's verbs, typed: ``tile``, ``align``, ``enrich``, ``compare``, ``run``,
``status``; every one is ``verb(input, options, *, execution)`` (``None``: the defaults).

Each imports its stage when called, so ``import standgrid`` stays light (no numpy); the
types (checked, imported for type checkers only) are the stages' own.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from standgrid.comparison.options import CompareOptions
    from standgrid.engine.execution import Execution
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.mission.model import Mission
    from standgrid.pipeline.compare import CompareReport
    from standgrid.pipeline.enrich import EnrichReport
    from standgrid.pipeline.run import RunReport
    from standgrid.pipeline.tile import TileReport
    from standgrid.tiling.options import TileOptions

__all__ = ["align", "compare", "enrich", "run", "status", "tile"]


def _execution(execution: Execution | None) -> Execution:
    from standgrid.engine.execution import Execution

    return Execution() if execution is None else execution


def tile(
    missions: Sequence[str | Path | Mission],
    catalog: str | Path,
    options: TileOptions | None = None,
    *,
    execution: Execution | None = None,
) -> TileReport:
    """Georeference ``missions`` (folders, plain scans, or opened missions) and tile them
    into ``catalog`` (made if absent): :func:`standgrid.pipeline.tile.tile_missions`."""
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    return tile_missions(
        missions, catalog, options or TileOptions(), execution=_execution(execution)
    )


def align(
    catalog: str | Path, options: TileOptions | None = None, *, execution: Execution | None = None
) -> TileReport:
    """Re-align a catalog's missions to each other and re-tile them, each in its epoch:
    :func:`standgrid.pipeline.tile.realign_catalog`."""
    from standgrid.pipeline.tile import realign_catalog
    from standgrid.tiling.options import TileOptions

    return realign_catalog(catalog, options or TileOptions(), execution=_execution(execution))


def enrich(
    catalog: str | Path,
    options: EnrichOptions | None = None,
    *,
    execution: Execution | None = None,
) -> EnrichReport:
    """Ground, terrain rasters, trees and stand metrics for every epoch of ``catalog`` (or
    ``options.epochs``): :func:`standgrid.pipeline.enrich.enrich_catalog`."""
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.enrich import enrich_catalog

    return enrich_catalog(catalog, options or EnrichOptions(), execution=_execution(execution))


def compare(
    catalog: str | Path,
    options: CompareOptions | None = None,
    *,
    execution: Execution | None = None,
) -> CompareReport:
    """Change between two enriched epochs (default: the first and the last):
    :func:`standgrid.pipeline.compare.compare_epochs`."""
    from standgrid.comparison.options import CompareOptions
    from standgrid.pipeline.compare import compare_epochs

    return compare_epochs(catalog, options or CompareOptions(), execution=_execution(execution))


def run(
    paths: Sequence[str | Path],
    catalog: str | Path,
    tile_options: TileOptions | None = None,
    enrich_options: EnrichOptions | None = None,
    compare_options: CompareOptions | None = None,
    *,
    execution: Execution | None = None,
) -> RunReport:
    """Tile, enrich every epoch and compare two: :func:`standgrid.pipeline.run.run_pipeline`."""
    from standgrid.comparison.options import CompareOptions
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.run import run_pipeline
    from standgrid.tiling.options import TileOptions

    return run_pipeline(
        paths,
        catalog,
        tile_options or TileOptions(),
        enrich_options or EnrichOptions(),
        compare_options or CompareOptions(),
        execution=_execution(execution),
    )


def status(catalog: str | Path, *, execution: Execution | None = None) -> dict[str, Any]:
    """What ``catalog`` holds and what is enriched, stale or compared (``standgrid status
    --json``): :func:`standgrid.pipeline.status.catalog_status`."""
    from standgrid.pipeline.status import catalog_status

    return catalog_status(catalog, execution=_execution(execution))
