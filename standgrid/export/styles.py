"""QGIS default styles inside a GeoPackage (the ``layer_styles`` table) and QML builders.

QGIS loads the row of ``layer_styles`` with ``useAsDefault`` for a layer when the layer is
opened, so every layer of the index opens styled. :func:`add_layer_style` is the one helper
every stage uses to add a style; the builders return QGIS 3 QML text:

- :func:`load_qml` — the fixed styles shipped in ``standgrid/export/styles/*.qml``
  (``cells``, ``payloads``, ``gnss_fixes``);
- :func:`categorized_style` — one colour per value (trajectories by mission);
- :func:`graduated_style` — equal-interval classes over a sequential ramp (density,
  canopy height; see :func:`stand_metric_style`);
- :func:`diverging_style` — classes symmetric around a centre on the RdBu ramp (change);
- :func:`with_no_value` — a graduated style as the same classes in a rule-based renderer
  plus an ``ELSE`` rule that draws features without a value (NULL) in grey
  (:data:`NO_VALUE`, as the web viewer draws them); QGIS's graduated renderer draws no
  symbol at all for NULL. ``graduated_style(..., no_value=NO_VALUE)`` builds one directly.

Rasters get their style as a sidecar: QGIS loads ``<name>.qml`` beside ``<name>.tif`` as the
layer's default style. :func:`write_raster_style` writes one for each kind of raster
standgrid makes (:data:`RASTER_KINDS`): a height ramp for the CHM, a terrain ramp for the
DTM, a density ramp, a diverging ramp centred on 0 for CHM change and a paletted style for
the observed-area mask.
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
import re
import sqlite3
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from standgrid._atomic import write_text_atomic
from standgrid.errors import CatalogError, FormatError

QGIS_VERSION = "3.28.0-Firenze"
STYLE_TABLE = "layer_styles"

#: ColorBrewer RdBu (11 classes), red = negative (loss), blue = positive (gain).
RDBU = (
    "#67001f",
    "#b2182b",
    "#d6604d",
    "#f4a582",
    "#fddbc7",
    "#f7f7f7",
    "#d1e5f0",
    "#92c5de",
    "#4393c3",
    "#2166ac",
    "#053061",
)
#: viridis, 5 stops (canopy height and other stand metrics).
VIRIDIS = ("#440154", "#3b528b", "#21918c", "#5ec962", "#fde725")
#: ColorBrewer YlGn (5 classes), for stocking (basal area) of the cells.
YLGN = ("#ffffcc", "#c2e699", "#78c679", "#31a354", "#006837")
#: ColorBrewer YlOrRd (5 classes), for point density.
YLORRD = ("#ffffb2", "#fecc5c", "#fd8d3c", "#f03b20", "#bd0026")
#: Terrain: green lowland through tan to brown and pale high ground (DTM).
TERRAIN = ("#1a9850", "#91cf60", "#d9ef8b", "#fee08b", "#d8b365", "#8c510a", "#f5f5f5")
#: ColorBrewer Set1 + Dark2: distinct colours for categories (cycled).
CATEGORY_COLOURS = (
    "#e41a1c",
    "#377eb8",
    "#4daf4a",
    "#984ea3",
    "#ff7f00",
    "#a65628",
    "#f781bf",
    "#1b9e77",
    "#d95f02",
    "#7570b3",
    "#e7298a",
    "#66a61e",
    "#e6ab02",
)

#: Features without a value (NULL) in a class style: the web viewer's grey, and its legend.
NO_VALUE = "#c8c8c8"
NO_VALUE_LABEL = "no value"

_GEOMETRY_TYPE = {"point": "0", "line": "1", "polygon": "2"}
_SYMBOL_TYPE = {"point": "marker", "line": "line", "polygon": "fill"}

_CREATE_TABLE = f"""
CREATE TABLE IF NOT EXISTS "{STYLE_TABLE}" (
  "id" INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
  "f_table_catalog" TEXT(256),
  "f_table_schema" TEXT(256),
  "f_table_name" TEXT(256),
  "f_geometry_column" TEXT(256),
  "styleName" TEXT(30),
  "styleQML" TEXT,
  "styleSLD" TEXT,
  "useAsDefault" BOOLEAN,
  "description" TEXT,
  "owner" TEXT(30),
  "ui" TEXT(30),
  "update_time" DATETIME DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now'))
)"""

STYLE_COLUMNS = (
    "id",
    "f_table_catalog",
    "f_table_schema",
    "f_table_name",
    "f_geometry_column",
    "styleName",
    "styleQML",
    "styleSLD",
    "useAsDefault",
    "description",
    "owner",
    "ui",
    "update_time",
)


# --- the layer_styles table --------------------------------------------------------------


def add_layer_style(
    gpkg_path: str | os.PathLike[str],
    layer_name: str,
    qml: str,
    *,
    style_name: str | None = None,
    sld: str = "",
    default: bool = True,
    description: str = "",
) -> None:
    """Create or update the style ``style_name`` (default: the layer name) of a GeoPackage layer.

    Creates ``layer_styles`` as QGIS does (registered in ``gpkg_contents`` as an attributes
    table). With ``default`` the style becomes the layer's only default style. Raises
    :class:`CatalogError` when the file or the layer is missing.
    """
    path = Path(gpkg_path)
    if not path.is_file():
        raise CatalogError("GeoPackage not found", path=path)
    name = style_name or layer_name
    try:
        with contextlib.closing(sqlite3.connect(path)) as db, db:
            row = db.execute(
                "SELECT data_type FROM gpkg_contents WHERE table_name = ?", (layer_name,)
            ).fetchone()
            if row is None or layer_name == STYLE_TABLE:
                raise CatalogError(f"no layer {layer_name!r} to style", path=path)
            geom = db.execute(
                "SELECT column_name FROM gpkg_geometry_columns WHERE table_name = ?", (layer_name,)
            ).fetchone()
            geometry_column = geom[0] if geom else ""
            db.execute(_CREATE_TABLE)
            db.execute(
                "INSERT INTO gpkg_contents (table_name, data_type, identifier, description, "
                "last_change) SELECT ?, 'attributes', ?, '', "
                "strftime('%Y-%m-%dT%H:%M:%fZ','now') WHERE NOT EXISTS "
                "(SELECT 1 FROM gpkg_contents WHERE table_name = ?)",
                (STYLE_TABLE, STYLE_TABLE, STYLE_TABLE),
            )
            if default:
                db.execute(
                    f'UPDATE "{STYLE_TABLE}" SET useAsDefault = 0 WHERE f_table_name = ?',
                    (layer_name,),
                )
            existing = db.execute(
                f'SELECT id FROM "{STYLE_TABLE}" WHERE f_table_name = ? AND styleName = ?',
                (layer_name, name),
            ).fetchone()
            values = (qml, sld, int(default), description, geometry_column)
            if existing:
                db.execute(
                    f'UPDATE "{STYLE_TABLE}" SET styleQML = ?, styleSLD = ?, useAsDefault = ?, '
                    "description = ?, f_geometry_column = ?, "
                    "update_time = strftime('%Y-%m-%dT%H:%M:%fZ','now') WHERE id = ?",
                    (*values, existing[0]),
                )
            else:
                db.execute(
                    f'INSERT INTO "{STYLE_TABLE}" (f_table_catalog, f_table_schema, f_table_name, '
                    "f_geometry_column, styleName, styleQML, styleSLD, useAsDefault, description, "
                    "owner, ui) VALUES ('', '', ?, ?, ?, ?, ?, ?, ?, '', '')",
                    (layer_name, geometry_column, name, qml, sld, int(default), description),
                )
    except sqlite3.DatabaseError as exc:
        raise CatalogError(f"cannot write layer style: {exc}", path=path) from exc


# --- QML builders ------------------------------------------------------------------------


def load_qml(name: str) -> str:
    """A fixed style shipped with standgrid (``cells``, ``payloads``, ``gnss_fixes``)."""
    return (resources.files("standgrid.export") / "styles" / f"{name}.qml").read_text("utf-8")


def _rgba(colour: str, alpha: int = 255) -> str:
    c = colour.lstrip("#")
    return f"{int(c[0:2], 16)},{int(c[2:4], 16)},{int(c[4:6], 16)},{alpha}"


def _options(parent: ET.Element, **values: str) -> None:
    opts = ET.SubElement(parent, "Option", type="Map")
    for key, value in values.items():
        ET.SubElement(opts, "Option", name=key, type="QString", value=value)


def _symbol(
    geometry: str,
    colour: str,
    *,
    name: str,
    alpha: int = 255,
    outline: str = "#232323",
    no_fill: bool = False,
    width: float = 0.26,
    size: float = 2.0,
) -> ET.Element:
    symbol = ET.Element(
        "symbol",
        type=_SYMBOL_TYPE[geometry],
        name=name,
        alpha="1",
        clip_to_extent="1",
        force_rhr="0",
        frame_rate="10",
        is_animated="0",
    )
    if geometry == "polygon":
        layer = ET.SubElement(symbol, "layer", {"class": "SimpleFill"}, enabled="1", pass_="0")
        _options(
            layer,
            color=_rgba(colour, alpha),
            outline_color=_rgba(outline),
            outline_style="solid",
            outline_width=f"{width:g}",
            outline_width_unit="MM",
            style="no" if no_fill else "solid",
            joinstyle="bevel",
        )
    elif geometry == "line":
        layer = ET.SubElement(symbol, "layer", {"class": "SimpleLine"}, enabled="1", pass_="0")
        _options(
            layer,
            line_color=_rgba(colour, alpha),
            line_style="solid",
            line_width=f"{width:g}",
            line_width_unit="MM",
            capstyle="round",
            joinstyle="round",
        )
    else:
        layer = ET.SubElement(symbol, "layer", {"class": "SimpleMarker"}, enabled="1", pass_="0")
        _options(
            layer,
            color=_rgba(colour, alpha),
            name="circle",
            outline_color=_rgba(outline),
            outline_style="solid",
            outline_width="0.1",
            outline_width_unit="MM",
            size=f"{size:g}",
            size_unit="MM",
        )
    for el in symbol.iter("layer"):  # "pass" is a Python keyword
        el.set("pass", el.attrib.pop("pass_"))
        el.set("locked", "0")
    return symbol


def _document(renderer: ET.Element, geometry: str, label: ET.Element | None = None) -> str:
    root = ET.Element(
        "qgis",
        version=QGIS_VERSION,
        styleCategories="AllStyleCategories",
        labelsEnabled="1" if label is not None else "0",
    )
    root.append(renderer)
    if label is not None:
        root.append(label)
    ET.SubElement(root, "blendMode").text = "0"
    ET.SubElement(root, "featureBlendMode").text = "0"
    ET.SubElement(root, "layerOpacity").text = "1"
    ET.SubElement(root, "layerGeometryType").text = _GEOMETRY_TYPE[geometry]
    ET.indent(root)
    body = ET.tostring(root, encoding="unicode")
    return "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + body + "\n"


def _renderer(kind: str, **attrs: str) -> ET.Element:
    base = {
        "type": kind,
        "symbollevels": "0",
        "enableorderby": "0",
        "forceraster": "0",
        "referencescale": "-1",
    }
    return ET.Element("renderer-v2", {**base, **attrs})


def _labeling(
    field: str, geometry: str, size: float = 8.0, *, expression: bool = False, priority: int = 5
) -> ET.Element:
    labeling = ET.Element("labeling", type="simple")
    settings = ET.SubElement(labeling, "settings", calloutType="simple")
    ET.SubElement(
        settings,
        "text-style",
        fieldName=field,
        isExpression="1" if expression else "0",
        fontFamily="Sans Serif",
        fontSize=f"{size:g}",
        fontSizeUnit="Point",
        textColor="0,0,0,255",
        textOpacity="1",
        fontWeight="50",
        fontItalic="0",
        namedStyle="Regular",
    )
    ET.SubElement(
        settings,
        "text-buffer",
        bufferDraw="1",
        bufferSize="0.8",
        bufferSizeUnits="MM",
        bufferColor="255,255,255,255",
        bufferOpacity="0.8",
        bufferJoinStyle="128",
    )
    placement = {"polygon": "1", "line": "2", "point": "0"}[geometry]
    ET.SubElement(settings, "placement", placement=placement, dist="0", priority=str(priority))
    ET.SubElement(
        settings,
        "rendering",
        obstacle="1",
        scaleVisibility="0",
        fontLimitPixelSize="0",
        displayAll="0",
        labelPerPart="0",
    )
    return labeling


def with_labels(
    qml: str, expression: str, *, geometry: str, size: float = 8.0, priority: int = 5
) -> str:
    """A vector style (QML) with labels: the text of the QGIS ``expression`` per feature
    (``priority`` 0..10: which labels QGIS keeps where they collide)."""
    head, body = qml.split("\n", 1) if qml.startswith("<!DOCTYPE") else ("", qml)
    root = ET.fromstring(body)
    for old in root.findall("labeling"):
        root.remove(old)
    root.insert(1, _labeling(expression, geometry, size, expression=True, priority=priority))
    root.set("labelsEnabled", "1")
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode")
    return f"{head}\n{text}\n" if head else text + "\n"


def single_style(
    geometry: str,
    colour: str,
    *,
    alpha: int = 255,
    no_fill: bool = False,
    outline: str = "#232323",
    width: float = 0.26,
    label_field: str | None = None,
) -> str:
    """One symbol for every feature, optionally labelled with ``label_field``."""
    renderer = _renderer("singleSymbol")
    symbols = ET.SubElement(renderer, "symbols")
    symbols.append(
        _symbol(
            geometry, colour, name="0", alpha=alpha, no_fill=no_fill, outline=outline, width=width
        )
    )
    label = _labeling(label_field, geometry) if label_field else None
    return _document(renderer, geometry, label)


def categorized_style(
    field: str,
    values: Sequence[object],
    *,
    geometry: str,
    labels: Sequence[str] | None = None,
    colours: Sequence[str] | None = None,
    width: float = 0.6,
) -> str:
    """One colour per value of ``field`` (e.g. trajectories by ``mission``)."""
    palette = list(colours) if colours else list(CATEGORY_COLOURS)
    names = list(labels) if labels else [str(v) for v in values]
    renderer = _renderer("categorizedSymbol", attr=field)
    categories = ET.SubElement(renderer, "categories")
    symbols = ET.SubElement(renderer, "symbols")
    for i, (value, label) in enumerate(zip(values, names, strict=True)):
        ET.SubElement(
            categories, "category", value=str(value), symbol=str(i), label=label, render="true"
        )
        symbols.append(_symbol(geometry, palette[i % len(palette)], name=str(i), width=width))
    source = ET.SubElement(renderer, "source-symbol")
    source.append(_symbol(geometry, "#808080", name="0", width=width))
    return _document(renderer, geometry)


def _interpolate(ramp: Sequence[str], t: float) -> str:
    """Linear interpolation along a list of ``#rrggbb`` stops, ``t`` in [0, 1]."""
    t = min(max(t, 0.0), 1.0) * (len(ramp) - 1)
    i = min(int(t), len(ramp) - 2)
    f = t - i
    a = [int(ramp[i].lstrip("#")[k : k + 2], 16) for k in (0, 2, 4)]
    b = [int(ramp[i + 1].lstrip("#")[k : k + 2], 16) for k in (0, 2, 4)]
    return "#" + "".join(f"{round(x + (y - x) * f):02x}" for x, y in zip(a, b, strict=True))


