"""Virtual point cloud (.vpc): STAC ItemCollection structure and EPSG:4326 footprints."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyproj
import pytest
from shapely.geometry import Point, box, shape

from standgrid.export.gpkg import VpcTile, write_vpc
from standgrid.export.las import write_tile
from standgrid.pointcloud import PointCloud

CRS = "EPSG:32632"


def test_vpc_structure_and_bbox(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    entries = []
    for i in range(2):
        xyz = rng.uniform(
            [500_000 + 50 * i, 6_000_000, 90], [500_050 + 50 * i, 6_000_050, 110], (300, 3)
        )
        core = PointCloud(xyz[:250])
        buffer = PointCloud(xyz[250:])
        info = write_tile(tmp_path / "tiles" / "2024" / f"c{i}.laz", core, crs=CRS, buffer=buffer)
        entries.append(info.vpc_entry("2024-05-01T00:00:00Z"))
    out = write_vpc(tmp_path / "index.vpc", entries)

    doc = json.loads(out.read_text())
    assert doc["type"] == "FeatureCollection" and len(doc["features"]) == 2
    to_wgs = pyproj.Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    for i, item in enumerate(doc["features"]):
        assert item["type"] == "Feature" and item["stac_version"] == "1.0.0"
        assert any("pointcloud" in e for e in item["stac_extensions"])
        assert any("projection" in e for e in item["stac_extensions"])
        props = item["properties"]
        assert props["pc:count"] == 300 and props["pc:type"] == "lidar"
        assert props["proj:epsg"] == 32632
        assert pyproj.CRS(props["proj:wkt2"]).to_epsg() == 32632
        assert props["datetime"] == "2024-05-01T00:00:00Z"
        xmin, ymin, zmin, xmax, ymax, zmax = props["proj:bbox"]
        assert 90 <= zmin < zmax <= 110
        assert shape(props["proj:geometry"]).equals(box(xmin, ymin, xmax, ymax))
        assert item["assets"]["data"]["href"] == f"./tiles/2024/c{i}.laz"
        assert (tmp_path / item["assets"]["data"]["href"]).is_file()
        lon, lat = to_wgs.transform((xmin + xmax) / 2, (ymin + ymax) / 2)
        assert shape(item["geometry"]).contains(Point(lon, lat))
        b = item["bbox"]
        assert b[0] < lon < b[3] and b[1] < lat < b[4]
        assert 8.9 < lon < 9.1 and 54.0 < lat < 54.2  # UTM 32N, 500 km E / 6000 km N


def test_vpc_accepts_plain_tuples_and_2d_bounds(tmp_path: Path) -> None:
    tile = tmp_path / "a.las"
    tile.write_bytes(b"")
    out = write_vpc(tmp_path / "sub" / "x.vpc", [VpcTile(tile, (0, 0, 10, 10), "EPSG:2154", 5)])
    item = json.loads(out.read_text())["features"][0]
    assert item["assets"]["data"]["href"] == "./../a.las"
    assert item["properties"]["pc:encoding"] == "application/vnd.las"
    assert item["properties"]["proj:bbox"] == pytest.approx([0, 0, 0, 10, 10, 0])
