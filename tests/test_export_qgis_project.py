"""The catalog's QGIS project (catalog.qgz) on the bundled pair, tiled, enriched and compared:
read back with a second reader (zipfile + xml.etree), its filters checked against the
GeoPackage read with pyogrio, and opened and rendered by real QGIS 3.22 (Debian's
python3-qgis, skipped when absent)."""

from __future__ import annotations

import json
import os
import re
import sqlite3
import subprocess
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import pyogrio
import pytest

from standgrid.export import styles
from standgrid.export.qgis_project import ProjectGroup, ProjectLayer, write_qgis_project
from tests.pipeline_fixtures import CRS, EnrichedPair, enriched_pair

QGIS_PYTHON = "/usr/bin/python3"
CHECKER = Path(__file__).with_name("qgis_check.py")
CHANGE = "change 2024→2028"


@pytest.fixture(scope="session")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    return enriched_pair(tmp_path_factory)


def read_project(root: Path) -> ET.Element:
    with zipfile.ZipFile(root / "catalog.qgz") as archive:
        assert archive.namelist() == ["catalog.qgs"]
        text = archive.read("catalog.qgs").decode("utf-8")
    return ET.fromstring(text.split("\n", 1)[1])


def tree_groups(project: ET.Element) -> dict[str, ET.Element]:
    return {g.get("name", ""): g for g in project.findall("layer-tree-group/layer-tree-group")}


def map_layers(project: ET.Element) -> dict[str, ET.Element]:
    return {m.findtext("id", ""): m for m in project.findall("projectlayers/maplayer")}


def split_source(datasource: str) -> tuple[str, dict[str, str]]:
    path, *parts = datasource.split("|")
    return path, dict(part.split("=", 1) for part in parts)


def test_every_datasource_is_relative_and_exists(pair: EnrichedPair) -> None:
    project = read_project(pair.path)
    layers = map_layers(project)
    assert len(layers) >= 20
    for layer in layers.values():
        path, _ = split_source(layer.findtext("datasource", ""))
        assert path.startswith("./"), path
        assert (pair.path / path).is_file(), path
    tree = {n.get("id"): n for n in project.iter("layer-tree-layer")}
    assert set(tree) == set(layers)
    for layer_id, node in tree.items():  # legend and layer agree on the source
        assert node.get("source") == layers[layer_id].findtext("datasource")
    assert project.findtext("properties/Paths/Absolute") == "false"
    assert project.findtext("projectCrs/spatialrefsys/authid") == CRS
    assert not (pair.path / ".staging").exists()  # committed with the catalog


def test_groups_order_and_visibility(pair: EnrichedPair) -> None:
    groups = tree_groups(read_project(pair.path))
    assert list(groups) == [CHANGE, "2028", "2024"]  # change, then epochs newest first
    checked = {name: g.get("checked") == "Qt::Checked" for name, g in groups.items()}
    assert checked == {CHANGE: False, "2028": True, "2024": False}
    for epoch in ("2028", "2024"):
        layers = [
            (n.get("name"), n.get("checked") == "Qt::Checked")
            for n in groups[epoch].findall("layer-tree-layer")
        ]
        assert layers == [
            ("Trees: crown by height (m), DBH (cm)", True),
            ("Trajectories", True),
            ("Stands 1 ha: basal area (m²/ha)", True),
            ("Basal area (m²/ha), 20 m cells", True),
            ("GNSS fixes", False),
            ("Payload footprints", False),
            ("Tiles (20 m cells, points)", False),
            ("Observed ground", False),
            ("Point density (pts/m²)", False),
            ("CHM (m)", True),
            ("DTM (m)", False),
        ]
    change = [n.get("name") for n in groups[CHANGE].findall("layer-tree-layer")]
    assert change == [
        "Tree changes (grown, new, removed)",
        "Basal area change (m²/ha), 20 m cells",
        "CHM change (m)",
    ]


