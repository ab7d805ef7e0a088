"""The provider of the OGC API's data: every read of the catalog's GeoPackage index.

As in pygeoapi, the routes (:mod:`standgrid.serve.ogc`, :mod:`standgrid.serve.viewer`) keep
HTTP (parameters, status codes, links, content negotiation) and ask a
:class:`GeoPackageProvider` for layers (collections: schema, extent), pages of items and
items by id, getting plain values back; all SQL is here. A query the index cannot answer as
asked raises :class:`QueryError` (HTTP 400).

A ``bbox`` is answered from the layer's R-tree (``rtree_<table>_<geom>``, the GeoPackage
spatial index extension; ``EXPLAIN QUERY PLAN`` shows a ``VIRTUAL TABLE INDEX`` search,
never a scan of the layer) and paged in SQL (:func:`bbox_sql`). A feature whose R-tree box
lies inside a box inscribed in the query area meets the area without a test; only the
candidates whose box crosses that inner box's edge are read and tested exactly (shapely),
so a page reads its own rows and the few edge candidates, never every candidate. Property
filters and the time filter are SQL; features come in ``fid`` order, so pages of one
snapshot of the index never overlap or skip. A feature's geometry is decoded, transformed
and written as GeoJSON once per index file and CRS (:meth:`GeoPackageProvider.geojson`).
"""

from __future__ import annotations

import datetime as dt
import functools
import json
import sqlite3
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from standgrid.errors import CatalogError

#: GeoPackage column type -> JSON schema type of a queryable.
_TYPES = {
    "INTEGER": "integer",
    "INT": "integer",
    "MEDIUMINT": "integer",
    "SMALLINT": "integer",
    "TINYINT": "integer",
    "BOOLEAN": "boolean",
    "REAL": "number",
    "DOUBLE": "number",
    "FLOAT": "number",
    "DATE": "string",
    "DATETIME": "string",
}
#: Envelope size in bytes by the GeoPackage binary header's envelope indicator.
_ENVELOPE_BYTES = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}
#: Tables of the index that are not feature layers.
_NOT_LAYERS = frozenset({"layer_styles"})
#: GeoJSON geometry texts kept per layer and CRS (beyond it, texts are written per request;
#: a tree crown's is ~0.6 kB).
MAX_CACHED_TEXTS = 50_000


_MISSING: Any = object()


class QueryError(ValueError):
    """A query the index cannot answer as asked: a value not of its property's type, an
    unknown property, a time filter on a layer without time (the client's mistake)."""


@dataclass(frozen=True)
class Column:
    name: str
    type: str  # integer | number | boolean | string


@dataclass(frozen=True)
class Layer:
    """One layer (table) of the index."""

    name: str
    columns: tuple[Column, ...]
    geometry_column: str | None = None
    geometry_type: str | None = None
    bounds: tuple[float, float, float, float] | None = None
    rtree: str | None = None
    description: str = ""

    @functools.cached_property
    def geojson_texts(self) -> dict[str, dict[int, str | None]]:
        """CRS URI -> fid -> the feature's geometry as GeoJSON text in that CRS (None: no
        geometry), filled by :meth:`GeoPackageProvider.geojson`. A layer is read once per
        index file (:func:`read_layers`), so these are the texts of that file's features."""
        return {}

    @functools.cached_property
    def column_types(self) -> dict[str, str]:
        return {c.name: c.type for c in self.columns}

    @functools.cached_property
    def property_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    @functools.cached_property
    def boolean_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns if c.type == "boolean")

    @property
    def temporal(self) -> str | None:
        """How a feature's time is known: ``stamp`` (stamp_sec/nsec), ``epoch_range``
        (epoch_from/to), ``epoch`` (an epoch label), ``date`` (a YYYY-MM-DD date) or None."""
        names = self.column_types
        if "stamp_sec" in names and "stamp_nsec" in names:
            return "stamp"
        if "epoch_from" in names and "epoch_to" in names:
            return "epoch_range"
        if "epoch" in names:
            return "epoch"
        if "date" in names:
            return "date"
        return None


@dataclass
class Query:
    """What an items request asks for. ``area`` is in the layer's CRS (x/y)."""

    area: Any = None
    equals: dict[str, str] = field(default_factory=dict)
    time: tuple[dt.datetime | None, dt.datetime | None] | None = None
    limit: int = 100
    offset: int = 0


