"""Individual trees: stems first, crowns grown from them, canopy tops where no stem is seen.

Points already height-normalised (``heights`` = height above ground):

1. **stems** (:mod:`.stems`): vertical chains of circles fitted in thin slices from 0.7 m to
   3.4 m; every stem is a tree (overstorey, understorey, dead snags), its DBH measured;
2. **canopy tops**: a canopy height model (CHM) of the points above ``min_height`` at
   ``pixel_size``, lightly smoothed (3x3 Gaussian), its local maxima within a
   height-dependent circular window (lidR ``lmf``, diameter ``2 + 0.05 h`` m, 2-6 m) and a
   marker-controlled watershed of the inverted CHM (scikit-image), a pixel kept only while
   it is at least ``crown_fraction`` of its top's height;
3. **tops on stems** (:func:`_tops_of_stems`): each top goes to the stem it stands over,
   the stoutest, whose crown grows into it (``detected_by = both``); a top no stem carries
   is a tree of its own (``detected_by = top``: airborne scans, stems hidden from a ground
   robot); stems without a top of their own (understorey under a crown, snags) are
   ``detected_by = stem``;
4. **crowns** (:mod:`.crowns`): every point goes to the tree it is nearest to along the
   vegetation (directed shortest paths through a voxel graph from every trunk and apex,
   dear going down), so each tree's height is its own top and a small tree under a big
   crown keeps its own height.

A tree stands where its stem is at breast height (``x``, ``y`` = ``stem_x``, ``stem_y``),
or under its top when no stem was seen; its top is its highest point (``top_x``, ``top_y``,
``height_m``). Its ``tree_id`` is derived from where it stands at 0.1 m
(:func:`tree_id_from_xy`), so the same tree found in two overlapping processing blocks has
the same id. Process blocks with a halo wider than a crown and keep a tree in the block that
contains it (``keep_bounds``; half-open, like the stand cells).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from standgrid.enrichment.crowns import CrownOptions, VoxelGraph
from standgrid.enrichment.ground import PointsLike, as_xyz
from standgrid.enrichment.rasters import chm
from standgrid.errors import EnrichError
from standgrid.features.circles import (
    CircleFit,
    fit_circle,
    fit_circles,
    kasa_circle,
    link_clusters,
)
from standgrid.features.stems import StemOptions, StemSet, empty_stems, find_stems, stem_points
from standgrid.rastergrid import RasterGrid

__all__ = [
    "TREE_COLUMNS",
    "CircleFit",
    "TreeSegmentation",
    "default_window",
    "fit_circle",
    "fit_circles",
    "kasa_circle",
    "link_clusters",
    "segment_trees",
    "tree_id_from_xy",
    "xy_from_tree_id",
]

ID_RESOLUTION_M = 0.1
#: Each canopy point also marks a disc of this radius in the CHM (lidR's ``subcircle``): a
#: pit-free surface, so sparse crowns do not split into several tops.
CHM_SUBCIRCLE_M = 0.2
#: With ``keep_bounds``, stems are looked for this far around the block's own area: a stem
#: there may grow into the crowns above the block's own points.
STEM_SEARCH_MARGIN_M = 8.0
#: A stem carries a canopy top at most this many times its DBH above breast height (a
#: slenderness h/d of 150: understorey stems under a crown whose own stem was not seen do
#: not take it over).
MAX_SLENDERNESS = 150.0
BREAST_HEIGHT_M = 1.3
#: Open air (m) between a trunk's top and a crown over it that costs a stem as much as
#: leaving the crown unpaired (a snag under another tree's crown).
CROWN_GAP_SCALE_M = 10.0
#: An apex the CHM missed is looked for this far (m) from a stem's axis.
APEX_REACH_M = 1.5
#: The highest points over a stem tried as its apex.
APEX_TRIES = 50
#: A top-only tree's DBH reason names a stem fit rejected this close to it (m).
REJECTED_FIT_REACH_M = 1.0
_X_OFFSET = 1 << 30
_Y_OFFSET = 1 << 31

REASON_NO_STEM = "no stem points at 1.3 m near the tree"
#: How a tree was found (the ``detected_by`` column).
STEM, BOTH, TOP = "stem", "both", "top"
TREE_COLUMNS = [
    "tree_id",
    "x",
    "y",
    "z_ground",
    "height_m",
    "top_x",
    "top_y",
    "crown_area_m2",
    "n_points",
    "detected_by",
    "dbh_m",
    "dbh_se_m",
    "dbh_reason",
    "stem_x",
    "stem_y",
    "dbh_rmse_m",
    "dbh_n_points",
    "dbh_arc_deg",
    "lean_deg",
    "stem_low_m",
    "stem_high_m",
    "owned",
    "crown",
]


def tree_id_from_xy(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.int64]:
    """Stable int64 id of a tree position: its x, y rounded to 0.1 m, packed as
    ``(round(x/0.1) + 2**30) << 32 | (round(y/0.1) + 2**31)`` (|x| < 1.07e7 m, |y| < 2.1e7 m)."""
    ix = np.round(np.asarray(x, dtype=np.float64) / ID_RESOLUTION_M).astype(np.int64) + _X_OFFSET
    iy = np.round(np.asarray(y, dtype=np.float64) / ID_RESOLUTION_M).astype(np.int64) + _Y_OFFSET
    if (ix < 0).any() or (ix >= 1 << 31).any() or (iy < 0).any() or (iy >= 1 << 32).any():
        raise EnrichError("tree position out of the range a tree id can encode")
    return (ix << 32) | iy


def xy_from_tree_id(tree_id: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The 0.1 m tree position encoded in ``tree_id``."""
    ids = np.asarray(tree_id, dtype=np.int64)
    ix = (ids >> 32) - _X_OFFSET
    iy = (ids & 0xFFFFFFFF) - _Y_OFFSET
    return (ix * ID_RESOLUTION_M).astype(np.float64), (iy * ID_RESOLUTION_M).astype(np.float64)


