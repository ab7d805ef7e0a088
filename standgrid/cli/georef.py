"""``standgrid georef``: fit (or read) a mission's georeference and report it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import emit, json_option, mission_argument, quiet_option, status


@click.command("georef")
@mission_argument()
@click.option(
    "--method",
    type=click.Choice(["yaw2d", "rigid3d"]),
    default="yaw2d",
    show_default=True,
    help="yaw2d: rotation about z + 3-D offset; rigid3d: full 3-D rotation.",
)
@click.option(
    "--crs",
    "crs_spec",
    default="auto",
    show_default=True,
    help="Output CRS: EPSG:XXXX, WKT2 or auto (UTM zone).",
)
@click.option(
    "--min-fixes",
    default=10,
    show_default=True,
    type=click.IntRange(2),
    help="Fewest good fixes accepted.",
)
@click.option(
    "--refit",
    is_flag=True,
    help="Fit the GNSS fixes even when the pose graph carries a GNSS anchor.",
)
@json_option
@quiet_option
def georef(
    mission: Path,
    method: str,
    crs_spec: str,
    min_fixes: int,
    refit: bool,
    as_json: bool,
    quiet: bool,
) -> None:
    """Georeference MISSION: fit its SLAM map frame to its GNSS fixes and report the fit.

    Prints fixes used/rejected (by reason), horizontal/vertical RMSE, yaw, translation and
    their 1-sigma uncertainty (a warning when the GNSS baseline is too short to fix the
    heading), the ENU reference and the output CRS; --json adds per-fix residuals (ENU
    metres, fit minus fix). Heights are WGS 84 ellipsoidal.

    \b
    Example:
      standgrid georef data/missions/2024-05-14-wytham-anymal-coyote --crs auto
      standgrid georef MISSION --method rigid3d --crs EPSG:25830 --json
    """
    from standgrid.georeference import MapProjector, georeference_mission
    from standgrid.mission.opening import open_mission

    status(f"opening {mission}", quiet)
    opened = open_mission(mission)
    status("fitting georeference", quiet)
    fit = georeference_mission(
        opened, method=method, min_fixes=min_fixes, use_graph_anchor=not refit
    )
    projector = MapProjector(fit, crs_spec)
    origin = projector.exact([[0.0, 0.0, 0.0]])[0]
    report: dict[str, Any] = {
        "mission": str(mission),
        "method": fit.method,
        "crs": projector.crs.text,
        "crs_name": projector.crs.name,
        "vertical": "WGS 84 ellipsoidal height (m)",
        "lla_ref": list(fit.lla_ref),
        "yaw_deg": fit.yaw_deg,
        "translation_enu_m": fit.translation.tolist(),
        "map_origin_crs": origin.tolist(),
        "fixes_total": len(fit.fix_stamps_ns),
        "fixes_used": fit.n_used,
        "fixes_rejected": fit.n_rejected,
        "rejected_by_reason": fit.rejected_by_reason,
        "rmse_horizontal_m": fit.rmse_m,
        "rmse_vertical_m": fit.rmse_vertical_m,
        "T_enu_map": fit.T_enu_map.tolist(),
        "uncertainty": None if fit.uncertainty is None else fit.uncertainty.to_dict(),
        "warnings": [] if fit.uncertainty is None else list(fit.uncertainty.warnings),
    }
    from standgrid.alignment.graph import placement_sigma

    honest = placement_sigma(fit, opened.trajectory()[1]) if fit.uncertainty else None
    # the fit's covariance sees white noise; under a canopy errors are correlated and biased
    report["placement_sigma_h_m"] = None if honest is None else honest[0]
    report["placement_sigma_how"] = None if honest is None else honest[1]
    from standgrid.errors import MisplacedMissionError
    from standgrid.georeference.placement import check_metadata_location

    try:  # a report, not a tiling: a fit far from the metadata's location is a warning here
        check_metadata_location(opened, fit)
    except MisplacedMissionError as exc:
        report["warnings"].append(exc.message)
    for warning in report["warnings"]:
        status(f"warning: {warning}", quiet)
    if as_json:
        d = fit.to_dict()
        report["rmse_horizontal_m"] = d["rmse_m"]
        report["rmse_vertical_m"] = d["rmse_vertical_m"]
        report["fixes"] = [
            {"stamp_ns": s, "status": st, "inlier": inl, "weight": w, "residual_enu_m": r}
            for s, st, inl, w, r in zip(
                d["fixes"]["stamps_ns"],
                d["fixes"]["status"],
                d["fixes"]["inliers"],
                d["fixes"]["weights"],
                d["fixes"]["residuals_m"],
                strict=True,
            )
        ]
    emit(report, as_json, _human)


def _human(r: dict[str, Any]) -> str:
    lat, lon, alt = r["lla_ref"]
    reasons = ", ".join(f"{k} {v}" for k, v in r["rejected_by_reason"].items() if v) or "none"
    tx, ty, tz = r["translation_enu_m"]
    ox, oy, oz = r["map_origin_crs"]
    u = r.get("uncertainty")
    sigma = ["uncertainty  none (a given transform, not a fit)"]
    if u:
        se, sn, su = (_num(v) for v in u["sigma_translation_m"])
        sigma = [
            f"uncertainty  1-sigma yaw {_num(u['sigma_yaw_deg'], 4)} deg, "
            f"translation E {se}  N {sn}  U {su} m ({u['method']})",
            f"             up to {_num(u['sigma_horizontal_max_m'])} m horizontally along the "
            f"fixes; GNSS baseline {_num(u['baseline_m'], 1)} m",
        ]
    if r.get("placement_sigma_h_m") is not None:
        sigma.append(
            f"placement    1-sigma {r['placement_sigma_h_m']:.3f} m horizontally (DRMS, the "
            f"largest along the trajectory; {r['placement_sigma_how']})"
        )
    sigma += [f"WARNING      {w}" for w in r.get("warnings", [])]
    return "\n".join(
        [
            f"mission      {r['mission']}",
            f"method       {r['method']}",
            f"fixes        {r['fixes_used']} used / {r['fixes_total']} "
            f"({r['fixes_rejected']} rejected: {reasons})",
            f"rmse         horizontal {r['rmse_horizontal_m']:.3f} m, "
            f"vertical {r['rmse_vertical_m']:.3f} m",
            f"yaw          {r['yaw_deg']:.4f} deg (map x axis, counter-clockwise from East)",
            f"translation  E {tx:.3f}  N {ty:.3f}  U {tz:.3f} m (map origin in ENU)",
            *sigma,
            f"ENU origin   lat {lat:.9f}  lon {lon:.9f}  h {alt:.3f} m",
            f"output CRS   {r['crs_name']} ({r['crs'] if len(r['crs']) < 40 else 'WKT2'})",
            f"map origin   x {ox:.3f}  y {oy:.3f}  h {oz:.3f} m ({r['vertical']})",
        ]
    )


def _num(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"
