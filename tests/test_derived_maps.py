"""Derived maps in payloads: elevation maps (npz, GeoTIFF, PNG + JSON) and voxel grids read,
kept with their payload, placed with its pose; a simulated mission's maps tiled into an
epoch mosaic whose error against the terrain truth is the simulated one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from standgrid.catalog import paths
from standgrid.errors import (
    DerivedMapFormatError,
    DuplicateStampError,
    MissionConsistencyError,
    OrphanPayloadError,
)
from standgrid.geotiff import read_raster, write_cog
from standgrid.mission.derived_maps import (
    read_elevation_map,
    read_voxel_grid,
    write_elevation_npz,
    write_voxel_npz,
)
from standgrid.mission.opening import open_mission
from standgrid.rastergrid import RasterGrid
from standgrid.simulate import simulate_mission
from standgrid.simulate.elevation import ElevationMapModel
from standgrid.simulate.mission import SimulationConfig
from standgrid.simulate.terrain import Terrain
from standgrid.tiling.elevation import difference, mean_mosaic, resample

MODEL = ElevationMapModel()


def _yaw(deg: float, t: tuple[float, float, float]) -> np.ndarray:
    a = np.radians(deg)
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    pose[:3, 3] = t
    return pose


# --- readers ----------------------------------------------------------------------------


def test_npz_elevation_map_round_trip_and_cells_in_the_base_frame(tmp_path: Path) -> None:
    heights = np.arange(12, dtype=np.float32).reshape(3, 4)
    heights[0, 0] = np.nan
    pose = _yaw(90, (1.0, 2.0, 0.5))
    path = write_elevation_npz(tmp_path / "e.npz", heights, 0.5, (-1.0, -0.75), pose)
    emap = read_elevation_map(path)
    np.testing.assert_array_equal(emap.heights, heights)
    assert emap.resolution == 0.5 and emap.origin == (-1.0, -0.75) and emap.crs is None
    pts = emap.cell_points()
    assert len(pts) == 11  # the NaN cell holds no height
    # cell (row 2, col 3): grid (-1 + 3.5 * 0.5, -0.75 + 2.5 * 0.5) = (0.75, 0.5), h 11;
    # yawed 90 degrees: (-0.5, 0.75), then moved by (1, 2, 0.5)
    np.testing.assert_allclose(pts[-1], [0.5, 2.75, 11.5], atol=1e-12)


def test_geotiff_elevation_map_in_the_payload_frame_and_in_a_crs(tmp_path: Path) -> None:
    values = np.array([[3.0, 4.0], [1.0, np.nan]], np.float32)  # row 0 north (GeoTIFF)
    write_cog(tmp_path / "local.tif", values, RasterGrid(-1.0, -1.0, 1.0, 2, 2))
    local = read_elevation_map(tmp_path / "local.tif")
    assert local.crs is None and local.origin == (-1.0, -1.0) and local.resolution == 1.0
    np.testing.assert_array_equal(local.heights, [[1.0, np.nan], [3.0, 4.0]])  # row 0 south
    grid = RasterGrid(600000.0, 5700000.0, 0.5, 2, 2, crs="EPSG:32630")
    write_cog(tmp_path / "utm.tif", values, grid)
    placed = read_elevation_map(tmp_path / "utm.tif")
    assert placed.crs is not None and placed.crs.is_projected
    np.testing.assert_allclose(placed.cell_points()[0], [600000.25, 5700000.25, 1.0])


def test_png_elevation_map_with_its_json_sidecar(tmp_path: Path) -> None:
    from PIL import Image

    raw = np.array([[0, 1000], [2000, 65535]], np.uint16)  # row 0 at the top
    Image.fromarray(raw).save(tmp_path / "elevation_1_000000001.png")
    sidecar = {"resolution": 0.2, "origin": [0, 0], "scale": 0.001, "offset": 100.0}
    (tmp_path / "elevation_1_000000001.json").write_text(json.dumps(sidecar))
    emap = read_elevation_map(tmp_path / "elevation_1_000000001.png")
    np.testing.assert_allclose(emap.heights, [[102.0, 165.535], [np.nan, 101.0]], atol=1e-4)
    (tmp_path / "elevation_1_000000001.json").unlink()
    with pytest.raises(DerivedMapFormatError, match="sidecar") as err:
        read_elevation_map(tmp_path / "elevation_1_000000001.png")
    assert err.value.path == tmp_path / "elevation_1_000000001.png"


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"resolution": 0.5, "origin": [0, 0]}, "missing 'heights'"),
        ({"heights": np.zeros((2, 2)), "resolution": 0.0, "origin": [0, 0]}, "'resolution'"),
        ({"heights": np.zeros((2, 2)), "resolution": 0.5, "origin": [0]}, "'origin'"),
        ({"heights": np.zeros(4), "resolution": 0.5, "origin": [0, 0]}, "2-D"),
        (
            {
                "heights": np.zeros((2, 2)),
                "resolution": 0.5,
                "origin": [0, 0],
                "pose": np.full((4, 4), 2.0),
            },
            "rigid",
        ),
    ],
)
def test_bad_elevation_maps_give_typed_errors_naming_the_file(
    tmp_path: Path, arrays: dict[str, Any], message: str
) -> None:
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(DerivedMapFormatError, match=message) as err:
        read_elevation_map(path)
    assert err.value.path == path and str(path) in str(err.value)


def test_unreadable_files_give_typed_errors(tmp_path: Path) -> None:
    for name in ("garbage.npz", "garbage.tif", "garbage.png"):
        (tmp_path / name).write_bytes(b"not a map at all")
        if name.endswith(".png"):
            (tmp_path / "garbage.json").write_text(
                '{"resolution": 1, "origin": [0, 0], "scale": 1}'
            )
        with pytest.raises(DerivedMapFormatError) as err:
            read_elevation_map(tmp_path / name)
        assert err.value.path == tmp_path / name
    (tmp_path / "map.bt").write_bytes(b"# Octomap OcTree binary file\n")
    with pytest.raises(DerivedMapFormatError, match="OctoMap"):
        read_voxel_grid(tmp_path / "map.bt")


def test_voxel_grid_round_trip_corners_and_occupied_voxels(tmp_path: Path) -> None:
    occupancy = np.zeros((4, 3, 2), np.float32)
    occupancy[1, 2, 1] = 0.9
    pose = _yaw(0, (10.0, 0.0, 0.0))
    path = write_voxel_npz(tmp_path / "v.npz", occupancy, 0.5, (0.0, 0.0, -1.0), pose=pose)
    grid = read_voxel_grid(path)
    assert grid.kind == "occupancy" and grid.values.shape == (4, 3, 2)
    corners = grid.corners()
    np.testing.assert_allclose(corners.min(axis=0), [10.0, 0.0, -1.0])
    np.testing.assert_allclose(corners.max(axis=0), [12.0, 1.5, 0.0])
    np.testing.assert_allclose(grid.occupied_points(), [[10.75, 1.25, -0.25]])
    np.savez(
        tmp_path / "both.npz", occupancy=occupancy, tsdf=occupancy, voxel_size=1.0, origin=[0, 0, 0]
    )
    with pytest.raises(DerivedMapFormatError, match="exactly one"):
        read_voxel_grid(tmp_path / "both.npz")


# --- placement on the lattice -------------------------------------------------------------


def test_resample_averages_fine_cells_and_interpolates_coarse_ones() -> None:
    from standgrid.crs import CRS

    crs = CRS.of("EPSG:32630")
    # 0.25 m cells of the plane z = x over 4 x 2 m: each 1 m pixel the mean of its 16 cells
    c = np.arange(0.125, 4, 0.25)
    x, y = np.meshgrid(c, c[:8])
    fine = np.column_stack([x.ravel() + 100, y.ravel() + 200, x.ravel()])
    grid, values = resample(fine, 0.25, (0.0, 0.0), crs)
    assert (grid.x0, grid.y0, grid.ncols, grid.nrows) == (100.0, 200.0, 4, 2)
    np.testing.assert_allclose(values, [[0.5, 1.5, 2.5, 3.5]] * 2)
    # 2 m cells: the pixels between cell centres are linear between them
    coarse = np.array(
        [[101.0, 201.0, 1.0], [103.0, 201.0, 3.0], [101.0, 203.0, 1.0], [103.0, 203.0, 3.0]]
    )
    grid, values = resample(coarse, 2.0, (0.0, 0.0), crs)
    row = values[grid.nrows - 1 - 1]  # y 201.5
    np.testing.assert_allclose(row[~np.isnan(row)], [1.5, 2.5], atol=1e-12)
    # two rasters on the lattice: the mean where they overlap
    a = (RasterGrid(0.0, 0.0, 1.0, 2, 1, crs), np.array([[1.0, 3.0]]))
    b = (RasterGrid(1.0, 0.0, 1.0, 2, 1, crs), np.array([[5.0, 7.0]]))
    grid, mosaic = mean_mosaic([a, b], (0.0, 0.0), crs)
    np.testing.assert_allclose(mosaic, [[1.0, 4.0, 7.0]])
    stats = difference(
        mosaic, grid, np.array([[0.0, 4.0, 6.0, 9.0]]), RasterGrid(0.0, 0.0, 1.0, 4, 1, crs)
    )
    # [1, 4, 7] - [0, 4, 6]: differences 1, 0, 1 (the fourth reference pixel has no mosaic)
    assert (stats["pixels"], stats["median_m"], stats["mad_m"]) == (3, 1.0, 0.0)
    assert (stats["mean_m"], stats["rmse_m"]) == (0.6667, 0.8165)


# --- a simulated mission, tiled ----------------------------------------------------------


@pytest.fixture(scope="module")
def sim_maps(tmp_path_factory: pytest.TempPathFactory) -> Any:
    root = tmp_path_factory.mktemp("maps")
    config = SimulationConfig(area=50.0, points_per_payload=2000, elevation_maps=MODEL)
    return simulate_mission(root, seed=4, epoch=1, config=config)


def test_simulated_missions_carry_elevation_maps_with_their_stated_error(sim_maps: Any) -> None:
    mission = open_mission(sim_maps.mission_dir)
    assert all(p.elevation_map is not None for p in mission.payloads)
    assert mission.summary()["elevation_maps"] == len(mission.payloads) == len(sim_maps.spans)
    truth = json.loads((sim_maps.truth_dir / "truth.json").read_text())["elevation_maps"]
    assert truth["bias_m"] == MODEL.bias and truth["noise_std_m"] == MODEL.noise_std
    emap = mission.load_elevation_map(mission.payloads[0])
    assert emap.heights.shape == (80, 80) and emap.resolution == MODEL.resolution


def test_missions_without_maps_are_as_before(tmp_path: Path, sim_maps: Any) -> None:
    bare = tmp_path / sim_maps.mission_dir.name
    shutil.copytree(sim_maps.mission_dir, bare, ignore=shutil.ignore_patterns("elevation"))
    mission = open_mission(bare)
    assert all(p.elevation_map is None and p.volumetric_map is None for p in mission.payloads)
    assert "elevation_maps" not in mission.summary()


def test_orphan_and_duplicate_maps_are_reported(tmp_path: Path, sim_maps: Any) -> None:
    folder = tmp_path / sim_maps.mission_dir.name
    shutil.copytree(sim_maps.mission_dir, folder)
    maps = folder / "payloads" / "elevation"
    first = sorted(maps.iterdir())[0]
    shutil.copy(first, maps / "elevation_1_000000001.npz")
    with pytest.raises(OrphanPayloadError) as err:
        open_mission(folder)
    assert err.value.path == maps / "elevation_1_000000001.npz"
    loose = open_mission(folder, strict=False)
    assert any("elevation_1_000000001.npz" in p for p in loose.problems)
    (maps / "elevation_1_000000001.npz").unlink()
    np.save(maps / "x.npy", np.zeros(1))  # a file named without a stamp: not read, said
    with pytest.raises(MissionConsistencyError, match="no stamp"):
        open_mission(folder)
    (maps / "x.npy").unlink()
    tif = first.with_suffix(".tif")
    write_cog(tif, np.zeros((1, 1), np.float32), RasterGrid(0.0, 0.0, 1.0, 1, 1))
    with pytest.raises(DuplicateStampError):
        open_mission(folder)


@pytest.fixture(scope="module")
def tiled(sim_maps: Any, tmp_path_factory: pytest.TempPathFactory) -> Any:
    from standgrid.api import tile

    out = tmp_path_factory.mktemp("cat") / "catalog"
    return out, tile([sim_maps.mission_dir], out)


def test_tiling_places_the_maps_into_an_epoch_mosaic_with_the_simulated_error(
    sim_maps: Any, tiled: Any
) -> None:
    out, report = tiled
    mosaic = report.epochs["2024"]["elevation_map"]
    assert mosaic["raster"] == paths.raster("2024", paths.ELEVATION_MAP) and mosaic["missions"] == 1
    name = sim_maps.mission_dir.name
    assert report.missions[name]["derived_maps"]["elevation_maps"] == len(sim_maps.spans)
    assert (out / paths.mission_elevation_map("2024", name)).is_file()
    raster = read_raster(out / mosaic["raster"])
    assert raster.crs is not None and raster.crs.epsg == 32630
    assert raster.grid.pixel_size == 1.0 and (raster.grid.x0 % 1, raster.grid.y0 % 1) == (0, 0)
    terrain = Terrain.from_dict(
        json.loads((sim_maps.truth_dir / "truth.json").read_text())["terrain"]
    )
    cx, cy = raster.grid.centers()
    error = (raster.array - terrain.height(cx, cy))[np.isfinite(raster.array)]
    assert error.size == mosaic["pixels"] > 500
    # the stated bias, within 2 cm; the noise averages over a pixel's 16 cells and over the
    # payloads' overlaps, so the RMSE is the bias's, within 20 % (placement error included)
    assert abs(float(np.median(error)) - MODEL.bias) < 0.02
    rmse = float(np.sqrt(np.mean(error**2)))
    assert 0.8 * MODEL.bias < rmse < 1.2 * np.hypot(MODEL.bias, MODEL.noise_std / 4)
    print(f"mosaic - truth: median {np.median(error):.4f} m, RMSE {rmse:.4f} m, n {error.size}")


def test_enrich_reports_the_mosaic_minus_the_dtm(tiled: Any) -> None:
    from standgrid.api import enrich

    out, _ = tiled
    report = enrich(out)
    stats = report.epochs["2024"]["elevation_map_minus_dtm"]
    assert stats["pixels"] > 500
    # the DTM from points is unbiased to a few cm: the difference is about the maps' bias
    assert abs(stats["median_m"] - MODEL.bias) < 0.03
    assert stats["rmse_m"] < 0.3 and stats["mad_m"] < 0.1
    assert (out / paths.raster("2024", "elevation_map")).is_file()  # enrich keeps it
    print(f"mosaic - DTM: {stats}")


def test_tiling_an_unchanged_epoch_again_reports_the_mosaic_minus_its_dtm(
    sim_maps: Any, tiled: Any
) -> None:
    """Nothing moved: the DTM still holds, so tiling says the difference at once."""
    from standgrid.api import tile

    out, _ = tiled
    enriched = json.loads((out / paths.CATALOG_FILE).read_text())["epochs"]["2024"]
    again = tile([sim_maps.mission_dir], out)
    mosaic = again.epochs["2024"]["elevation_map"]
    assert mosaic["minus_dtm"] == enriched["enrichment"]["elevation_map_minus_dtm"]


def test_voxel_grids_are_placed_and_maps_leave_with_their_mission(
    sim_maps: Any, tmp_path: Path
) -> None:
    """A voxel grid's bounds land around its payload's pose in the catalog CRS; an OctoMap is
    kept (listed without bounds); re-tiling the mission without maps removes its map and the
    epoch's mosaic."""
    from standgrid.api import tile
    from standgrid.catalog import Catalog
    from standgrid.catalog.index import CatalogIndex

    folder = tmp_path / sim_maps.mission_dir.name
    shutil.copytree(sim_maps.mission_dir, folder)
    stamps = [p.stamp for p in open_mission(folder).payloads]
    volumetric = folder / "payloads" / "volumetric"
    write_voxel_npz(
        volumetric / stamps[0].filename("voxels", "npz"),
        np.zeros((4, 4, 4)),
        0.5,
        (-1.0, -1.0, -1.0),
    )
    bt = volumetric / stamps[1].filename("voxels", "bt")
    try:  # a real OctoMap where octomap-python is installed, else one it would not read
        import octomap

        tree = octomap.OcTree(0.2)
        tree.updateNode(np.array([0.1, 0.1, 0.1]), True)
        assert tree.writeBinary(str(bt).encode())
    except ImportError:
        octomap = None
        bt.write_bytes(b"# Octomap OcTree binary file\n")
    out = tmp_path / "catalog"
    report = tile([folder], out)
    maps = report.missions[folder.name]["derived_maps"]
    assert maps["elevation_maps"] == len(stamps)
    voxels, octree = maps["volumetric_maps"]
    assert octree["kind"] == "octomap"
    assert octree["bounds"] is None if octomap is None else len(octree["bounds"]) == 6
    assert voxels["kind"] == "occupancy" and voxels["shape"] == [4, 4, 4]
    lo, hi = np.array(voxels["bounds"][:3]), np.array(voxels["bounds"][3:])
    rows = CatalogIndex(Catalog.open(out)).read("payloads")
    row = rows[rows["stamp_nsec"] == stamps[0].nsec].iloc[0]
    np.testing.assert_allclose((lo + hi) / 2, [row["x"], row["y"], row["z"]], atol=0.01)
    assert 1.9 < hi[2] - lo[2] < 2.2 and 1.99 < hi[0] - lo[0] < 2.83  # a 2 m cube, yawed
    record = Catalog.open(out).mission_records[folder.name]
    assert record.extra["derived_maps"]["elevation_maps"] == len(stamps)

    shutil.rmtree(folder / "payloads" / "elevation")
    shutil.rmtree(volumetric)
    again = tile([folder], out)
    assert "derived_maps" not in again.missions[folder.name]
    assert "elevation_map" not in again.epochs["2024"]
    assert not (out / paths.mission_elevation_map("2024", folder.name)).exists()
    assert not (out / paths.raster("2024", paths.ELEVATION_MAP)).exists()