def default_window(height: NDArray[np.float64]) -> NDArray[np.float64]:
    """Local-maximum window diameter (m) for a tree of ``height`` m: 2 + 0.05 h, in [2, 6].

    Narrow enough that a tree 3-4 m from a taller neighbour keeps its own top (tuned on the
    simulator's stands and the synthetic crowns of the tests)."""
    return np.clip(2.0 + 0.05 * np.asarray(height, dtype=np.float64), 2.0, 6.0)


@dataclass(frozen=True)
class TreeSegmentation:
    """``table``: one row per tree (columns :data:`TREE_COLUMNS`; ``crown`` holds shapely
    polygons of the owned trees); ``labels``: per point, 1-based row of ``table`` (uint32,
    0 = no tree)."""

    table: pd.DataFrame
    labels: NDArray[np.uint32]

    def owned(self) -> pd.DataFrame:
        """The trees standing in the block (``keep_bounds``) of the segmentation."""
        return self.table[self.table["owned"].to_numpy(dtype=bool)].reset_index(drop=True)

    def point_tree_ids(self) -> NDArray[np.int64]:
        """Per point, the stable ``tree_id`` of its tree (0 = none)."""
        ids = np.concatenate([[0], self.table["tree_id"].to_numpy(dtype=np.int64)])
        return ids[self.labels]


@dataclass(frozen=True)
class _Tops:
    """Canopy tops: the CHM lattice, its crown segments (0 = none), each kept segment's
    number and highest point (a row of the points), and each point's segment."""

    grid: RasterGrid
    crowns: NDArray[np.int64]
    seeds: NDArray[np.int64]
    top_rows: NDArray[np.int64]
    point_segment: NDArray[np.int64]


