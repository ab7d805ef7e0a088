"""Read every collection of an OGC API - Features service with real QGIS (its "OAPIF" provider,
what "Layer > Add WFS / OGC API - Features Layer" uses); run by Debian's /usr/bin/python3.

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 tests/qgis_oapif_check.py BASE_URL NAME...

Prints one JSON object: name -> {valid, features (counted by iterating them), fields, crs,
extent}, and ``messages`` (message-log entries of level warning or worse). Needs no standgrid
import (the system Python has no standgrid).
"""

from __future__ import annotations

import json
import sys


def main(base: str, names: list[str]) -> dict[str, object]:
    from qgis.core import QgsVectorLayer
    from qgis_app import start_qgis

    app, messages = start_qgis()
    out: dict[str, object] = {}
    for name in names:
        layer = QgsVectorLayer(f"url='{base}' typename='{name}'", name, "OAPIF")
        entry: dict[str, object] = {"valid": layer.isValid()}
        if layer.isValid():
            entry["features"] = sum(1 for _ in layer.getFeatures())
            entry["fields"] = [f.name() for f in layer.fields()]
            entry["crs"] = layer.crs().authid()
            extent = layer.extent()
            entry["extent"] = [
                extent.xMinimum(),
                extent.yMinimum(),
                extent.xMaximum(),
                extent.yMaximum(),
            ]
        out[name] = entry
        del layer  # before exitQgis: a provider outliving the application crashes it
    out["messages"] = messages
    app.exitQgis()
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2:])))