@dataclass
class Page:
    """Features in fid order: booleans as bool, other values as SQLite gives them (a
    non-finite number is written as JSON null); ``blobs`` their GeoPackage geometries."""

    number_matched: int
    fids: list[int]
    properties: list[dict[str, Any]]
    blobs: list[bytes | None]

    @functools.cached_property
    def geometries(self) -> np.ndarray:
        """Shapely geometries (None for attribute rows and empty geometries)."""
        return decode_geometries(self.blobs)


def connect(path: str | Path) -> sqlite3.Connection:
    """A read-only connection to a GeoPackage (opened now: later renames do not affect it)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogError("the catalog has no index yet", path=path)
    try:
        # check_same_thread=False: a pooled connection serves one request at a time, but
        # not always in the thread that opened it (:mod:`standgrid.serve.snapshot`)
        conn = sqlite3.connect(
            f"{path.absolute().as_uri()}?mode=ro", uri=True, check_same_thread=False
        )
        conn.execute("SELECT 1 FROM gpkg_contents LIMIT 1").fetchall()
    except sqlite3.Error as exc:
        raise CatalogError(f"unreadable GeoPackage index ({exc})", path=path) from exc
    return conn


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def read_layers(conn: sqlite3.Connection) -> dict[str, Layer]:
    """Every feature and attribute layer of the index, by name."""
    geometry = {
        str(t): (str(c), str(g))
        for t, c, g in conn.execute(
            "SELECT table_name, column_name, geometry_type_name FROM gpkg_geometry_columns"
        )
    }
    tables = {str(r[0]) for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    layers: dict[str, Layer] = {}
    rows = conn.execute(
        "SELECT table_name, data_type, description, min_x, min_y, max_x, max_y "
        "FROM gpkg_contents WHERE data_type IN ('features', 'attributes') ORDER BY table_name"
    ).fetchall()
    for name, _kind, description, *box in rows:
        name = str(name)
        if name in _NOT_LAYERS or name not in tables:
            continue
        geom_col, geom_type = geometry.get(name, (None, None))
        columns = tuple(
            Column(str(c[1]), _TYPES.get(str(c[2]).split("(")[0].upper(), "string"))
            for c in conn.execute(f"PRAGMA table_info({_quote(name)})")
            if str(c[1]) != "fid" and str(c[1]) != geom_col
        )
        rtree = f"rtree_{name}_{geom_col}" if geom_col else None
        bounds = (
            (float(box[0]), float(box[1]), float(box[2]), float(box[3]))
            if geom_col and None not in box
            else None
        )
        layers[name] = Layer(
            name,
            columns,
            geom_col,
            geom_type,
            bounds,
            rtree if rtree in tables else None,
            str(description or ""),
        )
    return layers


def decode_geometries(blobs: Sequence[bytes | None]) -> np.ndarray:
    """GeoPackage binary geometries -> shapely (None for NULL and empty geometries)."""
    import shapely

    wkb: list[bytes | None] = []
    for blob in blobs:
        if blob is None or len(blob) < 8 or blob[:2] != b"GP":
            wkb.append(None)
            continue
        flags = blob[3]
        if flags & 0x10:  # empty geometry
            wkb.append(None)
            continue
        envelope = _ENVELOPE_BYTES.get((flags >> 1) & 0x07)
        if envelope is None:
            raise CatalogError(f"GeoPackage geometry with an invalid envelope flag {flags:#x}")
        wkb.append(bytes(blob[8 + envelope :]))
    return np.asarray(shapely.from_wkb(np.array(wkb, dtype=object)), dtype=object)


def _coerce(layer: Layer, name: str, text: str) -> Any:
    kind = layer.column_types[name]
    shown = text if len(text) <= 40 else text[:40] + "..."
    try:
        if kind == "integer":
            value = int(text) if len(text) <= 40 else None
            if value is None or not -(2**63) <= value < 2**63:
                raise QueryError(f"{name}: {shown!r} is not a 64-bit integer")
            return value
        if kind == "number":
            number = float(text)
            if not np.isfinite(number):
                raise QueryError(f"{name}: {shown!r} is not a finite number")
            return number
    except QueryError:
        raise
    except ValueError as exc:
        raise QueryError(f"{name}: {shown!r} is not a {kind}") from exc
    if kind == "boolean":
        lowered = text.strip().lower()
        if lowered in ("true", "1"):
            return 1
        if lowered in ("false", "0"):
            return 0
        raise QueryError(f"{name}: {text!r} is not true or false")
    return text


def _day(value: dt.datetime | None) -> str | None:
    if value is None:
        return None
    try:
        return value.astimezone(dt.UTC).date().isoformat()
    except OverflowError:  # years 1 or 9999 shifted out of range by their offset
        return value.date().isoformat()


def _time_clause(
    layer: Layer,
    time: tuple[dt.datetime | None, dt.datetime | None],
    epoch_dates: Mapping[str, str],
) -> tuple[str, list[Any]]:
    """SQL keeping the features whose time meets the closed interval ``time``.
    Dates (and epochs, by their date) are whole UTC days."""
    start, end = time
    kind = layer.temporal
    if kind is None:
        raise QueryError(f"collection {layer.name!r} has no time: datetime cannot filter it")
    if kind == "stamp":
        clauses, stamps = [], []
        if start is not None:
            clauses.append('("stamp_sec" * 1000000000 + "stamp_nsec") >= ?')
            stamps.append(_ns(start))
        if end is not None:
            clauses.append('("stamp_sec" * 1000000000 + "stamp_nsec") <= ?')
            stamps.append(_ns(end))
        return " AND ".join(clauses) or "1", stamps
    first, last = _day(start), _day(end)

    def within(day: str) -> bool:
        return (first is None or day >= first) and (last is None or day <= last)

    if kind == "date":
        clauses = ['"date" IS NOT NULL']
        params: list[Any] = []
        if first is not None:
            clauses.append('substr("date", 1, 10) >= ?')
            params.append(first)
        if last is not None:
            clauses.append('substr("date", 1, 10) <= ?')
            params.append(last)
        return " AND ".join(clauses), params
    if kind == "epoch":
        labels = [e for e, d in epoch_dates.items() if d and within(d[:10])]
        return _in("epoch", labels)
    # epoch_range: the change spans [date_from, date_to]; it meets [start, end] when
    # date_from <= end and date_to >= start.
    before_end = [e for e, d in epoch_dates.items() if d and (last is None or d[:10] <= last)]
    after_start = [e for e, d in epoch_dates.items() if d and (first is None or d[:10] >= first)]
    a, pa = _in("epoch_from", before_end)
    b, pb = _in("epoch_to", after_start)
    return f"{a} AND {b}", [*pa, *pb]


def _in(column: str, values: list[str]) -> tuple[str, list[Any]]:
    if not values:
        return "0", []
    return f"{_quote(column)} IN ({', '.join('?' * len(values))})", list(values)


def _ns(value: dt.datetime) -> int:
    """Nanoseconds since 1970 UTC, clamped to SQLite's 64-bit integers (years 1678-2262:
    a bound beyond them keeps every stamp on its side)."""
    epoch = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    try:
        delta = value.astimezone(dt.UTC) - epoch
    except OverflowError:  # years 1 or 9999 shifted out of range by their offset
        return -(2**63) if value.year < 1970 else 2**63 - 1
    ns = (delta.days * 86400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000
    return max(-(2**63), min(2**63 - 1, ns))


def where_sql(layer: Layer, query: Query, epoch_dates: Mapping[str, str]) -> tuple[str, list[Any]]:
    """The WHERE clause (without the bbox) and its parameters."""
    clauses: list[str] = []
    params: list[Any] = []
    for name, text in query.equals.items():
        if name not in layer.column_types:
            raise QueryError(f"collection {layer.name!r} has no property {name!r}")
        clauses.append(f"{_quote(name)} = ?")
        params.append(_coerce(layer, name, text))
    if query.time is not None:
        clause, extra = _time_clause(layer, query.time, epoch_dates)
        clauses.append(clause)
        params.extend(extra)
    return " AND ".join(clauses) or "1", params


def _inner_box(area: Any) -> tuple[float, float, float, float] | None:
    """An axis-aligned box inside ``area`` (its bounds when it is a box, else the largest of
    its bounds shrunk about their centre that ``area`` contains), None when it has no
    area: a geometry inside this box meets ``area`` for certain."""
    import shapely

    xmin, ymin, xmax, ymax = (float(v) for v in area.bounds)
    if not (xmax > xmin and ymax > ymin):
        return None
    if shapely.contains(area, shapely.box(xmin, ymin, xmax, ymax)):  # a box: its bounds
        return xmin, ymin, xmax, ymax
    cx, cy, hw, hh = (xmin + xmax) / 2, (ymin + ymax) / 2, (xmax - xmin) / 2, (ymax - ymin) / 2
    scales = np.linspace(1.0, 0.5, 26)
    boxes = shapely.box(cx - hw * scales, cy - hh * scales, cx + hw * scales, cy + hh * scales)
    boxes[0] = shapely.box(xmin, ymin, xmax, ymax)  # the bounds exactly
    inside = np.flatnonzero(shapely.contains(area, boxes))
    if not len(inside):
        return None
    x0, y0, x1, y1 = (float(v) for v in boxes[inside[0]].bounds)
    return x0, y0, x1, y1


@dataclass(frozen=True)
class BboxSql:
    """The statements of a bbox query, each ``(sql, params)``. ``edges``: ``fid`` and
    geometry of the candidates to test exactly; ``inside_count``: how many match without a
    test; :meth:`page`: the page's rows, given the edge candidates that passed the test."""

    edges: tuple[str, list[Any]]
    inside_count: tuple[str, list[Any]]
    page_sql: str
    page_params: tuple[list[Any], list[Any]]  # before and after the edge fids

    def page(self, passed: Sequence[int]) -> tuple[str, list[Any]]:
        before, after = self.page_params
        return self.page_sql, [*before, json.dumps([int(f) for f in passed]), *after]


