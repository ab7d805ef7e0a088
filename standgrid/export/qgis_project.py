"""A QGIS project file (``.qgz``: a zip holding one ``.qgs`` document) from plain data.

The caller says what the project shows: groups of layers (:class:`ProjectGroup`, top of the
legend first), each layer a file path relative to the project, a provider (``ogr`` for a
GeoPackage layer, optionally filtered by a subset string; ``gdal`` for a raster), and the
QGIS style document (QML) whose renderer, labels and opacity the layer gets. The styles are
the ones standgrid already writes (``layer_styles`` rows, raster ``.qml`` sidecars, the
builders of :mod:`standgrid.export.styles`): the project embeds them, it adds none of its own,
but for one thing: a graduated style is embedded as the same classes with a grey "no value"
rule (:func:`standgrid.export.styles.with_no_value`), so a cell whose value is NULL is drawn
grey as in the web viewer instead of not at all.

The project opens on the given extent (the data's, with its margin): the map canvas, the
default view and the project's full extent (QGIS's "zoom full", which otherwise is the union
of every layer's extent, e.g. the whole of a 1 ha stand that holds one edge cell).

Paths are saved relative (``Paths/Absolute = false``), so the catalog folder can be moved or
copied whole. The document is QGIS 3.22 compatible (the version Debian ships).
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from standgrid._atomic import atomic_output
from standgrid.crs import CRS, CRSLike
from standgrid.errors import CRSError
from standgrid.export.styles import with_no_value

PROJECT_VERSION = "3.22.16-Białowieża"
_DOCTYPE = "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
_GEOMETRY = {"point": "Point", "line": "Line", "polygon": "Polygon"}
#: Attributes of a QML document's root that belong on the project's ``maplayer`` element.
_LAYER_ATTRIBUTES = ("labelsEnabled", "hasScaleBasedVisibilityFlag", "minScale", "maxScale")


@dataclass(frozen=True)
class ProjectLayer:
    """One layer: legend ``name``, ``source`` relative to the project, its style (QML text).

    Vector layers (``provider="ogr"``) name their GeoPackage ``table``, ``geometry``
    (``point``, ``line``, ``polygon``) and optionally a ``subset`` (an SQL WHERE clause);
    rasters use ``provider="gdal"``.
    """

    name: str
    source: str
    qml: str
    provider: str = "ogr"
    table: str | None = None
    geometry: str | None = None
    subset: str = ""
    visible: bool = True

    @property
    def datasource(self) -> str:
        """The datasource string as QGIS saves it (``./index.gpkg|layername=x|subset=...``)."""
        source = "./" + Path(self.source).as_posix().removeprefix("./")
        if self.provider != "ogr":
            return source
        if self.table:
            source += f"|layername={self.table}"
        if self.subset:
            source += f"|subset={self.subset}"
        return source


@dataclass(frozen=True)
class ProjectGroup:
    """A legend group: its layers top first; ``visible`` is the group's check box."""

    name: str
    layers: tuple[ProjectLayer, ...]
    visible: bool = True


def _crs_element(crs: CRSLike) -> ET.Element:
    try:
        parsed = CRS.of(crs)
    except CRSError as exc:
        raise CRSError(f"unusable CRS {crs!r} for the QGIS project: {exc.message}") from exc
    srs = ET.Element("spatialrefsys", nativeFormat="Wkt")
    ET.SubElement(srs, "wkt").text = parsed.wkt2
    authority = parsed.authority
    authid = f"{authority[0]}:{authority[1]}" if authority else ""
    ET.SubElement(srs, "authid").text = authid
    ET.SubElement(srs, "description").text = parsed.name
    ET.SubElement(srs, "geographicflag").text = "true" if parsed.is_geographic else "false"
    return srs


def _layer_id(name: str, index: int) -> str:
    return f"{re.sub(r'[^A-Za-z0-9]+', '_', name).strip('_')}_{index:03d}"


def _style_root(qml: str) -> ET.Element:
    return ET.fromstring(qml.split("\n", 1)[1] if qml.startswith("<!DOCTYPE") else qml)


def _map_layer(layer: ProjectLayer, layer_id: str, crs: CRSLike) -> ET.Element:
    vector = layer.provider == "ogr"
    style = _style_root(with_no_value(layer.qml) if vector else layer.qml)
    element = ET.Element(
        "maplayer",
        type="vector" if vector else "raster",
        autoRefreshTime="0",
        autoRefreshEnabled="0",
        refreshOnNotifyEnabled="0",
        refreshOnNotifyMessage="",
        styleCategories="AllStyleCategories",
    )
    if vector:
        if layer.geometry not in _GEOMETRY:
            raise ValueError(f"layer {layer.name!r}: geometry must be one of {sorted(_GEOMETRY)}")
        element.set("geometry", _GEOMETRY[layer.geometry])
    for key in _LAYER_ATTRIBUTES:
        if key in style.attrib:
            element.set(key, style.attrib[key])
    ET.SubElement(element, "id").text = layer_id
    ET.SubElement(element, "datasource").text = layer.datasource
    ET.SubElement(element, "layername").text = layer.name
    ET.SubElement(ET.SubElement(element, "srs"), "spatialrefsys").extend(list(_crs_element(crs)))
    ET.SubElement(element, "provider", encoding="UTF-8").text = layer.provider
    element.extend(child for child in style if child.tag != "layerGeometryType")
    return element