def test_filters_select_the_rows_of_their_group(pair: EnrichedPair) -> None:
    project = read_project(pair.path)
    layers = map_layers(project)
    missions = json.loads((pair.path / "catalog.json").read_text())["missions"]
    for name, group in tree_groups(project).items():
        for node in group.findall("layer-tree-layer"):
            layer = layers[node.get("id", "")]
            if layer.findtext("provider") != "ogr":
                continue
            path, options = split_source(layer.findtext("datasource", ""))
            subset = options["subset"]
            rows = pyogrio.read_dataframe(
                pair.path / path, layer=options["layername"], where=subset, read_geometry=False
            )
            assert len(rows) > 0, (name, node.get("name"))
            if name == CHANGE:
                assert set(rows["epoch_from"]) == {"2024"} and set(rows["epoch_to"]) == {"2028"}
            elif "epoch" in rows.columns:
                assert set(rows["epoch"].astype(str)) == {name}, node.get("name")
            else:  # GNSS fixes: by the epoch's missions
                assert {missions[m]["epoch"] for m in rows["mission"]} == {name}
            if "level" in rows.columns:
                assert rows["level"].nunique() == 1
            if name != CHANGE:  # one comparison: its rows are all the change layers hold
                everything = pyogrio.read_info(pair.path / path, layer=options["layername"])
                assert len(rows) < everything["features"]  # the filter does filter


def canonical(element: ET.Element | None) -> bytes:
    """An element without its layout whitespace (the project is indented anew)."""
    assert element is not None
    copy = ET.fromstring(ET.tostring(element))
    for node in copy.iter():
        node.text = (node.text or "").strip() or None
        node.tail = None
    return ET.tostring(copy)


def test_styles_are_the_catalogs_own(pair: EnrichedPair) -> None:
    """Rasters embed their .qml sidecar's renderer, but the CHMs share one range (the same
    colour is the same height in every epoch); stand_changes its default layer style."""
    project = read_project(pair.path)
    layers = map_layers(project)
    rasters = [m for m in layers.values() if m.findtext("provider") == "gdal"]
    assert len(rasters) == 2 * 4 + 1
    chm_tops, chm_ranges = [], set()
    for layer in rasters:
        path, _ = split_source(layer.findtext("datasource", ""))
        sidecar = (pair.path / path).with_suffix(".qml").read_text("utf-8")
        expected = ET.fromstring(sidecar.split("\n", 1)[1]).find("pipe/rasterrenderer")
        assert expected is not None
        got = layer.find("pipe/rasterrenderer")
        assert got is not None
        if Path(path).name == "chm.tif":
            chm_tops.append(float(expected.get("classificationMax", "nan")))
            chm_ranges.add((got.get("classificationMin"), got.get("classificationMax")))
            for key in ("classificationMin", "classificationMax"):
                expected.attrib.pop(key)
                got.attrib.pop(key)
            for node in (expected, got):  # the shader and its stops follow the range
                for shader in node.iter("colorrampshader"):
                    shader.attrib.pop("minimumValue", None)
                    shader.attrib.pop("maximumValue", None)
                for item in node.iter("item"):
                    item.attrib.pop("value", None)
                    item.attrib.pop("label", None)
        assert canonical(got) == canonical(expected)
    assert len(chm_tops) == 2 and len(set(chm_tops)) == 2  # the sidecars: each its own
    ((low, high),) = chm_ranges  # the project: one range
    assert float(low) == 0.0 and float(high) == pytest.approx(max(chm_tops))
    with sqlite3.connect(pair.path / "index.gpkg") as db:
        qml = db.execute(
            "SELECT styleQML FROM layer_styles WHERE f_table_name = 'tree_changes' AND useAsDefault"
        ).fetchone()[0]
    (changes,) = [m for m in layers.values() if "=tree_changes" in m.findtext("datasource", "")]
    expected = ET.fromstring(qml.split("\n", 1)[1]).find("renderer-v2")
    assert canonical(changes.find("renderer-v2")) == canonical(expected)
    (stands,) = [m for m in layers.values() if "=stand_changes" in m.findtext("datasource", "")]
    # graduated styles come as their classes' rules plus a grey "no value" rule (NULL)
    renderer = stands.find("renderer-v2")
    assert renderer is not None and renderer.get("type") == "RuleRenderer"
    rules = renderer.findall("rules/rule")
    assert rules[-1].get("filter") == "ELSE" and rules[-1].get("label") == "no value"
    assert all('"basal_area_m2_ha_delta"' in r.get("filter", "") for r in rules[:-1])
    bounds = [
        float(b)
        for r in rules[:-1]
        for b in re.findall(r"[<>]=? (-?[0-9.e+-]+)", r.get("filter", ""))
    ]
    assert min(bounds) == pytest.approx(-max(bounds))  # diverging: symmetric around 0
    trees = [m for m in layers.values() if "layername=trees" in m.findtext("datasource", "")]
    for layer in trees:  # crowns by height, labelled with DBH in cm
        tree_rules = layer.findall("renderer-v2/rules/rule")
        assert all('"height_m"' in r.get("filter", "") for r in tree_rules[:-1])
        assert layer.get("labelsEnabled") == "1"
        assert "dbh_m" in layer.find("labeling/settings/text-style").get("fieldName")


