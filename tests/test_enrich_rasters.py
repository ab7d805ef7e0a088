"""Rasters aligned to the stand grid: DTM, CHM, density, height above ground, COG output."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import rasterio

from standgrid.crs import CRS
from standgrid.enrichment.ground import classify_ground
from standgrid.enrichment.rasters import (
    chm,
    chm_from_pixels,
    density,
    density_from_pixels,
    dtm_from_ground,
    height_above_ground,
    heights_and_pixels,
    pixel_counts,
)
from standgrid.errors import EnrichError, GridError, OutputExistsError
from standgrid.geotiff import read_raster, write_cog
from standgrid.rastergrid import RasterGrid
from tests.conftest import real_file

ORIGIN = (600_000.5, 5_100_000.25)


def test_grid_is_aligned_to_the_stand_grid() -> None:
    a = RasterGrid.covering(
        (600_013.0, 5_100_007.0, 600_051.0, 5_100_033.0),
        origin=ORIGIN,
        cell_size=20.0,
        pixel_size=1.0,
    )
    # extent = whole stand cells containing the bounds
    assert (a.x0 - ORIGIN[0]) % 20.0 == 0 and (a.y0 - ORIGIN[1]) % 20.0 == 0
    assert a.x0 <= 600_013.0 < 600_051.0 < a.bounds[2] and a.bounds[2] - a.x0 == 60.0
    assert a.shape == (40, 60)
    # another epoch with other bounds: pixel edges coincide exactly
    b = RasterGrid.covering(
        (600_071.3, 5_100_102.0, 600_090.0, 5_100_110.0),
        origin=ORIGIN,
        cell_size=20.0,
        pixel_size=0.5,
    )
    assert ((b.x0 - a.x0) / 0.5) % 1 == 0 and ((b.y0 - a.y0) / 0.5) % 1 == 0
    # without snapping: pixel multiples of the origin only
    c = RasterGrid.covering(
        (600_013.2, 5_100_007.9, 600_014.0, 5_100_008.1),
        origin=ORIGIN,
        cell_size=20.0,
        pixel_size=1.0,
        snap_to_cells=False,
    )
    assert c.x0 == 600_012.5 and c.y0 == 5_100_007.25 and c.shape == (1, 2)
    with pytest.raises(GridError):
        RasterGrid.covering((0, 0, 1, 1), origin=(0.0, 0.0), cell_size=20.0, pixel_size=3.0)
    # pixel_of / centres agree; row 0 is the north row
    cx, cy = a.centers()
    row, col = a.pixel_of(cx.ravel(), cy.ravel())
    assert (row.reshape(a.shape) == np.arange(a.nrows)[:, None]).all()
    assert (col.reshape(a.shape) == np.arange(a.ncols)[None, :]).all()
    assert cy[0, 0] > cy[-1, 0]


def plane(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 412.0 + 0.3 * (x - ORIGIN[0]) - 0.2 * (y - ORIGIN[1])


def test_dtm_and_heights_are_exact_on_a_plane() -> None:
    rng = np.random.default_rng(0)
    gx = rng.uniform(ORIGIN[0], ORIGIN[0] + 40, 3000)
    gy = rng.uniform(ORIGIN[1], ORIGIN[1] + 40, 3000)
    grid = RasterGrid.covering(
        (gx.min(), gy.min(), gx.max(), gy.max()), origin=ORIGIN, cell_size=20.0
    )
    dtm = dtm_from_ground(np.column_stack([gx, gy, plane(gx, gy)]), grid)
    cx, cy = grid.centers()
    assert dtm.dtype == np.float32 and dtm.shape == grid.shape
    inside = (cx > gx.min() + 2) & (cx < gx.max() - 2) & (cy > gy.min() + 2) & (cy < gy.max() - 2)
    assert np.abs(dtm - plane(cx, cy))[inside].max() < 1e-3  # TIN of a plane is the plane
    assert np.isfinite(dtm).all()  # outside the hull: nearest ground point
    px = rng.uniform(ORIGIN[0] + 1, ORIGIN[0] + 39, 500)
    py = rng.uniform(ORIGIN[1] + 1, ORIGIN[1] + 39, 500)
    true_h = rng.uniform(0, 30, 500)
    h = height_above_ground(np.column_stack([px, py, plane(px, py) + true_h]), dtm, grid)
    assert h.dtype == np.float32 and np.abs(h - true_h).max() < 2e-3
    with pytest.raises(EnrichError):
        height_above_ground(np.array([[ORIGIN[0] - 100, ORIGIN[1], 0.0]]), dtm, grid)
    with pytest.raises(EnrichError):
        dtm_from_ground(np.empty((0, 3)), grid)


def test_chm_and_density_by_hand() -> None:
    grid = RasterGrid(x0=0.0, y0=0.0, pixel_size=1.0, ncols=3, nrows=2)
    xyz = np.array(
        [[0.5, 1.5, 0], [0.2, 1.1, 0], [2.5, 0.5, 0], [2.7, 0.1, 0], [2.1, 0.9, 0]], float
    )
    heights = np.array([3.0, 7.0, -0.2, 1.0, 0.5])
    raw = chm(xyz, heights, grid, fill_empty=False)
    expected = np.array([[7.0, np.nan, np.nan], [np.nan, np.nan, 1.0]])
    assert np.array_equal(raw, expected.astype(np.float32), equal_nan=True)
    filled = chm(xyz, heights, grid)  # no empty pixel has >= 6 of 8 non-empty neighbours
    assert np.array_equal(filled, raw, equal_nan=True)
    inflated = chm(xyz, heights, grid, subcircle=0.6, fill_empty=False)
    # each point also lands 0.6 m away in 8 directions: (0.5, 1.5) reaches the middle
    # pixel east, (0.2, 1.1) reaches the south-west pixel diagonally
    assert inflated[0, 1] == 3.0 and inflated[1, 0] == 7.0 and inflated[1, 1] == 0.5
    dens = density(xyz, grid)
    assert dens[0, 0] == 2 and dens[1, 2] == 3 and dens.sum() == 5
    quarter = RasterGrid(x0=0.0, y0=0.0, pixel_size=0.5, ncols=6, nrows=4)
    assert density(xyz, quarter).sum() * 0.25 == pytest.approx(5)
    with pytest.raises(EnrichError):
        density(np.array([[5.0, 5.0, 0.0]]), grid)


def test_pixels_found_with_the_heights_are_each_points_pixel_and_serve_the_rasters() -> None:
    grid = RasterGrid(x0=ORIGIN[0], y0=ORIGIN[1], pixel_size=0.5, ncols=90, nrows=70)
    rng = np.random.default_rng(7)
    n = 200_000  # several blocks of the element-wise arithmetic
    x = ORIGIN[0] + rng.uniform(0, 45, n)
    y = ORIGIN[1] + rng.uniform(0, 35, n)
    x[:500] = ORIGIN[0] + rng.integers(0, 90, 500) * 0.5  # on pixel edges
    y[:500] = ORIGIN[1] + rng.integers(0, 70, 500) * 0.5
    xyz = np.column_stack([x, y, rng.uniform(400, 430, n)])
    dtm = rng.uniform(400, 410, grid.shape).astype(np.float32)
    heights, pixels = heights_and_pixels(xyz, dtm, grid)
    assert np.array_equal(heights, height_above_ground(xyz, dtm, grid))
    # by hand: the pixel whose half-open square holds the point, row 0 in the north
    col = np.array([int(np.floor((v - grid.x0) / grid.pixel_size)) for v in x[:2000]])
    row = grid.nrows - 1 - np.array([int(np.floor((v - grid.y0) / 0.5)) for v in y[:2000]])
    assert np.array_equal(pixels[:2000], row * grid.ncols + col)
    assert np.array_equal(pixels, grid.flat_index(x, y))
    # rasters from the pixels: those of the points (NaN heights left out of the CHM)
    h = np.where(rng.random(n) < 0.3, np.nan, heights).astype(np.float32)
    with_height = np.isfinite(h)
    expected = chm(xyz[with_height], h[with_height], grid)
    assert np.array_equal(chm_from_pixels(pixels, h, grid), expected, equal_nan=True)
    assert np.array_equal(density_from_pixels(pixels, grid), density(xyz, grid))
    assert pixel_counts(pixels, grid).sum() == n
    with pytest.raises(EnrichError):  # a pixel off the raster
        chm_from_pixels(np.array([grid.nrows * grid.ncols]), np.array([1.0]), grid)
    with pytest.raises(EnrichError, match="1 of 2 points"):
        grid.flat_index(np.array([x[0], grid.x0 - 0.1]), np.array([y[0], y[0]]))


def test_write_cog_and_read_back(tmp_path) -> None:
    grid = RasterGrid.covering(
        (ORIGIN[0], ORIGIN[1], ORIGIN[0] + 599, ORIGIN[1] + 599),
        origin=ORIGIN,
        cell_size=20.0,
        crs="EPSG:32632",
    )
    rng = np.random.default_rng(2)
    data = rng.uniform(0, 40, grid.shape).astype(np.float32)
    data[5, 7] = np.nan
    path = tmp_path / "rasters" / "chm.tif"
    write_cog(path, data, grid, description="canopy height (m)")
    assert [p.name for p in path.parent.iterdir()] == ["chm.tif"]  # no temporary left
    with rasterio.open(path) as ds:
        assert ds.driver == "GTiff" and ds.crs.to_epsg() == 32632
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert ds.profile["compress"] == "deflate" and ds.profile["tiled"]
        assert ds.block_shapes[0] == (256, 256)
        assert ds.overviews(1)  # 600 x 600: internal overviews
        assert ds.transform.c == grid.x0 and ds.transform.f == grid.bounds[3]
        assert ds.descriptions[0] == "canopy height (m)"
        back = ds.read(1)
    assert np.array_equal(back, data, equal_nan=True)
    raster = read_raster(path)
    assert raster.grid == grid and raster.crs == CRS.of(32632) and raster.crs.text == "EPSG:32632"
    assert np.isnan(raster.array[5, 7]) and np.nansum(raster.array) == pytest.approx(
        np.nansum(data), rel=1e-6
    )
    with pytest.raises(OutputExistsError):
        write_cog(path, data, grid, overwrite=False)
    local_grid = replace(grid, crs=None)
    counts = np.arange(grid.nrows * grid.ncols, dtype=np.uint16).reshape(grid.shape)
    write_cog(tmp_path / "n.tif", counts, local_grid, nodata=0)
    local = read_raster(tmp_path / "n.tif")
    assert local.grid == local_grid and local.crs is None
    assert np.isnan(local.array[0, 0]) and local.array[0, 1] == 1
    with pytest.raises(EnrichError):
        write_cog(tmp_path / "bad.tif", data[:-1], grid)


@pytest.mark.realdata
def test_real_chablais_dtm_from_own_csf_matches_the_file_ground(tmp_path) -> None:
    import laspy

    las = laspy.read(real_file("als/las_chablais3.laz"))
    xyz = np.column_stack([las.x, las.y, las.z])
    file_ground = np.asarray(las.classification) == 2
    ours = classify_ground(xyz)
    grid = RasterGrid.covering(
        (xyz[:, 0].min(), xyz[:, 1].min(), xyz[:, 0].max(), xyz[:, 1].max()),
        origin=(0.0, 0.0),
        cell_size=20.0,
        pixel_size=1.0,
    )
    dtm = dtm_from_ground(xyz[ours], grid)
    # the file's ground points against our DTM (the classification never saw the labels)
    residual = height_above_ground(xyz[file_ground], dtm, grid)
    assert np.median(np.abs(residual)) < 0.3
    assert np.percentile(np.abs(residual), 95) < 0.6
    heights = height_above_ground(xyz, dtm, grid)
    canopy = chm(xyz, heights, grid)
    assert 25 < np.nanmax(canopy) < 45  # a mountain conifer stand
    write_cog(tmp_path / "dtm.tif", dtm, replace(grid, crs=CRS.of(2154)), description="DTM")
    back = read_raster(tmp_path / "dtm.tif")
    assert back.crs == CRS.of("EPSG:2154") and np.allclose(back.array, dtm)
    assert np.nanmin(back.array) > 1340 and np.nanmax(back.array) < 1410


def test_raster_pixels_tile_the_stand_grid_cells() -> None:
    from standgrid.partition.grid import StandGrid

    stand = StandGrid(crs="EPSG:32632", cell_size=20.0, origin=ORIGIN)
    cell = stand.cell(600_033.0, 5_100_047.0)
    xmin, ymin, xmax, ymax = stand.bounds(cell)
    raster = RasterGrid.covering(
        (600_013.0, 5_100_007.0, 600_051.0, 5_100_053.0),
        origin=stand.origin,
        cell_size=stand.cell_size,
        pixel_size=0.5,
    )
    # the cell's corners fall on pixel edges: a whole number of pixels from the raster corner
    for value, corner in (
        (xmin, raster.x0),
        (xmax, raster.x0),
        (ymin, raster.y0),
        (ymax, raster.y0),
    ):
        steps = (value - corner) / raster.pixel_size
        assert steps == round(steps)
    cx, cy = raster.centers()
    in_cell = (cx >= xmin) & (cx < xmax) & (cy >= ymin) & (cy < ymax)
    assert in_cell.sum() == (20 / 0.5) ** 2  # exactly 1600 pixels per 20 m cell


def test_chm_fill_closes_single_pits_not_canopy_gaps_or_the_data_edge() -> None:
    grid = RasterGrid(x0=0.0, y0=0.0, pixel_size=1.0, ncols=12, nrows=7)
    cx, cy = np.meshgrid(np.arange(12) + 0.5, np.arange(7) + 0.5)
    centres = np.column_stack([cx.ravel(), cy.ravel()])
    row, col = grid.pixel_of(centres[:, 0], centres[:, 1])
    in_data = (col >= 1) & (col <= 10) & (row >= 1) & (row <= 5)  # a 1 px empty frame around
    gap_3x3 = (row >= 2) & (row <= 4) & (col >= 2) & (col <= 4)
    pit = (row == 3) & (col == 8)
    keep = in_data & ~gap_3x3 & ~pit
    xyz = np.column_stack([centres[keep], np.zeros(keep.sum())])
    heights = 10.0 + col[keep].astype(float)  # a height gradient west to east
    filled = chm(xyz, heights, grid)
    assert filled[3, 8] == pytest.approx(np.median([17, 17, 17, 19, 19, 19, 18, 18]))  # the pit
    assert np.isnan(filled[2:5, 2:5]).all()  # all 9 pixels of the canopy gap stay empty
    assert np.isnan(filled[0, :]).all() and np.isnan(filled[:, 0]).all()  # beyond the data edge
    assert np.isnan(filled[-1, :]).all() and np.isnan(filled[:, -1]).all()
    assert np.isfinite(filled).sum() == keep.sum() + 1  # only the pit was filled
    loose = chm(xyz, heights, grid, fill_min_neighbours=3)  # the old one-neighbour-ish fill
    assert np.isnan(loose[2:5, 2:5]).sum() == 1 and np.isnan(loose[3, 3])
    with pytest.raises(EnrichError):
        chm(xyz, heights, grid, fill_min_neighbours=9)


def reference_dtm(
    ground: np.ndarray, grid: RasterGrid, max_edge: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The DTM as standgrid computed it before issue 22 (scipy's ``LinearNDInterpolator`` at
    every pixel centre, ``find_simplex`` for the long triangles), and which pixels took the
    nearest ground point."""
    import contextlib

    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import Delaunay, QhullError, cKDTree

    xyz = np.asarray(ground, dtype=np.float64)
    local = xyz[:, :2] - (grid.x0, grid.y0)
    cx, cy = grid.centers()
    query = np.column_stack([cx.ravel() - grid.x0, cy.ravel() - grid.y0])
    values = np.full(len(query), np.nan)
    if len(xyz) >= 3:
        with contextlib.suppress(QhullError):
            tin = Delaunay(local)
            values = LinearNDInterpolator(tin, xyz[:, 2])(query)
            if max_edge is not None:
                corners = tin.points[tin.simplices]
                edges = corners - np.roll(corners, 1, axis=1)
                long = ((edges**2).sum(axis=2) > max_edge**2).any(axis=1)
                simplex = tin.find_simplex(query)
                values[(simplex >= 0) & long[np.maximum(simplex, 0)]] = np.nan
    missing = ~np.isfinite(values)
    if missing.any():
        _, nearest = cKDTree(local).query(query[missing])
        values[missing] = xyz[nearest, 2]
    return values.reshape(grid.shape).astype(np.float32), missing.reshape(grid.shape)


