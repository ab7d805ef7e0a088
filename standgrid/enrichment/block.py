"""Enrich one buffered chunk: a pure function of its points (no files, no catalog).

Over the whole block (the owned cells plus the neighbours' points in the buffer): ground
(CSF), a terrain model (TIN of the thinned ground), heights above it, where the ground was
observed, and tree crowns, tops and stems. Kept for the owned cells only: their points'
classification, height and tree id, their raster pixels (DTM, CHM, density, observed, near
ground), the trees whose top stands in them and one :class:`StandSample` per cell. The
buffer must be wider than a crown and than twice the coverage closing radius, and the
chunk brings the lowest points of a ring out to the halo of every ground square it
touches (:func:`standgrid.enrichment.terrain.ground_reach`), so that the owned part is what one
computation over the whole epoch gives, whatever the chunk layout (docs/METRICS.md,
"Chunks").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.enrichment.stands import StandSample, measure_heights, stem_xy
from standgrid.rastergrid import RasterGrid

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.enrichment.chunks import ChunkPoints
    from standgrid.enrichment.options import EnrichOptions

GROUND = 2
OTHER = 1
#: The rasters a block returns, and their value where nothing was computed.
RASTERS = {"dtm": np.nan, "chm": np.nan, "density": 0.0, "observed": False, "near_ground": False}


@dataclass(frozen=True)
class BlockContext:
    """What a block needs besides its points: the epoch's raster lattice and the scheme."""

    grid: RasterGrid
    options: EnrichOptions
    #: grid cells are half-open squares (a top on an edge has one owner); Voronoi polygons
    #: are closed (a top on a shared edge goes to the first cell)
    half_open: bool
    cell_size: float


@dataclass
class BlockResult:
    """What one chunk gives back: fields per block row (written into its tiles by the
    engine, not shipped), raster windows on ``window``, trees, and per-cell samples."""

    window: RasterGrid
    rasters: dict[str, NDArray[Any]]
    trees: pd.DataFrame
    samples: list[StandSample]
    fields: dict[str, NDArray[Any]] = field(default_factory=dict)


def enrich_block(points: ChunkPoints, context: BlockContext) -> BlockResult:
    """Ground, heights, coverage, trees and rasters of one chunk (see the module doc)."""
    from standgrid.enrichment.coverage import cells_mask, coverage_from_hits
    from standgrid.enrichment.rasters import chm_from_pixels, density_from_pixels, pixel_counts
    from standgrid.enrichment.terrain import classify_terrain

    chunk, xyz, options = points.chunk, points.xyz, context.options
    buffered = _window(context.grid, chunk.buffered_bounds)
    core = _window(context.grid, chunk.bounds)
    terrain = classify_terrain(
        xyz,
        buffered,
        lattice=(context.grid.x0, context.grid.y0),
        cloth_resolution=options.cloth_resolution,
        rigidness=options.rigidness,
        source=chunk.cells[0].tile,
        ring=points.ring_xyz,
    )
    ground, dtm, hag = terrain.ground, terrain.dtm, terrain.heights
    pixels = terrain.pixels  # each point's pixel on the buffered window
    polygons = [c.polygon for c in (*chunk.cells, *chunk.neighbours)]
    hits = pixel_counts(pixels[ground], buffered)
    # a cell without ground in it or within the buffer has no terrain to measure from
    no_ground = [not hits[_slices(buffered, c.bounds, chunk.buffer)].any() for c in chunk.cells]
    coverage = coverage_from_hits(
        hits, buffered, cells_mask(buffered, polygons), closing_radius=options.coverage_closing_m
    )
    for rows, empty in zip(points.cell_rows, no_ground, strict=True):
        if empty:  # heights there would come from a distant terrain
            hag[rows] = np.nan

    trees, tree_ids = _trees(points, hag, no_ground, context)
    if len(trees):
        trees["observed"] = coverage.observed_at(*stem_xy(trees))

    # rasters over the whole block (a pixel's CHM fill looks at its neighbours, a Voronoi
    # edge pixel holds points of two cells), kept on the chunk's core window; the CHM of
    # the points with a height
    rasters = {
        "dtm": _crop(dtm, buffered, core),
        "chm": _crop(chm_from_pixels(pixels, hag, buffered), buffered, core),
        "density": _crop(density_from_pixels(pixels, buffered), buffered, core),
        "observed": _crop(coverage.observed, buffered, core),
        "near_ground": _crop(coverage.near_ground, buffered, core),
    }
    samples = []
    for cell, rows, empty in zip(chunk.cells, points.cell_rows, no_ground, strict=True):
        polygon = cell.polygon
        on_observed = coverage.observed_in(pixels[rows])
        samples.append(
            StandSample(
                stand_id=cell.cell_id,
                level=0,
                cell_size=context.cell_size,
                area_m2=float(polygon.area),
                observed_m2=coverage.observed_m2(polygon),
                n_points=rows.stop - rows.start,
                heights=hag[rows][on_observed],
                trees=trees.iloc[0:0],
                no_ground=empty,
            )
        )
    # sorted here (on the worker): a coarser stand merges its cells' runs
    measure_heights(samples, height_break=options.height_break, sort_heights=True)
    rule = options.coverage_rule
    for cell, sample in zip(chunk.cells, samples, strict=True):
        if cell.stand_id is None or not sample.measured(rule):
            sample.release_heights()  # only a coarser stand of measured cells needs them
    fields: dict[str, NDArray[Any]] = {
        "classification": np.where(ground, np.uint8(GROUND), np.uint8(OTHER)),
        "height_above_ground": hag,
        "tree_id": tree_ids,
    }
    return BlockResult(core, rasters, trees, samples, fields)


