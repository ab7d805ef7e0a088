"""GeoPackage index: layers written by IndexWriter/write_index, read back with pyogrio + sqlite."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import pyogrio
import pyproj
import pytest
from shapely.geometry import LineString, Point, box

from standgrid.errors import CatalogError, CRSError
from standgrid.export.gpkg import (
    LAYER_COLUMNS,
    IndexWriter,
    cell_row,
    iso_time,
    layer_frame,
    write_index,
)
from standgrid.export.las import write_tile
from standgrid.pointcloud import PointCloud

CRS = "EPSG:32632"
X0, Y0 = 500_000.0, 6_000_000.0


def cells_rows(tmp_path: Path) -> list[dict]:
    rows = []
    rng = np.random.default_rng(0)
    for i in range(3):
        cell = box(X0 + 20 * i, Y0, X0 + 20 * (i + 1), Y0 + 20)
        xyz = rng.uniform(
            [X0 + 20 * i, Y0, 100], [X0 + 20 * (i + 1), Y0 + 20, 120], (400 * (i + 1), 3)
        )
        tile = tmp_path / "cat" / "tiles" / "2024-05-01" / f"c{i}.laz"
        info = write_tile(tile, PointCloud(xyz), crs=CRS, core_bounds=cell)
        rows.append(
            cell_row(
                f"L0_{i}_0",
                info,
                level=0,
                cell_size=20.0,
                epoch="2024-05-01",
                catalog_root=tmp_path / "cat",
                missions=["m2", "m1", "m2"],
            )
        )
    return rows


def other_layers() -> dict[str, list[dict]]:
    payloads = [
        {
            "payload_id": i,
            "mission": "m1",
            "stamp_sec": 1_700_000_000 + i,
            "stamp_nsec": 5,
            "time": f"2023-11-14T22:13:{20 + i:02d}.000000005Z",
            "node_id": 10 + i,
            "point_count": 1000,
            "x": X0 + 5 * i,
            "y": Y0 + 5,
            "z": 101.0,
            "yaw": 0.1 * i,
            "geometry": Point(X0 + 5 * i, Y0 + 5).buffer(10),
        }
        for i in range(4)
    ]
    trajectories = [
        {
            "mission": "m1",
            "epoch": "2024-05-01",
            "geometry": LineString([(X0, Y0), (X0 + 30, Y0 + 10)]),
        },
        {
            "mission": "m2",
            "epoch": "2024-05-01",
            "geometry": LineString([(X0, Y0 + 5), (X0 + 50, Y0)]),
        },
    ]
    fixes = [
        {
            "mission": "m1",
            "stamp_sec": 1_700_000_000 + i,
            "stamp_nsec": 0,
            "quality": 4,
            "residual_e": 0.01 * i,
            "residual_n": -0.02,
            "residual_u": 0.05,
            "residual_h": 0.03,
            "inlier": i != 2,
            "geometry": Point(X0 + i, Y0 + i),
        }
        for i in range(5)
    ]
    missions = [
        {
            "mission": "2024-05-01-wytham-anymal",
            "number": 1,
            "epoch": "2024-05-01",
            "date": "2024-05-01",
            "robot": "anymal",
            "place": "wytham",
            "unit": "",
            "sensors": "lidar,gnss",
            "fit_method": "yaw2d",
            "rmse_m": 0.04,
            "n_used": 120,
            "n_rejected": 3,
            "grid_fingerprint": "abc123",
            "crs": CRS,
        }
    ]
    return {
        "payloads": payloads,
        "trajectories": trajectories,
        "gnss_fixes": fixes,
        "missions": missions,
    }


def test_write_index_round_trip(tmp_path: Path) -> None:
    rows = cells_rows(tmp_path)
    gpkg = tmp_path / "cat" / "index.gpkg"
    write_index(gpkg, crs=CRS, cells=rows, **other_layers())

    layers = dict(pyogrio.list_layers(gpkg))
    assert {"cells", "payloads", "trajectories", "gnss_fixes", "missions", "layer_styles"} <= set(
        layers
    )
    assert layers["cells"] == "Polygon" and layers["trajectories"] == "LineString"
    assert layers["gnss_fixes"] == "Point" and layers["missions"] is None

    cells = gpd.read_file(gpkg, layer="cells", engine="pyogrio")
    assert pyproj.CRS(cells.crs) == pyproj.CRS(CRS)
    assert list(cells.columns[: len(LAYER_COLUMNS["cells"])]) == list(LAYER_COLUMNS["cells"])
    assert list(cells["point_count"]) == [400, 800, 1200]
    np.testing.assert_allclose(cells["density"], [1.0, 2.0, 3.0])  # points / 400 m²
    assert cells["tile_path"][1] == "tiles/2024-05-01/c1.laz"
    assert cells["missions"][0] == "m1,m2"
    assert cells.geometry[2].equals(box(X0 + 40, Y0, X0 + 60, Y0 + 20))
    assert (cells["z_min"] >= 100).all() and (cells["z_p95"] <= cells["z_max"]).all()

    fixes = gpd.read_file(gpkg, layer="gnss_fixes", engine="pyogrio")
    assert list(fixes["inlier"]) == [True, True, False, True, True]
    assert pyproj.CRS(fixes.crs).to_epsg() == 32632
    missions = pyogrio.read_dataframe(gpkg, layer="missions")
    assert missions["rmse_m"][0] == pytest.approx(0.04) and missions["number"][0] == 1
    payloads = gpd.read_file(gpkg, layer="payloads", engine="pyogrio")
    assert len(payloads) == 4 and payloads["time"][0].startswith("2023-11-14T22:13:20")

    with sqlite3.connect(gpkg) as db:
        styled = dict(
            db.execute("SELECT f_table_name, count(*) FROM layer_styles GROUP BY f_table_name")
        )
        defaults = db.execute(
            "SELECT f_table_name, styleName FROM layer_styles WHERE useAsDefault = 1"
        ).fetchall()
    assert styled == {"cells": 2, "payloads": 1, "trajectories": 1, "gnss_fixes": 1}
    assert ("cells", "cells") in defaults and ("cells", "cells by density") not in defaults


def test_replacing_one_layer_keeps_the_others(tmp_path: Path) -> None:
    gpkg = tmp_path / "index.gpkg"
    write_index(gpkg, crs=CRS, **other_layers())
    new_traj = [
        {"mission": "m3", "epoch": "2025", "geometry": LineString([(X0, Y0), (X0 + 1, Y0 + 1)])}
    ]
    write_index(gpkg, crs=CRS, trajectories=new_traj)
    assert len(pyogrio.read_dataframe(gpkg, layer="trajectories")) == 1
    assert len(pyogrio.read_dataframe(gpkg, layer="gnss_fixes")) == 5
    with sqlite3.connect(gpkg) as db:
        qml = db.execute(
            "SELECT styleQML FROM layer_styles WHERE f_table_name = 'trajectories'"
        ).fetchone()[0]
    assert 'value="m3"' in qml and 'value="m1"' not in qml


def test_failed_write_leaves_previous_index(tmp_path: Path) -> None:
    gpkg = tmp_path / "index.gpkg"
    write_index(gpkg, crs=CRS, **other_layers())
    before = gpkg.read_bytes()
    with pytest.raises(CatalogError, match="lacks columns"), IndexWriter(gpkg, CRS) as writer:
        writer.write_layer("trajectories", [{"mission": "x", "geometry": Point(0, 0)}])
    assert gpkg.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["index.gpkg"]  # no temporary left


def test_layer_in_another_crs_is_refused(tmp_path: Path) -> None:
    frame = gpd.GeoDataFrame(
        {"mission": ["m"], "epoch": ["e"]}, geometry=[LineString([(0, 0), (1, 1)])], crs="EPSG:4326"
    )
    with pytest.raises(CRSError, match="EPSG:4326"), IndexWriter(tmp_path / "i.gpkg", CRS) as w:
        w.write_layer("trajectories", frame)
    assert not (tmp_path / "i.gpkg").exists()


def test_custom_layer_and_wkt_crs(tmp_path: Path) -> None:
    wkt = pyproj.CRS("EPSG:2154").to_wkt()
    gpkg = tmp_path / "i.gpkg"
    with IndexWriter(gpkg, wkt) as writer:
        writer.write_layer(
            "trees", gpd.GeoDataFrame({"tree_id": [1, 2]}, geometry=[Point(0, 0), Point(1, 1)])
        )
        writer.write_layer("table", pd.DataFrame({"a": [1.5]}))
    trees = gpd.read_file(gpkg, layer="trees", engine="pyogrio")
    assert pyproj.CRS(trees.crs).equals(pyproj.CRS(wkt))
    assert list(pyogrio.read_dataframe(gpkg, layer="table")["a"]) == [1.5]


def test_iso_time_keeps_nanoseconds() -> None:
    assert iso_time(1_700_000_000, 5) == "2023-11-14T22:13:20.000000005Z"


def test_layer_frame_needs_geometry() -> None:
    with pytest.raises(CatalogError, match="geometry"):
        layer_frame("cells", [dict.fromkeys(LAYER_COLUMNS["cells"], 0)], CRS)