def _colour_ramp(ramp: Sequence[str]) -> ET.Element:
    element = ET.Element("colorramp", type="gradient", name="[source]")
    stops = ":".join(
        f"{i / (len(ramp) - 1):.4f};{_rgba(c)}" for i, c in enumerate(ramp[1:-1], start=1)
    )
    _options(
        element,
        color1=_rgba(ramp[0]),
        color2=_rgba(ramp[-1]),
        discrete="0",
        rampType="gradient",
        stops=stops,
    )
    return element


def graduated_style(
    field: str,
    vmin: float,
    vmax: float,
    *,
    classes: int = 5,
    geometry: str = "polygon",
    ramp: Sequence[str] = VIRIDIS,
    alpha: int = 255,
    precision: int = 2,
    outline: str = "#606060",
    outline_only: bool = False,
    width: float = 0.26,
    unit: str = "",
    no_value: str | None = None,
) -> str:
    """Equal-interval classes of ``field`` between ``vmin`` and ``vmax`` on ``ramp``.

    The lowest class starts at -inf and the highest ends at +inf, so every value is styled.
    ``outline_only`` draws polygons as unfilled outlines in the class colour (``width`` mm);
    ``unit`` ends each legend label (``12.0 - 16.0 m``). With ``no_value`` (a colour, e.g.
    :data:`NO_VALUE`) features whose value is NULL are drawn in it too (legend "no value"):
    the classes then come as a rule-based renderer (:func:`with_no_value`).
    """
    if not vmax > vmin:
        vmax = vmin + 1.0
    edges = [vmin + (vmax - vmin) * i / classes for i in range(classes + 1)]
    renderer = _renderer("graduatedSymbol", attr=field, graduatedMethod="GraduatedColor")
    ranges = ET.SubElement(renderer, "ranges")
    symbols = ET.SubElement(renderer, "symbols")
    for i in range(classes):
        lower = -1e300 if i == 0 else edges[i]
        upper = 1e300 if i == classes - 1 else edges[i + 1]
        label = f"{edges[i]:.{precision}f} - {edges[i + 1]:.{precision}f} {unit}".rstrip()
        ET.SubElement(
            ranges,
            "range",
            lower=f"{lower:.15g}",
            upper=f"{upper:.15g}",
            symbol=str(i),
            label=label,
            render="true",
            uuid=f"range-{i}",
        )
        colour = _interpolate(ramp, (i + 0.5) / classes)
        symbols.append(
            _symbol(
                geometry,
                colour,
                name=str(i),
                alpha=alpha,
                outline=colour if outline_only else outline,
                no_fill=outline_only,
                width=width,
            )
        )
    source = ET.SubElement(renderer, "source-symbol")
    source.append(_symbol(geometry, ramp[0], name="0", alpha=alpha))
    renderer.append(_colour_ramp(ramp))
    ET.SubElement(renderer, "classificationMethod", id="EqualInterval")
    qml = _document(renderer, geometry)
    return qml if no_value is None else with_no_value(qml, no_value)


