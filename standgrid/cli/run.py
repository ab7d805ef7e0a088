"""``standgrid run``: missions -> catalog -> enriched -> compared, in one command."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import (
    CLUSTER,
    COMPARE,
    ENRICH,
    TILE,
    Location,
    build,
    emit,
    execution,
    json_option,
    options,
    output_option,
    quiet_option,
)

#: enrichment's --epoch (which epochs to enrich) is tiling's there: run enriches all it tiled
RUN_OPTIONS = (*TILE, "overwrite", *(n for n in ENRICH if n != "epochs"), *COMPARE, *CLUSTER)

QGIS_GUIDE = """\
Open it in QGIS:
  0. Project > Open..., pick {project}: all of the below, grouped per epoch and change,
     styled, with legends in m and m²/ha (QGIS 3.22+). Or add layers one by one:
  1. Layer > Add Layer > Add Vector Layer..., pick {gpkg}, select all layers:
     cells (stand grid), stand_metrics (canopy height zq95), trees (crowns by height),
     stand_changes (growth per year, red-blue ramp), tree_changes (grown/new/removed),
     payloads, trajectories, gnss_fixes. Each layer opens with its own default style.
  2. Point clouds: drag {vpcs} into QGIS (3.32+), one layer per epoch.
  3. Rasters: drag {rasters} (DTM, CHM, density, observed ground) and {chm_diff}
     (CHM change); each opens with its own style (the .qml beside it)."""


def _human(r: dict[str, Any]) -> str:
    from standgrid.catalog import paths
    from standgrid.cli.compare import _human as compare_human
    from standgrid.cli.enrich import _human as enrich_human
    from standgrid.cli.tile import _human as tile_human

    catalog = Path(r["tile"]["catalog"])
    parts = [tile_human(r["tile"]), enrich_human(r["enrich"])]
    if r["compare"] is not None:
        parts.append(compare_human(r["compare"]))
    epochs = sorted(r["enrich"]["epochs"])
    chm_diff = (
        catalog / r["compare"]["outputs"]["chm_difference"] if r["compare"] else "(one epoch)"
    )
    parts.append(
        QGIS_GUIDE.format(
            project=catalog / paths.QGIS_PROJECT,
            gpkg=catalog / paths.INDEX,
            vpcs=", ".join(str(catalog / paths.vpc(e)) for e in epochs),
            rasters=catalog / paths.raster("<epoch>", "*"),
            chm_diff=chm_diff,
        )
    )
    return "\n\n".join(parts)


@click.command("run")
@click.argument(
    "paths",
    nargs=-1,
    required=True,
    type=Location(click.Path(exists=True, path_type=Path)),
)
@output_option(help="Catalog folder.")
@options(*RUN_OPTIONS)
@json_option
@quiet_option
def run(paths: tuple[Path, ...], output: Path, as_json: bool, quiet: bool, **params: Any) -> None:
    """Run the whole path: tile PATHS (missions, folders of missions, or plain scans: LAS/LAZ/
    COPC files, folders of tiles, VPCs) into -o CATALOG,
    enrich every epoch, compare the first epoch with the last, and say what to open in QGIS.

    \b
    Example:
      standgrid run data/missions -o standgrid-demo --overwrite
      standgrid run survey-2024/ survey-2028/ -o catalog --grid 100 --crs EPSG:25832
    """
    from standgrid.comparison.options import CompareOptions
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.run import run_pipeline
    from standgrid.tiling.options import TileOptions

    report = run_pipeline(
        list(paths),
        output,
        build(TileOptions, params),
        build(EnrichOptions, params),
        build(CompareOptions, params),
        execution=execution(params, quiet),
    )
    emit(report.to_dict(), as_json, _human)
