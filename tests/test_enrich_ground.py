"""Ground classification (CSF) on the real steep chablais3 scan and on a generated slope."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from standgrid.enrichment.ground import as_xyz, classify_ground
from standgrid.errors import EnrichError
from standgrid.pointcloud import PointCloud
from tests.conftest import real_file


def read_chablais() -> tuple[np.ndarray, np.ndarray]:
    import laspy

    las = laspy.read(real_file("als/las_chablais3.laz"))
    return np.column_stack([las.x, las.y, las.z]), np.asarray(las.classification)


def height_above_file_ground(xyz: np.ndarray, cls: np.ndarray) -> np.ndarray:
    """Heights above a TIN of the file's own class-2 points (NaN outside their hull)."""
    from scipy.interpolate import LinearNDInterpolator

    origin = xyz[:, :2].min(axis=0)
    ground = cls == 2
    tin = LinearNDInterpolator(xyz[ground, :2] - origin, xyz[ground, 2])
    return xyz[:, 2] - tin(xyz[:, :2] - origin)


@pytest.mark.realdata
def test_csf_finds_the_ground_of_the_real_steep_scan() -> None:
    xyz, cls = read_chablais()
    ground = classify_ground(xyz)  # defaults tuned for ~20 deg slopes
    file_ground = cls == 2
    recall = (ground & file_ground).sum() / file_ground.sum()
    assert recall > 0.95
    # vegetation clearly above the producer's terrain must not be called ground; the file
    # leaves many near-ground returns in classes 4/15, so "vegetation" means > 1 m up
    hag = height_above_file_ground(xyz, cls)
    vegetation = (cls != 2) & (hag > 1.0)
    assert vegetation.sum() > 50_000
    assert (ground & vegetation).sum() / vegetation.sum() < 0.005
    # and what CSF calls ground hugs that terrain
    assert np.nanmedian(np.abs(hag[ground & ~file_ground])) < 0.3


@pytest.mark.realdata
def test_a_stiff_flat_cloth_does_worse_on_slopes() -> None:
    """The slope tuning matters: rigidness 3 at 1 m misses much of the steep ground."""
    xyz, cls = read_chablais()
    tuned = classify_ground(xyz)
    stiff = classify_ground(xyz, rigidness=3, cloth_resolution=1.0, slope_smooth=False)
    file_ground = cls == 2
    assert (stiff & file_ground).sum() < (tuned & file_ground).sum()