def _trees(
    points: ChunkPoints, hag: NDArray[np.float32], no_ground: list[bool], context: BlockContext
) -> tuple[pd.DataFrame, NDArray[np.int64]]:
    """Trees whose top stands in an owned cell with ground (tagged with its cell and stand),
    and every block point's tree id."""
    import shapely

    from standgrid.enrichment.trees import segment_trees

    chunk, options = points.chunk, context.options
    segmentation = segment_trees(
        points.xyz,
        hag.astype(np.float64),
        pixel_size=options.tree_pixel_size,
        min_height=options.tree_min_height,
        keep_bounds=chunk.bounds,
    )
    tree_ids = segmentation.point_tree_ids()
    for rows, empty in zip(points.cell_rows, no_ground, strict=True):
        if empty:
            tree_ids[rows] = 0
    table = segmentation.table
    tx, ty = table["x"].to_numpy(), table["y"].to_numpy()
    owner = np.full(len(table), -1, dtype=np.int64)
    for k, (cell, empty) in enumerate(zip(chunk.cells, no_ground, strict=True)):
        if context.half_open:
            xmin, ymin, xmax, ymax = cell.bounds
            inside = (tx >= xmin) & (tx < xmax) & (ty >= ymin) & (ty < ymax)
        else:
            inside = shapely.intersects_xy(cell.polygon, tx, ty)
        hit = inside & (owner == -1)
        owner[hit] = k if not empty else -2  # -2: in a cell without ground, claimed by none
    keep = owner >= 0
    owned = table[keep].reset_index(drop=True)
    owned.insert(0, "cell_id", [chunk.cells[k].cell_id for k in owner[keep]])
    stands = [chunk.cells[k].stand_id for k in owner[keep]]
    if chunk.cells and chunk.cells[0].stand_id is not None:
        owned.insert(1, "stand_id", stands)
    return owned, tree_ids.astype(np.int64, copy=False)


def _window(grid: RasterGrid, bounds: tuple[float, float, float, float]) -> RasterGrid:
    """The pixels of ``grid``'s lattice covering ``bounds`` (may reach beyond ``grid``)."""
    return grid.window_grid(grid.window(bounds, clip=False))


def _slices(
    grid: RasterGrid, bounds: tuple[float, float, float, float], margin: float
) -> tuple[slice, slice]:
    """The array slices of ``grid`` covering ``bounds`` grown by ``margin``, clipped."""
    xmin, ymin, xmax, ymax = bounds
    sub = _window(grid, (xmin - margin, ymin - margin, xmax + margin, ymax + margin))
    ps = grid.pixel_size
    i0 = round((sub.x0 - grid.x0) / ps)
    j0 = round((sub.y0 - grid.y0) / ps)
    top = grid.nrows - (j0 + sub.nrows)
    rows = slice(max(top, 0), max(top + sub.nrows, 0))
    return rows, slice(max(i0, 0), max(i0 + sub.ncols, 0))


def _crop(array: NDArray[Any], outer: RasterGrid, inner: RasterGrid) -> NDArray[Any]:
    """The part of ``array`` (on ``outer``) that ``inner`` covers (inner lies within outer)."""
    ps = outer.pixel_size
    i0 = round((inner.x0 - outer.x0) / ps)
    j0 = round((inner.y0 - outer.y0) / ps)
    top = outer.nrows - (j0 + inner.nrows)
    return array[top : top + inner.nrows, i0 : i0 + inner.ncols].copy()


def paste(
    target: NDArray[Any], grid: RasterGrid, window: RasterGrid, values: NDArray[Any], mask: Any
) -> None:
    """Copy ``values`` (on ``window``) into ``target`` (on ``grid``) where ``mask`` is set,
    clipped to ``grid``."""
    ps = grid.pixel_size
    i0 = round((window.x0 - grid.x0) / ps)
    j0 = round((window.y0 - grid.y0) / ps)
    top = grid.nrows - (j0 + window.nrows)
    r0, c0 = max(top, 0), max(i0, 0)
    r1, c1 = min(top + window.nrows, grid.nrows), min(i0 + window.ncols, grid.ncols)
    if r1 <= r0 or c1 <= c0:
        return
    src = (slice(r0 - top, r1 - top), slice(c0 - i0, c1 - i0))
    dst = target[r0:r1, c0:c1]
    keep = mask[src]
    dst[keep] = values[src][keep]
