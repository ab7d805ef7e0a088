"""Evidence in the other survey before a tree is called removed or new.

A tree found by one survey and not matched in the other is *removed* (harvested, fallen)
or *new* (ingrowth) only if the other survey saw its place empty. For a tree found from
its stem: fewer than :data:`MIN_RETURNS` of that survey's returns between 1 and 2 m above
ground (:data:`STEM_BAND_M`) on the stem's round, or those covering less than a quarter of
it (:func:`stems_standing`; from the catalog's enriched tiles, their
``height_above_ground``, read only for the cells holding such trees). For a tree found
from its top alone (its stem unseen): that survey's canopy height model lower than
:data:`CANOPY_SHARE` of its height within :data:`CANOPY_REACH_M` of its top. Otherwise it
stands in both surveys and one of them did not make it a tree (a stem behind others, too
few points for its circles, a crown's top found once): the tree is ``missed``, neither
harvest nor ingrowth.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import NDArray

if TYPE_CHECKING:
    from standgrid.catalog import Catalog

MISSED = "missed"
#: Heights above ground (m) of the returns that show a stem standing.
STEM_BAND_M = (1.0, 2.0)
#: Returns in that band on the stem's round, over a quarter of it at least, that show it
#: stands (foliage and shrubs in its place do not lie on a ring of its radius).
MIN_RETURNS = 8
MIN_SECTORS = 3
#: How far off the stem's radius such a return may lie: MARGIN_M + RING_SHARE x radius (m;
#: the two surveys' placement, bark and noise).
MARGIN_M = 0.05
RING_SHARE = 0.25
#: A tree found from its top alone stands where the other survey's canopy height model
#: reaches this share of its height within this distance (m) of its top.
CANOPY_SHARE = 0.8
CANOPY_REACH_M = 0.5


def stems_standing(
    catalog: Catalog,
    epoch: str,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    radius: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Per position, whether the epoch's points show a stem of ``radius`` standing there:
    at least :data:`MIN_RETURNS` returns in :data:`STEM_BAND_M` on its round (within
    :data:`MARGIN_M` + :data:`RING_SHARE` x radius of it), in at least
    :data:`MIN_SECTORS` of its twelve 30-degree sectors."""
    import shapely
    from scipy.spatial import cKDTree

    from standgrid.catalog.index import CatalogIndex
    from standgrid.export.las import read_tile

    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    r = np.nan_to_num(np.asarray(radius, dtype=np.float64), nan=0.0)
    reach = r * (1.0 + RING_SHARE) + MARGIN_M
    standing = np.zeros(len(x), dtype=bool)
    if not len(x):
        return standing
    cells = CatalogIndex(catalog).read("cells", epoch).reset_index(drop=True)
    if not len(cells):
        return standing
    windows = shapely.buffer(shapely.points(x, y), reach)
    tree_of, cell_of = shapely.STRtree(cells.geometry.to_numpy()).query(
        windows, predicate="intersects"
    )
    sectors = np.zeros((len(x), 12), dtype=bool)
    counts = np.zeros(len(x), dtype=np.int64)
    lo, hi = STEM_BAND_M
    for cell in np.unique(cell_of).tolist():
        cloud = read_tile(catalog.path(str(cells.loc[cell, "tile_path"])))
        if "height_above_ground" not in cloud.fields or not len(cloud):
            continue
        h = np.asarray(cloud.fields["height_above_ground"], dtype=np.float64)
        band = np.flatnonzero((h >= lo) & (h <= hi))
        if not len(band):
            continue
        xy = cloud.xyz[band, :2]
        index = cKDTree(xy)
        for k in tree_of[cell_of == cell].tolist():
            near = np.asarray(index.query_ball_point((x[k], y[k]), reach[k]), dtype=np.int64)
            if not len(near):
                continue
            dx, dy = xy[near, 0] - x[k], xy[near, 1] - y[k]
            ring = np.abs(np.hypot(dx, dy) - r[k]) <= MARGIN_M + RING_SHARE * r[k]
            counts[k] += int(ring.sum())
            angle = np.arctan2(dy[ring], dx[ring])
            sectors[k, (np.floor((angle + np.pi) / (np.pi / 6)).astype(np.int64) % 12)] = True
    standing = (counts >= MIN_RETURNS) & (sectors.sum(axis=1) >= MIN_SECTORS)
    return standing


