"""Change between campaigns: matched trees, per-stand change, CHM difference, outputs.

- :func:`match_trees` (:mod:`.trees`): one-to-one tree matching -> grown / new / removed.
- :func:`compare_stands`, :func:`check_same_grid`, :func:`assign_stands` (:mod:`.stands`).
- :func:`chm_difference` (:mod:`.rasters`): ``to - from`` CHM as a Cloud-Optimized GeoTIFF.
- :func:`write_change_outputs` (:mod:`.report`): CSV/Parquet tables + styled GeoPackage layers.

Annualisation everywhere: change / years, years = days between the epochs' dates / 365.25.
"""

from standgrid.comparison.rasters import NODATA, ChmDifference, chm_difference
from standgrid.comparison.report import ChangeOutputs, write_change_outputs
from standgrid.comparison.stands import assign_stands, check_same_grid, compare_stands
from standgrid.comparison.trees import (
    ChangeInputError,
    TreeMatches,
    interval_years,
    match_trees,
)

__all__ = [
    "NODATA",
    "ChangeInputError",
    "ChangeOutputs",
    "ChmDifference",
    "TreeMatches",
    "assign_stands",
    "check_same_grid",
    "chm_difference",
    "compare_stands",
    "interval_years",
    "match_trees",
    "write_change_outputs",
]