def bbox_sql(layer: Layer, query: Query, epoch_dates: Mapping[str, str]) -> BboxSql:
    """The SQL of a query with an ``area``: candidates are the R-tree boxes meeting the
    area's bounds; those inside :func:`_inner_box` match as they are."""
    if layer.geometry_column is None or layer.rtree is None:
        raise CatalogError(f"layer {layer.name!r} has no spatial index")
    where, params = where_sql(layer, query, epoch_dates)
    table, rtree = _quote(layer.name), _quote(layer.rtree)
    xmin, ymin, xmax, ymax = (float(v) for v in query.area.bounds)
    meets = "minx <= ? AND maxx >= ? AND miny <= ? AND maxy >= ?"
    meets_params: list[Any] = [xmax, xmin, ymax, ymin]
    inner = _inner_box(query.area)
    within = "minx >= ? AND maxx <= ? AND miny >= ? AND maxy <= ?"
    if inner is None:  # no area: every candidate is tested
        within, within_params = "0", []
    else:
        within_params = [inner[0], inner[2], inner[1], inner[3]]
    inside = f"SELECT id FROM {rtree} WHERE {meets} AND {within}"
    inside_params = [*meets_params, *within_params]
    edges = (
        f"SELECT fid, {_quote(layer.geometry_column)} FROM {table} "
        f"WHERE fid IN (SELECT id FROM {rtree} WHERE {meets} AND NOT ({within})) AND ({where})",
        [*meets_params, *within_params, *params],
    )
    inside_count = (
        f"SELECT COUNT(*) FROM {table} WHERE fid IN ({inside}) AND ({where})",
        [*inside_params, *params],
    )
    page_sql = (
        f"SELECT {_columns_sql(layer)} FROM {table} "
        f"WHERE fid IN ({inside} UNION ALL SELECT value FROM json_each(?)) AND ({where}) "
        "ORDER BY fid LIMIT ? OFFSET ?"
    )
    return BboxSql(
        edges, inside_count, page_sql, (inside_params, [*params, query.limit, query.offset])
    )