def ground_cases() -> list[tuple[str, np.ndarray, RasterGrid]]:
    """Ground point sets with their grid: uniform, clustered with holes, on a lattice through
    the pixel centres (points on centres, edges through centres, co-circular squares),
    collinear, tiny."""
    rng = np.random.default_rng(22)
    x0, y0 = ORIGIN
    grid = RasterGrid(x0=x0, y0=y0, pixel_size=0.5, ncols=80, nrows=60)
    cases = []

    def terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 400 + 0.2 * (x - x0) + np.sin((y - y0) / 3) + rng.normal(0, 0.05, len(x))

    x, y = x0 + rng.uniform(-2, 42, 4000), y0 + rng.uniform(-2, 32, 4000)
    cases.append(("uniform", np.column_stack([x, y, terrain(x, y)]), grid))
    centres = rng.uniform((x0 + 3, y0 + 3), (x0 + 37, y0 + 27), (12, 2))
    spread = centres[rng.integers(0, 12, 3000)] + rng.normal(0, 1.5, (3000, 2))
    hole = np.hypot(spread[:, 0] - x0 - 20, spread[:, 1] - y0 - 15) < 6
    x, y = spread[~hole, 0], spread[~hole, 1]
    cases.append(("clustered with holes", np.column_stack([x, y, terrain(x, y)]), grid))
    # a lattice of 0.5 m through the pixel centres, thinned with holes, quantised to 1 cm
    gx, gy = np.meshgrid(np.arange(2, 78) * 0.5 + 0.25, np.arange(2, 58) * 0.5 + 0.25)
    keep = rng.random(gx.size) < 0.7
    keep &= np.hypot(gx.ravel() - 25, gy.ravel() - 12) > 4
    x, y = x0 + gx.ravel()[keep], y0 + gy.ravel()[keep]
    z = np.round(terrain(x, y), 2)
    cases.append(("lattice on pixel centres", np.column_stack([x, y, z]), grid))
    # points on a 0.25 m lattice, 1 cm jitter: edges through centres, exact ties
    q = rng.integers(0, 160, (2500, 2)) * 0.25 + rng.integers(-1, 2, (2500, 2)) * 0.01
    x, y = x0 + q[:, 0], y0 + q[:, 1] * 0.75
    cases.append(("quantised lattice", np.column_stack([x, y, np.round(terrain(x, y), 2)]), grid))
    t = rng.uniform(0, 1, 50)
    line = np.column_stack([x0 + 5 + 30 * t, y0 + 5 + 20 * t, 400 + t])
    cases.append(("collinear", line, grid))
    nearly = line.copy()
    nearly[::7, 1] += 1e-9
    cases.append(("nearly collinear", nearly, grid))
    small = RasterGrid(x0=x0, y0=y0, pixel_size=1.0, ncols=6, nrows=5)
    triangle = np.array(
        [[x0 + 0.5, y0 + 0.5, 400.0], [x0 + 5.5, y0 + 0.5, 401], [x0 + 0.5, y0 + 4.5, 402]]
    )
    for k in (1, 2, 3):
        cases.append((f"{k} points", triangle[:k], small))
    raised = triangle + np.array([0.0, 0.0, 1.0])  # the same places, other heights
    duplicates = np.concatenate([triangle, raised, [[x0 + 5.5, y0 + 4.5, 399.0]]])
    cases.append(("duplicates and a square on centres", duplicates, small))
    return cases


