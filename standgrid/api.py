"""The front door's verbs, typed: ``tile``, ``align``, ``enrich``, ``compare``, ``run``,
``status``; every one is ``verb(input, options, *, execution)`` (``None``: the defaults).
And the payload retrievals, which with a ``catalog`` give each payload with its layers.

Each imports its stage when called, so ``import standgrid`` stays light (no numpy); the
types (checked, imported for type checkers only) are the stages' own.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from standgrid.catalog import Catalog
    from standgrid.comparison.options import CompareOptions
    from standgrid.engine.execution import Execution
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.enrichment.payload_layers import PayloadLayers
    from standgrid.mission.model import Mission
    from standgrid.mission.payload import Payload
    from standgrid.pipeline.compare import CompareReport
    from standgrid.pipeline.enrich import EnrichReport
    from standgrid.pipeline.run import RunReport
    from standgrid.pipeline.tile import TileReport
    from standgrid.tiling.options import TileOptions

#: The verbs (every one ``verb(input, options, *, execution)``).
__all__ = ["align", "compare", "enrich", "run", "status", "tile"]
#: The retrievals (a mission and a query; with ``catalog=``, each payload with its layers).
RETRIEVALS = ("retrieve_payload_by_type", "retrieve_payload_by_pose", "retrieve_payload_by_gnss")


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


# --- retrieval ---------------------------------------------------------------------------


@overload
def retrieve_payload_by_type(
    mission: str | Path | Mission,
    data_type: str,
    *,
    catalog: None = None,
    layers: str | Sequence[str] | None = None,
) -> list[Payload]: ...
@overload
def retrieve_payload_by_type(
    mission: str | Path | Mission,
    data_type: str,
    *,
    catalog: str | Path | Catalog,
    layers: str | Sequence[str] | None = None,
) -> list[PayloadLayers]: ...
def retrieve_payload_by_type(
    mission: str | Path | Mission,
    data_type: str,
    *,
    catalog: str | Path | Catalog | None = None,
    layers: str | Sequence[str] | None = None,
) -> list[Payload] | list[PayloadLayers]:
    """Every payload of one data type (:func:`standgrid.mission.retrieval.
    retrieve_payload_by_type`); with ``catalog``, each with its ``layers`` from it (default
    all: :func:`standgrid.enrichment.payload_layers.layers_of`)."""
    from standgrid.mission.retrieval import retrieve_payload_by_type as by_type

    wanted = _layer_names(catalog, layers)  # an unknown layer is refused before any work
    opened = _opened(mission)
    found = by_type(opened, data_type)
    return found if catalog is None else _with_layers(catalog, opened, found, wanted)


@overload
def retrieve_payload_by_pose(
    mission: str | Path | Mission,
    slam_pose: ArrayLike,
    *,
    catalog: None = None,
    layers: str | Sequence[str] | None = None,
    **by_pose: Any,
) -> list[Payload]: ...
@overload
def retrieve_payload_by_pose(
    mission: str | Path | Mission,
    slam_pose: ArrayLike,
    *,
    catalog: str | Path | Catalog,
    layers: str | Sequence[str] | None = None,
    **by_pose: Any,
) -> list[PayloadLayers]: ...
def retrieve_payload_by_pose(
    mission: str | Path | Mission,
    slam_pose: ArrayLike,
    *,
    catalog: str | Path | Catalog | None = None,
    layers: str | Sequence[str] | None = None,
    **by_pose: Any,
) -> list[Payload] | list[PayloadLayers]:
    """Payload clouds near a map-frame pose (:func:`standgrid.mission.retrieval.
    retrieve_payload_by_pose`: ``k``, ``radius``, ``covering``); with ``catalog``, each with
    its ``layers`` from it."""
    from standgrid.mission.retrieval import retrieve_payload_by_pose as by_pose_

    wanted = _layer_names(catalog, layers)
    opened = _opened(mission)
    found = by_pose_(opened, slam_pose, **by_pose)
    return found if catalog is None else _with_layers(catalog, opened, found, wanted)


@overload
def retrieve_payload_by_gnss(
    mission: str | Path | Mission,
    gnss: ArrayLike,
    *,
    catalog: None = None,
    layers: str | Sequence[str] | None = None,
    **by_gnss: Any,
) -> list[Payload]: ...
@overload
def retrieve_payload_by_gnss(
    mission: str | Path | Mission,
    gnss: ArrayLike,
    *,
    catalog: str | Path | Catalog,
    layers: str | Sequence[str] | None = None,
    **by_gnss: Any,
) -> list[PayloadLayers]: ...
def retrieve_payload_by_gnss(
    mission: str | Path | Mission,
    gnss: ArrayLike,
    *,
    catalog: str | Path | Catalog | None = None,
    layers: str | Sequence[str] | None = None,
    **by_gnss: Any,
) -> list[Payload] | list[PayloadLayers]:
    """Payloads near a GNSS coordinate ``(lat, lon[, alt])`` (:func:`standgrid.georeference.
    retrieval.retrieve_payload_by_gnss`: ``max_distance``, ``k``, ...); with ``catalog``,
    each with its ``layers`` from it."""
    from standgrid.georeference.retrieval import retrieve_payload_by_gnss as by_gnss_

    wanted = _layer_names(catalog, layers)
    opened = _opened(mission)
    found = by_gnss_(opened, gnss, **by_gnss)
    return found if catalog is None else _with_layers(catalog, opened, found, wanted)


def _opened(mission: str | Path | Mission) -> Mission:
    from standgrid.mission.model import Mission
    from standgrid.mission.opening import open_mission

    return mission if isinstance(mission, Mission) else open_mission(mission, strict=False)


def _layer_names(
    catalog: str | Path | Catalog | None, layers: str | Sequence[str] | None
) -> tuple[str, ...]:
    from standgrid.enrichment.payload_layers import parse_layers

    return () if catalog is None else parse_layers(layers)


def _with_layers(
    catalog: str | Path | Catalog,
    mission: Mission,
    payloads: list[Payload],
    layers: tuple[str, ...],
) -> list[PayloadLayers]:
    from standgrid.enrichment.payload_layers import layers_of

    return layers_of(catalog, mission, payloads, layers)