def generated_slope(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 25 deg slope with bumps, canopy blobs 3-20 m above it; returns points and truth."""
    rng = np.random.default_rng(seed)
    n_ground, n_canopy = 20_000, 30_000
    gx, gy = rng.uniform(0, 60, n_ground), rng.uniform(0, 60, n_ground)

    def terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 900.0 + np.tan(np.radians(25)) * x + 1.5 * np.sin(y / 7.0)

    cx, cy = rng.uniform(0, 60, n_canopy), rng.uniform(0, 60, n_canopy)
    crowns = terrain(cx, cy) + rng.uniform(3, 20, n_canopy)
    xyz = np.concatenate(
        [
            np.column_stack([gx, gy, terrain(gx, gy) + rng.normal(0, 0.03, n_ground)]),
            np.column_stack([cx, cy, crowns]),
        ]
    ) + np.array([2_600_000.0, 1_200_000.0, 0.0])  # large projected coordinates
    truth = np.r_[np.ones(n_ground, bool), np.zeros(n_canopy, bool)]
    return xyz, truth


def test_csf_on_a_generated_steep_slope() -> None:
    xyz, truth = generated_slope()
    ground = classify_ground(PointCloud(xyz))
    assert (ground & truth).sum() / truth.sum() > 0.95
    assert (ground & ~truth).sum() == 0


def test_csf_does_not_write_to_stdout(capfd: pytest.CaptureFixture[str]) -> None:
    xyz, _ = generated_slope(1)
    classify_ground(xyz[::10])
    out, _ = capfd.readouterr()
    assert out == ""


def test_bad_input_and_parameters() -> None:
    assert classify_ground(np.empty((0, 3))).shape == (0,)
    with pytest.raises(EnrichError):
        classify_ground(np.zeros((4, 2)))
    with pytest.raises(EnrichError):
        classify_ground(np.array([[0.0, 0.0, np.nan]]))
    with pytest.raises(EnrichError):
        classify_ground(np.zeros((4, 3)), method="pmf")
    with pytest.raises(EnrichError):
        classify_ground(np.zeros((4, 3)), rigidness=5)
    assert as_xyz(PointCloud(np.ones((2, 3)))).dtype == np.float64


@pytest.mark.realdata
def test_a_las_file_read_as_a_point_cloud_gives_the_same_ground() -> None:
    """LAS files go in as PointClouds (standgrid's reader) with the same result as arrays."""
    from standgrid.clouds import read_cloud

    path = real_file("als/las_chablais3.laz")
    cloud = read_cloud(path)
    xyz, cls = read_chablais()
    assert np.array_equal(cloud.xyz, xyz)
    from_cloud = classify_ground(cloud, cloth_resolution=1.0, rigidness=2)
    from_array = classify_ground(xyz, cloth_resolution=1.0, rigidness=2)
    assert from_cloud.sum() > 0
    # CSF's OpenMP loops may break ties differently run to run: near-identical masks
    assert (from_cloud != from_array).mean() < 0.001
    assert np.array_equal(np.asarray(cloud.fields["classification"]), cls)


def _window_over(xyz: np.ndarray) -> Any:
    """The 1 m raster (on the 20 m lattice) covering the points."""
    from standgrid.rastergrid import RasterGrid

    bounds = (xyz[:, 0].min(), xyz[:, 1].min(), xyz[:, 0].max(), xyz[:, 1].max())
    return RasterGrid.covering(bounds, origin=(0.0, 0.0), cell_size=20.0)


@pytest.mark.realdata
def test_terrain_from_the_lowest_returns_finds_the_ground_of_the_real_steep_scan() -> None:
    """What enrichment runs: CSF over the lowest return of each quarter cloth cell, in 40 m
    squares, then every return within 0.5 m of the TIN terrain is ground."""
    from standgrid.enrichment.terrain import classify_terrain

    xyz, cls = read_chablais()
    window = _window_over(xyz)
    terrain = classify_terrain(xyz, window)
    file_ground = cls == 2
    recall = (terrain.ground & file_ground).sum() / file_ground.sum()
    print(f"\nrecall of the producer's ground {recall:.4f}")
    assert recall > 0.95
    hag = height_above_file_ground(xyz, cls)
    vegetation = (cls != 2) & (hag > 1.0)
    wrong = (terrain.ground & vegetation).sum() / vegetation.sum()
    print(f"vegetation > 1 m called ground {wrong:.5f}")
    assert wrong < 0.005
    # the producer's ground lies on our terrain model
    residual = np.abs(terrain.heights[file_ground])
    print(
        f"|producer ground - terrain| median {np.median(residual):.3f} m, "
        f"p95 {np.percentile(residual, 95):.3f} m"
    )
    assert np.median(residual) < 0.1 and np.percentile(residual, 95) < 0.5


def test_terrain_on_a_generated_slope() -> None:
    """A 25 deg slope: all of the ground away from the survey's upslope edge is found, and
    nothing else. CSF over a 40 m window (a 20 m square and 10 m around it) leaves the cloth
    above the ground along the last ~6 m upslope (measured: recall 0.949 overall, 1.0 more
    than 10 m from that edge; whole-area CSF: 0.99): a documented limit (docs/METRICS.md)."""
    from standgrid.enrichment.terrain import classify_terrain

    xyz, truth = generated_slope()
    terrain = classify_terrain(xyz, _window_over(xyz))
    upslope = xyz[:, 0] - xyz[:, 0].min()  # the terrain rises with x
    interior = upslope < np.ptp(xyz[:, 0]) - 10.0
    assert (terrain.ground & truth & interior).sum() == (truth & interior).sum()
    assert (terrain.ground & truth).sum() / truth.sum() > 0.93
    assert (terrain.ground & ~truth).sum() == 0
    assert np.nanmedian(np.abs(terrain.heights[truth & interior])) < 0.05
