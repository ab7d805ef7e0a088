"""``standgrid tile``: georeference missions and tile them into a catalog."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import (
    TerminalProgress,
    cluster_options,
    emit,
    json_option,
    lock_timeout_option,
    memory_option,
    mission_argument,
    no_align_option,
    output_option,
    overwrite_option,
    quiet_option,
    replace_option,
    scan_options,
)


def _levels(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[float, ...]:
    if not value:
        return ()
    try:
        return tuple(float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"cell sizes in metres, comma separated: {value!r}") from None


def _epoch(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    import re

    if value is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", value):
        raise click.BadParameter(f"letters, digits, '.', '_' and '-' only: {value!r}")
    return value


def _human(report: dict[str, Any]) -> str:
    lines = [
        f"catalog  {report['catalog']}  ({report['scheme']}, {report['crs']})",
        f"points   {report['points_in']:,} in, {report['points_out']:,} out"
        f" ({'conserved' if report['conserved'] else 'NOT CONSERVED'})",
    ]
    if report["withheld_left_out"]:
        lines.append(
            f"         {report['withheld_left_out']:,} points the source files flag withheld "
            "(deleted) left out, not counted in"
        )
    for epoch, e in report["epochs"].items():
        lines.append(
            f"epoch {epoch} ({e['date'] or 'no date'}): {e['cells']} tiles,"
            f" {e['points_out']:,} points, {e['buffer_points']:,} buffer copies,"
            f" {e['cells_removed']} tiles removed"
        )
    for name, m in report["missions"].items():
        g = m["georeference"]
        rmse = g["rmse_horizontal_m"]
        u = g.get("uncertainty") or {}
        for warning in [*m.get("warnings", []), *u.get("warnings", [])]:
            lines.append(f"  WARNING {name}: {warning}")
        lines.append(
            f"  {name}: #{m['number']}, {m['payloads']} payloads, {m['points']:,} points,"
            f" {m['tiles']} tiles; georef {g['method']} with {g['fixes_used']} fixes"
            f" ({g['fixes_rejected']} rejected), RMSE {rmse:.3f} m"
            if rmse is not None
            else f"  {name}: #{m['number']}, {m['payloads']} payloads, {m['points']:,} points"
        )
    lines += alignment_lines(report.get("alignment"))
    from standgrid.catalog import paths

    lines.append(f"open {Path(report['catalog']) / paths.INDEX} in QGIS")
    return "\n".join(lines)


def alignment_lines(alignment: dict[str, Any] | None) -> list[str]:
    """What alignment did, for people: each registration, each mission's 1-sigma."""
    if not alignment:
        return []
    lines = ["alignment (1-sigma DRMS: absolute / relative to the missions it shares stems with)"]
    for r in alignment["registrations"]:
        if r["accepted"]:
            lines.append(
                f"  {r['moving']} onto {r['fixed']}: {r['stems_matched']} stems, moved "
                f"{r['t_m'][0]:+.3f} {r['t_m'][1]:+.3f} m, {r['yaw_deg']:+.3f} deg, "
                f"dz {r['dz_m']:+.3f} m; residual {r['rms_m']:.3f} m; GICP {r['gicp']}"
            )
        else:
            lines.append(f"  {r['moving']} onto {r['fixed']}: not registered: {r['reason']}")
    for name, m in alignment["missions"].items():
        if m.get("held"):
            continue
        rel = m["sigma_rel_m"]
        lines.append(
            f"  {name}: {'aligned' if m['aligned'] else 'GNSS only'}, moved {m['moved_m']:.3f} m;"
            f" 1-sigma {m['sigma_h_m']:.3f} m"
            + (f" / {rel:.3f} m" if rel is not None else "")
            + (
                f" (GNSS alone {m['sigma_prior_m']:.3f} m)"
                if m["sigma_prior_m"] is not None
                else " (no GNSS: placed by registration alone)"
            )
        )
    lines += [f"  WARNING {w}" for w in alignment["warnings"]]
    return lines