def _bbox_page(
    conn: sqlite3.Connection, layer: Layer, query: Query, epoch_dates: Mapping[str, str]
) -> Page:
    import shapely

    if layer.geometry_column is None:  # attribute rows have no place: none meets a bbox
        return Page(0, [], [], [])
    if layer.rtree is None:
        raise CatalogError(f"layer {layer.name!r} of the index has no R-tree spatial index")
    statements = bbox_sql(layer, query, epoch_dates)
    edges = conn.execute(*statements.edges).fetchall()
    passed: list[int] = []
    if edges:
        hit = shapely.intersects(decode_geometries([r[1] for r in edges]), query.area)
        passed = sorted(int(r[0]) for r, ok in zip(edges, hit, strict=True) if ok)
    inside = int(conn.execute(*statements.inside_count).fetchone()[0])
    result = _rows(conn, layer, *statements.page(passed))
    result.number_matched = inside + len(passed)
    return result


def _rows(conn: sqlite3.Connection, layer: Layer, sql: str, params: list[Any]) -> Page:
    rows = conn.execute(sql, params).fetchall()
    first = 2 if layer.geometry_column else 1
    names = layer.property_names
    properties = [dict(zip(names, row[first:], strict=True)) for row in rows]
    for name in layer.boolean_names:
        for record in properties:
            value = record[name]
            if value is not None:
                record[name] = bool(value)
    blobs = [row[1] for row in rows] if layer.geometry_column else [None] * len(rows)
    return Page(0, [int(row[0]) for row in rows], properties, blobs)


