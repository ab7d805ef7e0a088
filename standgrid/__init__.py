"""standgrid: forest-mapping robot missions -> a georeferenced, partitioned stand-grid map.

The data flow, one subpackage per stage::

    mission -> georeference -> partition -> export (tiles + index) -> enrich -> compare
"""

from standgrid.errors import StandgridError
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp

__version__ = "0.1.0"
__all__ = ["PointCloud", "StandgridError", "Stamp", "__version__"]
