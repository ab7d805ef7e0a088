"""Features of the catalog's GeoPackage index, read with SQLite.

A ``bbox`` is answered from the layer's R-tree (``rtree_<table>_<geom>``, the GeoPackage
spatial index extension): the candidates are the features whose envelope meets the box's,
found through the R-tree virtual table (:func:`select_sql`; ``EXPLAIN QUERY PLAN`` shows a
``VIRTUAL TABLE INDEX`` search, never a scan of the layer), then the exact test keeps those
whose geometry intersects it. Property filters and the time filter are SQL; features come in
``fid`` order, so pages of one snapshot of the index never overlap or skip.
"""

from __future__ import annotations

import datetime as dt
import math
import sqlite3
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from standgrid.errors import CatalogError
from standgrid.serve.problems import Problem

#: GeoPackage column type -> JSON schema type of a queryable.
_TYPES = {
    "INTEGER": "integer", "INT": "integer", "MEDIUMINT": "integer", "SMALLINT": "integer",
    "TINYINT": "integer", "BOOLEAN": "boolean", "REAL": "number", "DOUBLE": "number",
    "FLOAT": "number", "DATE": "string", "DATETIME": "string",
}  # fmt: skip
#: Envelope size in bytes by the GeoPackage binary header's envelope indicator.
_ENVELOPE_BYTES = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}
#: Tables of the index that are not feature layers.
_NOT_LAYERS = frozenset({"layer_styles"})


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

    @property
    def column_types(self) -> dict[str, str]:
        return {c.name: c.type for c in self.columns}

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
    number_matched: int
    fids: list[int]
    properties: list[dict[str, Any]]
    geometries: np.ndarray  # shapely geometries (None for attribute rows)


def connect(path: str | Path) -> sqlite3.Connection:
    """A read-only connection to a GeoPackage (opened now: later renames do not affect it)."""
    path = Path(path)
    if not path.is_file():
        raise CatalogError("the catalog has no index yet", path=path)
    try:
        conn = sqlite3.connect(f"{path.absolute().as_uri()}?mode=ro", uri=True)
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
            name, columns, geom_col, geom_type, bounds,
            rtree if rtree in tables else None, str(description or ""),
        )  # fmt: skip
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
    try:
        if kind == "integer":
            return int(text)
        if kind == "number":
            return float(text)
    except ValueError as exc:
        raise Problem(400, f"{name}: {text!r} is not a {kind}") from exc
    if kind == "boolean":
        lowered = text.strip().lower()
        if lowered in ("true", "1"):
            return 1
        if lowered in ("false", "0"):
            return 0
        raise Problem(400, f"{name}: {text!r} is not true or false")
    return text


