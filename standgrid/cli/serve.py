"""``standgrid serve``: the catalog as a live service (OGC API - Features, files, retrieval)."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import click

from standgrid.cli.options import catalog_argument, json_option


@click.command(name="serve")
@catalog_argument()
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to listen on (0.0.0.0: every interface).",
)
@click.option(
    "--port",
    type=click.IntRange(0, 65535),
    default=8000,
    show_default=True,
    help="Port to listen on (0: any free port).",
)
@click.option(
    "--token-file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="File holding the bearer token writes need (else $STANDGRID_TOKEN; "
    "without either the service is read-only).",
)
@click.option(
    "--missions",
    "missions_folder",
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for missions robots send (default: CATALOG-missions beside it).",
)
@click.option(
    "--max-body",
    type=click.IntRange(1),
    default=64 * 1024 * 1024,
    show_default=True,
    help="Largest request body accepted, in bytes.",
)
# default: standgrid.serve.app.DEFAULT_PLACEMENT_TOLERANCE_M (not imported: --help stays instant)
@click.option(
    "--placement-tolerance",
    type=click.FloatRange(0),
    default=0.05,
    show_default=True,
    metavar="METRES",
    help="A streamed mission tiled again keeps its placement while a GNSS refit "
    "moves none of its points this far (in-place re-tiles; the offset is "
    "reported); 0: always the fresh fit. 'tile?exact=true' settles exactly.",
)
# default: standgrid.serve.workers.DEFAULT_WRITE_TIME_LIMIT_S
@click.option(
    "--write-time-limit",
    type=click.FloatRange(0, min_open=True),
    default=60.0,
    show_default=True,
    metavar="SECONDS",
    help="A mission write (payload, graph, GNSS) still running after this long is "
    "stopped (its worker process killed) and refused with 400.",
)
@click.option(
    "--tile-time-limit",
    type=click.FloatRange(0),
    default=0.0,
    show_default=True,
    metavar="SECONDS",
    help="A 'tile' still running after this long is stopped and answered 503 "
    "(the catalog keeps its last commit); 0: no limit.",
)
@json_option
def serve(
    catalog: Path | str,
    host: str,
    port: int,
    token_file: Path | None,
    missions_folder: Path | None,
    max_body: int,
    placement_tolerance: float,
    write_time_limit: float,
    tile_time_limit: float,
    as_json: bool,
) -> None:
    """Serve CATALOG over HTTP until Ctrl-C.

    \b
    /ogc       OGC API - Features (QGIS: "WFS / OGC API - Features"), CRS84 + catalog CRS
    /files     tiles, rasters, VPCs, tables, index (HTTP range requests: GDAL /vsicurl/)
    /missions  retrieval API: search, summary, payloads by type / pose / GNSS, clouds;
               online ingest (token): create, payloads, graph, gnss, tile
    /docs      the OpenAPI documentation of every endpoint

    Reads are open; a write needs 'Authorization: Bearer <token>'. The URLs are printed on
    stdout once the server listens (--json: one JSON line). A CATALOG in object storage
    (s3://bucket/prefix) is served read-only, as the generation current at start.

    \b
    Example:
      standgrid serve standgrid-demo --port 8000
      curl 'http://127.0.0.1:8000/ogc/collections/cells/items?limit=5'
    """
    from standgrid.serve.auth import load_token
    from standgrid.serve.server import check_port_free
    from standgrid.storage import is_url

    check_port_free(host, port)  # one clear line, not uvicorn's, and before the app loads
    token = load_token(token_file)
    with contextlib.ExitStack() as stack:
        if is_url(catalog):
            if token is not None:
                raise click.UsageError("a catalog in object storage is served read-only")
            from standgrid.catalog.remote import catalog_at

            local = stack.enter_context(catalog_at(catalog, write=False))
        else:
            local = Path(catalog)
        _serve(
            local,
            str(catalog),
            token,
            host,
            port,
            as_json,
            max_body,
            missions_folder,
            placement_tolerance,
            write_time_limit,
            tile_time_limit,
        )


def _serve(
    catalog: Path,
    name: str,
    token: str | None,
    host: str,
    port: int,
    as_json: bool,
    max_body: int,
    missions_folder: Path | None,
    placement_tolerance: float,
    write_time_limit: float,
    tile_time_limit: float,
) -> None:
    from standgrid.serve.app import create_app
    from standgrid.serve.server import Server, config, service_urls

    app = create_app(
        catalog,
        token=token,
        max_body=max_body,
        missions=missions_folder,
        placement_tolerance=placement_tolerance or None,
        write_time_limit=write_time_limit,
        tile_time_limit=tile_time_limit or None,
    )

    def started(base: str) -> None:
        urls = service_urls(base)
        if as_json:
            click.echo(json.dumps({"catalog": name, "writes": token is not None, **urls}))
        else:
            click.echo(f"serving {name} ({'read-write' if token else 'read-only'})")
            for what, url in urls.items():
                click.echo(f"  {what:9} {url}")
            click.echo("Ctrl-C stops it.", err=True)

    server = Server(config(app, host, port), on_started=started)
    with contextlib.suppress(KeyboardInterrupt):  # uvicorn stops, then re-raises SIGINT
        server.run()
    if server.base_url is None:
        raise click.ClickException(f"could not listen on {host}:{port}")
    click.echo("stopped", err=True)
