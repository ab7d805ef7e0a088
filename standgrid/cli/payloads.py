"""``standgrid payloads``: build payloads from per-node scans."""

from __future__ import annotations

from pathlib import Path

import click

from standgrid.cli.options import emit, json_option, overwrite_option, quiet_option, status


@click.group(name="payloads")
def payloads() -> None:
    """Work on a mission's payloads (accumulated point clouds attached to graph nodes).

    \b
    Example:
      standgrid payloads build MISSION -o MISSION_WITH_PAYLOADS --distance 20
    """


@payloads.command(name="build")
@click.argument("mission", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "-o", "--output", required=True, type=click.Path(path_type=Path), help="Output mission folder."
)
@click.option(
    "--distance", type=float, default=20.0, show_default=True, help="Metres travelled per payload."
)
@click.option(
    "--area", type=float, help="Instead: square tiles of this side (metres) in the map x/y."
)
@click.option(
    "--graph",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Pose the scans with this graph (.g2o/.slam) or pose table, matched by stamp.",
)
@overwrite_option
@quiet_option
@json_option
def build(
    mission: Path,
    output: Path,
    distance: float,
    area: float | None,
    graph: Path | None,
    overwrite: bool,
    quiet: bool,
    as_json: bool,
) -> None:
    """Accumulate MISSION's per-node scans into payloads; write a canonical mission.

    Each payload holds the scans of DISTANCE metres of travel (or of one AREA x AREA m
    tile), in the base frame of the node at its centre, stamped with that node's stamp.
    A folder whose scans cannot be posed (no graph at its root, no VIEWPOINTs telling the
    scans apart) is refused; the message names graph files seen elsewhere (e.g. graphs/),
    to pass with --graph.

    \b
    Example:
      standgrid payloads build 2023-05-01-14-01-05 -o 2023-05-01-forest-anymal --distance 20
      standgrid payloads build MISSION -o OUT --area 25 --overwrite --json
      standgrid payloads build slam_tutorial -o OUT --graph slam_tutorial/graphs/ground_truth.slam
    """
    from standgrid.mission.build import build_payloads
    from standgrid.mission.opening import open_mission

    how = f"{area} m tiles" if area is not None else f"every {distance} m"
    status(f"building payloads ({how}) from {mission} ...", quiet)
    out = build_payloads(
        mission, output, distance=distance, area=area, graph=graph, overwrite=overwrite
    )
    built = open_mission(out)
    points = built.summary()["points"]
    result = {
        "output": str(out),
        "payloads": len(built.payloads),
        "points": points,
        "stamps": [str(p.stamp) for p in built.payloads],
    }
    emit(
        result,
        as_json,
        lambda r: f"{r['payloads']} payloads, {r['points']:,} points -> {r['output']}",
    )