def segment_trees(
    points: PointsLike,
    heights: NDArray[np.floating],
    *,
    pixel_size: float = 0.5,
    min_height: float = 2.0,
    window: Callable[[NDArray[np.float64]], NDArray[np.float64]] = default_window,
    crown_fraction: float = 0.3,
    point_min_height: float = 0.5,
    keep_bounds: tuple[float, float, float, float] | None = None,
    stems: bool = True,
    stem_options: StemOptions | None = None,
    crown_options: CrownOptions | None = None,
) -> TreeSegmentation:
    """Trees in height-normalised points (``heights`` = height above ground; module doc).
    ``stems=False``: canopy tops only (the airborne recipe)."""
    xyz = as_xyz(points)
    h = np.asarray(heights, dtype=np.float64)
    if h.shape != (len(xyz),):
        raise EnrichError(f"{h.shape} heights for {len(xyz)} points")
    finite = np.isfinite(h)
    search = None
    if keep_bounds is not None:  # stems that can reach the block's own points
        x0, y0, x1, y1 = keep_bounds
        m = STEM_SEARCH_MARGIN_M
        search = (x0 - m, y0 - m, x1 + m, y1 + m)
    found = find_stems(xyz, h, within=search, options=stem_options) if stems else empty_stems()
    tops = _canopy_tops(xyz, h, finite, pixel_size, min_height, window, crown_fraction)

    # trees: the stems (numbered first), each with the canopy top it carries, then the tops
    # no stem carries; every tree grows its crown from its stem and its apex
    n_stems = len(found)
    graph = VoxelGraph(xyz, h, crown_options)
    # the trunks' voxels (a voxel centre is up to half a voxel's diagonal off its points)
    stem_voxels, stem_of = stem_points(
        graph.centres, graph.heights, found.table, widen=graph.voxel_size / math.sqrt(2)
    )
    stem_reach, _ = graph.reach(stem_voxels, stem_of)  # crowns grown from the stems alone
    trunk_top = np.full(n_stems, -np.inf)  # where each trunk was last seen
    np.maximum.at(trunk_top, stem_of, graph.heights[stem_voxels])
    stem_top = _tops_of_stems(found.table, tops, xyz, h, graph, stem_reach, trunk_top)
    top_tree = np.full(len(tops.seeds), -1, dtype=np.int64)
    top_tree[stem_top[stem_top >= 0]] = np.flatnonzero(stem_top >= 0)
    top_only = np.flatnonzero(
        (top_tree < 0) & ~_secondary_tops(tops, xyz, h, graph, stem_reach, stem_top)
    )
    top_tree[top_only] = n_stems + np.arange(len(top_only))
    # a stem carrying no canopy top may have one the CHM smoothed away (a sparse apex)
    lone = np.flatnonzero(stem_top < 0)
    apex = _apexes_over_stems(found.table.iloc[lone], tops, xyz, h, finite, min_height, window)
    has_apex = apex >= 0
    seeded = top_tree >= 0  # a secondary top is its tree's crown, no seed
    sources = np.concatenate(
        [stem_voxels, graph.voxels(tops.top_rows[seeded]), graph.voxels(apex[has_apex])]
    )
    source_trees = np.concatenate([stem_of, top_tree[seeded], lone[has_apex]])
    label = graph.labels(graph.reach(sources, source_trees)[0])
    label[~(finite & (h >= point_min_height))] = -1

    # a tree's top is its apex (the canopy top it carries), else its highest point; a stem
    # tree too short to be a tree (a stump, a shrub's stems) is dropped
    n_trees = n_stems + len(top_only)
    labelled = np.flatnonzero(label >= 0)
    if not len(labelled):
        return TreeSegmentation(_empty_table(), np.zeros(len(xyz), dtype=np.uint32))
    tree_of = label[labelled]
    highest = np.full(n_trees, -np.inf)
    np.maximum.at(highest, tree_of, h[labelled])
    at_top = labelled[h[labelled] >= highest[tree_of]]
    order = at_top[np.lexsort((xyz[at_top, 1], xyz[at_top, 0], label[at_top]))]
    first = np.concatenate([[True], label[order][1:] != label[order][:-1]])
    top_row = np.full(n_trees, -1, dtype=np.int64)
    top_row[label[order][first]] = order[first]
    top_row[top_tree[seeded]] = tops.top_rows[seeded]
    top_row[lone[has_apex]] = apex[has_apex]
    highest = np.where(top_row >= 0, h[np.maximum(top_row, 0)], highest)
    kept = (top_row >= 0) & (highest >= min_height)
    row_of_tree = np.zeros(n_trees, dtype=np.int64)  # 1-based table row, 0 = dropped
    row_of_tree[np.flatnonzero(kept)] = np.arange(1, int(kept.sum()) + 1)
    labels = np.zeros(len(xyz), dtype=np.uint32)
    labels[labelled] = row_of_tree[tree_of]

    carries_top = stem_top >= 0
    carries_top[lone[has_apex]] = True
    table = _table(xyz, h, found, carries_top, top_row, kept, labels, keep_bounds)
    owned = np.flatnonzero(table["owned"].to_numpy(dtype=bool))
    crowns: list[object] = [None] * len(table)
    for k, (polygon, area) in _footprints(
        xyz, h, labels, table, owned, pixel_size, crown_fraction
    ).items():
        crowns[k] = polygon
        table.loc[k, "crown_area_m2"] = area
    table["crown"] = crowns
    table["tree_id"] = _unique_ids(table)
    return TreeSegmentation(table[TREE_COLUMNS], labels)


def _empty_table() -> pd.DataFrame:
    table = pd.DataFrame({name: pd.Series(dtype=float) for name in TREE_COLUMNS})
    for column in ("tree_id", "n_points", "dbh_n_points"):
        table[column] = table[column].astype(np.int64)
    table["owned"] = table["owned"].astype(bool)
    for column in ("dbh_reason", "detected_by"):
        table[column] = table[column].astype("string")
    table["crown"] = table["crown"].astype(object)
    return table


