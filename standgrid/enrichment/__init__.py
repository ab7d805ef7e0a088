"""Enrichment: terrain, trees and stand metrics.

- :mod:`.ground`: ``classify_ground`` (Cloth Simulation Filter).
- :mod:`.rasters`: ``RasterGrid`` aligned to the stand grid, ``dtm_from_ground``,
  ``height_above_ground``, ``chm``, ``density``, ``write_cog`` / ``read_raster``.
- :mod:`.stems`: ``find_stems`` (stems as vertical chains of circles: position, lean, DBH).
- :mod:`.crowns`: ``grow_crowns`` (every point to the stem it grows from: shortest paths).
- :mod:`.trees`: ``segment_trees`` (stems first, crowns from stems, canopy tops where no stem
  is seen), stable ``tree_id_from_xy``; :mod:`.circles`: ``fit_circle``, ``fit_circles``.
- :mod:`.metrics`: ``area_metrics`` (lidR ``stdmetrics_z`` set per cell), ``tree_metrics``
  (stems/ha, basal area, QMD, mean and dominant height). Definitions: docs/METRICS.md.
- :mod:`.apply`: ``catalog_apply``, an epoch enriched chunk by chunk (:mod:`.chunks`: the
  buffered chunks' layout; :mod:`.engine`: runs them and gives results back in order).
"""

from standgrid.enrichment.ground import as_xyz, classify_ground
from standgrid.enrichment.metrics import (
    DEFAULT_STRATA,
    QUANTILE_PERCENTS,
    REASON_NO_DBH,
    REASON_NO_HEIGHT,
    REASON_NO_POINTS,
    REASON_NO_TREES,
    area_metrics,
    cell_index,
    strata_columns,
    tree_metrics,
)
from standgrid.enrichment.rasters import (
    chm,
    density,
    dtm_from_ground,
    height_above_ground,
)
from standgrid.enrichment.trees import (
    TREE_COLUMNS,
    CircleFit,
    TreeSegmentation,
    default_window,
    fit_circle,
    kasa_circle,
    segment_trees,
    tree_id_from_xy,
    xy_from_tree_id,
)
from standgrid.geotiff import RasterData, read_raster, write_cog
from standgrid.rastergrid import RasterGrid

__all__ = [
    "DEFAULT_STRATA",
    "QUANTILE_PERCENTS",
    "REASON_NO_DBH",
    "REASON_NO_HEIGHT",
    "REASON_NO_POINTS",
    "REASON_NO_TREES",
    "TREE_COLUMNS",
    "CircleFit",
    "RasterData",
    "RasterGrid",
    "TreeSegmentation",
    "area_metrics",
    "as_xyz",
    "cell_index",
    "chm",
    "classify_ground",
    "default_window",
    "density",
    "dtm_from_ground",
    "fit_circle",
    "height_above_ground",
    "kasa_circle",
    "read_raster",
    "segment_trees",
    "strata_columns",
    "tree_id_from_xy",
    "tree_metrics",
    "write_cog",
    "xy_from_tree_id",
]
