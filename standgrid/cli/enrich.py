"""``standgrid enrich``: terrain, trees and stand metrics for a catalog."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import click

from standgrid.cli.options import (
    CLUSTER,
    ENRICH,
    build,
    catalog_argument,
    emit,
    execution,
    json_option,
    options,
    quiet_option,
)


def _human(r: dict[str, Any]) -> str:
    from standgrid.enrichment.allometry import MIN_TREES

    lines = [f"enriched {r['catalog']}"]
    for epoch, e in r["epochs"].items():
        without = (
            f", {e['trees_dbh_none']} without a DBH"
            + (
                f" (no height-diameter model: fewer than {MIN_TREES} measured stems in the"
                " catalog; basal area and QMD null where they stand)"
                if e["height_diameter_model"] is None
                else ""
            )
            if e["trees_dbh_none"]
            else ""
        )
        lines.append(
            f"epoch {epoch}: {e['cells']} cells ({e['cells_without_ground']} without ground),"
            f" {100 * e['observed_fraction']:.0f} % of their area observed;"
            f" {e['trees']} trees ({e['trees_on_observed_ground']} on observed ground),"
            f" DBH {e['trees_dbh_measured']} measured, {e['trees_dbh_imputed']} imputed" + without
        )
    lines.append(
        "outputs: rasters/<epoch>/{dtm,chm,density,observed}.tif,"
        " tables/stand_metrics.{csv,parquet}, tables/tree_list_<epoch>.{csv,parquet};"
        " index.gpkg layers stand_metrics and trees"
    )
    return "\n".join(lines)


@click.command("enrich")
@catalog_argument()
@options(*ENRICH, *CLUSTER)
@json_option
@quiet_option
def enrich(catalog: Path, as_json: bool, quiet: bool, **params: Any) -> None:
    """Classify ground, build terrain rasters, find trees and compute stand metrics.

    Tiles get LAS class 2 for ground, a height_above_ground and a tree_id dimension; each
    epoch gets DTM, CHM, density and observed-ground Cloud-Optimized GeoTIFFs aligned to the
    stand grid; stand metrics (over each stand's observed ground; null with a reason below
    --min-observed / --min-density) and tree lists (every tree with a measured DBH, one
    imputed from its height, or none with a reason when the catalog has fewer than 15
    measured stems to fit a height-diameter model) go to tables/ (CSV, Parquet) and to
    index.gpkg. Column definitions: docs/METRICS.md.

    Enriching an epoch again replaces its outputs inside the catalog (no --overwrite: they
    are the catalog's own, replaced in one transaction; comparisons made from them are
    removed). Ctrl-C stops it; the catalog keeps its last complete state.

    \b
    Example:
      standgrid enrich catalog
      standgrid enrich catalog --epoch 2028 --pixel 0.5 --json
      standgrid enrich catalog --workers 2 --memory 4096
    """
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.enrich import enrich_catalog

    enrich_options, running = build(EnrichOptions, params), execution(params, quiet)
    with interruptible():
        report = enrich_catalog(catalog, enrich_options, execution=running)
    emit(report.to_dict(), as_json, _human)


#: What an interrupted command says: nothing it did is committed.
INTERRUPTED = "interrupted: the catalog keeps its last complete state"


@contextlib.contextmanager
def interruptible() -> Iterator[None]:
    """Ctrl-C said at once and obeyed: the first stops the work (chunks in progress are
    waited for, those not started are cancelled, the staged files removed), a second one
    exits at once (what was staged is removed by the next command that opens the catalog:
    a commit not completed is discarded). Either way :data:`INTERRUPTED` is said and the
    exit status is 130."""
    import os
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    said: list[bool] = []

    def on_interrupt(signum: int, frame: FrameType | None) -> None:
        if said:
            click.echo(f"\n{INTERRUPTED}", err=True)
            os._exit(130)
        said.append(True)
        click.echo(
            "\ninterrupting: stopping the chunks in progress (Ctrl-C again to stop at once)",
            err=True,
        )
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_interrupt)
    try:
        yield
    except KeyboardInterrupt:
        click.echo(INTERRUPTED, err=True)
        raise SystemExit(130) from None
    finally:
        signal.signal(signal.SIGINT, previous)
