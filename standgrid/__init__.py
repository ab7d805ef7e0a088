"""standgrid: forest-mapping robot missions -> a georeferenced, partitioned stand-grid map.

The data flow, one subpackage per stage::

    mission -> georeference -> partition -> export (file writers) -> catalog -> enrich -> compare

``standgrid.pipeline`` strings the stages together; ``standgrid.cli`` is a thin click layer.
The front door, for scripts (every name is imported on first use, so ``import standgrid``
and ``standgrid --help`` stay instant)::

    import standgrid

    if __name__ == "__main__":  # workers=N spawns processes that import the script again
        mission = standgrid.open_mission("missions/2024-05-14-wytham-anymal-coyote")
        tiled = standgrid.tile([mission], "catalog", standgrid.TileOptions(buffer=2.0))
        enriched = standgrid.enrich("catalog", workers=2)  # chunks on a local dask cluster
        change = standgrid.compare("catalog", standgrid.CompareOptions("2024", "2028"))
        catalog = standgrid.open_catalog("catalog")  # .epoch_records, .mission_records

``tile``, ``enrich``, ``compare`` and ``run`` are ``pipeline.tile_missions``,
``enrich_catalog``, ``compare_epochs`` and ``run_pipeline``. ``standgrid.enrich`` and
``standgrid.compare`` are also the stage packages (callable, see :mod:`standgrid._stage`).
Every stage has one shape: ``stage(input, options, *, progress=...)`` returning a report;
``progress`` is any :class:`standgrid.Progress` (``track(items, total, desc)``,
``status(text)``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

# (names of the front door: ``standgrid.wait_passively``, ``standgrid.WAIT_POLICY``)
from standgrid._threads import THREAD_COUNTS as THREAD_COUNTS
from standgrid._threads import WAIT_POLICY as WAIT_POLICY
from standgrid._threads import wait_passively

wait_passively()

from standgrid.errors import StandgridError  # noqa: E402

if TYPE_CHECKING:
    from standgrid.catalog.store import Catalog, open_catalog
    from standgrid.compare.options import CompareOptions
    from standgrid.engine.progress import Progress
    from standgrid.enrich.options import EnrichOptions
    from standgrid.georeference.retrieval import retrieve_payload_by_gnss
    from standgrid.mission.model import open_mission
    from standgrid.mission.retrieval import retrieve_payload_by_pose, retrieve_payload_by_type
    from standgrid.partition.grid import StandGrid
    from standgrid.pipeline.run import run_pipeline as run
    from standgrid.pipeline.tile import TileOptions
    from standgrid.pipeline.tile import tile_missions as tile
    from standgrid.pointcloud import PointCloud
    from standgrid.stamps import Stamp

__version__ = "0.1.0"
__all__ = [
    "Catalog",
    "CompareOptions",
    "EnrichOptions",
    "PointCloud",
    "Progress",
    "Stamp",
    "StandGrid",
    "StandgridError",
    "TileOptions",
    "__version__",
    "compare",
    "enrich",
    "open_catalog",
    "open_mission",
    "retrieve_payload_by_gnss",
    "retrieve_payload_by_pose",
    "retrieve_payload_by_type",
    "run",
    "tile",
]

#: name -> (module, attribute); attribute None: the (callable) stage package itself.
_LAZY: dict[str, tuple[str, str | None]] = {
    "PointCloud": ("standgrid.pointcloud", "PointCloud"),
    "Stamp": ("standgrid.stamps", "Stamp"),
    "Catalog": ("standgrid.catalog.store", "Catalog"),
    "open_catalog": ("standgrid.catalog.store", "open_catalog"),
    "open_mission": ("standgrid.mission.model", "open_mission"),
    "StandGrid": ("standgrid.partition.grid", "StandGrid"),
    "TileOptions": ("standgrid.pipeline.tile", "TileOptions"),
    "EnrichOptions": ("standgrid.enrich.options", "EnrichOptions"),
    "CompareOptions": ("standgrid.compare.options", "CompareOptions"),
    "Progress": ("standgrid.engine.progress", "Progress"),
    "tile": ("standgrid.pipeline.tile", "tile_missions"),
    "run": ("standgrid.pipeline.run", "run_pipeline"),
    "enrich": ("standgrid.enrich", None),
    "compare": ("standgrid.compare", None),
    "retrieve_payload_by_type": ("standgrid.mission.retrieval", "retrieve_payload_by_type"),
    "retrieve_payload_by_pose": ("standgrid.mission.retrieval", "retrieve_payload_by_pose"),
    "retrieve_payload_by_gnss": ("standgrid.georeference.retrieval", "retrieve_payload_by_gnss"),
}


def __getattr__(name: str) -> Any:
    """Import the front door's names on first use (PEP 562)."""
    if name in _LAZY:
        import importlib

        module_name, attribute = _LAZY[name]
        module = importlib.import_module(module_name)
        return module if attribute is None else getattr(module, attribute)
    raise AttributeError(f"module 'standgrid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