def canopy_standing(
    catalog: Catalog,
    epoch: str,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    height: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Per top, whether the epoch's canopy height model reaches :data:`CANOPY_SHARE` of
    ``height`` within :data:`CANOPY_REACH_M` of it: the crown is there."""
    from standgrid.catalog import paths
    from standgrid.geotiff import read_raster

    chm = read_raster(catalog.path(paths.raster(epoch, "chm")))
    grid = chm.grid
    standing = np.zeros(len(x), dtype=bool)
    r = int(np.ceil(CANOPY_REACH_M / grid.pixel_size))
    row, col = grid.pixel_of(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    for k in range(len(x)):
        window = chm.array[
            max(row[k] - r, 0) : max(row[k] + r + 1, 0), max(col[k] - r, 0) : max(col[k] + r + 1, 0)
        ]
        if window.size and np.isfinite(window).any():
            standing[k] = float(np.nanmax(window)) >= CANOPY_SHARE * float(height[k])
    return standing


def confirm_change(
    table: pd.DataFrame,
    source: Catalog,
    epoch_from: str,
    target: Catalog,
    epoch_to: str,
    trees_from: pd.DataFrame,
    trees_to: pd.DataFrame,
) -> pd.DataFrame:
    """The matched-tree table (after :func:`standgrid.comparison.coverage.mark_unobserved`)
    with its removed and new trees on co-observed ground checked against the other survey:
    a tree found from its stem against the other survey's points (:func:`stems_standing`),
    one found from its top alone against its canopy height model (:func:`canopy_standing`).
    Those still standing become ``missed`` (``missed_in``: ``from`` or ``to``, the survey
    that did not make them a tree)."""
    table = table.copy()
    table["missed_in"] = pd.Series([None] * len(table), dtype="string")
    on = table["co_observed"].to_numpy(dtype=bool)
    for status, catalog, epoch, side, trees, key in (
        ("removed", target, epoch_to, "to", trees_from, "tree_id_from"),
        ("new", source, epoch_from, "from", trees_to, "tree_id_to"),
    ):
        rows = np.flatnonzero((table["status"] == status).to_numpy() & on)
        if not len(rows):
            continue
        tree = trees.set_index("tree_id").loc[table[key].to_numpy()[rows]]
        by_top = (
            (tree["detected_by"] == "top").to_numpy(dtype=bool)
            if "detected_by" in tree.columns
            else np.zeros(len(rows), dtype=bool)
        )
        there = np.zeros(len(rows), dtype=bool)
        stem = ~by_top
        there[stem] = stems_standing(
            catalog,
            epoch,
            table["stem_x"].to_numpy(dtype=np.float64)[rows[stem]],
            table["stem_y"].to_numpy(dtype=np.float64)[rows[stem]],
            tree["dbh_m"].to_numpy(dtype=np.float64)[stem] / 2.0,
        )
        if by_top.any():
            top_x = tree["top_x"] if "top_x" in tree.columns else tree["x"]
            top_y = tree["top_y"] if "top_y" in tree.columns else tree["y"]
            there[by_top] = canopy_standing(
                catalog,
                epoch,
                top_x.to_numpy(dtype=np.float64)[by_top],
                top_y.to_numpy(dtype=np.float64)[by_top],
                tree["height_m"].to_numpy(dtype=np.float64)[by_top],
            )
        table.loc[table.index[rows[there]], "status"] = MISSED
        table.loc[table.index[rows[there]], "missed_in"] = side
    return table
