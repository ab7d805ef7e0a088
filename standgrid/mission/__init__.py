"""Reading, building and writing robot missions."""

from standgrid.clouds import (
    CloudHeader,
    iter_cloud_chunks,
    read_cloud,
    read_cloud_header,
    write_cloud,
)
from standgrid.mission.metadata import (
    MissionMetadata,
    metadata_from_folder_name,
    read_metadata,
    write_metadata,
)
from standgrid.mission.mission_name import (
    KNOWN_ROBOTS,
    MissionName,
    RosbagName,
    parse_mission_name,
    parse_rosbag_name,
    register_robot,
)
from standgrid.mission.posegraph import (
    Edge,
    EdgeKind,
    PoseGraph,
    Vertex,
    read_pose_graph,
    write_pose_graph,
)
from standgrid.mission.poses_csv import PoseTable, read_poses_csv, write_poses_csv
from standgrid.mission.sensors import (
    FixQuality,
    GnssFixes,
    ImageRef,
    ImuSamples,
    concat_gnss,
    load_image,
    read_gnss,
    read_imu,
    write_gnss,
    write_imu,
)

__all__ = [
    "KNOWN_ROBOTS",
    "CloudHeader",
    "Edge",
    "EdgeKind",
    "FixQuality",
    "GnssFixes",
    "ImageRef",
    "ImuSamples",
    "MissionMetadata",
    "MissionName",
    "PoseGraph",
    "PoseTable",
    "RosbagName",
    "Vertex",
    "concat_gnss",
    "iter_cloud_chunks",
    "load_image",
    "metadata_from_folder_name",
    "parse_mission_name",
    "parse_rosbag_name",
    "read_cloud",
    "read_cloud_header",
    "read_gnss",
    "read_imu",
    "read_metadata",
    "read_pose_graph",
    "read_poses_csv",
    "register_robot",
    "write_cloud",
    "write_gnss",
    "write_imu",
    "write_metadata",
    "write_pose_graph",
    "write_poses_csv",
]