def project_document(
    groups: Sequence[ProjectGroup],
    *,
    crs: CRSLike,
    extent: tuple[float, float, float, float],
    title: str = "",
) -> str:
    """The ``.qgs`` XML of a project with ``groups`` (legend order), in ``crs``, opening on
    ``extent`` (xmin, ymin, xmax, ymax in ``crs``): the canvas, the default view and the
    project's full extent are all ``extent``."""
    xmin, ymin, xmax, ymax = (float(v) for v in extent)
    if not (xmax > xmin and ymax > ymin):
        raise ValueError(f"the project's extent must not be empty: {tuple(extent)}")
    root = ET.Element(
        "qgis",
        projectname=title,
        version=PROJECT_VERSION,
        saveUser="",
        saveUserFull="",
        saveDateTime="",
    )
    ET.SubElement(root, "homePath", path="")
    ET.SubElement(root, "title").text = title
    ET.SubElement(ET.SubElement(root, "projectCrs"), "spatialrefsys").extend(
        list(_crs_element(crs))
    )
    tree = ET.SubElement(root, "layer-tree-group")
    ET.SubElement(tree, "customproperties")
    layers = ET.Element("projectlayers")
    order: list[str] = []
    index = 0
    for group in groups:
        node = ET.SubElement(
            tree,
            "layer-tree-group",
            name=group.name,
            expanded="1",
            checked="Qt::Checked" if group.visible else "Qt::Unchecked",
        )
        ET.SubElement(node, "customproperties")
        for layer in group.layers:
            index += 1
            layer_id = _layer_id(f"{group.name} {layer.name}", index)
            ET.SubElement(
                node,
                "layer-tree-layer",
                id=layer_id,
                name=layer.name,
                source=layer.datasource,
                providerKey=layer.provider,
                expanded="1",
                legend_exp="",
                checked="Qt::Checked" if layer.visible else "Qt::Unchecked",
            )
            layers.append(_map_layer(layer, layer_id, crs))
            order.append(layer_id)
    canvas = ET.SubElement(root, "mapcanvas", name="theMapCanvas", annotationsVisible="1")
    ET.SubElement(canvas, "units").text = "meters"
    box = ET.SubElement(canvas, "extent")
    for tag, value in zip(("xmin", "ymin", "xmax", "ymax"), (xmin, ymin, xmax, ymax), strict=True):
        ET.SubElement(box, tag).text = repr(value)
    ET.SubElement(canvas, "rotation").text = "0"
    ET.SubElement(ET.SubElement(canvas, "destinationsrs"), "spatialrefsys").extend(
        list(_crs_element(crs))
    )
    view = ET.SubElement(root, "ProjectViewSettings", UseProjectScales="0", rotation="0")
    ET.SubElement(view, "Scales")
    bounds = {
        k: repr(v)
        for k, v in zip(("xmin", "ymin", "xmax", "ymax"), (xmin, ymin, xmax, ymax), strict=True)
    }
    for tag in ("DefaultViewExtent", "PresetFullExtent"):  # QGIS >= 3.18 reads the second
        ET.SubElement(view, tag, bounds).append(_crs_element(crs))
    root.append(layers)
    layer_order = ET.SubElement(root, "layerorder")
    for layer_id in order:
        ET.SubElement(layer_order, "layer", id=layer_id)
    properties = ET.SubElement(root, "properties")
    ET.SubElement(ET.SubElement(properties, "Paths"), "Absolute", type="bool").text = "false"
    # QGIS reads <projectCrs> only when this says the project has a CRS
    projection = ET.SubElement(properties, "SpatialRefSys")
    ET.SubElement(projection, "ProjectionsEnabled", type="int").text = "1"
    measure = ET.SubElement(properties, "Measurement")
    ET.SubElement(measure, "DistanceUnits", type="QString").text = "meters"
    ET.SubElement(measure, "AreaUnits", type="QString").text = "m2"
    ET.indent(root)
    return _DOCTYPE + ET.tostring(root, encoding="unicode") + "\n"


def write_qgis_project(
    path: str | os.PathLike[str],
    groups: Sequence[ProjectGroup],
    *,
    crs: CRSLike,
    extent: tuple[float, float, float, float],
    title: str = "",
) -> Path:
    """Write a ``.qgz`` (zip of ``<stem>.qgs``) atomically; see :func:`project_document`."""
    out = Path(path)
    text = project_document(groups, crs=crs, extent=extent, title=title)
    with atomic_output(out) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(f"{out.stem}.qgs", text)
    return out
