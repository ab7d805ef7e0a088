"""Accuracy of the whole chain on a real scan: cut a mission out of a georeferenced ALS tile
(random map frame, GNSS with ~3 cm noise and 5 % outliers), tile it back into the scan's
own CRS, and compare every tiled point (read with laspy) with its original coordinates."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyogrio
import pytest
from scipy.spatial import cKDTree

from standgrid.pipeline.tile import tile_missions
from standgrid.simulate import load_truth, mission_from_scan
from standgrid.stamps import Stamp
from standgrid.tiling.options import TileOptions
from tests.conftest import real_file

pytestmark = pytest.mark.realdata

#: Horizontal accuracy the tiles must reach (median over all points).
MEDIAN_HORIZONTAL_M = 0.05


@pytest.fixture(scope="module")
def tiled_scan(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    scan = real_file("als/lasR_bcts/bcts_1.laz")
    root = tmp_path_factory.mktemp("accuracy")
    made = mission_from_scan([scan], root, seed=21, gnss_noise_m=0.03, outlier_fraction=0.05)
    catalog = root / "catalog"
    report = tile_missions(
        [made.mission_dir], catalog, TileOptions(crs="EPSG:3005", cell_size=20.0, laz=True)
    )
    return {"made": made, "catalog": catalog, "report": report}


def _errors(tiled: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-point (horizontal, vertical) error against the truth; and the unique-match ratio."""
    catalog: Path = tiled["catalog"]
    truth = load_truth(tiled["made"].truth_dir)
    payloads = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    stamp_of = {
        int(r.payload_id): Stamp(int(r.stamp_sec), int(r.stamp_nsec)) for r in payloads.itertuples()
    }
    by_payload: dict[int, list[np.ndarray]] = {}
    for path in sorted(catalog.glob("tiles/*/*.laz")):
        las = laspy.read(path)
        xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        pids = np.asarray(las.payload_id)
        for pid in np.unique(pids):
            by_payload.setdefault(int(pid), []).append(xyz[pids == pid])
    horizontal, vertical, unique, total = [], [], 0, 0
    for pid, parts in by_payload.items():
        tiled_xyz = np.concatenate(parts)
        original, _ = truth.payload_points(stamp_of[pid])
        assert len(tiled_xyz) == len(original), f"payload {pid}: point count changed"
        _, match = cKDTree(original).query(tiled_xyz)
        unique += len(np.unique(match))
        total += len(match)
        diff = tiled_xyz - original[match]
        horizontal.append(np.hypot(diff[:, 0], diff[:, 1]))
        vertical.append(diff[:, 2])
    return np.concatenate(horizontal), np.concatenate(vertical), unique / total


def test_tiles_reproduce_the_scan_coordinates(tiled_scan: dict[str, Any]) -> None:
    report = tiled_scan["report"].to_dict()
    made = tiled_scan["made"]
    assert report["crs"] == "EPSG:3005"
    assert report["points_in"] == report["points_out"] == made.n_points
    horizontal, vertical, unique = _errors(tiled_scan)
    # the nearest original point is the point's own original (a one-to-one matching)
    assert unique > 0.99
    median_h = float(np.median(horizontal))
    median_v = float(np.median(np.abs(vertical)))
    bias_v = float(np.median(vertical))
    print(
        f"\nhorizontal error: median {median_h * 100:.2f} cm, p95 "
        f"{np.percentile(horizontal, 95) * 100:.2f} cm; vertical: median |dz| "
        f"{median_v * 100:.2f} cm, bias {bias_v * 100:+.2f} cm over {len(horizontal):,} points"
    )
    assert median_h < MEDIAN_HORIZONTAL_M
    assert float(np.percentile(horizontal, 95)) < 2 * MEDIAN_HORIZONTAL_M
    # heights: the simulator treats scan heights as ellipsoidal, the tiler writes ellipsoidal
    assert median_v < 0.10


def test_georeference_rejects_the_outliers(tiled_scan: dict[str, Any]) -> None:
    made = tiled_scan["made"]
    fit = tiled_scan["report"].missions[made.name]["georeference"]
    outliers = int(made.gnss.outlier.sum())
    assert outliers > 0
    assert fit["fixes_rejected"] >= outliers
    assert fit["rmse_horizontal_m"] < 0.1
