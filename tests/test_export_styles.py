"""QGIS styles: the layer_styles table as QGIS writes it, and QML that parses."""

from __future__ import annotations

import sqlite3
import xml.etree.ElementTree as ET
from pathlib import Path

import geopandas as gpd
import pyogrio
import pytest
from shapely.geometry import Point, box

from standgrid.errors import CatalogError
from standgrid.export import styles
from standgrid.export.styles import STYLE_COLUMNS, add_layer_style

CRS = "EPSG:32632"


def make_gpkg(path: Path) -> Path:
    cells = gpd.GeoDataFrame({"cell_id": ["a", "b"], "density": [1.0, 9.0]},
                             geometry=[box(0, 0, 1, 1), box(1, 0, 2, 1)], crs=CRS)  # fmt: skip
    cells.to_file(path, layer="cells", engine="pyogrio")
    pts = gpd.GeoDataFrame({"inlier": [True, False]}, geometry=[Point(0, 0), Point(1, 1)], crs=CRS)
    pts.to_file(path, layer="gnss_fixes", engine="pyogrio")
    return path


def parse(qml: str) -> ET.Element:
    root = ET.fromstring(qml.split("\n", 1)[1] if qml.startswith("<!DOCTYPE") else qml)
    assert root.tag == "qgis"
    assert (
        root.get("version", "").startswith("3.")
        and root.get("styleCategories") == "AllStyleCategories"
    )
    return root


def test_layer_styles_table_as_qgis_writes_it(tmp_path: Path) -> None:
    gpkg = make_gpkg(tmp_path / "i.gpkg")
    add_layer_style(gpkg, "cells", styles.load_qml("cells"), description="outline")
    add_layer_style(gpkg, "gnss_fixes", styles.load_qml("gnss_fixes"))
    with sqlite3.connect(gpkg) as db:
        columns = [row[1] for row in db.execute("PRAGMA table_info(layer_styles)")]
        contents = db.execute(
            "SELECT data_type FROM gpkg_contents WHERE table_name = 'layer_styles'"
        ).fetchone()
        rows = db.execute(
            "SELECT f_table_name, f_geometry_column, styleName, useAsDefault, update_time, "
            "styleQML FROM layer_styles ORDER BY id"
        ).fetchall()
        layers = {r[0] for r in db.execute("SELECT table_name FROM gpkg_contents")}
        geom_column = db.execute(
            "SELECT column_name FROM gpkg_geometry_columns WHERE table_name = 'cells'"
        ).fetchone()[0]
    assert tuple(columns) == STYLE_COLUMNS
    assert contents == ("attributes",)
    assert geom_column == "geom"
    assert [r[:4] for r in rows] == [
        ("cells", "geom", "cells", 1),
        ("gnss_fixes", "geom", "gnss_fixes", 1),
    ]
    assert all(r[0] in layers for r in rows)
    assert rows[0][4].endswith("Z")  # update_time default filled in
    parse(rows[0][5])
    # reading is not disturbed by the extra table
    listed = dict(pyogrio.list_layers(gpkg))
    assert listed["cells"] == "Polygon" and listed["layer_styles"] is None
    assert len(gpd.read_file(gpkg, layer="cells", engine="pyogrio")) == 2
    assert len(pyogrio.read_dataframe(gpkg, layer="layer_styles")) == 2


def test_update_and_single_default(tmp_path: Path) -> None:
    gpkg = make_gpkg(tmp_path / "i.gpkg")
    add_layer_style(gpkg, "cells", "<qgis/>", style_name="one")
    add_layer_style(gpkg, "cells", styles.density_style(1, 9), style_name="two")
    add_layer_style(gpkg, "cells", "<qgis version='3.28'/>", style_name="one", default=False)
    with sqlite3.connect(gpkg) as db:
        rows = db.execute(
            "SELECT styleName, useAsDefault, styleQML FROM layer_styles ORDER BY id"
        ).fetchall()
    assert [(r[0], r[1]) for r in rows] == [("one", 0), ("two", 1)]
    assert rows[0][2] == "<qgis version='3.28'/>"


def test_missing_layer_or_file(tmp_path: Path) -> None:
    gpkg = make_gpkg(tmp_path / "i.gpkg")
    with pytest.raises(CatalogError, match="no layer 'trees'"):
        add_layer_style(gpkg, "trees", "<qgis/>")
    with pytest.raises(CatalogError, match="not found"):
        add_layer_style(tmp_path / "none.gpkg", "cells", "<qgis/>")


@pytest.mark.parametrize("name", ["cells", "payloads", "gnss_fixes"])
def test_shipped_qml_parse_and_match_the_builders(name: str) -> None:
    qml = styles.load_qml(name)
    root = parse(qml)
    assert root.find("renderer-v2") is not None
    assert qml == styles._builtin_styles()[name]  # the files are regenerated from the code


def test_cells_style_labels_cell_id() -> None:
    root = parse(styles.load_qml("cells"))
    assert root.find("labeling/settings/text-style").get("fieldName") == "cell_id"
    fill = root.find("renderer-v2/symbols/symbol/layer/Option")
    assert {o.get("name"): o.get("value") for o in fill}["style"] == "no"


def test_diverging_style_is_symmetric_rdbu() -> None:
    root = parse(styles.diverging_style("chm_change", -3.0, 1.0, classes=6))
    renderer = root.find("renderer-v2")
    assert renderer.get("type") == "graduatedSymbol" and renderer.get("attr") == "chm_change"
    ranges = renderer.findall("ranges/range")
    assert len(ranges) == 7  # made odd: one class holds 0
    labels = [r.get("label") for r in ranges]
    assert labels[0].startswith("-3.00") and labels[-1].endswith("3.00")
    middle = ranges[3]
    assert float(middle.get("lower")) < 0 < float(middle.get("upper"))
    colours = [
        {o.get("name"): o.get("value") for o in s.find("layer/Option")}["color"]
        for s in renderer.findall("symbols/symbol")
    ]
    red, _, blue, _ = map(int, colours[0].split(","))
    assert red > blue  # losses are red
    middle_rgb = list(map(int, colours[3].split(",")))[:3]
    assert min(middle_rgb) > 230  # the class holding 0 is near white
    red, _, blue, _ = map(int, colours[-1].split(","))
    assert blue > red  # gains are blue
    assert float(ranges[0].get("lower")) < -1e100 and float(ranges[-1].get("upper")) > 1e100


def test_categorized_and_metric_styles() -> None:
    root = parse(styles.categorized_style("mission", ["m1", "m2", "m3"], geometry="line"))
    assert [c.get("value") for c in root.findall("renderer-v2/categories/category")] == [
        "m1",
        "m2",
        "m3",
    ]
    assert root.find("layerGeometryType").text == "1"
    metric = parse(styles.stand_metric_style("canopy_height_p95", 0, 30))
    assert metric.find("renderer-v2").get("attr") == "canopy_height_p95"
    assert len(metric.findall("renderer-v2/ranges/range")) == 5
