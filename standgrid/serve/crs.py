"""CRS by reference (OGC API - Features Part 2): CRS URIs, axis order, transformations.

The service offers CRS84 (longitude, latitude: the default) and the catalog's CRS when it has
an EPSG code. Coordinates are written and bboxes read in the axis order of the CRS named
(``EPSG:4326`` would be latitude first; CRS84 and most projected CRSs are x/easting first).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from standgrid.crs import CRS
from standgrid.errors import CRSError
from standgrid.serve.problems import Problem

CRS84 = "http://www.opengis.net/def/crs/OGC/1.3/CRS84"
_EPSG_URI = "http://www.opengis.net/def/crs/EPSG/0/"


@functools.lru_cache(maxsize=16)
def _crs(uri_or_spec: str) -> CRS:
    spec = "OGC:CRS84" if uri_or_spec == CRS84 else uri_or_spec
    if spec.startswith(_EPSG_URI):
        spec = "EPSG:" + spec.removeprefix(_EPSG_URI)
    try:
        return CRS.of(spec)
    except CRSError as exc:
        raise CRSError(f"unusable CRS {uri_or_spec!r}: {exc.message}") from exc


@functools.lru_cache(maxsize=16)
def catalog_crs_uri(catalog_crs: str) -> str | None:
    """The URI of the catalog's CRS (``.../EPSG/0/<code>``), or None without an EPSG code."""
    code = _crs(catalog_crs).epsg
    return None if code is None else f"{_EPSG_URI}{code}"


def supported(catalog_crs: str) -> list[str]:
    """The CRS URIs the service answers in: CRS84 first (the default), then the catalog's."""
    own = catalog_crs_uri(catalog_crs)
    return [CRS84] if own is None or own == CRS84 else [CRS84, own]


def check(uri: str | None, catalog_crs: str, parameter: str) -> str:
    """``uri`` if the service supports it (CRS84 when None); else a 400 problem."""
    if uri is None or uri == "":
        return CRS84
    uri = uri.strip().strip("<>")
    offered = supported(catalog_crs)
    if uri not in offered:
        raise Problem(400, f"{parameter}: unsupported CRS {uri!r}; supported: {offered}")
    return uri


def geographic_axes(uri: str) -> tuple[str, str] | None:
    """``("lon", "lat")`` or ``("lat", "lon")``: the axis order of a geographic CRS; None
    for any other."""
    crs = _crs(uri)
    if not crs.is_geographic:
        return None
    return ("lat", "lon") if crs.northing_first else ("lon", "lat")


def _transformer(source: str, target: str) -> Any:
    return _crs(source).transformer_to(_crs(target))


def transform_xy(
    x: np.ndarray, y: np.ndarray, source: str, target: str
) -> tuple[np.ndarray, np.ndarray]:
    """x/y (easting/longitude first) from ``source`` to ``target``, both in x/y order."""
    if _same(source, target):
        return x, y
    tx, ty = _transformer(source, target).transform(x, y, errcheck=True)
    return np.asarray(tx, dtype=np.float64), np.asarray(ty, dtype=np.float64)


def _reproject(geoms: np.ndarray, source: str, target: str, *, swap: bool) -> np.ndarray:
    import shapely

    def apply(coords: np.ndarray) -> np.ndarray:
        x, y = transform_xy(coords[:, 0], coords[:, 1], source, target)
        out = np.column_stack([y, x] if swap else [x, y])
        return out if coords.shape[1] == 2 else np.column_stack([out, coords[:, 2:]])

    return np.asarray(shapely.transform(geoms, apply, include_z=None))


def geometries_to(geoms: np.ndarray, source: str, target_uri: str) -> np.ndarray:
    """Shapely geometries (x/y) from ``source`` to the CRS ``target_uri``, in its axis order."""
    return _reproject(geoms, source, target_uri, swap=_uri_northing_first(target_uri))


def bbox_polygon(bbox: list[float], bbox_crs_uri: str, target: str) -> Any:
    """A ``bbox`` (in ``bbox_crs_uri``'s axis order) as a polygon in ``target`` (x/y), its
    edges densified so the transformed box keeps its shape."""
    import shapely

    if len(bbox) == 6:  # minx, miny, minz, maxx, maxy, maxz: heights play no part
        bbox = [bbox[0], bbox[1], bbox[3], bbox[4]]
    a0, b0, a1, b1 = bbox
    if _crs(bbox_crs_uri).northing_first:
        a0, b0, a1, b1 = b0, a0, b1, a1
    if a0 > a1 or b0 > b1:
        raise Problem(400, f"bbox: lower corner {bbox[:2]} above or right of the upper one")
    box = shapely.box(a0, b0, a1, b1)
    if _same(bbox_crs_uri, target):
        return box
    if (a1 - a0) > 0 and (b1 - b0) > 0:
        box = shapely.segmentize(box, max(a1 - a0, b1 - b0) / 64.0)
    import pyproj

    try:
        return _reproject(np.array([box]), bbox_crs_uri, target, swap=False)[0]
    except pyproj.exceptions.ProjError as exc:
        raise Problem(400, f"bbox: {bbox} does not transform to the catalog's CRS ({exc})") from exc


@functools.lru_cache(maxsize=64)
def _same(a: str, b: str) -> bool:
    return a == b or _crs(a).equivalent(_crs(b))


@functools.lru_cache(maxsize=16)
def _uri_northing_first(uri: str) -> bool:
    return _crs(uri).northing_first


def bounds_to_crs84(bounds: tuple[float, float, float, float], source: str) -> list[float]:
    """Layer bounds in ``source`` as a CRS84 bbox (densified edges)."""
    import pyproj

    transformer = _transformer(source, CRS84)
    west, south, east, north = transformer.transform_bounds(*bounds, densify_pts=21)
    if not all(np.isfinite([west, south, east, north])):
        raise pyproj.exceptions.ProjError(f"bounds {bounds} do not transform to CRS84")
    return [float(west), float(south), float(east), float(north)]


def prepare(catalog_crs: str) -> None:
    """Fill the caches every OGC request of this catalog uses (CRS objects, EPSG codes,
    transformers; 0.1-0.3 s), so the first requests do not each build them at once."""
    for uri in supported(catalog_crs):
        _uri_northing_first(uri)
        _same(uri, catalog_crs)
        if not _same(uri, catalog_crs):
            _transformer(catalog_crs, uri)
            _transformer(uri, catalog_crs)
