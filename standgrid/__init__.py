"""standgrid: forest-mapping robot missions -> a georeferenced, partitioned stand-grid map.

The data flow, one subpackage per stage::

    mission -> georeference -> partition -> export (file writers) -> catalog -> enrich -> compare

``standgrid.pipeline`` strings the stages together; ``standgrid.cli`` is a thin click layer.
The front door, for scripts (:mod:`standgrid.api`: typed verbs that import their stage on
call, so ``import standgrid`` and ``standgrid --help`` stay instant)::

    import standgrid

    if __name__ == "__main__":  # workers=N spawns processes that import the script again
        mission = standgrid.open_mission("missions/2024-05-14-wytham-anymal-coyote")
        tiled = standgrid.tile([mission], "catalog", standgrid.TileOptions(buffer=2.0))
        on_two = standgrid.Execution(workers=2)  # chunks on a local dask cluster
        enriched = standgrid.enrich("catalog", execution=on_two)
        change = standgrid.compare("catalog", standgrid.CompareOptions("2024", "2028"))
        catalog = standgrid.open_catalog("catalog")  # .epoch_records, .mission_records

Every verb has one shape, ``verb(input, options, *, execution)`` returning a report: the
options (:class:`TileOptions`, :class:`EnrichOptions`, :class:`CompareOptions`) say what to
compute, the :class:`Execution` how to run (workers or a scheduler, memory, lock timeout,
``progress``: any :class:`standgrid.Progress`); both validate themselves
(:class:`~standgrid.errors.OptionError` naming the field at fault).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

# (names of the front door: ``standgrid.wait_passively``, ``standgrid.WAIT_POLICY``)
from standgrid._threads import THREAD_COUNTS as THREAD_COUNTS
from standgrid._threads import WAIT_POLICY as WAIT_POLICY
from standgrid._threads import wait_passively

wait_passively()

from standgrid.errors import OptionError, StandgridError  # noqa: E402

if TYPE_CHECKING:
    from standgrid.api import (
        align,
        compare,
        enrich,
        retrieve_payload_by_gnss,
        retrieve_payload_by_pose,
        retrieve_payload_by_type,
        run,
        status,
        tile,
    )
    from standgrid.catalog.store import Catalog, open_catalog
    from standgrid.comparison.options import CompareOptions
    from standgrid.engine.execution import Execution
    from standgrid.engine.progress import Progress
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.mission.opening import open_mission
    from standgrid.partition.grid import StandGrid
    from standgrid.pointcloud import PointCloud
    from standgrid.stamps import Stamp
    from standgrid.tiling.options import TileOptions

__version__ = "0.1.0"
__all__ = [
    "Catalog",
    "CompareOptions",
    "EnrichOptions",
    "Execution",
    "OptionError",
    "PointCloud",
    "Progress",
    "Stamp",
    "StandGrid",
    "StandgridError",
    "TileOptions",
    "__version__",
    "align",
    "compare",
    "enrich",
    "open_catalog",
    "open_mission",
    "retrieve_payload_by_gnss",
    "retrieve_payload_by_pose",
    "retrieve_payload_by_type",
    "run",
    "status",
    "tile",
]

#: name -> (module, attribute), imported on first use.
_LAZY: dict[str, tuple[str, str]] = {
    "PointCloud": ("standgrid.pointcloud", "PointCloud"),
    "Stamp": ("standgrid.stamps", "Stamp"),
    "Catalog": ("standgrid.catalog.store", "Catalog"),
    "open_catalog": ("standgrid.catalog.store", "open_catalog"),
    "open_mission": ("standgrid.mission.opening", "open_mission"),
    "StandGrid": ("standgrid.partition.grid", "StandGrid"),
    "TileOptions": ("standgrid.tiling.options", "TileOptions"),
    "EnrichOptions": ("standgrid.enrichment.options", "EnrichOptions"),
    "CompareOptions": ("standgrid.comparison.options", "CompareOptions"),
    "Execution": ("standgrid.engine.execution", "Execution"),
    "Progress": ("standgrid.engine.progress", "Progress"),
    # the retrievals, which with a catalog give each payload with its layers (standgrid.api)
    "retrieve_payload_by_type": ("standgrid.api", "retrieve_payload_by_type"),
    "retrieve_payload_by_pose": ("standgrid.api", "retrieve_payload_by_pose"),
    "retrieve_payload_by_gnss": ("standgrid.api", "retrieve_payload_by_gnss"),
    # the verbs (typed in standgrid.api); the stage packages are nouns (tiling, enrichment,
    # comparison, alignment), so importing one never rebinds a verb
    **{verb: ("standgrid.api", verb) for verb in ("tile", "align", "enrich", "compare", "run")},
    "status": ("standgrid.api", "status"),
}


def __getattr__(name: str) -> Any:
    """Import the front door's names on first use (PEP 562)."""
    if name in _LAZY:
        import importlib

        module_name, attribute = _LAZY[name]
        return getattr(importlib.import_module(module_name), attribute)
    raise AttributeError(f"module 'standgrid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
