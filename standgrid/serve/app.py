"""The application factory: one ASGI app over one catalog."""

from __future__ import annotations

import contextlib
import gc
import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from standgrid.catalog import Catalog
from standgrid.serve.limits import DEFAULT_MAX_BODY
from standgrid.serve.workers import DEFAULT_WRITE_MEMORY_LIMIT, DEFAULT_WRITE_TIME_LIMIT_S

#: Metres a refit may move a streamed mission before its epoch re-tiles whole (the default
#: of ``standgrid serve --placement-tolerance``): a GNSS fit's own residuals and 1-sigma are
#: centimetres (RTK fixes 2-3 cm; the bundled mission's fit settles to < 1 cm 1-sigma), and
#: a forest point cloud's noise is ~1 cm, so 5 cm keeps every point as close to the fresh
#: fit as the fit itself is to the truth, while a robot's stream re-tiles in place.
DEFAULT_PLACEMENT_TOLERANCE_M = 0.05
#: CPU priority of the tiling worker below the server's: tiling is background work that
#: takes seconds of CPU, and on a busy machine the readers' requests come first.
TILER_NICENESS = 10
#: Mission-folder writer processes at most: a write that hangs one (until its time limit)
#: leaves the others to the other robots.
WRITER_PROCESSES = 4


def create_app(
    catalog: str | os.PathLike[str],
    *,
    token: str | None = None,
    max_body: int = DEFAULT_MAX_BODY,
    missions: str | os.PathLike[str] | None = None,
    placement_tolerance: float | None = DEFAULT_PLACEMENT_TOLERANCE_M,
    write_time_limit: float | None = DEFAULT_WRITE_TIME_LIMIT_S,
    tile_time_limit: float | None = None,
    write_memory_limit: int | None = DEFAULT_WRITE_MEMORY_LIMIT,
) -> Any:
    """The FastAPI app serving ``catalog``: ``/ogc`` (OGC API - Features), ``/files``
    (catalog files with range requests), ``/missions`` (retrieval API and online ingest).
    Reads are open; a write needs ``Authorization: Bearer <token>`` (none is accepted when
    ``token`` is None). Missions sent by robots are written under ``missions`` (default:
    ``<catalog>-missions`` beside the catalog). Writes (mission folders, tiling) run in worker
    processes, stopped with the app (its lifespan). A mission tiled again keeps its placement
    while a refit moves it less than ``placement_tolerance`` metres (None: always the fresh
    fit; ``POST /missions/{name}/tile?exact=true`` settles on it). A mission-folder write
    taking longer than ``write_time_limit`` seconds, or more address space than
    ``write_memory_limit`` bytes, is stopped (its worker killed) and refused with 400; a
    tiling longer than ``tile_time_limit`` seconds with 503 (None: no limit).
    Raises :class:`~standgrid.errors.CatalogNotFoundError` when ``catalog`` is not one."""
    import math

    from fastapi import FastAPI

    from standgrid.errors import TilingError

    for what, limit in (("write", write_time_limit), ("tile", tile_time_limit)):
        if limit is not None and not (math.isfinite(limit) and limit > 0):
            raise ValueError(
                f"{what} time limit must be a positive number of seconds, got {limit!r}"
            )
    if placement_tolerance is not None and not (
        math.isfinite(placement_tolerance) and placement_tolerance >= 0
    ):
        raise TilingError(
            f"placement tolerance must be a finite number of metres >= 0, "
            f"got {placement_tolerance!r}"
        )

    from standgrid.serve import events, files, ingest, ogc, problems, viewer
    from standgrid.serve import missions as retrieval
    from standgrid.serve.auth import WriteGuard
    from standgrid.serve.limits import BodyLimit
    from standgrid.serve.workers import WorkerProcess

    root = Path(catalog).absolute()
    opened = Catalog.open(root)  # refuse a folder that is not a catalog now, not per request
    _preload(opened.crs, writes=token is not None)
    # writes run in worker processes, each started at its first call
    workers = {
        "mission_writer": WorkerProcess(
            "mission writer",
            processes=WRITER_PROCESSES,
            time_limit=write_time_limit,
            memory_limit=write_memory_limit,
            limit_status=400,
            limit_hint=": its data could not be read in bounded time",
        ),
        "tiler": WorkerProcess(
            "tiling",
            niceness=TILER_NICENESS,
            time_limit=tile_time_limit,
            limit_status=503,
            limit_hint="; the catalog keeps its last commit (a longer limit: --tile-time-limit)",
        ),
    }

    @contextlib.asynccontextmanager
    async def lifespan(_: Any) -> AsyncIterator[None]:
        # what exists now (modules, the app) lives as long as the server: out of the cyclic
        # collector's way, a full collection walks only what requests made (~80 ms -> less,
        # and every reader waits for it)
        gc.collect()
        gc.freeze()
        try:
            yield
        finally:
            hub.close()
            for worker in workers.values():
                worker.shutdown()

    app = FastAPI(
        title="standgrid",
        summary="A stand-grid catalog as a service: OGC API - Features, files, retrieval",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.state.catalog_root = root
    app.state.placement_tolerance = placement_tolerance
    for name, worker in workers.items():
        setattr(app.state, name, worker)
    hub = events.EventHub()
    app.state.events = hub  # the live event stream (serve.events), closed as the server stops
    app.state.mission_turns = {}  # mission name -> [lock, users] (serve.ingest._turn)
    default_missions = root.with_name(f"{root.name}-missions")
    app.state.missions_root = Path(missions).absolute() if missions else default_missions
    problems.install(app)
    app.include_router(ogc.router)
    app.include_router(files.router)
    app.include_router(retrieval.router)
    app.include_router(ingest.router)
    app.include_router(events.router)

    viewer.install(
        app,
        description={
            "title": "standgrid",
            "catalog": root.name,
            "links": [
                {"rel": "ogc", "href": "/ogc", "title": "OGC API - Features"},
                {"rel": "files", "href": "/files", "title": "catalog files (range requests)"},
                {
                    "rel": "stac",
                    "href": "/files/stac/catalog.json",
                    "type": "application/json",
                    "title": "static STAC catalog (pystac-client, QGIS, STAC Browser)",
                },
                {"rel": "missions", "href": "/missions", "title": "retrieval API"},
                {
                    "rel": "events",
                    "href": "/events",
                    "type": "text/event-stream",
                    "title": "live events (Server-Sent Events)",
                },
                {"rel": "service-desc", "href": "/openapi.json", "title": "OpenAPI 3.1"},
                {"rel": "service-doc", "href": "/docs", "title": "API documentation"},
                {"rel": "viewer", "href": "/", "type": "text/html", "title": "web viewer"},
            ],
        },
    )

    # The middleware added last runs first: the write guard answers before the body limit
    # reads anything or a route is found.
    app.add_middleware(BodyLimit, max_bytes=max_body)
    app.add_middleware(WriteGuard, token=token)
    return app


def _preload(catalog_crs: str, *, writes: bool) -> None:
    """Import and build now what requests would on first use: an import holds the GIL
    (scipy.spatial ~0.5 s), and each of the first concurrent OGC requests would build the
    same CRS transformers at once, stalling every reader meanwhile."""
    import shapely  # noqa: F401

    from standgrid.serve import crs

    crs.prepare(catalog_crs)

    if writes:
        import scipy.spatial.transform  # noqa: F401  (the node pose a payload carries)
