"""Open a QGIS project with real PyQGIS and render it (run by Debian's /usr/bin/python3).

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 tests/qgis_check.py PROJECT OUT.png [GROUP [PAGE]]

Prints one JSON object: ``read`` (QgsProject.read's result), ``layers`` (name -> valid,
provider, feature count or raster size), ``bad_layers`` (layers QGIS could not load),
``messages`` (message-log entries of level warning or worse), ``groups`` (name -> checked,
layer names top first) and ``image`` (non-transparent pixels and distinct colours of the
PNG). With ``GROUP``, only that group is checked before rendering; else the project's own
visibility is used. With ``PAGE.png``, also a printable page (map, legend, scale bar) for
people to look at. Needs no standgrid import (the system Python has no standgrid).
"""

from __future__ import annotations

import json
import sys


def main(
    project_path: str, png: str, group: str | None = None, layout_png: str | None = None
) -> dict[str, object]:
    from qgis.core import (
        Qgis,
        QgsMapRendererParallelJob,
        QgsMapSettings,
        QgsProject,
    )
    from qgis.PyQt.QtCore import QSize
    from qgis.PyQt.QtGui import QColor
    from qgis_app import start_qgis

    app, messages = start_qgis()
    project = QgsProject.instance()
    bad: list[str] = []
    ok = project.read(project_path)
    for layer in project.mapLayers().values():
        if not layer.isValid():
            bad.append(layer.name())
    root = project.layerTreeRoot()
    groups = {}
    for node in root.findGroups():
        if group:  # "" or None: the project's own visibility
            node.setItemVisibilityChecked(node.name() == group)
        groups[node.name()] = {
            "checked": node.itemVisibilityChecked(),
            "layers": [child.name() for child in node.findLayers()],
            "visible": [
                child.name() for child in node.findLayers() if child.itemVisibilityChecked()
            ],
        }
    layers = {}
    for tree_layer in root.findLayers():
        layer = tree_layer.layer()
        info: dict[str, object] = {
            "valid": layer.isValid(),
            "provider": layer.providerType(),
            "group": tree_layer.parent().name(),
        }
        if layer.type() == layer.VectorLayer:
            info["features"] = layer.featureCount()
            info["subset"] = layer.subsetString()
            info["renderer"] = layer.renderer().type() if layer.renderer() else None
            info["labels"] = layer.labelsEnabled()
        else:
            info["size"] = [layer.width(), layer.height()]
            info["renderer"] = layer.renderer().type() if layer.renderer() else None
        info["source"] = layer.source()
        layers[f"{tree_layer.parent().name()}/{layer.name()}"] = info

    visible = [t.layer() for t in root.findLayers() if t.isVisible() and t.layer() is not None]
    settings = QgsMapSettings()
    settings.setLayers(visible)  # top first, as in the legend
    settings.setDestinationCrs(project.crs())
    settings.setOutputSize(QSize(1200, 1000))
    settings.setBackgroundColor(QColor(255, 255, 255, 0))
    extent = project.viewSettings().defaultViewExtent()
    settings.setExtent(extent if not extent.isEmpty() else settings.fullExtent())
    job = QgsMapRendererParallelJob(settings)
    job.start()
    job.waitForFinished()
    image = job.renderedImage()
    image.save(png, "PNG")
    opaque = 0
    colours = set()
    for y in range(0, image.height(), 4):
        for x in range(0, image.width(), 4):
            pixel = image.pixelColor(x, y)
            if pixel.alpha() > 0:
                opaque += 1
                colours.add(pixel.rgb())
    result = {
        "read": bool(ok),
        "version": Qgis.QGIS_VERSION,
        "crs": project.crs().authid(),
        "extent": [extent.xMinimum(), extent.yMinimum(), extent.xMaximum(), extent.yMaximum()],
        "groups": groups,
        "layers": layers,
        "bad_layers": bad,
        "project_error": project.error(),
        "messages": messages,
        "render_errors": [f"{e.layerID}: {e.message}" for e in job.errors()],
        "image": {
            "sampled": (image.width() // 4) * (image.height() // 4),
            "opaque": opaque,
            "colours": len(colours),
        },
    }
    if layout_png:
        result["layout"] = export_layout(project, settings, layout_png)
    project.clear()
    app.exitQgis()
    return result


def export_layout(project: object, settings: object, png: str) -> bool:
    """A printable page: the map with its legend (visible layers) and a scale bar."""
    from qgis.core import (
        QgsLayoutExporter,
        QgsLayoutItemLegend,
        QgsLayoutItemMap,
        QgsLayoutItemScaleBar,
        QgsLayoutPoint,
        QgsLayoutSize,
        QgsLegendStyle,
        QgsPrintLayout,
        QgsUnitTypes,
    )
    from qgis.PyQt.QtGui import QFont

    layout = QgsPrintLayout(project)
    layout.initializeDefaults()  # A4 landscape, 297 x 210 mm
    mm = QgsUnitTypes.LayoutMillimeters
    page = QgsLayoutItemMap(layout)
    page.setLayers(settings.layers())
    page.attemptMove(QgsLayoutPoint(5, 5, mm))
    page.attemptResize(QgsLayoutSize(175, 200, mm))
    page.setExtent(settings.extent())
    page.setFrameEnabled(True)
    layout.addLayoutItem(page)
    legend = QgsLayoutItemLegend(layout)
    legend.setLinkedMap(page)
    legend.setLegendFilterByMapEnabled(True)
    model = legend.model().rootGroup()
    for node in list(model.findLayers()):
        if node.layer() not in settings.layers():
            node.parent().removeChildNode(node)
    for group in list(model.findGroups()):
        if not group.findLayers():
            group.parent().removeChildNode(group)
    legend.setAutoUpdateModel(False)
    legend.setStyleFont(QgsLegendStyle.Title, QFont("Sans Serif", 10))
    legend.setTitle(project.title())
    legend.attemptMove(QgsLayoutPoint(185, 5, mm))
    layout.addLayoutItem(legend)
    bar = QgsLayoutItemScaleBar(layout)
    bar.setStyle("Single Box")
    bar.setLinkedMap(page)
    bar.applyDefaultSize()
    bar.setUnitLabel("m")
    bar.attemptMove(QgsLayoutPoint(185, 190, mm))
    layout.addLayoutItem(bar)
    exporter = QgsLayoutExporter(layout)
    options = QgsLayoutExporter.ImageExportSettings()
    options.dpi = 110
    options.generateWorldFile = False
    options.exportMetadata = False
    return bool(exporter.exportToImage(png, options) == QgsLayoutExporter.Success)


if __name__ == "__main__":
    print(json.dumps(main(*sys.argv[1:5])))