def diverging_style(
    field: str,
    vmin: float,
    vmax: float,
    *,
    centre: float = 0.0,
    classes: int = 7,
    geometry: str = "polygon",
    ramp: Sequence[str] = RDBU,
    alpha: int = 255,
    precision: int = 2,
    unit: str = "",
    no_value: str | None = None,
) -> str:
    """Classes symmetric around ``centre`` on the RdBu ramp (loss red, gain blue).

    The half-width is ``max(|vmin - centre|, |vmax - centre|)`` so equal changes get equal
    colour strength on either side; ``classes`` is made odd so one class holds ``centre``.
    ``no_value`` as in :func:`graduated_style`.
    """
    half = max(abs(vmin - centre), abs(vmax - centre)) or 1.0
    classes = classes if classes % 2 else classes + 1
    return graduated_style(
        field,
        centre - half,
        centre + half,
        classes=classes,
        geometry=geometry,
        ramp=ramp,
        alpha=alpha,
        precision=precision,
        unit=unit,
        no_value=no_value,
    )


def stand_metric_style(field: str, vmin: float, vmax: float, *, classes: int = 5) -> str:
    """Stand metric polygons (e.g. canopy height) on viridis; cells without a value grey."""
    return graduated_style(
        field, vmin, vmax, classes=classes, geometry="polygon", ramp=VIRIDIS, no_value=NO_VALUE
    )