def _canopy_tops(
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    finite: NDArray[np.bool_],
    pixel_size: float,
    min_height: float,
    window: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    crown_fraction: float,
) -> _Tops:
    """CHM local maxima and their watershed crowns (steps 3 of the module doc)."""
    from scipy import ndimage
    from skimage.measure import label as label_regions
    from skimage.segmentation import watershed

    canopy = finite & (h >= min_height)
    none = np.zeros(0, dtype=np.int64)
    if not canopy.any():
        grid = RasterGrid(0.0, 0.0, pixel_size, 1, 1)
        return _Tops(grid, np.zeros((1, 1), np.int64), none, none, np.zeros(len(xyz), np.int64))
    # a CHM on a lattice aligned to multiples of the pixel size (same pixels in every block)
    canopy_index = np.flatnonzero(canopy)
    canopy_xyz = xyz.take(canopy_index, axis=0)
    cx, cy = canopy_xyz[:, 0], canopy_xyz[:, 1]
    # with room for the sub-circles and the smoothing around the outermost points: a crown
    # at the data's edge is not clipped by a raster that ends where one block's points end
    margin = CHM_SUBCIRCLE_M + 2 * pixel_size
    grid = RasterGrid.covering(
        (cx.min() - margin, cy.min() - margin, cx.max() + margin, cy.max() + margin),
        origin=(0.0, 0.0),
        cell_size=pixel_size,
        pixel_size=pixel_size,
    )
    raw = chm(canopy_xyz, h[canopy_index], grid, fill_empty=True, subcircle=CHM_SUBCIRCLE_M)
    raw = np.nan_to_num(raw, nan=0.0).astype(np.float64)
    smooth = ndimage.gaussian_filter(raw, sigma=0.5, truncate=2.0)

    # tops: local maxima within a height-dependent circular window
    radius_px = np.maximum(np.round(window(smooth) / 2.0 / pixel_size).astype(np.int64), 1)
    is_top = np.zeros(smooth.shape, dtype=bool)
    candidate = smooth >= min_height
    for r in np.unique(radius_px[candidate]):
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        disc = xx * xx + yy * yy <= r * r
        local_max = ndimage.maximum_filter(smooth, footprint=disc, mode="constant", cval=0.0)
        use = candidate & (radius_px == r)
        is_top |= use & (smooth >= local_max)
    markers = label_regions(is_top, connectivity=2)  # a plateau of equal maxima is one top

    # crowns: watershed of the inverted CHM, cut where the canopy drops below the top
    crowns = watershed(-smooth, markers, mask=smooth >= min_height)
    n_seeds = int(markers.max())
    if n_seeds == 0:
        return _Tops(grid, crowns, none, none, np.zeros(len(xyz), np.int64))
    seed_height = ndimage.maximum(raw, labels=crowns, index=np.arange(1, n_seeds + 1))
    seed_height = np.concatenate([[0.0], np.asarray(seed_height, dtype=np.float64)])
    crowns[raw < crown_fraction * seed_height[crowns]] = 0

    # each point's crown segment by its pixel; a segment's top is its highest canopy point
    pixel, col = grid.pixel_of(xyz[:, 0], xyz[:, 1])
    outside = (pixel < 0) | (pixel >= grid.nrows) | (col < 0) | (col >= grid.ncols)
    pixel *= grid.ncols
    pixel += col
    # one lookup: the points outside the raster read the 0 appended after its pixels
    pixel[outside] = crowns.size
    del col, outside
    point_segment = np.append(crowns.ravel(), 0).astype(np.int64)[pixel]
    in_tree = (point_segment > 0) & canopy
    if not in_tree.any():
        return _Tops(grid, crowns, none, none, point_segment)
    idx = np.flatnonzero(in_tree)
    # highest point per crown; ties broken by x then y (deterministic across blocks): only
    # the points as high as their crown's highest are sorted
    crown_of, height_of = point_segment[idx], h[idx]
    highest = np.full(n_seeds + 1, -np.inf)
    np.maximum.at(highest, crown_of, height_of)
    at_top = height_of >= highest[crown_of]
    idx = idx[at_top]
    order = idx[np.lexsort((xyz[idx, 1], xyz[idx, 0], crown_of[at_top]))]
    seg = point_segment[order]
    first = np.concatenate([[True], seg[1:] != seg[:-1]])
    return _Tops(grid, crowns, seg[first], order[first], point_segment)