def _columns_sql(layer: Layer) -> str:
    names = ["fid", *([layer.geometry_column] if layer.geometry_column else [])]
    names += [c.name for c in layer.columns]
    return ", ".join(_quote(n) for n in names)


class GeoPackageProvider:
    """Every read of one GeoPackage index file through one connection (one request at a
    time): its layers, pages of items, items by id, queryables. ``layers`` (read once per
    index file, :func:`read_layers`) may be shared by the providers of one file."""

    def __init__(
        self, connection: sqlite3.Connection, layers: dict[str, Layer] | None = None
    ) -> None:
        self.connection = connection
        self.layers = read_layers(connection) if layers is None else layers

    @classmethod
    def open(cls, path: str | Path, layers: dict[str, Layer] | None = None) -> GeoPackageProvider:
        """A provider reading the file now at ``path`` (:func:`connect`)."""
        return cls(connect(path), layers)

    def close(self) -> None:
        self.connection.close()

    def queryables(self, layer: Layer) -> dict[str, str]:
        """The layer's properties and their JSON schema types."""
        return {c.name: c.type for c in layer.columns}

    def items(
        self, layer: Layer, query: Query, epoch_dates: Mapping[str, str] | None = None
    ) -> Page:
        """One page of a layer's features matching ``query`` and how many match in all
        (``epoch_dates``: epoch label -> date, for a time filter on epochs)."""
        conn, dates = self.connection, epoch_dates or {}
        if query.area is not None:
            return _bbox_page(conn, layer, query, dates)
        columns, table = _columns_sql(layer), _quote(layer.name)
        where, params = where_sql(layer, query, dates)
        matched = conn.execute(f"SELECT COUNT(*) FROM {table} WHERE {where}", params).fetchone()
        result = _rows(
            conn,
            layer,
            f"SELECT {columns} FROM {table} WHERE {where} ORDER BY fid LIMIT ? OFFSET ?",
            [*params, query.limit, query.offset],
        )
        result.number_matched = int(matched[0])
        return result

    def geojson(self, layer: Layer, page: Page, source_crs: str, crs: str) -> list[str | None]:
        """The page's geometries as GeoJSON text in the CRS URI ``crs`` (in its axis order;
        ``source_crs`` the index's), written by GEOS (exact doubles) in one vectorised call;
        kept per layer and CRS (:attr:`Layer.geojson_texts`), so a feature's geometry is
        decoded, transformed and written once per index file."""
        import shapely

        from standgrid.serve import crs as crs_mod

        texts = layer.geojson_texts.setdefault(crs, {})
        found = [texts.get(fid, _MISSING) for fid in page.fids]
        todo = [k for k, text in enumerate(found) if text is _MISSING]
        if todo:
            geoms = decode_geometries([page.blobs[k] for k in todo])
            present = np.flatnonzero(shapely.is_geometry(geoms))
            written: list[str | None] = [None] * len(todo)
            if len(present):
                moved = crs_mod.geometries_to(geoms[present], source_crs, crs)
                for k, text in zip(
                    present.tolist(), shapely.to_geojson(moved).tolist(), strict=True
                ):
                    written[k] = text
            keep = len(texts) < MAX_CACHED_TEXTS
            for k, text in zip(todo, written, strict=True):
                found[k] = text
                if keep:
                    texts[page.fids[k]] = text
        return found

    def get(self, layer: Layer, fid: int) -> Page:
        """The feature ``fid`` (an empty page when there is none)."""
        return _rows(
            self.connection,
            layer,
            f"SELECT {_columns_sql(layer)} FROM {_quote(layer.name)} WHERE fid = ?",
            [fid],
        )