@pytest.mark.parametrize("max_edge", [None, 1.0, 3.0])
def test_dtm_matches_the_reference_tin_interpolation(max_edge: float | None) -> None:
    for name, ground, grid in ground_cases():
        expected, filled = reference_dtm(ground, grid, max_edge)
        dtm = dtm_from_ground(ground, grid, max_edge=max_edge)
        assert dtm.dtype == np.float32 and dtm.shape == grid.shape, name
        assert np.isfinite(dtm).all(), name
        assert np.abs(dtm.astype(np.float64) - expected).max() <= 1e-3, name
        # the pixels the reference filled with the nearest ground point hold it here too
        assert np.array_equal(dtm[filled], expected[filled]), name
        assert np.array_equal(dtm, expected), name  # in fact bit for bit


def test_barycentric_transforms_are_scipys() -> None:
    from scipy.spatial import Delaunay

    from standgrid.enrichment.rasters import _barycentric_transforms

    for name, ground, _ in ground_cases()[:4]:
        tin = Delaunay(ground[:, :2] - ORIGIN)
        # the cache dtm_from_ground fills: a scipy without it would silently be slow again
        assert tin._transform is None, "scipy no longer caches Delaunay.transform there"
        ours = _barycentric_transforms(tin.points, tin.simplices)
        assert np.allclose(ours, tin.transform, rtol=1e-9, atol=1e-12, equal_nan=True), name
    # a sliver scipy would give a NaN transform (so find_simplex avoids it), and a triangle
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 1e-14], [1.0, 1.0]])
    ours = _barycentric_transforms(corners, np.array([[0, 1, 2], [0, 1, 3]], dtype=np.intc))
    assert np.isnan(ours[0]).all() and np.isfinite(ours[1]).all()
