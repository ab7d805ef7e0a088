"""``standgrid missions``: list and search the missions under a folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import emit, json_option, status


def _human(data: dict[str, Any]) -> str:
    rows = data["missions"]
    if not rows:
        return "no matching missions"
    lines = [f"{'date':10}  {'site':20}  {'robot':12}  {'sensors':30}  folder"]
    for r in rows:
        lines.append(
            f"{r['date'] or '-':10}  {r['site'] or '-':20}  {r['robot'] or '-':12}  "
            f"{','.join(r['sensors']) or '-':30}  {r['where']}"
        )
    lines.append(f"{len(rows)} of {data['total']} missions")
    return "\n".join(lines)


@click.command(name="missions")
@click.argument("root", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--site", help="Site (place) name, case-insensitive.")
@click.option(
    "--from", "date_from", type=click.DateTime(["%Y-%m-%d"]), help="First date (inclusive)."
)
@click.option("--to", "date_to", type=click.DateTime(["%Y-%m-%d"]), help="Last date (inclusive).")
@click.option("--robot", help="Robot id, case-insensitive.")
@click.option(
    "--sensor", "sensors", multiple=True, help="A sensor the mission must have (repeatable)."
)
@click.option("--strict", is_flag=True, help="Fail on unreadable metadata instead of reporting it.")
@json_option
def missions(
    root: Path,
    site: str | None,
    date_from: Any,
    date_to: Any,
    robot: str | None,
    sensors: tuple[str, ...],
    strict: bool,
    as_json: bool,
) -> None:
    """List the missions under ROOT whose metadata match every given filter.

    Metadata come from each mission's metadata.yaml, else from a folder name
    YYYY-MM-DD-<place>-<robot>[-<unit>]. Unreadable metadata is reported on stderr.

    \b
    Example:
      standgrid missions data/missions --site wytham --from 2023-01-01 --sensor lidar
      standgrid missions data/missions --robot anymal --json
    """
    from standgrid.mission.collection import MissionCollection

    collection = MissionCollection(root, strict=strict)
    found = collection.search(
        site=site,
        date_from=date_from.date() if date_from else None,
        date_to=date_to.date() if date_to else None,
        robot=robot,
        sensors=sensors or None,
    )
    for problem in collection.problems:
        status(f"problem: {problem}")
    emit(
        {
            "total": len(collection),
            "missions": [
                r.to_dict() | {"where": str(r.path.relative_to(collection.root))} for r in found
            ],
            "problems": collection.problems,
        },
        as_json,
        _human,
    )