def _field_expression(attr: str) -> str:
    """A graduated renderer's ``attr`` (a field name or an expression) as an expression."""
    if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", attr):
        return f'"{attr}"'
    if attr.startswith('"') and attr.endswith('"') and attr.count('"') == 2:
        return attr
    return f"({attr})"


def _grey_symbol(symbol: ET.Element, colour: str, name: str) -> ET.Element:
    """A copy of a class symbol in ``colour`` (its alpha, outline and width kept; an
    outline-only fill gets the colour on its outline)."""
    grey = copy.deepcopy(symbol)
    grey.set("name", name)
    for layer in grey.iter("layer"):
        options = {o.get("name"): o for o in layer.iter("Option") if o.get("name")}
        outline_only = options.get("style") is not None and options["style"].get("value") == "no"
        keys = ("outline_color",) if outline_only else ("color", "line_color")
        for key in keys:
            option = options.get(key)
            if option is None:
                continue
            alpha = (option.get("value") or "").split(",")[3:4] or ["255"]
            option.set("value", _rgba(colour, int(alpha[0])))
    return grey


def with_no_value(qml: str, colour: str = NO_VALUE, label: str = NO_VALUE_LABEL) -> str:
    """A graduated style whose features without a value (NULL) are drawn too, in ``colour``.

    QGIS's graduated renderer skips a feature whose value is NULL, so such cells vanish from
    the map (the web viewer draws them grey). The classes are kept as they are (same
    symbols, legend labels and order) in a rule-based renderer, one rule per class (lower
    bound excluded but the first's, upper bound included: as the graduated renderer picks
    a class), plus an ``ELSE`` rule with ``colour`` for everything else, i.e. NULL. Any
    other style (not graduated) is returned unchanged.
    """
    head, body = qml.split("\n", 1) if qml.startswith("<!DOCTYPE") else ("", qml)
    root = ET.fromstring(body)
    renderer = root.find("renderer-v2")
    if renderer is None or renderer.get("type") != "graduatedSymbol":
        return qml
    value = _field_expression(renderer.get("attr", ""))
    symbols = {s.get("name"): s for s in renderer.findall("symbols/symbol")}
    ranges = renderer.findall("ranges/range")
    rules_renderer = _renderer("RuleRenderer")
    for key in ("symbollevels", "enableorderby", "forceraster", "referencescale"):
        if key in renderer.attrib:
            rules_renderer.set(key, renderer.attrib[key])
    rules = ET.SubElement(rules_renderer, "rules", key="root")
    out_symbols = ET.SubElement(rules_renderer, "symbols")
    for i, element in enumerate(ranges):
        lower, upper = float(element.get("lower", "-inf")), float(element.get("upper", "inf"))
        terms = []
        if lower > -1e299:  # the open ends of the outer classes (+-1e300) need no bound
            terms.append(f"{value} {'>' if i else '>='} {lower:.15g}")
        if upper < 1e299:
            terms.append(f"{value} <= {upper:.15g}")
        condition = " AND ".join(terms) or f"{value} IS NOT NULL"
        ET.SubElement(
            rules,
            "rule",
            key=f"class-{i}",
            filter=condition,
            symbol=str(i),
            label=element.get("label", ""),
        )
        symbol = copy.deepcopy(symbols[element.get("symbol", "")])
        symbol.set("name", str(i))
        out_symbols.append(symbol)
    first = symbols.get(ranges[0].get("symbol", "")) if ranges else None
    if first is not None:
        n = str(len(ranges))
        ET.SubElement(rules, "rule", key="no-value", filter="ELSE", symbol=n, label=label)
        out_symbols.append(_grey_symbol(first, colour, n))
    index = list(root).index(renderer)
    root.remove(renderer)
    root.insert(index, rules_renderer)
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode")
    return f"{head}\n{text}\n" if head else text + "\n"


