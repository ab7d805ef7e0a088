"""``standgrid status``: epochs, missions and what is enriched, compared or stale."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import catalog_argument, emit, execution, json_option, options


def _human(s: dict[str, Any]) -> str:
    lines = [f"catalog {s['catalog']} ({s['scheme']}, {s['crs'].splitlines()[0][:60]})"]
    if not s["epochs"]:
        lines.append("no epochs: tile missions into it first")
    for epoch, e in s["epochs"].items():
        state = e["state"]
        if e["enrichment"]:
            state += f" ({e['enrichment'].get('trees', '?')} trees)"
        if e["invalidated"]:
            stale = e["invalidated"]
            state += f": {stale['reason']} at {stale['at']}; run `standgrid enrich`"
        lines.append(
            f"epoch {epoch}  {e['date'] or 'no date'}  {len(e['missions'])} missions, "
            f"{e['tiles']} tiles, {e['points']:,} points  {state}"
        )
        lines.extend(f"  mission {name}" for name in e["missions"])
    if s["comparisons"]:
        lines.append("comparisons:")
    for key, c in s["comparisons"].items():
        other = f" (to from {c['other_catalog']})" if c.get("other_catalog") else ""
        if c["state"] == "present":
            lines.append(f"  {key}  present{other}")
        elif c["state"] == "stale":
            lines.append(f"  {key}  stale{other}: {c['reason']}; run `standgrid compare` again")
        else:
            lines.append(f"  {key}  invalidated: {c['reason']}; run `standgrid compare` again")
    return "\n".join(lines)


@click.command(name="status")
@catalog_argument()
@options("lock_timeout")
@json_option
def status(catalog: Path, as_json: bool, **params: Any) -> None:
    """List a catalog's epochs and what is enriched, compared or stale.

    An epoch is enriched, stale (re-tiled after it was enriched: its rasters, tree list,
    stand metrics and comparisons were removed; the reason is shown) or not enriched. A
    comparison is present, invalidated (removed) or stale (made against another catalog
    whose epoch was re-tiled, re-enriched or removed since). Reads catalog.json (and that of
    each other catalog compared against) only.

    \b
    Example:
      standgrid status catalog
      standgrid status catalog --json | jq '.epochs[] | .state'
    """
    from standgrid.pipeline.status import catalog_status

    emit(catalog_status(catalog, execution=execution(params, True)), as_json, _human)