def _day(value: dt.datetime | None) -> str | None:
    return None if value is None else value.astimezone(dt.UTC).date().isoformat()


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
        raise Problem(400, f"collection {layer.name!r} has no time: datetime cannot filter it")
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
    value = value.astimezone(dt.UTC)
    epoch = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    delta = value - epoch
    return (delta.days * 86400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


def where_sql(
    layer: Layer, query: Query, epoch_dates: Mapping[str, str]
) -> tuple[str, list[Any]]:
    """The WHERE clause (without the bbox) and its parameters."""
    clauses: list[str] = []
    params: list[Any] = []
    for name, text in query.equals.items():
        if name not in layer.column_types:
            raise Problem(400, f"collection {layer.name!r} has no property {name!r}")
        clauses.append(f"{_quote(name)} = ?")
        params.append(_coerce(layer, name, text))
    if query.time is not None:
        clause, extra = _time_clause(layer, query.time, epoch_dates)
        clauses.append(clause)
        params.extend(extra)
    return " AND ".join(clauses) or "1", params


def select_sql(
    layer: Layer, query: Query, epoch_dates: Mapping[str, str]
) -> tuple[str, list[Any]]:
    """``SELECT fid, <geometry>`` of the bbox candidates (through the R-tree) that pass the
    other filters, in fid order. Only for a query with an ``area``."""
    if layer.geometry_column is None or layer.rtree is None:
        raise CatalogError(f"layer {layer.name!r} has no spatial index")
    where, params = where_sql(layer, query, epoch_dates)
    xmin, ymin, xmax, ymax = (float(v) for v in query.area.bounds)
    sql = (
        f"SELECT fid, {_quote(layer.geometry_column)} FROM {_quote(layer.name)} "
        f"WHERE fid IN (SELECT id FROM {_quote(layer.rtree)} "
        "WHERE minx <= ? AND maxx >= ? AND miny <= ? AND maxy >= ?) "
        f"AND ({where}) ORDER BY fid"
    )
    return sql, [xmax, xmin, ymax, ymin, *params]


def _bbox_fids(
    conn: sqlite3.Connection, layer: Layer, query: Query, epoch_dates: Mapping[str, str]
) -> list[int]:
    import shapely

    if layer.geometry_column is None:  # attribute rows have no place: none meets a bbox
        return []
    if layer.rtree is None:
        raise CatalogError(f"layer {layer.name!r} of the index has no R-tree spatial index")
    sql, params = select_sql(layer, query, epoch_dates)
    rows = conn.execute(sql, params).fetchall()
    if not rows:
        return []
    geoms = decode_geometries([r[1] for r in rows])
    hit = shapely.intersects(geoms, query.area)
    return [int(r[0]) for r, ok in zip(rows, hit, strict=True) if ok]


def _rows(conn: sqlite3.Connection, layer: Layer, sql: str, params: list[Any]) -> Page:
    cursor = conn.execute(sql, params)
    names = [d[0] for d in cursor.description]
    types = layer.column_types
    fids: list[int] = []
    props: list[dict[str, Any]] = []
    blobs: list[bytes | None] = []
    for row in cursor:
        record = dict(zip(names, row, strict=True))
        fids.append(int(record.pop("fid")))
        blobs.append(record.pop(layer.geometry_column) if layer.geometry_column else None)
        props.append({k: _json_value(v, types.get(k)) for k, v in record.items()})
    return Page(0, fids, props, decode_geometries(blobs))


def _json_value(value: Any, kind: str | None) -> Any:
    if kind == "boolean" and value is not None:
        return bool(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _columns_sql(layer: Layer) -> str:
    names = ["fid", *([layer.geometry_column] if layer.geometry_column else [])]
    names += [c.name for c in layer.columns]
    return ", ".join(_quote(n) for n in names)


def page(
    conn: sqlite3.Connection, layer: Layer, query: Query, epoch_dates: Mapping[str, str]
) -> Page:
    """One page of a layer's features matching ``query`` and how many match in all."""
    columns, table = _columns_sql(layer), _quote(layer.name)
    if query.area is not None:
        fids = _bbox_fids(conn, layer, query, epoch_dates)
        chosen = fids[query.offset : query.offset + query.limit]
        result = _chunked_rows(conn, layer, columns, table, chosen)
        result.number_matched = len(fids)
        return result
    where, params = where_sql(layer, query, epoch_dates)
    matched = int(conn.execute(f"SELECT COUNT(*) FROM {table} WHERE {where}", params).fetchone()[0])
    result = _rows(
        conn, layer,
        f"SELECT {columns} FROM {table} WHERE {where} ORDER BY fid LIMIT ? OFFSET ?",
        [*params, query.limit, query.offset],
    )  # fmt: skip
    result.number_matched = matched
    return result


def _chunked_rows(
    conn: sqlite3.Connection, layer: Layer, columns: str, table: str, fids: list[int]
) -> Page:
    pages = [
        _rows(
            conn,
            layer,
            f"SELECT {columns} FROM {table} WHERE fid IN ({', '.join('?' * len(chunk))}) "
            "ORDER BY fid",
            list(chunk),
        )
        for chunk in _chunks(fids, 500)
    ]
    if not pages:
        return Page(0, [], [], np.zeros(0, dtype=object))
    return Page(
        0,
        [f for p in pages for f in p.fids],
        [r for p in pages for r in p.properties],
        np.concatenate([p.geometries for p in pages]),
    )


def _chunks(values: list[int], size: int) -> Iterator[list[int]]:
    for i in range(0, len(values), size):
        yield values[i : i + size]


def feature(conn: sqlite3.Connection, layer: Layer, fid: int) -> Page:
    """The feature ``fid`` (an empty page when there is none)."""
    return _rows(
        conn, layer,
        f"SELECT {_columns_sql(layer)} FROM {_quote(layer.name)} WHERE fid = ?", [fid],
    )  # fmt: skip


def parse_datetime(text: str) -> tuple[dt.datetime | None, dt.datetime | None]:
    """An RFC 3339 instant or interval (``a/b``, ``../b``, ``a/..``) as a closed UTC
    interval; a bare date is its whole day."""

    def instant(part: str, *, end: bool) -> dt.datetime | None:
        part = part.strip()
        if part in ("", ".."):
            return None
        try:
            if len(part) == 10:
                day = dt.datetime.fromisoformat(part).replace(tzinfo=dt.UTC)
                return day + dt.timedelta(days=1, microseconds=-1) if end else day
            value = dt.datetime.fromisoformat(part)
        except ValueError as exc:
            raise Problem(400, f"datetime: {part!r} is not an RFC 3339 date-time") from exc
        return value if value.tzinfo else value.replace(tzinfo=dt.UTC)

    if "/" in text:
        a, _, b = text.partition("/")
        start, end = instant(a, end=False), instant(b, end=True)
        if start is not None and end is not None and start > end:
            raise Problem(400, f"datetime: interval {text!r} ends before it starts")
        return start, end
    if text.strip() == "..":
        raise Problem(400, "datetime: '..' alone is not an instant")
    return instant(text, end=False), instant(text, end=True)
