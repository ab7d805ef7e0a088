"""``standgrid tile``: georeference missions and tile them into a catalog."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import (
    CLUSTER,
    TILE,
    build,
    emit,
    execution,
    json_option,
    mission_argument,
    options,
    output_option,
    quiet_option,
)


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
@mission_argument(nargs=-1, scans=True, urls=True)
@output_option(help="Catalog folder (created, or added to when it is a catalog).")
@options(*TILE, "overwrite", *CLUSTER)
@json_option
@quiet_option
def tile(
    missions: tuple[Path, ...], output: Path, as_json: bool, quiet: bool, **params: Any
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
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    report = tile_missions(
        list(missions), output, build(TileOptions, params), execution=execution(params, quiet)
    )
    emit(report.to_dict(), as_json, _human)