def density_style(vmin: float, vmax: float, *, field: str = "density") -> str:
    """Cells by point density (points per m²), YlOrRd, semi-transparent."""
    return graduated_style(field, vmin, vmax, classes=5, ramp=YLORRD, alpha=180, precision=0)


def _builtin_styles() -> dict[str, str]:
    """The fixed styles as shipped in ``styles/*.qml`` (see :func:`write_builtin_styles`)."""
    return {
        "cells": single_style(
            "polygon", "#ffffff", no_fill=True, outline="#303030", width=0.4, label_field="cell_id"
        ),
        "payloads": single_style("polygon", "#4393c3", alpha=60, outline="#2166ac", width=0.2),
        # an expression, so the style works whether OGR reads ``inlier`` as bool or integer
        "gnss_fixes": categorized_style(
            "if(\"inlier\", 'inlier', 'rejected')",
            ["inlier", "rejected"],
            geometry="point",
            colours=["#1a9641", "#d7191c"],
        ),
    }


def write_builtin_styles(folder: Path | None = None) -> None:
    """Regenerate the shipped ``styles/*.qml`` from :func:`_builtin_styles`."""
    target = folder or Path(__file__).with_name("styles")
    target.mkdir(exist_ok=True)
    for style_name, text in _builtin_styles().items():
        (target / f"{style_name}.qml").write_text(text, encoding="utf-8")


