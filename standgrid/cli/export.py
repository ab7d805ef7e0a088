"""``standgrid export``: a catalog's stands and trees for growth simulators."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import emit, json_option, overwrite_option, quiet_option, status

catalog_argument = click.argument(
    "catalog", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
epoch_option = click.option(
    "--epoch", "epochs", multiple=True, help="Only this epoch (repeatable; default: all enriched)."
)
level_option = click.option(
    "--level",
    type=click.IntRange(0, 1),
    default=1,
    show_default=True,
    help="Stand level: 1 = the 1 ha stands, 0 = the tile cells.",
)


@click.group(name="export")
def export() -> None:
    """Export an enriched catalog's stands and trees for growth simulators.

    \b
    Example:
      standgrid export fvs CATALOG -o stands.db --species DF --keywords stands.key
      standgrid export trees CATALOG -o trees.gpkg
    """


def _species_table(path: Path | None) -> dict[str, str]:
    """``stand_id,species`` CSV (a header row naming those two columns)."""
    if path is None:
        return {}
    import pandas as pd

    table = pd.read_csv(path, dtype=str)
    missing = {"stand_id", "species"} - set(table.columns)
    if missing:
        raise click.BadParameter(f"{path}: needs the columns stand_id, species")
    return dict(zip(table["stand_id"], table["species"], strict=True))


@export.command(name="fvs")
@catalog_argument
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="SQLite database to write (FVS_StandInit, FVS_TreeInit).",
)
@click.option("--variant", default="PN", show_default=True, help="FVS variant code.")
@click.option("--species", help="FVS species code of every tree (default DF, a placeholder).")
@click.option(
    "--species-table",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="CSV stand_id,species: a code per stand (others get --species).",
)
@click.option(
    "--no-increments",
    is_flag=True,
    help="Leave DG/HTG empty even when an earlier campaign was compared.",
)
@click.option(
    "--keywords",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Also write an FVS keyword file running every exported stand.",
)
@click.option(
    "--heights-above-sea-level",
    is_flag=True,
    help="Already-projected clouds carry heights above sea level: ElevFt is their "
    "DTM height (else NULL: their vertical datum is unknown).",
)
@level_option
@epoch_option
@overwrite_option
@quiet_option
@json_option
def fvs(
    catalog: Path,
    output: Path,
    variant: str,
    species: str | None,
    species_table: Path | None,
    no_increments: bool,
    keywords: Path | None,
    heights_above_sea_level: bool,
    level: int,
    epochs: tuple[str, ...],
    overwrite: bool,
    quiet: bool,
    as_json: bool,
) -> None:
    """Write FVS database input tables for CATALOG's stands (docs/FVS.md).

    One FVS stand per stand and epoch, one fixed plot of the stand's observed area, one
    record per tree with a DBH (trees without one are counted, not exported), in FVS units
    (inches, feet, acres). LiDAR does not tell species: give --species or --species-table.
    ElevFt is height above sea level: for missions placed by GNSS or an anchor, their WGS 84
    ellipsoidal heights minus the geoid (EGM2008 or EGM96 grid from PROJ's data folders,
    /usr/share/proj or $STANDGRID_GEOID_PATH); for clouds already projected, their heights
    with --heights-above-sea-level. Else NULL, with a warning saying why (per epoch).

    \b
    Example:
      standgrid export fvs catalog -o stands.db --species DF --keywords stands.key
      standgrid export fvs catalog -o cells.db --level 0 --epoch 2028 --overwrite --json
    """
    import sqlite3

    from standgrid._atomic import write_text_atomic
    from standgrid.growth.fvs import export_fvs, keyword_file

    if keywords is not None and keywords.exists() and not overwrite:  # before writing anything
        raise click.ClickException(f"{keywords} exists (--overwrite replaces it)")
    status(f"exporting FVS stands from {catalog} ...", quiet or as_json)
    report = export_fvs(
        catalog,
        output,
        level=level,
        epochs=epochs or None,
        variant=variant,
        species=species,
        species_by_stand=_species_table(species_table),
        increments=not no_increments,
        overwrite=overwrite,
        heights_above_sea_level=heights_above_sea_level,
    )
    result: dict[str, Any] = report.to_dict()
    if keywords is not None:
        conn = sqlite3.connect(output)
        try:
            ids = [r[0] for r in conn.execute("SELECT Stand_ID FROM FVS_StandInit")]
        finally:
            conn.close()
        write_text_atomic(keywords, keyword_file(output.resolve(), ids))
        result["keywords"] = str(keywords)
    if report.species_default_used:
        status("warning: species not given; every tree is DF (Douglas-fir), a placeholder", quiet)
    for epoch, reason in report.elev_ft_null_reason.items():
        status(f"warning: epoch {epoch}: {reason}", quiet)
    if report.elev_ft_null_stands:
        status(
            f"warning: ElevFt is NULL for {len(report.elev_ft_null_stands)} stand(s) "
            "(elev_ft_null_stands in --json says why)",
            quiet,
        )
    for note in report.notes:
        status(f"note: {note}", quiet)
    emit(result, as_json, _fvs_human)


def _fvs_human(r: dict[str, Any]) -> str:
    return (
        f"{r['stands']} stands, {r['trees']} trees ({r['trees_with_dg_htg']} with DG/HTG), "
        f"{r['trees_without_dbh_skipped']} trees without a DBH left out -> {r['output']}"
        + "".join(f"\nElevFt of epoch {e}: {ref}" for e, ref in r["elevation_reference"].items())
        + "".join(f"\nElevFt of epoch {e}: {why}" for e, why in r["elev_ft_null_reason"].items())
    )


@export.command(name="trees")
@catalog_argument
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Tree list: .csv, .parquet, .gpkg or .sqlite/.db (table trees).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["csv", "parquet", "gpkg", "sqlite"]),
    help="Format, when the suffix does not say.",
)
@level_option
@epoch_option
@overwrite_option
@quiet_option
@json_option
def trees(
    catalog: Path,
    output: Path,
    fmt: str | None,
    level: int,
    epochs: tuple[str, ...],
    overwrite: bool,
    quiet: bool,
    as_json: bool,
) -> None:
    """Write CATALOG's trees as one generic tree list (columns: docs/TREES.md).

    \b
    Example:
      standgrid export trees catalog -o trees.parquet
      standgrid export trees catalog -o trees.gpkg --epoch 2028 --overwrite
    """
    from standgrid.catalog import Catalog
    from standgrid.growth.treelist import generic_tree_list, summary, write_tree_list

    status(f"exporting trees from {catalog} ...", quiet or as_json)
    with Catalog.reading(catalog) as cat:  # one consistent state of every file read
        table = generic_tree_list(cat, epochs or None, level=level)
    out = write_tree_list(table, output, crs=cat.crs, fmt=fmt, overwrite=overwrite)
    result = {"output": str(out), "trees": len(table), "epochs": summary(table)}
    emit(result, as_json, lambda r: f"{r['trees']} trees -> {r['output']}")