def _tops_of_stems(
    stems: pd.DataFrame,
    tops: _Tops,
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    graph: VoxelGraph,
    stem_reach: NDArray[np.int64],
    trunk_top: NDArray[np.float64],
) -> NDArray[np.int64]:
    """The canopy top (index into ``tops.seeds``) each stem carries, or -1.

    A stem can carry a top higher than its observed part if it is stout enough (height above
    breast height at most :data:`MAX_SLENDERNESS` times the DBH) and its axis, carried up,
    passes within ``reach = 1 m + 0.08 x height`` of the top, or it stands under the top's
    crown. Stems and tops are then paired one to one at the least total cost, each pair
    costing ``(offset / reach)^2``, plus 0.25 when the stem is not the one whose crown, grown
    through the vegetation from the trunks alone (``stem_reach``), reaches the apex first,
    plus ``1 - dbh / the stoutest candidate's``, plus ``(gap / 10 m)^2`` (at most 1) for
    the open air between where the trunk was last seen and the crown's lowest point over
    it, and each unpaired stem or top 1 (the optimal assignment of
    :mod:`standgrid.enrichment.identity`): a crown goes to the stem it grows from and stands
    over, the stoutest under it whose trunk runs into it; a small tree under a big crown
    and a snag under another tree's crown keep none."""
    from standgrid.enrichment.identity import solve_pairs

    n = len(stems)
    stem_top = np.full(n, -1, dtype=np.int64)
    if not n or not len(tops.seeds):
        return stem_top
    from scipy.spatial import cKDTree

    sx, sy = stems["stem_x"].to_numpy(), stems["stem_y"].to_numpy()
    ax, ay = stems["axis_dx"].to_numpy(), stems["axis_dy"].to_numpy()
    dbh, high = stems["dbh_m"].to_numpy(), stems["stem_high_m"].to_numpy()
    tx, ty, th = xyz[tops.top_rows, 0], xyz[tops.top_rows, 1], h[tops.top_rows]
    row, col = tops.grid.pixel_of(sx, sy)
    inside = (row >= 0) & (row < tops.grid.nrows) & (col >= 0) & (col < tops.grid.ncols)
    under = np.zeros(n, dtype=np.int64)  # the crown segment each stem's foot stands in
    under[inside] = tops.crowns[row[inside], col[inside]]
    reach_max = 1.0 + 0.08 * float(th.max())
    lean = float(np.hypot(ax, ay).max()) * float(th.max())
    near = cKDTree(np.column_stack([sx, sy])).query_ball_point(
        np.column_stack([tx, ty]), reach_max + lean
    )
    counts = np.fromiter((len(v) for v in near), np.int64, len(near))
    top = np.repeat(np.arange(len(near)), counts)
    stem = np.fromiter((v for n_ in near for v in n_), np.int64, int(counts.sum()))
    dz = th[top] - BREAST_HEIGHT_M
    off = np.hypot(tx[top] - sx[stem] - ax[stem] * dz, ty[top] - sy[stem] - ay[stem] * dz)
    reach = 1.0 + 0.08 * th[top]
    ok = (th[top] > high[stem]) & (dz <= MAX_SLENDERNESS * dbh[stem])
    ok &= (off <= reach) | (under[stem] == tops.seeds[top])
    top, stem, off, reach = top[ok], stem[ok], off[ok], reach[ok]
    grown_into = stem_reach[graph.voxels(tops.top_rows)][top] == stem
    stoutest = np.zeros(len(tops.seeds))
    np.maximum.at(stoutest, top, dbh[stem])
    thinner = 1.0 - dbh[stem] / np.maximum(stoutest[top], 1e-9)
    gap = _crown_gaps(stems, trunk_top, stem, top, tops, graph)
    cost = np.minimum(off / reach, 1.0) ** 2 + np.where(grown_into, 0.0, 0.25) + thinner
    cost += np.minimum(gap / CROWN_GAP_SCALE_M, 1.0) ** 2
    paired_stem, paired_top = solve_pairs(n, len(tops.seeds), stem, top, cost)
    stem_top[paired_stem] = paired_top
    return stem_top


