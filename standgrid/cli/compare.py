"""``standgrid compare``: change between two enriched epochs of a catalog."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import (
    COMPARE,
    build,
    catalog_argument,
    emit,
    execution,
    json_option,
    options,
    quiet_option,
)


def _human(r: dict[str, Any]) -> str:
    trees = r["trees"]
    stands = r["stands"]
    lines = [
        f"{r['epoch_from']} -> {r['epoch_to']} ({r['years']:.2f} years) in {r['catalog']}",
        f"trees: {trees.get('grown', 0)} grown, {trees.get('new', 0)} new,"
        f" {trees.get('removed', 0)} removed (harvested or fallen),"
        f" {trees.get('missed', 0)} missed (a stem stands there in both surveys, one did not"
        " make it a tree),"
        f" {trees.get('unobserved', 0)} unobserved (outside the ground both epochs observed:"
        " neither harvest nor ingrowth)",
        f"stand cells: {stands['in_both']} in both epochs, {stands['from_only']} only in"
        f" {r['epoch_from']}, {stands['to_only']} only in {r['epoch_to']}",
    ]
    if r.get("stands_1ha"):
        s = r["stands_1ha"]
        lines.append(
            f"1 ha stands: {s['in_both']} in both epochs, {s['from_only']} only in"
            f" {r['epoch_from']}, {s['to_only']} only in {r['epoch_to']}"
        )
    for name, value in r["headline"].items():
        if value is not None and name != "trees_removed":
            lines.append(f"mean {name}: {value:+.3f}")
    lines.append("outputs: " + ", ".join(r["outputs"].values()))
    return "\n".join(lines)


@click.command("compare")
@catalog_argument()
@options(*COMPARE, "lock_timeout")
@json_option
@quiet_option
def compare(catalog: Path, as_json: bool, quiet: bool, **params: Any) -> None:
    """Compare two enriched epochs of CATALOG, stand by stand and tree by tree.

    Writes compare/<from>__<to>/ (stand_changes and tree_changes as CSV and Parquet,
    chm_diff.tif) and the stand_changes / tree_changes layers of index.gpkg, styled with a
    diverging colour ramp. Growth is annualised from the epochs' dates. Tree counts, basal
    area and harvest are compared over the ground both epochs observed; trees elsewhere are
    "unobserved", and stands with less than --min-observed of such ground get no change.

    \b
    Example:
      standgrid compare catalog --from 2024 --to 2028
      standgrid compare catalog-2024 --other catalog-2028 --json
    """
    from standgrid.comparison.options import CompareOptions
    from standgrid.pipeline.compare import compare_epochs

    compare_options, running = build(CompareOptions, params), execution(params, quiet)
    report = compare_epochs(catalog, compare_options, execution=running)
    emit(report.to_dict(), as_json, _human)