def test_octomaps_read_with_octomap_python(tmp_path: Path) -> None:
    """``.bt`` and ``.ot`` files written by OctoMap itself (octomap-python, the optional
    ``octomap`` extra) read back: occupied leaves, box, the sidecar's pose."""
    octomap = pytest.importorskip("octomap")
    tree = octomap.OcTree(0.2)
    for point in ((0.05, 0.05, 0.05), (1.05, 0.45, 0.25)):
        tree.updateNode(np.array(point), True)
    tree.updateInnerOccupancy()
    assert tree.writeBinary(str(tmp_path / "v.bt").encode())
    assert tree.write(str(tmp_path / "v.ot").encode())
    (tmp_path / "v.json").write_text(json.dumps({"pose": _yaw(0, (5.0, 0.0, 0.0)).tolist()}))
    for name in ("v.bt", "v.ot"):
        octree = read_voxel_grid(tmp_path / name)
        assert octree.kind == "octomap" and octree.voxel_size == pytest.approx(0.2)
        occupied = octree.occupied_points()
        np.testing.assert_allclose(
            sorted(occupied.tolist()), [[5.1, 0.1, 0.1], [6.1, 0.5, 0.3]], atol=1e-6
        )
        np.testing.assert_allclose(octree.corners().min(axis=0), [5.0, 0.0, 0.0], atol=1e-6)
    (tmp_path / "bad.bt").write_bytes(b"garbage")
    with pytest.raises(DerivedMapFormatError, match="OctoMap binary"):
        read_voxel_grid(tmp_path / "bad.bt")


def test_the_mosaic_outlives_another_mission_tiled_into_its_epoch(
    sim_maps: Any, tmp_path: Path
) -> None:
    """A second robot's mission (no maps) into the same epoch re-tiles it: the mosaic is made
    again from the first mission's kept map; invalidation leaves it (tiling's own)."""
    from standgrid.api import tile

    out = tmp_path / "catalog"
    first = tile([sim_maps.mission_dir], out).epochs["2024"]["elevation_map"]
    before = read_raster(out / first["raster"])
    other = simulate_mission(tmp_path / "b", seed=4, epoch=3, area=50.0, points_per_payload=800)
    report = tile([other.mission_dir], out)
    assert report.epochs["2024"]["points_new"] > 0 and "invalidated" not in report.epochs["2024"]
    after = read_raster(out / report.epochs["2024"]["elevation_map"]["raster"])
    assert after.grid == before.grid
    np.testing.assert_array_equal(after.array, before.array)
