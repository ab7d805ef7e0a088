"""``standgrid serve``: the catalog as a live service (FastAPI on uvicorn).

- :mod:`~standgrid.serve.app`: :func:`create_app`, the application factory;
- :mod:`~standgrid.serve.ogc`: OGC API - Features at ``/ogc`` (Part 1 Core, Part 2 CRS;
  HTTP only), asking :mod:`~standgrid.serve.provider` (every query of the GeoPackage index:
  layers, R-tree bbox, paging, filters), :mod:`~standgrid.serve.crs` (CRS URIs, axis
  order), OpenAPI 3.0 in :mod:`~standgrid.serve.ogc_openapi`;
- :mod:`~standgrid.serve.files`: catalog files with HTTP range requests;
- :mod:`~standgrid.serve.missions`: the retrieval API;
- :mod:`~standgrid.serve.auth` (bearer token for writes), :mod:`~standgrid.serve.limits`
  (request body size), :mod:`~standgrid.serve.problems` (RFC 9457 problem documents),
  :mod:`~standgrid.serve.snapshot` (a consistent catalog view per request).

Sits on top of every stage, beside ``cli/``; nothing below imports it. FastAPI is imported
only by the modules that need it.
"""

from standgrid.serve.app import create_app

__all__ = ["create_app"]
