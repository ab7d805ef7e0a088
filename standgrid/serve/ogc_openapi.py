"""The OpenAPI 3.0 definition of ``/ogc`` (OGC API - Features requirement class oas30).

FastAPI's own document (``/openapi.json``) is OpenAPI 3.1 and covers the whole service; this
one describes the OGC API alone, with one items path per collection and its queryables.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from standgrid.serve.provider import Layer

_JSON = {"application/json": {"schema": {"type": "object"}}}
_GEOJSON = {"application/geo+json": {"schema": {"type": "object"}}}
_PROBLEM = {
    "description": "a problem document (RFC 9457)",
    "content": {"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}},
}


def _param(
    name: str,
    schema: dict[str, Any],
    description: str,
    *,
    where: str = "query",
    required: bool = False,
    **extra: Any,
) -> dict[str, Any]:
    return {
        "name": name,
        "in": where,
        "required": required,
        "schema": schema,
        "description": description,
        **extra,
    }


def _get(
    summary: str,
    content: dict[str, Any],
    parameters: list[dict[str, Any]] | None = None,
    operation_id: str = "",
) -> dict[str, Any]:
    op: dict[str, Any] = {
        "summary": summary,
        "operationId": operation_id,
        "responses": {
            "200": {"description": summary, "content": content},
            "400": _PROBLEM,
            "404": _PROBLEM,
        },
    }
    if parameters:
        op["parameters"] = parameters
    return {"get": op}


def openapi_document(base: str, layers: Mapping[str, Layer], crs: list[str]) -> dict[str, Any]:
    """The document for the layers of the index (``base``: the URL of ``/ogc``)."""
    crs_schema = {"type": "string", "format": "uri", "enum": crs, "default": crs[0]}
    common = [
        _param(
            "bbox",
            {"type": "array", "minItems": 4, "maxItems": 6, "items": {"type": "number"}},
            "minx,miny,maxx,maxy in bbox-crs (default CRS84: lon,lat)",
            style="form",
            explode=False,
        ),
        _param("bbox-crs", crs_schema, "CRS of bbox"),
        _param("crs", crs_schema, "CRS of the geometries returned"),
        _param(
            "datetime",
            {"type": "string"},
            "RFC 3339 instant or interval (a/b, ../b, a/..); epochs by their date",
        ),
        _param(
            "limit",
            {"type": "integer", "minimum": 1, "maximum": 10000, "default": 100},
            "features per page",
        ),
        _param(
            "offset",
            {"type": "integer", "minimum": 0, "default": 0},
            "features skipped (the next link carries it)",
        ),
    ]
    paths: dict[str, Any] = {
        "/": _get("Landing page", _JSON, operation_id="getLandingPage"),
        "/conformance": _get("Conformance classes", _JSON, operation_id="getConformance"),
        "/api": _get(
            "This document",
            {"application/vnd.oai.openapi+json;version=3.0": {"schema": {"type": "object"}}},
            operation_id="getApi",
        ),
        "/collections": _get("The collections", _JSON, operation_id="getCollections"),
    }
    for name, layer in layers.items():
        properties = [
            _param(c.name, {"type": c.type}, f"features whose {c.name} equals this value")
            for c in layer.columns
            if c.name not in {p["name"] for p in common}
        ]
        prefix = f"/collections/{name}"
        paths[prefix] = _get(f"Collection {name}", _JSON, operation_id=f"describe_{name}")
        paths[f"{prefix}/queryables"] = _get(
            f"Queryables of {name}",
            {"application/schema+json": {"schema": {"type": "object"}}},
            operation_id=f"queryables_{name}",
        )
        paths[f"{prefix}/items"] = _get(
            f"Features of {name}", _GEOJSON, [*common, *properties], operation_id=f"items_{name}"
        )
        paths[f"{prefix}/items/{{featureId}}"] = _get(
            f"One feature of {name}",
            _GEOJSON,
            [
                _param(
                    "featureId", {"type": "integer"}, "the feature id", where="path", required=True
                ),
                common[2],
            ],
            operation_id=f"item_{name}",
        )
    return {
        "openapi": "3.0.3",
        "info": {"title": "standgrid catalog: OGC API - Features", "version": "1.0.0"},
        "servers": [{"url": base}],
        "paths": paths,
        "components": {
            "schemas": {
                "Problem": {
                    "type": "object",
                    "properties": {
                        "type": {"type": "string"},
                        "title": {"type": "string"},
                        "status": {"type": "integer"},
                        "detail": {"type": "string"},
                        "instance": {"type": "string"},
                    },
                }
            }
        },
    }
