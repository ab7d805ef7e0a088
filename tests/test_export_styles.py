"""QGIS styles: the layer_styles table as QGIS writes it, and QML that parses."""

from __future__ import annotations

import re
import sqlite3
import xml.etree.ElementTree as ET
from pathlib import Path

import geopandas as gpd
import numpy as np
import pyogrio
import pytest
import rasterio
from rasterio.transform import Affine
from shapely.geometry import Point, box

from standgrid.errors import CatalogError, FormatError
from standgrid.export import styles
from standgrid.export.styles import STYLE_COLUMNS, add_layer_style

CRS = "EPSG:32632"


def make_gpkg(path: Path) -> Path:
    cells = gpd.GeoDataFrame(
        {"cell_id": ["a", "b"], "density": [1.0, 9.0]},
        geometry=[box(0, 0, 1, 1), box(1, 0, 2, 1)],
        crs=CRS,
    )
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
    rules = metric.findall("renderer-v2/rules/rule")  # 5 classes and cells without a value
    assert len(rules) == 6 and rules[-1].get("filter") == "ELSE"
    assert all('"canopy_height_p95"' in r.get("filter", "") for r in rules[:-1])


def _rule_matches(rule_filter: str, value: float | None) -> bool:
    """A class rule of :func:`styles.with_no_value` (``"f" > a AND "f" <= b``) on a value."""
    if value is None:  # NULL compares to nothing: no class rule holds
        return False
    ops = {">": float.__gt__, ">=": float.__ge__, "<=": float.__le__, "<": float.__lt__}
    terms = re.findall(r'"\w+" (>=|<=|>|<) (-?[0-9.e+-]+)', rule_filter)
    assert terms and len(terms) == rule_filter.count(" AND ") + 1, rule_filter
    return all(ops[op](float(value), float(bound)) for op, bound in terms)


@pytest.mark.parametrize(
    "graduated",
    [
        styles.graduated_style(
            "ba", 10.0, 35.0, ramp=styles.YLGN, alpha=190, precision=1, unit="m²/ha"
        ),
        styles.diverging_style("ba_delta", -4.0, 2.5, alpha=170),
    ],
)
def test_no_value_rule_draws_null_cells_grey_like_the_viewer(graduated: str) -> None:
    """QGIS's graduated renderer draws nothing for NULL; the same classes as rules plus an
    ELSE rule draw such a cell grey (the viewer's #c8c8c8), labelled "no value"."""
    qml = styles.with_no_value(graduated)
    root = parse(qml)
    renderer = root.find("renderer-v2")
    assert renderer is not None and renderer.get("type") == "RuleRenderer"
    *classes, rest = renderer.findall("rules/rule")
    assert rest.get("filter") == "ELSE" and rest.get("label") == "no value"
    symbols = {s.get("name"): s for s in renderer.findall("symbols/symbol")}

    def colour(symbol: ET.Element) -> str:
        return {o.get("name"): o.get("value") for o in symbol.iter("Option")}["color"]

    grey = colour(symbols[rest.get("symbol")]).split(",")
    first = colour(symbols[classes[0].get("symbol")]).split(",")
    assert grey[:3] == ["200", "200", "200"] and grey[3] == first[3]  # alpha as the classes
    # the graduated style's classes: same labels and colours, each value in exactly one
    source = parse(graduated).find("renderer-v2")
    assert source is not None and source.get("type") == "graduatedSymbol"
    ranges = source.findall("ranges/range")
    by_name = {s.get("name"): s for s in source.findall("symbols/symbol")}
    assert [r.get("label") for r in classes] == [r.get("label") for r in ranges]
    assert [colour(symbols[r.get("symbol")]) for r in classes] == [
        colour(by_name[r.get("symbol")]) for r in ranges
    ]
    for value in [*np.linspace(-60.0, 60.0, 2401).tolist(), None]:
        hits = [i for i, r in enumerate(classes) if _rule_matches(r.get("filter", ""), value)]
        assert len(hits) == (0 if value is None else 1), (value, hits)
        if value is not None:  # the class the graduated renderer picks (first that holds it)
            lower = [float(r.get("lower")) for r in ranges]
            upper = [float(r.get("upper")) for r in ranges]
            picked = next(i for i in range(len(ranges)) if lower[i] <= value <= upper[i])
            assert hits == [picked], value
    # built directly; a style that is not graduated is left as it is; idempotent
    field = source.get("attr", "")
    if field == "ba":
        direct = styles.graduated_style(
            field,
            10.0,
            35.0,
            ramp=styles.YLGN,
            alpha=190,
            precision=1,
            unit="m²/ha",
            no_value=styles.NO_VALUE,
        )
        assert direct == qml
    assert styles.with_no_value(styles.load_qml("cells")) == styles.load_qml("cells")
    assert styles.with_no_value(qml) == qml


# --- raster styles (QML sidecars) ---------------------------------------------------------


def _raster(path: Path, data: np.ndarray, nodata: float = -9999.0) -> Path:
    """A real GeoTIFF (rasterio) of ``data`` at 1 m pixels."""
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[1],
        height=data.shape[0],
        count=1,
        dtype=data.dtype,
        crs=CRS,
        transform=Affine(1.0, 0, 500_000.0, 0, -1.0, 6_700_000.0),
        nodata=nodata,
    ) as dst:
        dst.write(data, 1)
    return path


