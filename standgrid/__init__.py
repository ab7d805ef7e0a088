"""standgrid: forest-mapping robot missions -> a georeferenced, partitioned stand-grid map.

The data flow, one subpackage per stage::

    mission -> georeference -> partition -> export (tiles + index) -> enrich -> compare

``standgrid.pipeline`` strings the stages together; ``standgrid.cli`` is a thin click layer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from standgrid.errors import StandgridError

if TYPE_CHECKING:
    from standgrid.pointcloud import PointCloud
    from standgrid.stamps import Stamp

__version__ = "0.1.0"
__all__ = ["PointCloud", "Stamp", "StandgridError", "__version__"]

_LAZY = {"PointCloud": "standgrid.pointcloud", "Stamp": "standgrid.stamps"}


def __getattr__(name: str) -> Any:
    """Import the core types on first use, so ``standgrid --help`` stays instant."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'standgrid' has no attribute {name!r}")