# --- raster styles (QML sidecars) --------------------------------------------------------

#: Percentile of the data a one-sided ramp ends at (outliers do not wash the ramp out).
RASTER_UPPER_PERCENTILE = 98.0
#: Observed-area mask: value -> (colour, alpha 0-255, legend label).
OBSERVED_PALETTE = {1: ("#1a9641", 90, "observed"), 0: ("#d7191c", 140, "not observed")}


@dataclass(frozen=True)
class RasterKind:
    """How one kind of raster is styled: ramp, unit of the legend, how its range is found."""

    ramp: tuple[str, ...]
    unit: str
    precision: int
    #: "zero_to_upper" (0 .. p98), "min_max" (data min .. max), "symmetric" (+-p98 of |v|),
    #: "palette" (fixed classes, no range).
    range_rule: str


#: Raster kinds (the file stem of the raster) and their styles.
RASTER_KINDS: dict[str, RasterKind] = {
    "chm": RasterKind(VIRIDIS, "m", 1, "zero_to_upper"),
    "dtm": RasterKind(TERRAIN, "m", 1, "min_max"),
    "density": RasterKind(YLORRD, "pts/m²", 0, "zero_to_upper"),
    "chm_change": RasterKind(RDBU, "m", 2, "symmetric"),
    "observed": RasterKind((), "", 0, "palette"),
}
#: Raster file stems whose kind differs from their stem.
_KIND_OF_STEM = {"chm_diff": "chm_change"}


