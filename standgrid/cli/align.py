"""``standgrid align``: re-align a catalog's missions to each other and re-tile them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import (
    CLUSTER,
    catalog_argument,
    emit,
    execution,
    json_option,
    options,
    quiet_option,
)


def _human(report: dict[str, Any]) -> str:
    from standgrid.cli.tile import alignment_lines

    lines = [
        f"catalog  {report['catalog']}: {len(report['missions'])} missions re-tiled, "
        f"{report['points_out']:,} points"
    ]
    lines += alignment_lines(report.get("alignment")) or ["nothing to align (one mission)"]
    return "\n".join(lines)


@click.command("align")
@catalog_argument()
@options(*CLUSTER)
@json_option
@quiet_option
def align(catalog: Path, as_json: bool, quiet: bool, **params: Any) -> None:
    """Register CATALOG's missions to each other on their stems and ground, place them by
    one graph with their GNSS, and re-tile them (each in its own epoch).

    Prints every registration (accepted, or refused with its reason) and each mission's
    placement 1-sigma, absolute and relative. Every mission is read again from the folder
    it was tiled from. The enrichment and comparisons of re-tiled epochs are removed
    (`standgrid status` says so): run `standgrid enrich` again.

    \b
    Example:
      standgrid align catalog
    """
    from standgrid.pipeline.tile import realign_catalog
    from standgrid.tiling.options import TileOptions

    report = realign_catalog(catalog, TileOptions(), execution=execution(params, quiet))
    emit(report.to_dict(), as_json, _human)
