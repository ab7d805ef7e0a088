"""OGC API - Features at ``/ogc``: Part 1 Core (GeoJSON, OpenAPI 3.0) and Part 2 (CRS by
reference). One collection per layer of the catalog's ``index.gpkg``."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from pathlib import Path
from typing import Any

import orjson
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response

from standgrid.catalog.invalidate import CHANGE_LAYERS, other_catalog_change
from standgrid.serve import crs as crs_mod
from standgrid.serve.ogc_openapi import openapi_document
from standgrid.serve.problems import Problem
from standgrid.serve.provider import GeoPackageProvider, Layer, Page, Query
from standgrid.serve.snapshot import Snapshot, snapshot

GEOJSON = "application/geo+json"
OPENAPI_JSON = "application/vnd.oai.openapi+json;version=3.0"
CONFORMANCE = [
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/oas30",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/geojson",
    "http://www.opengis.net/spec/ogcapi-features-2/1.0/conf/crs",
]
DEFAULT_LIMIT = 100
MAX_LIMIT = 10_000
#: Largest offset and feature id (SQLite integers are 64-bit; no index holds 2**53 rows).
MAX_OFFSET = 2**53
MAX_FID = 2**63 - 1
#: Query parameters of an items request that are not property filters.
ITEMS_PARAMETERS = frozenset({"bbox", "bbox-crs", "crs", "datetime", "limit", "offset", "f"})
TITLES = {
    "cells": "Stand-grid cells with their tiles (one row per cell and epoch)",
    "payloads": "Payload footprints (one per payload cloud)",
    "trajectories": "Robot trajectories (one line per mission)",
    "gnss_fixes": "GNSS fixes with their georeference residuals",
    "missions": "Missions and their georeference fit",
    "stand_metrics": "Cell (level 0) and stand (level 1) metrics per epoch",
    "trees": "Trees found per epoch (crown polygons)",
    "stand_changes": "Change of stand metrics between two epochs",
    "tree_changes": "Matched, removed and new trees between two epochs",
}


def _root(request: Request) -> Path:
    root: Path = request.app.state.catalog_root
    return root


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/") + "/ogc"


def _json(body: Any, media_type: str = "application/json", **headers: str) -> JSONResponse:
    return JSONResponse(body, media_type=media_type, headers=headers or None)


router = APIRouter(prefix="/ogc", tags=["OGC API - Features"])


@router.get("", summary="Landing page")
@router.get("/", include_in_schema=False)
def landing(request: Request) -> JSONResponse:
    base = _base(request)
    return _json(
        {
            "title": "standgrid catalog",
            "description": "The stand-grid catalog's index layers as OGC API - Features",
            "links": [
                {"rel": "self", "type": "application/json", "href": base},
                {"rel": "service-desc", "type": OPENAPI_JSON, "href": f"{base}/api"},
                {
                    "rel": "service-doc",
                    "type": "text/html",
                    "href": str(request.base_url).rstrip("/") + "/docs",
                },
                {"rel": "conformance", "type": "application/json", "href": f"{base}/conformance"},
                {"rel": "data", "type": "application/json", "href": f"{base}/collections"},
            ],
        }
    )


@router.get("/conformance", summary="Conformance classes")
def conformance() -> JSONResponse:
    return _json({"conformsTo": CONFORMANCE})


@router.get("/api", summary="OpenAPI 3.0 definition of the OGC API")
def api(request: Request) -> JSONResponse:
    with snapshot(_root(request)) as snap:
        document = openapi_document(_base(request), snap.layers, _offered(snap))
    return _json(document, OPENAPI_JSON)


def _offered(snap: Snapshot) -> list[str]:
    return crs_mod.supported(snap.catalog.crs)


def _temporal_extent(snap: Snapshot, layer: Layer) -> list[str | None] | None:
    if layer.temporal is None:
        return None
    dates = sorted(d for d in snap.epoch_dates.values() if d)
    if not dates:
        return None
    return [f"{dates[0][:10]}T00:00:00Z", f"{dates[-1][:10]}T23:59:59Z"]


def _stale_comparisons(snap: Snapshot) -> list[dict[str, str]]:
    """Comparisons whose rows the change layers serve though the other catalog they read
    changed since (re-tiled, re-enriched, gone): key, epochs and why."""
    others: dict[str, Any] = {}
    stale = []
    for key, entry in sorted(snap.catalog.comparisons.items()):
        reason = other_catalog_change(entry, others)
        if reason is not None:
            stale.append(
                {
                    "comparison": key,
                    "epoch_from": str(entry.get("from")),
                    "epoch_to": str(entry.get("to")),
                    "reason": reason,
                }
            )
    return stale


def _collection(request: Request, snap: Snapshot, layer: Layer) -> dict[str, Any]:
    base = f"{_base(request)}/collections/{layer.name}"
    extent: dict[str, Any] = {}
    if layer.bounds is not None:
        extent["spatial"] = {
            "bbox": [crs_mod.bounds_to_crs84(layer.bounds, snap.catalog.crs)],
            "crs": crs_mod.CRS84,
        }
    interval = _temporal_extent(snap, layer)
    if interval is not None:
        extent["temporal"] = {
            "interval": [interval],
            "trs": "http://www.opengis.net/def/uom/ISO-8601/0/Gregorian",
        }
    body: dict[str, Any] = {
        "id": layer.name,
        "title": TITLES.get(layer.name, layer.name),
        "description": layer.description or TITLES.get(layer.name, layer.name),
        "itemType": "feature",
        "crs": _offered(snap),
        "links": [
            {"rel": "self", "type": "application/json", "href": base},
            {"rel": "items", "type": GEOJSON, "href": f"{base}/items"},
            {
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/queryables",
                "type": "application/schema+json",
                "href": f"{base}/queryables",
            },
        ],
    }
    own = crs_mod.catalog_crs_uri(snap.catalog.crs)
    if own is not None:
        body["storageCrs"] = own
    if layer.name in CHANGE_LAYERS:
        stale = _stale_comparisons(snap)
        body["standgrid:stale_comparisons"] = stale
        if stale:
            body["description"] += "; stale (the other catalog's epoch changed since): " + (
                "; ".join(f"{s['comparison']}: {s['reason']}" for s in stale)
            )
    if extent:
        body["extent"] = extent
    return body


@router.get("/collections", summary="The collections (one per index layer)")
def collections(request: Request) -> JSONResponse:
    with snapshot(_root(request)) as snap:
        items = [_collection(request, snap, layer) for layer in snap.layers.values()]
        offered = _offered(snap)
    base = _base(request)
    return _json(
        {
            "links": [{"rel": "self", "type": "application/json", "href": f"{base}/collections"}],
            "collections": items,
            "crs": offered,
        }
    )


@router.get("/collections/{collection_id}", summary="One collection")
def collection(request: Request, collection_id: str) -> JSONResponse:
    with snapshot(_root(request)) as snap:
        return _json(_collection(request, snap, snap.layer(collection_id)))


@router.get("/collections/{collection_id}/queryables", summary="Properties to filter by")
def queryables(request: Request, collection_id: str) -> JSONResponse:
    with snapshot(_root(request)) as snap:
        layer = snap.layer(collection_id)
        assert snap.provider is not None
        types = snap.provider.queryables(layer)
    base = f"{_base(request)}/collections/{layer.name}/queryables"
    return _json(
        {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": base,
            "type": "object",
            "title": layer.name,
            "properties": {name: {"type": kind} for name, kind in types.items()},
        },
        "application/schema+json",
    )


def _int(
    request: Request, name: str, default: int, low: int, high: int, *, clamp: bool = False
) -> int:
    """The integer parameter ``name``: at least ``low``; a larger value than ``high`` is
    ``high`` (``clamp``) or a 400 problem."""
    text = request.query_params.get(name)
    if text is None or text == "":
        return default
    shown = text if len(text) <= 40 else text[:40] + "..."
    if len(text) > 40:
        raise Problem(400, f"{name}: {shown!r} is not an integer of at most 40 digits")
    try:
        value = int(text)
    except ValueError as exc:
        raise Problem(400, f"{name}: {shown!r} is not an integer") from exc
    if value < low:
        raise Problem(400, f"{name}: must be at least {low}, got {value}")
    if value > high:
        if not clamp:
            raise Problem(400, f"{name}: must be at most {high}, got {value}")
        return high
    return value


def _bbox(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError as exc:
        raise Problem(400, f"bbox: {text!r} is not four or six numbers") from exc
    if len(values) not in (4, 6) or not all(abs(v) < float("inf") for v in values):
        raise Problem(400, f"bbox: {text!r} is not four or six finite numbers")
    return values


def _check_degrees(bbox: list[float], bbox_crs: str) -> None:
    """A 400 problem for a bbox in a geographic CRS with a latitude beyond +-90 degrees or
    a longitude beyond +-180 (in the CRS's axis order)."""
    axes = crs_mod.geographic_axes(bbox_crs)
    if axes is None:
        return
    corners = [bbox[:2], bbox[3:5]] if len(bbox) == 6 else [bbox[:2], bbox[2:]]
    for corner in corners:
        for value, axis in zip(corner, axes, strict=True):
            bound = 90.0 if axis == "lat" else 180.0
            if abs(value) > bound:
                word = "latitude" if axis == "lat" else "longitude"
                raise Problem(400, f"bbox: {word} {value} outside -{bound:g}..{bound:g}")


def _query(request: Request, snap: Snapshot, layer: Layer) -> Query:
    params = request.query_params
    unknown = [k for k in params if k not in ITEMS_PARAMETERS and k not in layer.column_types]
    if unknown:
        raise Problem(
            400,
            f"unknown parameters {unknown}; properties of {layer.name!r}: "
            f"{[c.name for c in layer.columns]}",
        )
    if len(set(params.keys())) != len(params.multi_items()):
        raise Problem(400, "a parameter is given more than once")
    if params.get("f") not in (None, "json", "geojson"):
        raise Problem(400, f"f: only json is offered, not {params.get('f')!r}")
    query = Query(
        limit=_int(request, "limit", DEFAULT_LIMIT, 1, MAX_LIMIT, clamp=True),
        offset=_int(request, "offset", 0, 0, MAX_OFFSET),
        # a property named like a parameter (missions.crs) cannot be filtered by name
        equals={
            k: v for k, v in params.items() if k in layer.column_types and k not in ITEMS_PARAMETERS
        },
    )
    if params.get("bbox"):
        bbox_crs = crs_mod.check(params.get("bbox-crs"), snap.catalog.crs, "bbox-crs")
        bbox = _bbox(params["bbox"])
        _check_degrees(bbox, bbox_crs)
        query.area = crs_mod.bbox_polygon(bbox, bbox_crs, snap.catalog.crs)
    elif params.get("bbox-crs"):
        raise Problem(400, "bbox-crs without bbox")
    if params.get("datetime"):
        query.time = parse_datetime(params["datetime"])
    return query


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
                return (
                    day.replace(hour=23, minute=59, second=59, microsecond=999999) if end else day
                )
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


def _features(
    provider: GeoPackageProvider,
    layer: Layer,
    page: Page,
    source_crs: str,
    out_crs: str,
    links: Callable[[int], list[dict[str, str]]],
) -> list[dict[str, Any]]:
    """The page's features as GeoJSON objects; their geometries (GeoJSON text from the
    provider) kept as :class:`orjson.Fragment`."""
    texts = provider.geojson(layer, page, source_crs, out_crs)
    return [
        {
            "type": "Feature",
            "id": fid,
            "geometry": None if text is None else orjson.Fragment(text),
            "properties": props,
            "links": links(fid),
        }
        for fid, props, text in zip(page.fids, page.properties, texts, strict=True)
    ]


def _geojson(body: Any, out_crs: str) -> Response:
    """``body`` written once by orjson (non-finite numbers as null, as before)."""
    return Response(orjson.dumps(body), media_type=GEOJSON, headers={"Content-Crs": f"<{out_crs}>"})


def _with_params(request: Request, **changes: Any) -> str:
    params = dict(request.query_params)
    params.update({k: str(v) for k, v in changes.items()})
    return str(request.url.replace_query_params(**params))


@router.get(
    "/collections/{collection_id}/items",
    summary="Features of a collection: bbox, datetime, property filters, limit/offset paging",
)
def items(request: Request, collection_id: str) -> Response:
    with snapshot(_root(request)) as snap:
        layer = snap.layer(collection_id)
        query = _query(request, snap, layer)
        out_crs = crs_mod.check(request.query_params.get("crs"), snap.catalog.crs, "crs")
        assert snap.provider is not None
        page = snap.provider.items(layer, query, snap.epoch_dates)
        items_url = f"{_base(request)}/collections/{layer.name}/items"
        body_features = _features(
            snap.provider,
            layer,
            page,
            snap.catalog.crs,
            out_crs,
            lambda fid: [{"rel": "self", "type": GEOJSON, "href": f"{items_url}/{fid}"}],
        )
    links = [
        {"rel": "self", "type": GEOJSON, "href": str(request.url)},
        {
            "rel": "collection",
            "type": "application/json",
            "href": f"{_base(request)}/collections/{layer.name}",
        },
    ]
    if query.offset + len(page.fids) < page.number_matched:
        links.append(
            {
                "rel": "next",
                "type": GEOJSON,
                "href": _with_params(request, offset=query.offset + query.limit, limit=query.limit),
            }
        )
    if query.offset > 0:
        links.append(
            {
                "rel": "prev",
                "type": GEOJSON,
                "href": _with_params(
                    request, offset=max(0, query.offset - query.limit), limit=query.limit
                ),
            }
        )
    return _geojson(
        {
            "type": "FeatureCollection",
            "features": body_features,
            "numberMatched": page.number_matched,
            "numberReturned": len(page.fids),
            "timeStamp": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "links": links,
        },
        out_crs,
    )


@router.get("/collections/{collection_id}/items/{feature_id}", summary="One feature")
def item(request: Request, collection_id: str, feature_id: str) -> Response:
    shown = feature_id if len(feature_id) <= 40 else feature_id[:40] + "..."
    try:
        fid = int(feature_id) if len(feature_id) <= 40 and feature_id.isascii() else None
    except ValueError:
        fid = None
    if fid is None or not 0 <= fid <= MAX_FID:
        raise Problem(404, f"no feature {shown!r}: feature ids are integers 0..{MAX_FID}")
    unknown = [k for k in request.query_params if k not in ("crs", "f")]
    if unknown:
        raise Problem(400, f"unknown parameters {unknown}; a feature takes crs and f")
    with snapshot(_root(request)) as snap:
        layer = snap.layer(collection_id)
        out_crs = crs_mod.check(request.query_params.get("crs"), snap.catalog.crs, "crs")
        assert snap.provider is not None
        page = snap.provider.get(layer, fid)
        if not page.fids:
            raise Problem(404, f"collection {layer.name!r} has no feature {fid}")
        links = [
            {"rel": "self", "type": GEOJSON, "href": str(request.url)},
            {
                "rel": "collection",
                "type": "application/json",
                "href": f"{_base(request)}/collections/{layer.name}",
            },
        ]
        body = _features(snap.provider, layer, page, snap.catalog.crs, out_crs, lambda fid: links)[
            0
        ]
    return _geojson(body, out_crs)