def raster_kind(path: str | os.PathLike[str]) -> str | None:
    """The style kind of a raster file from its name (``chm.tif`` -> ``chm``), or None."""
    stem = Path(path).stem
    kind = _KIND_OF_STEM.get(stem, stem)
    return kind if kind in RASTER_KINDS else None


def raster_style_path(tif_path: str | os.PathLike[str]) -> Path:
    """The sidecar QGIS loads as a raster's default style: ``<name>.qml`` beside ``<name>.tif``."""
    return Path(tif_path).with_suffix(".qml")


def _raster_document(renderer: ET.Element, opacity: float = 1.0) -> str:
    """A QGIS 3 raster layer style: the renderer in a pipe with the default filters."""
    root = ET.Element(
        "qgis",
        version=QGIS_VERSION,
        styleCategories="AllStyleCategories",
        hasScaleBasedVisibilityFlag="0",
        minScale="1e+08",
        maxScale="0",
    )
    pipe = ET.SubElement(root, "pipe")
    provider = ET.SubElement(pipe, "provider")
    ET.SubElement(
        provider,
        "resampling",
        enabled="false",
        maxOversampling="2",
        zoomedInResamplingMethod="nearestNeighbour",
        zoomedOutResamplingMethod="nearestNeighbour",
    )
    renderer.set("opacity", f"{opacity:g}")
    pipe.append(renderer)
    ET.SubElement(pipe, "brightnesscontrast", brightness="0", contrast="0", gamma="1")
    ET.SubElement(
        pipe,
        "huesaturation",
        saturation="0",
        grayscaleMode="0",
        invertColors="0",
        colorizeOn="0",
        colorizeRed="255",
        colorizeGreen="128",
        colorizeBlue="128",
        colorizeStrength="100",
    )
    ET.SubElement(pipe, "rasterresampler", maxOversampling="2")
    ET.SubElement(pipe, "resamplingStage").text = "resamplingFilter"
    ET.SubElement(root, "blendMode").text = "0"
    ET.indent(root)
    body = ET.tostring(root, encoding="unicode")
    return "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + body + "\n"


def _raster_renderer(kind: str, **attrs: str) -> ET.Element:
    base = {"type": kind, "band": "1", "alphaBand": "-1", "nodataColor": ""}
    renderer = ET.Element("rasterrenderer", {**base, **attrs})
    ET.SubElement(renderer, "rasterTransparency")
    origin = ET.SubElement(renderer, "minMaxOrigin")
    for tag, text in (
        ("limits", "None"),
        ("extent", "WholeRaster"),
        ("statAccuracy", "Estimated"),
        ("cumulativeCutLower", "0.02"),
        ("cumulativeCutUpper", "0.98"),
        ("stdDevFactor", "2"),
    ):
        ET.SubElement(origin, tag).text = text
    return renderer


def _value_label(value: float, unit: str, precision: int, signed: bool) -> str:
    text = f"{value:+.{precision}f}" if signed and value != 0 else f"{value:.{precision}f}"
    if text.lstrip("+-").strip("0.") == "":  # -0.00 and +0.00 read as 0
        text = f"{0:.{precision}f}"
    return f"{text} {unit}".strip()


def pseudocolor_raster_style(
    vmin: float,
    vmax: float,
    ramp: Sequence[str],
    *,
    unit: str = "",
    precision: int = 1,
    signed: bool = False,
    opacity: float = 1.0,
) -> str:
    """Band 1 on a continuous colour ramp from ``vmin`` to ``vmax`` (singlebandpseudocolor).

    One legend item per ramp stop, labelled with its value and ``unit``; values outside the
    range take the end colours (not clipped); nodata stays transparent.
    """
    if not (math.isfinite(vmin) and math.isfinite(vmax)):
        raise ValueError(f"raster style range must be finite, got {vmin}..{vmax}")
    if not vmax > vmin:
        vmax = vmin + 1.0
    renderer = _raster_renderer(
        "singlebandpseudocolor", classificationMin=f"{vmin:.10g}", classificationMax=f"{vmax:.10g}"
    )
    shader = ET.SubElement(ET.SubElement(renderer, "rastershader"), "colorrampshader")
    shader.attrib.update(
        colorRampType="INTERPOLATED",
        classificationMode="1",
        clip="0",
        minimumValue=f"{vmin:.10g}",
        maximumValue=f"{vmax:.10g}",
        labelPrecision=str(precision),
    )
    shader.append(_colour_ramp(ramp))
    # the legend lists the labelled stops ("12.0 m"), not a bare continuous bar
    ET.SubElement(
        shader,
        "rampLegendSettings",
        useContinuousLegend="0",
        minimumLabel="",
        maximumLabel="",
        prefix="",
        suffix="",
        direction="0",
        orientation="2",
    )
    for i, colour in enumerate(ramp):
        t = i / (len(ramp) - 1)
        value = vmin * (1 - t) + vmax * t  # exact ends, and exactly 0 mid-way on -h..h
        ET.SubElement(
            shader,
            "item",
            alpha="255",
            value=f"{value:.10g}",
            color=colour,
            label=_value_label(value, unit, precision, signed),
        )
    return _raster_document(renderer, opacity)