def _crown_gaps(
    stems: pd.DataFrame,
    trunk_top: NDArray[np.float64],
    stem: NDArray[np.int64],
    top: NDArray[np.int64],
    tops: _Tops,
    graph: VoxelGraph,
) -> NDArray[np.float64]:
    """For each (stem, top) pair, the widest open air (m) in the column over the stem's
    trunk top: the largest vertical gap between the voxels of the top's crown segment within
    :data:`APEX_REACH_M` of the stem's axis, from the trunk's top up (a live tree's trunk
    runs on into its crown; a snag ends in open air under another tree's crown);
    :data:`CROWN_GAP_SCALE_M` when no such voxel is over the stem."""
    gaps = np.zeros(len(stem))
    if not len(stem):
        return gaps
    # every voxel's crown segment (0: none), by its column on the CHM's lattice
    row, col = tops.grid.pixel_of(graph.centres[:, 0], graph.centres[:, 1])
    inside = (row >= 0) & (row < tops.grid.nrows) & (col >= 0) & (col < tops.grid.ncols)
    segment = np.zeros(len(graph.centres), dtype=np.int64)
    segment[inside] = tops.crowns[row[inside], col[inside]]
    wanted = np.isin(segment, tops.seeds[top])
    rows = np.flatnonzero(wanted)
    rows = rows[np.argsort(segment[rows], kind="stable")]
    seg = segment[rows]
    sx, sy = stems["stem_x"].to_numpy(), stems["stem_y"].to_numpy()
    ax, ay = stems["axis_dx"].to_numpy(), stems["axis_dy"].to_numpy()
    vx, vy, vh = graph.centres[rows, 0], graph.centres[rows, 1], graph.heights[rows]
    for k, (s_k, t_k) in enumerate(zip(stem.tolist(), top.tolist(), strict=True)):
        seed = tops.seeds[t_k]
        a, b = np.searchsorted(seg, seed), np.searchsorted(seg, seed, "right")
        dz = vh[a:b] - BREAST_HEIGHT_M
        off = np.hypot(vx[a:b] - sx[s_k] - ax[s_k] * dz, vy[a:b] - sy[s_k] - ay[s_k] * dz)
        column = np.sort(vh[a:b][(off <= APEX_REACH_M) & (vh[a:b] >= trunk_top[s_k])])
        # the widest empty layer between the trunk's top and the crown's highest voxel
        levels = np.concatenate([[trunk_top[s_k]], column])
        gaps[k] = float(np.diff(levels).max()) if len(column) else CROWN_GAP_SCALE_M
    return gaps


def _secondary_tops(
    tops: _Tops,
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    graph: VoxelGraph,
    stem_reach: NDArray[np.int64],
    stem_top: NDArray[np.int64],
) -> NDArray[np.bool_]:
    """The canopy tops no stem carries that are a lower maximum of another tree's crown: the
    crown of the stem that reaches the apex first (grown from the trunks alone) carries a
    higher top within ``1 m + 0.08 x its height`` of it. A tree whose stem was not seen keeps
    its top where no such stem's crown reaches it first."""
    secondary = np.zeros(len(tops.seeds), dtype=bool)
    if not len(tops.seeds) or not len(stem_top):
        return secondary
    carried = np.zeros(len(tops.seeds), dtype=bool)
    carried[stem_top[stem_top >= 0]] = True
    reacher = stem_reach[graph.voxels(tops.top_rows)]
    own = np.where(reacher >= 0, stem_top[np.maximum(reacher, 0)], -1)
    k = np.flatnonzero(~carried & (own >= 0))
    main = own[k]
    a, b = tops.top_rows[k], tops.top_rows[main]
    near = np.hypot(xyz[a, 0] - xyz[b, 0], xyz[a, 1] - xyz[b, 1]) <= 1.0 + 0.08 * h[b]
    secondary[k[near & (h[a] < h[b])]] = True
    return secondary


