"""``standgrid enrich``: terrain, trees and stand metrics for a catalog."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import click

from standgrid.cli.options import (
    TerminalProgress,
    cluster_options,
    emit,
    json_option,
    lock_timeout_option,
    memory_option,
    quiet_option,
)


def _human(r: dict[str, Any]) -> str:
    from standgrid.enrich.allometry import MIN_TREES

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
@click.argument("catalog", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--epoch", "epochs", multiple=True, help="Epoch(s) to enrich (default: all).")
@click.option(
    "--pixel", "pixel_size", type=float, default=1.0, show_default=True,
    help="DTM/CHM/density pixel size in metres (must divide the cell size).",
)  # fmt: skip
@click.option(
    "--halo", type=float, default=10.0, show_default=True,
    help="Metres of neighbouring tiles each stand is processed with (> a crown radius).",
)  # fmt: skip
@click.option(
    "--height-break", type=float, default=2.0, show_default=True,
    help="Height above ground (m) separating canopy from ground and understory in metrics.",
)  # fmt: skip
@click.option(
    "--rigidness", type=click.IntRange(1, 3), default=1, show_default=True,
    help="CSF cloth rigidness: 1 steep terrain, 2 relief, 3 flat.",
)  # fmt: skip
@click.option(
    "--min-observed", "min_observed_fraction", type=click.FloatRange(0.0, 1.0), default=0.25,
    show_default=True,
    help="Least share of a stand's area observed for its metrics to be reported.",
)  # fmt: skip
@click.option(
    "--min-density", "min_density", type=click.FloatRange(0.0), default=2.0, show_default=True,
    help="Least points per m2 of observed ground for a stand's metrics to be reported.",
)  # fmt: skip
@cluster_options
@memory_option
@lock_timeout_option
@json_option
@quiet_option
def enrich(
    catalog: Path,
    epochs: tuple[str, ...],
    pixel_size: float,
    halo: float,
    height_break: float,
    rigidness: int,
    min_observed_fraction: float,
    min_density: float,
    workers: int | None,
    scheduler: str | None,
    memory_mb: int,
    lock_timeout: float,
    as_json: bool,
    quiet: bool,
) -> None:
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
    from standgrid.engine import MemoryBudget
    from standgrid.pipeline.enrich import EnrichOptions, enrich_catalog

    options = EnrichOptions(
        pixel_size=pixel_size,
        halo=halo,
        height_break=height_break,
        rigidness=rigidness,
        min_observed_fraction=min_observed_fraction,
        min_density_pts_m2=min_density,
        epochs=epochs,
        memory_budget=MemoryBudget.megabytes(memory_mb),
    )
    with interruptible():
        report = enrich_catalog(
            catalog,
            options,
            progress=TerminalProgress(quiet),
            workers=workers,
            scheduler=scheduler,
            lock_timeout=lock_timeout,
        )
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