def test_writer_refuses_a_layer_without_geometry_type(tmp_path: Path) -> None:
    layer = ProjectLayer("x", "index.gpkg", "<qgis/>", table="cells")
    with pytest.raises(ValueError, match="geometry"):
        write_qgis_project(
            tmp_path / "p.qgz", [ProjectGroup("g", (layer,))], crs=CRS, extent=(0, 0, 1, 1)
        )
    assert not (tmp_path / "p.qgz").exists()


def _qgis_available() -> bool:
    if not os.path.exists(QGIS_PYTHON):
        return False
    probe = subprocess.run([QGIS_PYTHON, "-c", "import qgis.core"], capture_output=True)
    return probe.returncode == 0


def run_qgis(project: Path, png: Path, group: str | None = None) -> dict[str, object]:
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONPATH": ""}
    args = [QGIS_PYTHON, str(CHECKER), str(project), str(png), *([group] if group else [])]
    done = subprocess.run(args, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


@pytest.mark.skipif(not _qgis_available(), reason="no PyQGIS (apt-get install python3-qgis)")
@pytest.mark.parametrize("group", [None, CHANGE, "2024"])
def test_qgis_opens_and_renders_the_project(
    pair: EnrichedPair, tmp_path: Path, group: str | None
) -> None:
    png = tmp_path / "map.png"
    result = run_qgis(pair.path / "catalog.qgz", png, group)
    assert result["read"] is True
    assert result["crs"] == CRS
    assert result["bad_layers"] == [] and result["messages"] == []
    assert result["project_error"] == ""
    assert result["render_errors"] == []
    layers = result["layers"]
    assert isinstance(layers, dict) and len(layers) >= 20
    for name, info in layers.items():
        assert info["valid"], name
        if info["provider"] == "ogr":  # QGIS applies the same filter pyogrio does
            path, options = split_source(info["source"].replace(str(pair.path), "."))
            assert path == "./index.gpkg"  # the relative path resolved beside the project
            where = info["subset"]
            expected = len(
                pyogrio.read_dataframe(
                    pair.path / "index.gpkg",
                    layer=options["layername"],
                    where=where,
                    read_geometry=False,
                )
            )
            assert info["features"] == expected > 0, name
    image = result["image"]
    assert isinstance(image, dict)
    assert png.is_file()
    assert image["opaque"] > 0.3 * image["sampled"]  # the map is drawn, not blank
    assert image["colours"] > 50  # ramps, not one flat colour


@pytest.mark.skipif(not _qgis_available(), reason="no PyQGIS (apt-get install python3-qgis)")
def test_the_qgis_check_sees_a_broken_layer(pair: EnrichedPair, tmp_path: Path) -> None:
    """The checker can fail: a layer whose file is missing is reported, and drawn nowhere."""
    style = (pair.path / "rasters/2024/chm.qml").read_text("utf-8")
    layer = ProjectLayer("CHM (m)", "rasters/2024/gone.tif", style, provider="gdal")
    project = write_qgis_project(
        tmp_path / "broken.qgz",
        [ProjectGroup("2024", (layer,))],
        crs=CRS,
        extent=(614680.0, 5737100.0, 614800.0, 5737200.0),
    )
    result = run_qgis(project, tmp_path / "broken.png")
    assert result["bad_layers"] == ["CHM (m)"]
    assert any("gone.tif" in m for m in result["messages"])  # the log hook hears QGIS
    assert result["image"] == {"sampled": 75000, "opaque": 0, "colours": 0}


def test_writer_escapes_names_and_filters(tmp_path: Path) -> None:
    """A quote or ampersand in a name or filter survives the XML (read back with ElementTree)."""
    subset = "\"mission\" IN ('a&b', 'it''s')"
    layer = ProjectLayer(
        "GNSS <fixes> & more",
        "index.gpkg",
        "<qgis/>",
        table="gnss_fixes",
        geometry="point",
        subset=subset,
        visible=False,
    )
    out = write_qgis_project(
        tmp_path / "p.qgz",
        [ProjectGroup("it's", (layer,), visible=False)],
        crs=CRS,
        extent=(0.0, 0.0, 10.0, 20.0),
    )
    with zipfile.ZipFile(out) as archive:
        project = ET.fromstring(archive.read("p.qgs").decode("utf-8").split("\n", 1)[1])
    (group,) = project.findall("layer-tree-group/layer-tree-group")
    assert group.get("name") == "it's" and group.get("checked") == "Qt::Unchecked"
    (node,) = group.findall("layer-tree-layer")
    assert node.get("name") == "GNSS <fixes> & more" and node.get("checked") == "Qt::Unchecked"
    assert node.get("source") == f"./index.gpkg|layername=gnss_fixes|subset={subset}"
    assert project.find("projectlayers/maplayer").get("geometry") == "Point"
    view = project.find("ProjectViewSettings/DefaultViewExtent")
    assert [float(view.get(k)) for k in ("xmin", "ymin", "xmax", "ymax")] == [0, 0, 10, 20]


def test_project_opens_on_the_data_with_a_small_margin(pair: EnrichedPair) -> None:
    """Canvas, default view and the project's full extent ("zoom full") are the cells' extent
    plus a small margin, not the union of the layers (a 1 ha stand holding one edge cell
    reaches 80 m beyond the data: half the frame empty)."""
    project = read_project(pair.path)
    xmin, ymin, xmax, ymax = pyogrio.read_info(pair.path / "index.gpkg", layer="cells")[
        "total_bounds"
    ]
    stands = pyogrio.read_info(pair.path / "index.gpkg", layer="stand_metrics")["total_bounds"]
    assert stands[0] < xmin - 50  # the layers' union is much wider than the data
    canvas = project.find("mapcanvas/extent")
    assert canvas is not None
    boxes = {"canvas": [float(canvas.findtext(k, "nan")) for k in ("xmin", "ymin", "xmax", "ymax")]}
    for tag in ("DefaultViewExtent", "PresetFullExtent"):
        view = project.find(f"ProjectViewSettings/{tag}")
        assert view is not None, tag
        assert view.findtext("spatialrefsys/authid") == CRS
        boxes[tag] = [float(view.get(k, "nan")) for k in ("xmin", "ymin", "xmax", "ymax")]
    margin = 0.1 * max(xmax - xmin, ymax - ymin)
    for name, (x0, y0, x1, y1) in boxes.items():
        assert xmin - margin <= x0 < xmin and ymin - margin <= y0 < ymin, name
        assert xmax < x1 <= xmax + margin and ymax < y1 <= ymax + margin, name


#: Run by QGIS's python on a project: which features of each 20 m cell choropleth the
#: renderer draws (NULL and valued, with colours), its legend, and the extents QGIS takes.
QGIS_RENDERED = r"""
import json, sys
from qgis.core import QgsApplication, QgsProject, QgsRenderContext, QgsExpressionContextUtils
from qgis.gui import QgsMapCanvas
app = QgsApplication([], True)
app.initQgis()
project = QgsProject.instance()
canvas = QgsMapCanvas()
canvas.setObjectName("theMapCanvas")
canvas.resize(1200, 1000)
project.readProject.connect(canvas.readProject)
assert project.read(sys.argv[1])
box = lambda r: [r.xMinimum(), r.yMinimum(), r.xMaximum(), r.yMaximum()]
out = {"full": box(project.viewSettings().fullExtent()),
       "view": box(project.viewSettings().defaultViewExtent()), "canvas": box(canvas.extent()),
       "layers": {}}
for node in project.layerTreeRoot().findLayers():
    layer = node.layer()
    if not layer.name().startswith("Basal area (m²/ha), "):
        continue
    field = "basal_area_m2_ha"
    renderer = layer.renderer().clone()
    context = QgsRenderContext()
    context.expressionContext().appendScopes(
        QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    renderer.startRender(context, layer.fields())
    drawn = {"null": 0, "null_drawn": 0, "valued": 0, "valued_drawn": 0, "null_colours": []}
    for feature in layer.getFeatures():
        context.expressionContext().setFeature(feature)
        kind = "null" if feature[field] is None or str(feature[field]) == "NULL" else "valued"
        symbols = renderer.symbolsForFeature(feature, context)
        drawn[kind] += 1
        drawn[kind + "_drawn"] += int(bool(symbols))
        if kind == "null" and symbols:
            drawn["null_colours"].append(symbols[0].color().name())
    renderer.stopRender(context)
    drawn["legend"] = [item.label() for item in renderer.legendSymbolItems()]
    out["layers"][node.parent().name()] = drawn
project.clear()
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def rendered(pair: EnrichedPair) -> dict[str, object]:
    if not _qgis_available():
        pytest.skip("no PyQGIS (apt-get install python3-qgis)")
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONPATH": ""}
    done = subprocess.run(
        [QGIS_PYTHON, "-c", QGIS_RENDERED, str(pair.path / "catalog.qgz")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def test_qgis_draws_cells_without_a_value_grey(pair: EnrichedPair, rendered: dict) -> None:
    """As the web viewer: a cell whose basal area is NULL is drawn, grey, and the legend
    says "no value"; every valued cell is drawn as before."""
    metrics = pyogrio.read_dataframe(
        pair.path / "index.gpkg", layer="stand_metrics", where='"level" = 0', read_geometry=False
    )
    layers = rendered["layers"]
    assert set(layers) == {"2024", "2028"}
    for epoch, drawn in layers.items():
        rows = metrics[metrics["epoch"].astype(str) == epoch]["basal_area_m2_ha"]
        assert drawn["null"] == rows.isna().sum() > 0, epoch  # the pair has such edge cells
        assert drawn["valued"] == rows.notna().sum()
        assert drawn["null_drawn"] == drawn["null"] and drawn["valued_drawn"] == drawn["valued"]
        assert set(drawn["null_colours"]) == {styles.NO_VALUE}
        assert drawn["legend"][-1] == "no value" and len(drawn["legend"]) == 6


def test_qgis_zooms_full_to_the_data(pair: EnrichedPair, rendered: dict) -> None:
    """QGIS itself: the project's full extent ("zoom full"), default view and the canvas
    opened on it hold the cells with at most a small margin; before, zoom full reached the
    whole of the 1 ha stands (the union of the layers): half the frame empty."""
    xmin, ymin, xmax, ymax = pyogrio.read_info(pair.path / "index.gpkg", layer="cells")[
        "total_bounds"
    ]
    width, height = xmax - xmin, ymax - ymin
    for name in ("full", "view", "canvas"):
        x0, y0, x1, y1 = rendered[name]
        assert x0 <= xmin and y0 <= ymin and x1 >= xmax and y1 >= ymax, name
        # a little margin; the canvas widens one side to the window's shape
        assert (x1 - x0) <= 1.3 * width and (y1 - y0) <= 1.3 * height, (name, rendered[name])
    assert rendered["full"] == pytest.approx(rendered["view"])