def _apexes_over_stems(
    stems: pd.DataFrame,
    tops: _Tops,
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    finite: NDArray[np.bool_],
    min_height: float,
    window: Callable[[NDArray[np.float64]], NDArray[np.float64]],
) -> NDArray[np.int64]:
    """Per stem, the row of the apex above it that the canopy height model missed, or -1.

    The apex is the highest point within :data:`APEX_REACH_M` of the stem's axis carried up
    to it, above the stem's observed part, that is a local maximum of the points (the
    highest within half the window at its height, as lidR's ``lmf`` on points) and not
    within that distance of a top already found; the stem must be stout enough to carry
    it (:data:`MAX_SLENDERNESS`). A small tree under another's crown gets none: the
    highest point over it lies on that crown's flank, below its top."""
    apex = np.full(len(stems), -1, dtype=np.int64)
    if not len(stems):
        return apex
    from scipy.spatial import cKDTree

    sx, sy = stems["stem_x"].to_numpy(), stems["stem_y"].to_numpy()
    ax, ay = stems["axis_dx"].to_numpy(), stems["axis_dy"].to_numpy()
    dbh, high = stems["dbh_m"].to_numpy(), stems["stem_high_m"].to_numpy()
    # the canopy points that can be an apex over these stems, or decide one (its window)
    lean_reach = float(np.nanmax(h, initial=0.0)) * np.hypot(ax, ay)
    margin = float((APEX_REACH_M + lean_reach).max()) + float(window(np.array([np.inf]))[0])
    x, y = xyz[:, 0], xyz[:, 1]
    canopy = np.flatnonzero(
        finite
        & (h >= min_height)
        & (x >= sx.min() - margin)
        & (x <= sx.max() + margin)
        & (y >= sy.min() - margin)
        & (y <= sy.max() + margin)
    )
    if len(canopy):
        dist, _ = cKDTree(np.column_stack([sx, sy])).query(
            xyz[canopy, :2], distance_upper_bound=margin
        )
        canopy = canopy[np.isfinite(dist)]
    if not len(canopy):
        return apex
    index = cKDTree(xyz[canopy, :2])
    top_xy = xyz[tops.top_rows, :2]
    found_tops = cKDTree(top_xy) if len(top_xy) else None
    near = index.query_ball_point(np.column_stack([sx, sy]), APEX_REACH_M + lean_reach)
    for k, rows in enumerate(near):
        cand = canopy[np.asarray(rows, dtype=np.int64)]
        cand = cand[(h[cand] > high[k]) & (h[cand] - BREAST_HEIGHT_M <= MAX_SLENDERNESS * dbh[k])]
        dz = h[cand] - BREAST_HEIGHT_M
        off = np.hypot(xyz[cand, 0] - sx[k] - ax[k] * dz, xyz[cand, 1] - sy[k] - ay[k] * dz)
        cand = cand[off <= APEX_REACH_M]
        if not len(cand):
            continue
        # the highest of them that is a local maximum (a higher point may be a neighbour's
        # crown leaning over)
        for best in cand[np.lexsort((xyz[cand, 1], xyz[cand, 0], -h[cand]))[:APEX_TRIES]]:
            radius = float(window(np.array([h[best]]))[0]) / 2.0
            # over a stem, a local maximum within the apex reach: the stem says where the
            # tree is, so a neighbour's crown touching this one just beyond is no flank
            flank = min(radius, APEX_REACH_M)
            around = canopy[index.query_ball_point(xyz[best, :2], flank)]
            if (h[around] > h[best]).any():
                continue  # on a crown's flank
            if found_tops is not None and found_tops.query_ball_point(xyz[best, :2], radius):
                break  # the top there is another tree's
            apex[k] = best
            break
    return apex


def _table(
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    found: StemSet,
    has_top: NDArray[np.bool_],
    top_row: NDArray[np.int64],
    kept: NDArray[np.bool_],
    labels: NDArray[np.uint32],
    keep_bounds: tuple[float, float, float, float] | None,
) -> pd.DataFrame:
    """One row per kept tree: the stem trees, then the top-only trees."""
    stems = found.table
    n_stems = len(stems)
    rows = top_row[kept]
    n = len(rows)
    is_stem = np.flatnonzero(kept) < n_stems
    stem_rows = np.flatnonzero(kept[:n_stems])
    top_x, top_y = xyz[rows, 0], xyz[rows, 1]
    x, y = top_x.copy(), top_y.copy()
    x[is_stem] = stems["stem_x"].to_numpy()[stem_rows]
    y[is_stem] = stems["stem_y"].to_numpy()[stem_rows]
    table = pd.DataFrame(
        {
            "tree_id": np.zeros(n, dtype=np.int64),
            "x": x,
            "y": y,
            "z_ground": xyz[rows, 2] - h[rows],
            "height_m": h[rows],
            "top_x": top_x,
            "top_y": top_y,
            "crown_area_m2": np.nan,
            "n_points": np.bincount(labels, minlength=n + 1)[1:],
        }
    )
    detected = np.full(n, TOP, dtype=object)
    detected[is_stem] = np.where(has_top[stem_rows], BOTH, STEM)
    table["detected_by"] = pd.array(detected, dtype="string")
    for column in (
        "dbh_m",
        "dbh_se_m",
        "stem_x",
        "stem_y",
        "dbh_rmse_m",
        "dbh_arc_deg",
        "lean_deg",
        "stem_low_m",
        "stem_high_m",
    ):
        values = np.full(n, np.nan)
        values[is_stem] = stems[column].to_numpy(dtype=np.float64)[stem_rows]
        table[column] = values
    n_used = np.zeros(n, dtype=np.int64)
    n_used[is_stem] = stems["dbh_n_points"].to_numpy(dtype=np.int64)[stem_rows]
    table["dbh_n_points"] = n_used
    reasons = np.full(n, None, dtype=object)
    reasons[~is_stem] = _no_dbh_reasons(found.rejected, top_x[~is_stem], top_y[~is_stem])
    table["dbh_reason"] = pd.array(reasons, dtype="string")
    if keep_bounds is None:
        table["owned"] = True
    else:
        x0, y0, x1, y1 = keep_bounds
        table["owned"] = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    return table


