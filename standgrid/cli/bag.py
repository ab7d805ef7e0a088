"""``standgrid bag``: ROS bags (ROS 1, ROS 2 sqlite3, MCAP) to a canonical mission."""

from __future__ import annotations

from pathlib import Path

import click

from standgrid.cli.options import emit, json_option, overwrite_option, quiet_option, status


@click.command(name="bag")
@click.argument("bags", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(path_type=Path),
    help="Mission folder to write.",
)
@click.option("--clouds", "cloud_topic", help="PointCloud2 topic (default: the only one).")
@click.option("--odom", "odom_topic", help="Odometry topic (default: the only one; else /tf).")
@click.option("--gnss", "gnss_topic", help="NavSatFix topic (default: the only one).")
@click.option(
    "--grid-map",
    "grid_map_topic",
    help="grid_map_msgs/GridMap topic (default: the only one): payload elevation maps.",
)
@click.option(
    "--elevation-layer",
    default="elevation",
    show_default=True,
    help="The GridMap layer holding the heights.",
)
@click.option("--base-frame", help="Robot base frame (default: the odometry child frame).")
@click.option("--map-frame", help="Map frame for /tf poses (default: the root of the tf tree).")
@click.option(
    "--node-distance",
    type=click.FloatRange(min=0.0),
    default=1.0,
    show_default=True,
    help="Metres between pose-graph nodes (the VILENS logger's 1 m).",
)
@click.option(
    "--distance",
    type=float,
    default=20.0,
    show_default=True,
    help="Metres travelled per payload (as `payloads build`).",
)
@click.option("--area", type=float, help="Instead: square payload tiles of this side (m).")
@overwrite_option
@quiet_option
@json_option
def bag(
    bags: tuple[Path, ...],
    output: Path,
    cloud_topic: str | None,
    odom_topic: str | None,
    gnss_topic: str | None,
    grid_map_topic: str | None,
    elevation_layer: str,
    base_frame: str | None,
    map_frame: str | None,
    node_distance: float,
    distance: float,
    area: float | None,
    overwrite: bool,
    quiet: bool,
    as_json: bool,
) -> None:
    """Turn ROS bags into a mission: scans per node, pose graph, GNSS, then payloads.

    BAGS are ROS 1 .bag files or one ROS 2 bag folder (sqlite3 or MCAP). Topics are found
    by message type unless given.

    \b
    Example:
      standgrid bag anymal-2024-05-14-09-30.bag -o 2024-05-14-wytham-anymal-coyote
      standgrid bag rosbag2_folder -o MISSION --clouds /points --odom /odometry --json
    """
    from standgrid.mission.rosbag import bag_to_mission

    status(f"reading {len(bags)} bag(s) ...", quiet or as_json)
    report = bag_to_mission(
        bags,
        output,
        cloud_topic=cloud_topic,
        odom_topic=odom_topic,
        gnss_topic=gnss_topic,
        base_frame=base_frame,
        map_frame=map_frame,
        node_distance=node_distance,
        distance=distance,
        area=area,
        overwrite=overwrite,
        grid_map_topic=grid_map_topic,
        elevation_layer=elevation_layer,
    )
    emit(
        report.to_dict(),
        as_json,
        lambda r: (
            f"{r['nodes']} nodes from {r['scans']} scans ({r['scans_between_nodes']} skipped, "
            f"{r['scans_without_pose']} without a pose), {r['payloads']} payloads, "
            f"{r['points']:,} points ({r['nan_points_dropped']} NaN dropped), "
            f"{r['gnss_fixes']} GNSS fixes, {r['elevation_maps']} elevation maps "
            f"(of {r['grid_maps']} GridMaps) -> {r['output']}"
        ),
    )
