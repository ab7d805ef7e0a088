"""``standgrid retrieve``: find a mission's payloads by type, map pose or GNSS coordinate."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from standgrid.cli.options import emit, json_option

if TYPE_CHECKING:
    from standgrid.mission.model import Mission
    from standgrid.mission.payload import Payload

F = TypeVar("F", bound=Callable[..., Any])

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
        if "enrichment" in r:
            lines.append(f"{'':11} {_layers_line(r['enrichment'])}")
    return "\n".join(lines)


def _layers_line(e: dict[str, Any]) -> str:
    parts = [f"epoch {e['epoch']}: {e['points_tiled']} of {e['points']} points"]
    if "ground_points" in e:
        parts.append(f"{e['ground_points']} ground")
    if "tree_points" in e:
        parts.append(f"{e['tree_points']} in trees")
    if "trees" in e:
        parts.append(f"{e['trees']} trees")
    if "terrain" in e:
        t = e["terrain"]
        parts.append(f"terrain {t['ncols']}x{t['nrows']} px of {t['pixel_size']:g} m")
    if "written" in e:
        parts.append(f"-> {e['written']}")
    return ", ".join(parts)


def _layer_names(ctx: click.Context, param: click.Parameter, value: str) -> tuple[str, ...]:
    from standgrid.enrichment.payload_layers import LAYERS, parse_layers
    from standgrid.errors import OptionError

    try:
        return parse_layers(value)
    except OptionError:
        raise click.BadParameter(
            f"{value!r}: layers are {', '.join(LAYERS)} (comma separated) or all"
        ) from None


def _layer_options(command: F) -> F:
    """``--layers CATALOG`` (each payload with its layers from the catalog), ``--which``,
    ``--out``, ``--frame``."""
    decorators = [
        click.option(
            "--layers",
            "catalog",
            metavar="CATALOG",
            type=click.Path(exists=True, file_okay=False, path_type=Path),
            help="Each payload with its layers from this catalog: per-point ground class, "
            "height above ground and tree id, its trees and its terrain.",
        ),
        click.option(
            "--which",
            default="all",
            show_default=True,
            metavar="LAYERS",
            callback=_layer_names,
            help="The layers, comma separated: ground, height, trees, terrain (or all).",
        ),
        click.option(
            "--out",
            type=click.Path(path_type=Path),
            metavar="PATH",
            help="With --layers: write each payload's points with its per-point layers as "
            "LAS/LAZ: a .laz/.las file for one payload, else a folder of <stamp>.laz.",
        ),
        click.option(
            "--frame",
            type=click.Choice(["crs", "payload"]),
            default="crs",
            show_default=True,
            help="Coordinates of --out: the catalog CRS (as the tiles store them) or the "
            "payload frame.",
        ),
    ]
    for decorate in reversed(decorators):
        command = decorate(command)
    return command


def _with_layers(
    rows: list[dict[str, Any]],
    mission: Mission,
    found: list[Payload],
    catalog: Path | None,
    which: tuple[str, ...],
    out: Path | None,
    frame: str,
) -> list[dict[str, Any]]:
    """``rows`` with each payload's layers (``enrichment``), its cloud written to ``out``."""
    if catalog is None:
        if out is not None:
            raise click.UsageError("--out writes the layered clouds: give --layers CATALOG")
        return rows
    from standgrid.enrichment.payload_layers import layers_of, write_layered_cloud

    layered = layers_of(catalog, mission, found, which)
    single = out is not None and len(layered) == 1 and out.suffix.lower() in (".las", ".laz")
    if out is not None and not single:
        out.mkdir(parents=True, exist_ok=True)
    for row, one in zip(rows, layered, strict=True):
        row["enrichment"] = one.to_dict()
        if out is not None:
            stamp = one.payload.stamp
            target = out if single else out / f"{stamp.sec}_{stamp.nsec:09d}.laz"
            row["enrichment"]["written"] = str(write_layered_cloud(one, target, frame=frame))
    return rows


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
@_layer_options
@json_option
def by_type(
    mission: Path,
    data_type: str,
    catalog: Path | None,
    which: tuple[str, ...],
    out: Path | None,
    frame: str,
    as_json: bool,
) -> None:
    """Every payload of one TYPE: point_cloud, scan, gnss, imu, image (or camera).

    \b
    Example:
      standgrid retrieve by-type MISSION image --json
      standgrid retrieve by-type MISSION point_cloud --layers CATALOG --out clouds/
    """
    from standgrid.mission.opening import open_mission
    from standgrid.mission.retrieval import payload_records, retrieve_payload_by_type

    opened = open_mission(mission, strict=False)
    found = retrieve_payload_by_type(opened, data_type)
    rows = _with_layers(payload_records(found), opened, found, catalog, which, out, frame)
    emit(rows, as_json, _human)