def _pseudocolor(root: ET.Element) -> tuple[ET.Element, ET.Element, list[ET.Element]]:
    renderer = root.find("pipe/rasterrenderer")
    assert renderer is not None and renderer.get("type") == "singlebandpseudocolor"
    assert renderer.get("band") == "1"
    shader = renderer.find("rastershader/colorrampshader")
    assert shader is not None and shader.get("colorRampType") == "INTERPOLATED"
    assert shader.find("colorramp").get("type") == "gradient"
    return renderer, shader, shader.findall("item")


def test_chm_style_is_a_height_ramp_over_0_to_p98(tmp_path: Path) -> None:
    heights = np.linspace(0.0, 40.0, 10_000, dtype=np.float32).reshape(100, 100)
    heights[0, :5] = -9999.0  # nodata does not enter the range
    heights[99, 99] = 400.0  # an outlier does not stretch it
    tif = _raster(tmp_path / "chm.tif", heights)
    qml = styles.write_raster_style(tif)
    assert qml == tmp_path / "chm.qml"  # beside the raster, where QGIS looks for it
    renderer, shader, items = _pseudocolor(parse(qml.read_text("utf-8")))
    valid = heights[heights != -9999.0].astype(np.float64)
    p98 = float(np.percentile(valid, 98))
    assert float(shader.get("minimumValue")) == 0.0
    assert float(shader.get("maximumValue")) == pytest.approx(p98, rel=1e-6)
    assert float(renderer.get("classificationMax")) == pytest.approx(p98, rel=1e-6)
    values = [float(i.get("value")) for i in items]
    assert values[0] == 0.0 and values[-1] == pytest.approx(p98, rel=1e-6)
    assert values == sorted(values) and len(values) == len(styles.VIRIDIS)
    assert [i.get("color") for i in items] == list(styles.VIRIDIS)
    assert all(i.get("label").endswith(" m") for i in items)
    assert items[-1].get("label") == f"{p98:.1f} m"
    assert shader.get("clip") == "0"  # taller than p98: the top colour, not hidden


def test_dtm_density_and_change_ranges(tmp_path: Path) -> None:
    ground = np.arange(120.0, 220.0, dtype=np.float32).reshape(10, 10)
    _, _, items = _pseudocolor(
        parse(styles.write_raster_style(_raster(tmp_path / "dtm.tif", ground)).read_text())
    )
    assert [float(i.get("value")) for i in (items[0], items[-1])] == [120.0, 219.0]
    assert [i.get("color") for i in items] == list(styles.TERRAIN)

    density = np.full((10, 10), 50.0, dtype=np.float32)
    _, _, items = _pseudocolor(
        parse(styles.write_raster_style(_raster(tmp_path / "density.tif", density)).read_text())
    )
    assert float(items[0].get("value")) == 0.0 and items[-1].get("label") == "50 pts/m²"
    assert [i.get("color") for i in items] == list(styles.YLORRD)

    change = np.linspace(-1.0, 6.0, 100, dtype=np.float32).reshape(10, 10)
    tif = _raster(tmp_path / "chm_diff.tif", change)
    _, _, items = _pseudocolor(parse(styles.write_raster_style(tif).read_text()))
    half = float(np.percentile(np.abs(change.astype(np.float64)), 98))
    values = [float(i.get("value")) for i in items]
    assert values[0] == pytest.approx(-half) and values[-1] == pytest.approx(half)
    middle = items[len(items) // 2]
    assert float(middle.get("value")) == 0.0 and middle.get("label") == "0.00 m"
    assert middle.get("color") == "#f7f7f7"  # white at no change
    assert items[0].get("color") == styles.RDBU[0]  # loss red
    assert items[-1].get("color") == styles.RDBU[-1]  # gain blue
    assert items[0].get("label") == f"{-half:.2f} m" and items[-1].get("label").startswith("+")


def test_observed_mask_is_paletted_and_semi_transparent() -> None:
    root = parse(styles.raster_style("observed"))
    renderer = root.find("pipe/rasterrenderer")
    assert renderer.get("type") == "paletted"
    entries = {e.get("value"): e for e in renderer.findall("colorPalette/paletteEntry")}
    assert set(entries) == {"0", "1"}
    assert entries["1"].get("label") == "observed"
    assert entries["0"].get("label") == "not observed"
    assert all(0 < int(e.get("alpha")) < 255 for e in entries.values())
    assert entries["0"].get("color") != entries["1"].get("color")


def test_raster_style_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no raster style"):
        styles.write_raster_style(tmp_path / "something.tif")
    with pytest.raises(ValueError, match="unknown raster kind"):
        styles.raster_style("slope")
    with pytest.raises(FormatError, match="cannot read raster"):
        styles.write_raster_style(tmp_path / "chm.tif")  # no such file
    assert styles.raster_kind("compare/a__b/chm_diff.tif") == "chm_change"
    empty = _raster(tmp_path / "chm.tif", np.full((3, 3), -9999.0, dtype=np.float32))
    assert styles.raster_range(empty, "chm") == (0.0, 1.0)  # no valid pixel: a usable ramp