def paletted_raster_style(entries: dict[int, tuple[str, int, str]], *, opacity: float = 1.0) -> str:
    """One colour per integer value of band 1 (QGIS "paletted/unique values")."""
    renderer = _raster_renderer("paletted")
    palette = ET.SubElement(renderer, "colorPalette")
    for value, (colour, alpha, label) in sorted(entries.items()):
        ET.SubElement(
            palette, "paletteEntry", value=str(value), color=colour, alpha=str(alpha), label=label
        )
    return _raster_document(renderer, opacity)


def raster_style(kind: str, vmin: float = 0.0, vmax: float = 1.0) -> str:
    """The QML of a raster kind (:data:`RASTER_KINDS`) over ``vmin``..``vmax``.

    ``chm_change`` is made symmetric around 0 (half-width ``max(|vmin|, |vmax|)``); the
    ``observed`` mask ignores the range (1 = observed, 0 = not observed, semi-transparent).
    """
    spec = RASTER_KINDS.get(kind)
    if spec is None:
        raise ValueError(f"unknown raster kind {kind!r} (one of {sorted(RASTER_KINDS)})")
    if spec.range_rule == "palette":
        return paletted_raster_style(OBSERVED_PALETTE)
    signed = spec.range_rule == "symmetric"
    if signed:
        half = max(abs(vmin), abs(vmax)) or 1.0
        vmin, vmax = -half, half
    return pseudocolor_raster_style(
        vmin, vmax, spec.ramp, unit=spec.unit, precision=spec.precision, signed=signed
    )


def raster_range(tif_path: str | os.PathLike[str], kind: str) -> tuple[float, float]:
    """The style range of a raster's valid pixels by its kind's rule (0..1 when none valid)."""
    import numpy as np
    import rasterio

    spec = RASTER_KINDS[kind]
    if spec.range_rule == "palette":
        return 0.0, 1.0
    try:
        with rasterio.open(tif_path) as src:
            band = src.read(1, masked=True)
    except rasterio.errors.RasterioIOError as exc:
        raise FormatError(f"cannot read raster: {exc}", path=tif_path) from exc
    values = np.ma.compressed(band).astype(np.float64)
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return 0.0, 1.0
    upper = float(np.percentile(values, RASTER_UPPER_PERCENTILE))
    if spec.range_rule == "zero_to_upper":
        return 0.0, upper
    if spec.range_rule == "symmetric":
        half = float(np.percentile(np.abs(values), RASTER_UPPER_PERCENTILE))
        return -half, half
    return float(values.min()), float(values.max())


def write_raster_style(
    tif_path: str | os.PathLike[str],
    kind: str | None = None,
    vmin: float | None = None,
    vmax: float | None = None,
    *,
    qml: str | os.PathLike[str] | None = None,
) -> Path:
    """Write the default QGIS style ``<name>.qml`` beside the raster ``<name>.tif``.

    ``kind`` defaults to the one the file name says (:func:`raster_kind`); a range not given
    comes from the raster's valid pixels (:func:`raster_range`: CHM and density 0..p98, DTM
    min..max, change +-p98 of |change|). ``qml`` writes it elsewhere (a transaction's staged
    path of the sidecar). Returns the style's path (written atomically).
    """
    kind = kind or raster_kind(tif_path)
    if kind is None:
        raise ValueError(f"no raster style for {Path(tif_path).name} (give kind=)")
    if vmin is None or vmax is None:
        lo, hi = raster_range(tif_path, kind)
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
    path = Path(qml) if qml is not None else raster_style_path(tif_path)
    write_text_atomic(path, raster_style(kind, vmin, vmax))
    return path
