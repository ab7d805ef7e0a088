"""``standgrid info``: what a mission folder holds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from standgrid.cli.options import emit, json_option, say_flags


def _human(s: dict[str, Any]) -> str:
    lines = [f"mission   {s['name']}  ({s['path']})"]
    meta = s.get("metadata")
    if meta:
        shown = ", ".join(f"{k}={v}" for k, v in meta.items() if v not in (None, [], {}, ""))
        lines.append(f"metadata  {shown}")
    edges = ", ".join(f"{n} {k}" for k, n in s["edges"].items()) or "none"
    lines.append(f"graph     {s['graph'] or '-'}: {s['nodes']} nodes, edges: {edges}")
    folder = f" from {s['payload_folder']}/" if s["payload_folder"] else ""
    truncated = (
        f" ({s['payloads_truncated']} truncated, not counted)" if s["payloads_truncated"] else ""
    )
    lines.append(f"payloads  {s['payloads']}{folder}, {s['points']:,} points{truncated}")
    if s["scans"]:
        lines.append(f"scans     {s['scans']}, {s['scan_points']:,} points (per-node clouds)")
    folders = ", ".join(f"{name}/ ({n})" for name, n in s["cloud_folders"].items())
    lines.append(f"clouds    {folders or 'no cloud folder'}")
    lines.append(
        f"sensors   {s['gnss_fixes']} GNSS fixes, {s['imu_samples']} IMU samples, "
        f"{s['images']} images ({', '.join(s['cameras']) or 'no cameras'})"
    )
    span = s["time_span"]
    if span:
        lines.append(f"time      {span['start']} .. {span['end']} ({span['seconds']:.1f} s)")
    ext = s["extent_map"]
    if ext:
        lo = ", ".join(f"{v:.2f}" for v in ext["min"])
        hi = ", ".join(f"{v:.2f}" for v in ext["max"])
        lines.append(f"extent    map frame min ({lo}) max ({hi})")
    for problem in s["problems"]:
        lines.append(f"problem   {problem}")
    return "\n".join(lines)


def _scan_human(s: dict[str, Any]) -> str:
    lines = [f"scan      {s['name']}  ({s['path']}): {len(s['files'])} file(s)"]
    lines.append(f"points    {s['points']:,}")
    lines.append(f"crs       {s['crs'] or '-'}")
    date = s["date"]
    lines.append(f"date      {date['date']} (from the {date['from']})" if date else "date      -")
    lines.append(f"gps time  {s['gps_time']}")
    lo = ", ".join(f"{v:.2f}" for v in s["extent_crs"]["min"])
    hi = ", ".join(f"{v:.2f}" for v in s["extent_crs"]["max"])
    lines.append(f"extent    min ({lo}) max ({hi})")
    lines += [f"to tile   {need}" for need in s["needs"]]
    return "\n".join(lines)


@click.command(name="info")
@click.argument("mission", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--strict/--lenient",
    default=False,
    help="Fail on the first inconsistency (default: report them).",
)
@json_option
def info(mission: Path, strict: bool, as_json: bool) -> None:
    """Summarise a mission folder: graph, payloads, points, sensors, time span, extent (or a
    plain scan: LAS/LAZ/COPC file, folder of tiles, VPC: points, CRS, date, extent).

    Point counts come from the cloud headers; no point is read. Each file's size is checked
    against its header (binary PCD and PLY, uncompressed LAS, LAZ chunk tables): a truncated
    file, an empty one or an unreadable header is reported as a problem and its points are
    not counted (--strict: an error).

    \b
    Example:
      standgrid info data/missions/2024-05-14-wytham-anymal-coyote
      standgrid info MISSION --json | jq .payloads
      standgrid info SCAN.laz
    """
    from standgrid.mission.opening import open_mission
    from standgrid.mission.scan import is_scan, scan_summary

    if is_scan(mission):
        summary = scan_summary(mission)  # what tiling needs, as the library says it: flags here
        summary["needs"] = [say_flags(need) for need in summary["needs"]]
        emit(summary, as_json, _scan_human)
        return
    summary = open_mission(mission, strict=strict).summary()
    emit(summary, as_json, _human)