@click.command("tile")
@mission_argument(nargs=-1, scans=True)
@output_option(help="Catalog folder (created, or added to when it is a catalog).")
@click.option(
    "--grid", "cell_size", type=float, default=None,
    help="Stand-grid cell size in metres (default 20; an existing catalog keeps its own).",
)  # fmt: skip
@click.option(
    "--levels", default=None, callback=_levels,
    help="Nested cell sizes, finest first, comma separated (default: SIZE,5*SIZE).",
)  # fmt: skip
@click.option("--voronoi", is_flag=True, help="Voronoi cells around payload poses, not a grid.")
@click.option(
    "--crs", "crs_spec", default="auto", show_default=True,
    help="Output CRS: EPSG:XXXX, WKT2, or auto (a new catalog: the missions' UTM zone, or"
    " clouds already projected their own CRS; an existing catalog: its CRS, refused for a"
    " mission outside its area of use). Also the CRS of PCD/PLY clouds in"
    " payload_clouds_in_utm/, which name none.",
)  # fmt: skip
@click.option(
    "--anchor", type=float, nargs=4, default=None, metavar="LAT LON ALT YAW",
    help="Place a mission without GNSS: map origin at WGS 84 LAT LON (deg) and ellipsoidal"
    " ALT (m), map x axis YAW deg counter-clockwise from East (90 - compass heading).",
)  # fmt: skip
@click.option(
    "--buffer", type=float, default=None,
    help="Copy neighbours' points within this many metres into each tile, flagged withheld"
    " (default 0; an existing catalog keeps its own).",
)  # fmt: skip
@click.option(
    "--las/--laz", "las", default=None,
    help="Uncompressed LAS or LAZ tiles (default LAZ; an existing catalog keeps its own).",
)  # fmt: skip
@click.option(
    "--copc/--no-copc", "copc", default=None,
    help="COPC tiles (*.copc.laz: LAZ that QGIS 3.26+, PDAL and web viewers stream by range"
    " requests; 2-5x slower to write). Default: not COPC; an existing catalog keeps its own.",
)  # fmt: skip
@click.option(
    "--method", type=click.Choice(["yaw2d", "rigid3d"]), default="yaw2d", show_default=True,
    help="Georeference fit: rotation about z only, or full 3-D.",
)  # fmt: skip
@click.option(
    "--epoch", default=None, callback=_epoch,
    help="Epoch label (default: the year of each mission). Missions without a date (no"
    " metadata.yaml, no dated folder name) make an epoch without a date: a year as the label"
    " stands in for it where a year is needed (FVS Inv_Year); comparing needs dates.",
)  # fmt: skip
@scan_options
@replace_option
@memory_option
@no_align_option
@click.option(
    "--accept-poor-georeference", is_flag=True,
    help="Tile even when a GNSS fit's RMSE is far beyond the fixes' stated accuracy.",
)  # fmt: skip
@cluster_options
@overwrite_option
@lock_timeout_option
@json_option
@quiet_option
def tile(
    missions: tuple[Path, ...],
    output: Path,
    cell_size: float | None,
    levels: tuple[float, ...],
    voronoi: bool,
    crs_spec: str,
    buffer: float | None,
    las: bool | None,
    copc: bool | None,
    method: str,
    anchor: tuple[float, float, float, float] | None,
    epoch: str | None,
    scan_date: Any,
    trajectory: Path | None,
    replace_missions: bool,
    no_align: bool,
    memory_mb: int,
    accept_poor_georeference: bool,
    workers: int | None,
    scheduler: str | None,
    overwrite: bool,
    lock_timeout: float,
    as_json: bool,
    quiet: bool,
) -> None:
    """Georeference MISSIONs (or plain scans) and tile them into the catalog -o CATALOG.

    A MISSION is a mission folder, or a plain scan: a georeferenced LAS/LAZ/COPC file, a
    folder of such tiles (one mission) or a VPC, tiled in its own CRS (--crs where the files
    name none), dated by its header (or --date), named after the file or folder.

    Every point lands in exactly one stand cell (checked); tiles are LAS 1.4 / LAZ named by
    cell id under tiles/<epoch>/, indexed in index.gpkg (cells, payloads, trajectories, GNSS
    fixes, missions, with QGIS styles) and tiles_<epoch>.vpc. Adding missions to an existing
    catalog merges them into its epochs; re-ingesting a mission (from the folder it was tiled
    from) replaces its points; a mission of the same name from another folder is refused
    unless --replace.

    How a mission is placed: clouds already in a projected CRS (payload_clouds_in_utm/
    alone, or LAS/LAZ payloads with a CRS) are tiled as they are, without a GNSS fit (PCD/PLY
    need --crs); --anchor places a mission by hand; otherwise the pose graph's GNSS anchor
    or a fit of the GNSS fixes.

    \b
    Example:
      standgrid tile data/missions/* -o catalog
      standgrid tile SCAN.laz -o catalog
      standgrid tile TILES_FOLDER -o catalog --trajectory traj.txt --voronoi
      standgrid tile M1 M2 -o catalog --grid 100 --crs EPSG:25832 --buffer 5 --las
      standgrid tile data/missions/* -o catalog --copc
      standgrid tile NO_GNSS -o catalog --anchor 51.7733 -1.3372 147.6 78.1
      standgrid tile UTM_PCD_MISSION -o catalog --crs EPSG:32630
    """
    from standgrid.engine import MemoryBudget
    from standgrid.pipeline.tile import TileOptions, tile_missions

    options = TileOptions(
        scheme="voronoi" if voronoi else ("grid" if cell_size is not None else None),
        cell_size=cell_size,
        levels=levels,
        crs=crs_spec,
        buffer=buffer,
        laz=None if las is None else not las,
        copc=copc,
        method=method,
        anchor=anchor,
        epoch=epoch,
        memory_budget=MemoryBudget.megabytes(memory_mb),
        overwrite=overwrite,
        lock_timeout=lock_timeout,
        accept_poor_georeference=accept_poor_georeference,
        workers=workers,
        scheduler=scheduler,
        replace_missions=replace_missions,
        align=not no_align,
        scan_date=scan_date,
        trajectory=trajectory,
    )
    report = tile_missions(list(missions), output, options, progress=TerminalProgress(quiet))
    emit(report.to_dict(), as_json, _human)
