"""Rasters of the real pipeline open styled in QGIS: a ``.qml`` sidecar beside every raster
(enrich's DTM, CHM, density; compare's CHM difference), committed with the catalog, whose
ramp range matches the raster's own data read back with rasterio."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import rasterio

from tests.pipeline_fixtures import EnrichedPair, enriched_pair


@pytest.fixture(scope="session")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    return enriched_pair(tmp_path_factory)


def _shader(qml: Path) -> ET.Element:
    text = qml.read_text("utf-8")
    root = ET.fromstring(text.split("\n", 1)[1])
    renderer = root.find("pipe/rasterrenderer")
    assert renderer is not None and renderer.get("type") == "singlebandpseudocolor"
    shader = renderer.find("rastershader/colorrampshader")
    assert shader is not None
    return shader


def _valid(tif: Path) -> np.ndarray:
    with rasterio.open(tif) as src:
        return np.ma.compressed(src.read(1, masked=True)).astype(np.float64)


@pytest.mark.parametrize("epoch", ["2024", "2028"])
def test_enrich_writes_a_style_beside_every_raster(pair: EnrichedPair, epoch: str) -> None:
    folder = pair.path / "rasters" / epoch
    for name in ("dtm", "chm", "density"):
        assert (folder / f"{name}.qml").is_file(), name
    chm = _valid(folder / "chm.tif")
    shader = _shader(folder / "chm.qml")
    assert float(shader.get("minimumValue")) == 0.0
    assert float(shader.get("maximumValue")) == pytest.approx(np.percentile(chm, 98), rel=1e-5)
    assert all(i.get("label").endswith(" m") for i in shader.findall("item"))
    dtm = _valid(folder / "dtm.tif")
    shader = _shader(folder / "dtm.qml")
    assert float(shader.get("minimumValue")) == pytest.approx(dtm.min(), rel=1e-6)
    assert float(shader.get("maximumValue")) == pytest.approx(dtm.max(), rel=1e-6)
    labels = [i.get("label") for i in _shader(folder / "density.qml").findall("item")]
    assert all(label.endswith(" pts/m²") for label in labels)
    # nothing left in staging: the sidecars were committed with the catalog transaction
    assert not (pair.path / ".staging").exists()


def test_compare_writes_a_diverging_style_beside_the_chm_difference(pair: EnrichedPair) -> None:
    folder = pair.path / "compare" / "2024__2028"
    change = _valid(folder / "chm_diff.tif")
    shader = _shader(folder / "chm_diff.qml")
    lo, hi = float(shader.get("minimumValue")), float(shader.get("maximumValue"))
    assert lo == pytest.approx(-hi) and hi == pytest.approx(np.percentile(np.abs(change), 98))
    items = shader.findall("item")
    assert float(items[len(items) // 2].get("value")) == 0.0
    catalog = json.loads((pair.path / "catalog.json").read_text())
    outputs = catalog["comparisons"]["2024__2028"]["outputs"]
    assert outputs["chm_difference_style"] == "compare/2024__2028/chm_diff.qml"
