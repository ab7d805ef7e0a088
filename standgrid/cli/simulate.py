"""``standgrid simulate``: write a simulated mission pair (or one epoch) with ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import emit, json_option, overwrite_option, quiet_option, status


def _human(results: list[dict[str, Any]]) -> str:
    lines = []
    for r in results:
        lines.append(
            f"{r['name']}: {r['payloads']} payloads, {r['points']} points, {r['nodes']} nodes, "
            f"{r['loop_closures']} loop closures, {r['gnss_fixes']} GNSS fixes, "
            f"{r['trees_standing']} trees\n  mission: {r['mission']}\n  truth:   {r['truth']}"
        )
    return "\n".join(lines)


@click.command("simulate")
@click.argument("out_root", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--seed", type=int, default=0, show_default=True, help="Random seed (same seed, same bytes)."
)
@click.option(
    "--epochs",
    type=click.IntRange(1, 2),
    default=2,
    show_default=True,
    help="1: the 2024 mission only; 2: both campaigns (2024 and 2028).",
)
@click.option(
    "--area",
    type=click.FloatRange(min=40.0),
    default=120.0,
    show_default=True,
    help="Side of the square stand, metres.",
)
@click.option(
    "--points-per-payload",
    type=click.IntRange(min=100),
    default=30_000,
    show_default=True,
    help="Points per ~20 m payload (density knob).",
)
@click.option(
    "--write-georef", is_flag=True, help="Also write the true GNSS_LLA_REF / GNSS_LLA_TO_MAP."
)
@click.option(
    "--forest",
    type=click.Choice(["plantation", "mixed"]),
    default="plantation",
    show_default=True,
    help="plantation: evenly spaced vertical trees; mixed: overstorey, understorey, "
    "snags, leaning and forked stems, shrubs (scan it with a ray-casting "
    "--scanner).",
)
@click.option(
    "--scanner",
    type=click.Choice(["surface", "handheld", "legged", "airborne"]),
    default="surface",
    show_default=True,
    help="surface: points on the true surfaces (no occlusion); handheld, legged, "
    "airborne: ray casting with occlusion and porous crowns.",
)
@click.option(
    "--lane-spacing",
    type=click.FloatRange(min=2.0),
    default=32.0,
    show_default=True,
    help="Largest spacing of the robot's serpentine lanes, metres.",
)
@click.option(
    "--gnss",
    "gnss",
    type=click.Choice(["demo", "canopy"]),
    default="demo",
    show_default=True,
    help="demo: canopy noise with RTK windows, honest stated accuracies; canopy: "
    "as under a forest canopy (a 1 m bias per recording, a 2 m Gauss-Markov "
    "walk over 120 s, 0.3 m noise, RTK float or single fixes stating 0.5 m).",
)
@click.option(
    "--second-robot",
    is_flag=True,
    help="Also a second robot's mission over the same stand on the first campaign's day.",
)
@click.option(
    "--elevation-maps",
    is_flag=True,
    help="Also an elevation map per payload (payloads/elevation/): the terrain "
    "truth plus a known error (5 cm bias, 3 cm noise; stated in truth.json).",
)
@overwrite_option
@json_option
@quiet_option
def simulate(
    out_root: Path,
    seed: int,
    epochs: int,
    area: float,
    points_per_payload: int,
    write_georef: bool,
    forest: str,
    scanner: str,
    lane_spacing: float,
    gnss: str,
    second_robot: bool,
    elevation_maps: bool,
    overwrite: bool,
    as_json: bool,
    quiet: bool,
) -> None:
    """Simulate forest missions at Wytham Woods (EPSG:32630) with known ground truth.

    Missions go to OUT_ROOT/missions/<name>/ in the canonical layout; the truth (trees,
    terrain, true poses, map frame, GNSS truth) to OUT_ROOT/truth/<name>/.

    \b
    Example:
      standgrid simulate data --seed 7 --area 80 --points-per-payload 7000
      standgrid simulate /tmp/bench --epochs 1 --area 200 --points-per-payload 500000 --json
      standgrid simulate canopy --area 100 --forest mixed --scanner handheld --lane-spacing 15
      standgrid simulate robots --gnss canopy --second-robot --forest mixed --scanner legged
      standgrid simulate maps --epochs 1 --area 60 --elevation-maps
    """
    from standgrid.simulate.elevation import ElevationMapModel
    from standgrid.simulate.gnss import gnss_model
    from standgrid.simulate.mission import SimulationConfig, simulate_mission

    try:
        config = SimulationConfig(
            area=area,
            points_per_payload=points_per_payload,
            write_georef=write_georef,
            forest=forest,
            scanner_kind=scanner,
            lane_spacing=lane_spacing,
            gnss=gnss_model(gnss),
            elevation_maps=ElevationMapModel() if elevation_maps else None,
        )
    except ValueError as exc:
        raise click.UsageError(str(exc)) from exc
    results = []
    for epoch in [*range(1, epochs + 1), *([3] if second_robot else [])]:
        status(f"simulating epoch {epoch} (seed {seed}) ...", quiet or as_json)
        sim = simulate_mission(out_root, seed=seed, epoch=epoch, overwrite=overwrite, config=config)
        results.append(sim.summary())
    emit(results, as_json, _human)
