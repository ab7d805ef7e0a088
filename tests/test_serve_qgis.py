"""QGIS itself reads every collection of `standgrid serve`'s OGC API - Features (the OAPIF
provider of QGIS 3.22, Debian's python3-qgis; skipped when absent)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pyogrio
import pytest

QGIS_PYTHON = "/usr/bin/python3"
CHECKER = Path(__file__).with_name("qgis_oapif_check.py")


def _qgis_available() -> bool:
    if not Path(QGIS_PYTHON).exists():
        return False
    probe = subprocess.run(
        [QGIS_PYTHON, "-c", "import qgis.core"], capture_output=True, timeout=60, check=False
    )
    return probe.returncode == 0


pytestmark = pytest.mark.skipif(
    not _qgis_available(), reason="no PyQGIS (apt-get install python3-qgis)"
)


def test_qgis_loads_every_collection_with_all_its_features(
    enriched_base: str, enriched_catalog: Path
) -> None:
    base, catalog = enriched_base, enriched_catalog
    layers = sorted(
        n for n, _ in pyogrio.list_layers(catalog / "index.gpkg") if n != "layer_styles"
    )
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", PYTHONPATH="")
    run = subprocess.run(
        [QGIS_PYTHON, str(CHECKER), f"{base}/ogc", *layers],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    print(json.dumps({k: v for k, v in result.items() if k != "messages"}, indent=1)[:3000])
    assert result["messages"] == []
    for layer in layers:
        entry = result[layer]
        expected = pyogrio.read_info(catalog / "index.gpkg", layer=layer)["features"]
        assert entry["valid"], layer
        assert entry["features"] == expected, layer
        fields = set(pyogrio.read_info(catalog / "index.gpkg", layer=layer)["fields"])
        assert fields <= set(entry["fields"]), layer