def _no_dbh_reasons(
    rejected: pd.DataFrame, x: NDArray[np.float64], y: NDArray[np.float64]
) -> list[str]:
    """Why a top-only tree has no DBH: the nearest rejected breast-height fit within
    :data:`REJECTED_FIT_REACH_M` of its top, else no stem points."""
    reasons = [REASON_NO_STEM] * len(x)
    if not len(rejected) or not len(x):
        return reasons
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(rejected[["x", "y"]].to_numpy()).query(np.column_stack([x, y]))
    why = rejected["reason"].to_numpy(dtype=object)
    for k in np.flatnonzero(dist <= REJECTED_FIT_REACH_M):
        reasons[k] = f"stem fit rejected: {why[nearest[k]]}"
    return reasons


def _unique_ids(table: pd.DataFrame) -> NDArray[np.int64]:
    """Tree ids from where the trees stand; a tree on another's 0.1 m position (a top over
    another tree's stem) moves north by 0.1 m steps until free (stem trees come first)."""
    ids = tree_id_from_xy(table["x"].to_numpy(), table["y"].to_numpy())
    seen: set[int] = set()
    for k, value in enumerate(ids.tolist()):
        while value in seen:
            value += 1
        seen.add(value)
        ids[k] = value
    return ids


def _footprints(
    xyz: NDArray[np.float64],
    h: NDArray[np.float64],
    labels: NDArray[np.uint32],
    table: pd.DataFrame,
    rows: NDArray[np.int64],
    pixel_size: float,
    crown_fraction: float,
) -> dict[int, tuple[Any, float]]:
    """Crown outline and area of the stem trees ``rows`` of ``table``: the pixels (on the
    CHM's lattice) of their points at least ``crown_fraction`` of their height up, gaps of a
    pixel closed."""
    from rasterio import features
    from scipy import ndimage
    from shapely.geometry import shape
    from shapely.ops import unary_union

    out: dict[int, tuple[Any, float]] = {}
    if not len(rows):
        return out
    wanted = np.zeros(len(table) + 1, dtype=bool)
    wanted[rows + 1] = True
    tree_height = np.concatenate([[np.inf], table["height_m"].to_numpy(dtype=np.float64)])
    pick = np.flatnonzero(wanted[labels])
    pick = pick[h[pick] >= crown_fraction * tree_height[labels[pick]]]
    tree = labels[pick].astype(np.int64) - 1
    order = np.argsort(tree, kind="stable")
    pick, tree = pick[order], tree[order]
    starts = np.flatnonzero(np.concatenate([[True], tree[1:] != tree[:-1]]))
    ends = np.append(starts[1:], len(tree))
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        k = int(tree[a])
        pts = xyz[pick[a:b]]
        col = np.floor(pts[:, 0] / pixel_size).astype(np.int64)
        row = np.floor(pts[:, 1] / pixel_size).astype(np.int64)
        c0, r0 = col.min() - 1, row.min() - 1
        mask = np.zeros((row.max() - r0 + 2, col.max() - c0 + 2), dtype=bool)
        mask[row.max() + 1 - row, col - c0] = True  # rows from the north
        mask = ndimage.binary_closing(mask, structure=np.ones((3, 3), bool), border_value=0)
        mask |= ndimage.binary_fill_holes(mask)
        transform = RasterGrid(
            c0 * pixel_size, r0 * pixel_size, pixel_size, mask.shape[1], mask.shape[0]
        ).transform
        shapes = features.shapes(mask.astype(np.uint8), mask=mask, transform=transform)
        polygon = unary_union([shape(g) for g, _ in shapes])
        out[k] = (polygon, float(mask.sum()) * pixel_size**2)
    return out
