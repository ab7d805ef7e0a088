"""``standgrid retrieve``: find a mission's payloads by type, map pose or GNSS coordinate."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import emit, json_option

#: Let coordinates such as ``-1.338`` through as arguments instead of unknown options.
_NEGATIVE_NUMBERS = {"ignore_unknown_options": True}
_MISSION = click.argument("mission", type=click.Path(exists=True, file_okay=False, path_type=Path))


def _human(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "no payloads"
    lines = []
    for r in rows:
        extra = f"  {r['distance_m']:.2f} m" if "distance_m" in r else ""
        node = "-" if r["node_id"] is None else r["node_id"]
        sensor = f" [{r['sensor']}]" if "sensor" in r else ""
        lines.append(f"{r['kind']:11} {r['stamp']}  node {node}{sensor}{extra}  {r['path']}")
    return "\n".join(lines)


@click.group(name="retrieve")
def retrieve() -> None:
    """Find a mission's payloads by data type, by map-frame pose or by GNSS coordinate.

    \b
    Example:
      standgrid retrieve by-type MISSION point_cloud
      standgrid retrieve by-pose MISSION 12.5 -3.0 0.5 -k 2
      standgrid retrieve by-gnss MISSION 51.776 -1.338
    """


@retrieve.command(name="by-type")
@_MISSION
@click.argument("data_type", metavar="TYPE")
@json_option
def by_type(mission: Path, data_type: str, as_json: bool) -> None:
    """Every payload of one TYPE: point_cloud, scan, gnss, imu, image (or camera).

    \b
    Example:
      standgrid retrieve by-type MISSION image --json
    """
    from standgrid.mission.retrieval import payload_records, retrieve_payload_by_type

    emit(payload_records(retrieve_payload_by_type(mission, data_type)), as_json, _human)


@retrieve.command(name="by-pose", context_settings=_NEGATIVE_NUMBERS)
@_MISSION
@click.argument("x", type=float)
@click.argument("y", type=float)
@click.argument("z", type=float, required=False, default=None)
@click.option("-k", "k", type=int, default=1, show_default=True, help="Number of nearest payloads.")
@click.option("--radius", type=float, help="Every payload whose node is within this many metres.")
@click.option("--covering", is_flag=True, help="Every payload whose footprint covers the point.")
@json_option
def by_pose(
    mission: Path,
    x: float,
    y: float,
    z: float | None,
    k: int,
    radius: float | None,
    covering: bool,
    as_json: bool,
) -> None:
    """Payloads nearest a map-frame point X Y [Z], nearest first.

    Without Z the query is horizontal: nodes are ranked, and --radius and distance_m
    measured, by x/y distance alone.

    \b
    Example:
      standgrid retrieve by-pose MISSION 12.5 -3.0 0.5 --radius 30
      standgrid retrieve by-pose MISSION 12.5 -3.0 --covering --json
    """
    from standgrid.mission.model import open_mission
    from standgrid.mission.retrieval import payload_records, retrieve_payload_by_pose

    opened = open_mission(mission, strict=False)
    query = (x, y) if z is None else (x, y, z)
    found = retrieve_payload_by_pose(opened, query, k=k, radius=radius, covering=covering)
    emit(payload_records(found, query, opened), as_json, _human)


@retrieve.command(name="by-gnss", context_settings=_NEGATIVE_NUMBERS)
@_MISSION
@click.argument("lat", type=float)
@click.argument("lon", type=float)
@click.argument("alt", type=float, required=False)
@click.option("-k", "k", type=int, default=1, show_default=True, help="Number of nearest payloads.")
@click.option(
    "--max-distance", type=click.FloatRange(0, min_open=True), default=1000.0,
    show_default=True, metavar="METRES",
    help="Refuse when the nearest payload is farther (LAT and LON swapped, another place).",
)  # fmt: skip
@json_option
def by_gnss(
    mission: Path,
    lat: float,
    lon: float,
    alt: float | None,
    k: int,
    max_distance: float,
    as_json: bool,
) -> None:
    """Payloads nearest a WGS84 coordinate LAT LON [ALT] (needs a georeference), nearest
    first, with their distance (m) to it.

    \b
    Example:
      standgrid retrieve by-gnss MISSION 51.776 -1.338 --json
    """
    from standgrid.georeference.retrieval import locate_by_gnss
    from standgrid.mission.model import open_mission
    from standgrid.mission.retrieval import payload_records

    opened = open_mission(mission, strict=False)
    coord = (lat, lon) if alt is None else (lat, lon, alt)
    found = locate_by_gnss(opened, coord, k=k, max_distance=max_distance)
    emit(payload_records(found.payloads, found.query_map, opened), as_json, _human)