@retrieve.command(name="by-pose", context_settings=_NEGATIVE_NUMBERS)
@_MISSION
@click.argument("x", type=float)
@click.argument("y", type=float)
@click.argument("z", type=float, required=False, default=None)
@click.option("-k", "k", type=int, default=1, show_default=True, help="Number of nearest payloads.")
@click.option("--radius", type=float, help="Every payload whose node is within this many metres.")
@click.option("--covering", is_flag=True, help="Every payload whose footprint covers the point.")
@_layer_options
@json_option
def by_pose(
    mission: Path,
    x: float,
    y: float,
    z: float | None,
    k: int,
    radius: float | None,
    covering: bool,
    catalog: Path | None,
    which: tuple[str, ...],
    out: Path | None,
    frame: str,
    as_json: bool,
) -> None:
    """Payloads nearest a map-frame point X Y [Z], nearest first.

    Without Z the query is horizontal: nodes are ranked, and --radius and distance_m
    measured, by x/y distance alone.

    \b
    Example:
      standgrid retrieve by-pose MISSION 12.5 -3.0 0.5 --radius 30
      standgrid retrieve by-pose MISSION 12.5 -3.0 --covering --json
      standgrid retrieve by-pose MISSION 12.5 -3.0 --layers CATALOG --out payload.laz
    """
    from standgrid.mission.opening import open_mission
    from standgrid.mission.retrieval import payload_records, retrieve_payload_by_pose

    opened = open_mission(mission, strict=False)
    query = (x, y) if z is None else (x, y, z)
    found = retrieve_payload_by_pose(opened, query, k=k, radius=radius, covering=covering)
    rows = payload_records(found, query, opened)
    emit(_with_layers(rows, opened, found, catalog, which, out, frame), as_json, _human)


@retrieve.command(name="by-gnss", context_settings=_NEGATIVE_NUMBERS)
@_MISSION
@click.argument("lat", type=float)
@click.argument("lon", type=float)
@click.argument("alt", type=float, required=False)
@click.option("-k", "k", type=int, default=1, show_default=True, help="Number of nearest payloads.")
@click.option(
    "--max-distance",
    type=click.FloatRange(0, min_open=True),
    default=1000.0,
    show_default=True,
    metavar="METRES",
    help="Refuse when the nearest payload is farther (LAT and LON swapped, another place).",
)
@_layer_options
@json_option
def by_gnss(
    mission: Path,
    lat: float,
    lon: float,
    alt: float | None,
    k: int,
    max_distance: float,
    catalog: Path | None,
    which: tuple[str, ...],
    out: Path | None,
    frame: str,
    as_json: bool,
) -> None:
    """Payloads nearest a WGS84 coordinate LAT LON [ALT] (needs a georeference), nearest
    first, with their distance (m) to it.

    \b
    Example:
      standgrid retrieve by-gnss MISSION 51.776 -1.338 --json
      standgrid retrieve by-gnss MISSION 51.776 -1.338 --layers CATALOG --which ground
    """
    from standgrid.georeference.retrieval import locate_by_gnss
    from standgrid.mission.opening import open_mission
    from standgrid.mission.retrieval import payload_records

    opened = open_mission(mission, strict=False)
    coord = (lat, lon) if alt is None else (lat, lon, alt)
    found = locate_by_gnss(opened, coord, k=k, max_distance=max_distance)
    rows = payload_records(found.payloads, found.query_map, opened)
    emit(_with_layers(rows, opened, found.payloads, catalog, which, out, frame), as_json, _human)
