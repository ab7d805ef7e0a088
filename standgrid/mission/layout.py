"""Find what a mission folder holds: which file or folder plays which role.

Discovery only looks at names (no file is parsed here). Every layout of
../shared/docs/MISSION_FORMAT.md section 1 (VILENS ROS 1 and ROS 2 output) and our own
section 6 files are recognised; anything else in a cloud folder is listed in ``unrecognised``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from standgrid.clouds import CLOUD_EXTENSIONS as CLOUD_SUFFIXES
from standgrid.errors import MissionNotFoundError
from standgrid.mission.derived_maps import (
    ELEVATION_EXTENSIONS,
    ELEVATION_FOLDER,
    VOLUMETRIC_EXTENSIONS,
    VOLUMETRIC_FOLDER,
)
from standgrid.stamps import Stamp, stamp_from_filename

Frame = Literal["base", "map", "utm"]
CloudRole = Literal["payload", "scans", "layer"]

#: Pose-graph file names, most preferred first.
GRAPH_NAMES = ("slam_pose_graph.g2o", "slam_pose_graph.slam", "mission.g2o")
#: Pose-table file names, most preferred first.
POSES_CSV_NAMES = ("slam_poses.csv", "slam-poses.csv", "poses.txt")
#: Payload cloud folders, most preferred first (UTM clouds cannot be brought back to base
#: without a georeference, so they are never the payload source).
PAYLOAD_FOLDERS = ("payload_clouds", "payload_clouds_in_map", "payload_clouds_in_utm")
#: Per-node scan folders, most preferred first.
SCAN_FOLDERS = ("individual_clouds", "slam_clouds", "undist-clouds", "raw_data/raw_clouds")
#: Folders of clouds attached as named layers to the payload (or scan) of the same stamp.
LAYER_FOLDERS = {"ground_clouds": "ground"}
#: Cloud file suffixes without the dot (the formats of :mod:`standgrid.clouds`).
CLOUD_EXTENSIONS = frozenset(s.lstrip(".") for s in CLOUD_SUFFIXES)
IMAGE_EXTENSIONS = frozenset({"jpg", "jpeg", "png"})


def frame_of_folder(name: str) -> Frame:
    """``*_in_map`` -> map, ``*_in_utm`` -> utm, anything else -> base."""
    if name.endswith("_in_map"):
        return "map"
    if name.endswith("_in_utm"):
        return "utm"
    return "base"


@dataclass(frozen=True)
class StampedFile:
    """A file whose name carries a stamp: ``<prefix>_<sec>_<nsec>.<ext>``."""

    stamp: Stamp
    path: Path


@dataclass(frozen=True)
class CloudFolder:
    """A folder of stamped clouds, its role and the frame its clouds are in."""

    name: str  # path relative to the mission root, with "/" separators
    path: Path
    role: CloudRole
    frame: Frame
    files: tuple[StampedFile, ...]


@dataclass(frozen=True)
class MissionLayout:
    """The files of one mission, by role. Paths are absolute; absent roles are None/empty."""

    root: Path
    graph: Path | None = None
    #: Further graph files that are present but not used (a less preferred name).
    other_graphs: tuple[Path, ...] = ()
    #: Graph-like files elsewhere in the folder (``graphs/ground_truth.slam``, ``*.g2o`` of
    #: another name): never read, named in hints when no graph is found.
    stray_graphs: tuple[Path, ...] = ()
    poses_csv: Path | None = None
    metadata: Path | None = None
    #: Every payload cloud folder found, most preferred first.
    payload_folders: tuple[CloudFolder, ...] = ()
    scan_folders: tuple[CloudFolder, ...] = ()
    layer_folders: tuple[CloudFolder, ...] = ()
    gnss_log: Path | None = None
    gnss_payloads: tuple[StampedFile, ...] = ()
    imu_payloads: tuple[StampedFile, ...] = ()
    #: Elevation and volumetric maps of payloads (``payloads/elevation``, ``payloads/volumetric``;
    #: a PNG elevation map's JSON sidecar is not listed: it goes with its PNG).
    elevation_maps: tuple[StampedFile, ...] = ()
    volumetric_maps: tuple[StampedFile, ...] = ()
    #: camera name -> its stamped images (``payloads/cameras/<cam>`` or ``images_rectified/<cam>``).
    cameras: dict[str, tuple[StampedFile, ...]] = field(default_factory=dict)
    #: Files in cloud/sensor folders whose names do not carry a stamp.
    unrecognised: tuple[Path, ...] = ()

    @property
    def payload_source(self) -> CloudFolder | None:
        """The folder the payloads are read from: ``payload_clouds`` (base frame) first,
        then ``payload_clouds_in_map``; never the UTM folder."""
        for folder in self.payload_folders:
            if folder.frame != "utm":
                return folder
        return None

    @property
    def scans(self) -> CloudFolder | None:
        """The preferred per-node scan folder, if any."""
        return self.scan_folders[0] if self.scan_folders else None

    @property
    def is_mission(self) -> bool:
        """True when the folder holds anything a mission is made of."""
        return bool(
            self.graph
            or self.poses_csv
            or self.metadata
            or self.payload_folders
            or self.scan_folders
            or self.gnss_log
            or self.gnss_payloads
            or self.imu_payloads
            or self.cameras
        )


def _stamped_files(
    folder: Path, extensions: frozenset[str], unrecognised: list[Path]
) -> tuple[StampedFile, ...]:
    found: list[StampedFile] = []
    for child in sorted(folder.iterdir()):
        if child.name.startswith("."):
            continue
        parsed = stamp_from_filename(child.name)
        if child.is_dir() and (parsed is None or parsed[2] not in extensions):
            continue  # a folder named like a payload is kept: reading it says what is wrong
        if parsed is None or parsed[2] not in extensions:
            unrecognised.append(child)
            continue
        found.append(StampedFile(parsed[1], child))
    found.sort(key=lambda f: (f.stamp, f.path.name))
    return tuple(found)


def _cloud_folder(
    root: Path, name: str, role: CloudRole, unrecognised: list[Path]
) -> CloudFolder | None:
    path = root / name
    if not path.is_dir():
        return None
    files = _stamped_files(path, CLOUD_EXTENSIONS, unrecognised)
    return CloudFolder(name, path, role, frame_of_folder(name), files)


def _first_file(root: Path, names: tuple[str, ...]) -> tuple[Path | None, tuple[Path, ...]]:
    present = [root / n for n in names if (root / n).is_file()]
    return (present[0] if present else None), tuple(present[1:])


#: Suffixes of pose-graph files.
GRAPH_SUFFIXES = frozenset({".g2o", ".slam"})


def _stray_graphs(root: Path, used: set[Path], depth: int = 2) -> tuple[Path, ...]:
    """Graph and pose-table files under ``root`` (``depth`` folders deep) that are not used;
    cloud, camera and sensor folders are not searched."""
    skip = {*PAYLOAD_FOLDERS, *SCAN_FOLDERS, *LAYER_FOLDERS, "payloads", "images_rectified"}
    found: list[Path] = []

    def visit(folder: Path, left: int) -> None:
        try:
            children = sorted(folder.iterdir())
        except OSError:
            return
        for child in children:
            if child.name.startswith("."):
                continue
            if child.is_dir():
                rel = child.relative_to(root).as_posix()
                if left > 0 and rel not in skip and not rel.startswith("raw_data/raw_clouds"):
                    visit(child, left - 1)
            elif child not in used and (
                child.suffix.lower() in GRAPH_SUFFIXES or child.name in POSES_CSV_NAMES
            ):
                found.append(child)

    visit(root, depth)
    return tuple(found)


def discover_layout(path: str | Path) -> MissionLayout:
    """Look at the names in a mission folder and return its :class:`MissionLayout`.

    Raises :class:`MissionNotFoundError` if the folder does not exist.
    """
    root = Path(path).absolute()
    if not root.is_dir():
        raise MissionNotFoundError("mission folder does not exist", path=root)
    unrecognised: list[Path] = []
    graph, other_graphs = _first_file(root, GRAPH_NAMES)
    poses_csv, _ = _first_file(root, POSES_CSV_NAMES)
    metadata = root / "metadata.yaml"

    payloads = [_cloud_folder(root, n, "payload", unrecognised) for n in PAYLOAD_FOLDERS]
    scans = [_cloud_folder(root, n, "scans", unrecognised) for n in SCAN_FOLDERS]
    layers = [_cloud_folder(root, n, "layer", unrecognised) for n in LAYER_FOLDERS]

    gnss_dir = root / "payloads" / "gnss"
    imu_dir = root / "payloads" / "imu"
    text = frozenset({"txt", "csv"})
    gnss_payloads = _stamped_files(gnss_dir, text, unrecognised) if gnss_dir.is_dir() else ()
    imu_payloads = _stamped_files(imu_dir, text, unrecognised) if imu_dir.is_dir() else ()

    maps: dict[str, tuple[StampedFile, ...]] = {}
    for folder, exts in (
        (ELEVATION_FOLDER, ELEVATION_EXTENSIONS),
        (VOLUMETRIC_FOLDER, VOLUMETRIC_EXTENSIONS),
    ):
        if (root / folder).is_dir():
            found = _stamped_files(root / folder, exts | {"json"}, unrecognised)
            maps[folder] = tuple(f for f in found if f.path.suffix.lower() != ".json")

    cameras: dict[str, tuple[StampedFile, ...]] = {}
    for cam_root in (root / "payloads" / "cameras", root / "images_rectified"):
        if not cam_root.is_dir():
            continue
        for cam in sorted(p for p in cam_root.iterdir() if p.is_dir()):
            images = _stamped_files(cam, IMAGE_EXTENSIONS, unrecognised)
            cameras[cam.name] = tuple(
                sorted(cameras.get(cam.name, ()) + images, key=lambda f: f.stamp)
            )

    gnss_log = root / "gnss" / "fixes.txt"
    return MissionLayout(
        root=root,
        graph=graph,
        other_graphs=other_graphs,
        stray_graphs=_stray_graphs(
            root, {p for p in (graph, poses_csv, *other_graphs) if p is not None}
        ),
        poses_csv=poses_csv,
        metadata=metadata if metadata.is_file() else None,
        payload_folders=tuple(f for f in payloads if f is not None),
        scan_folders=tuple(f for f in scans if f is not None),
        layer_folders=tuple(f for f in layers if f is not None),
        gnss_log=gnss_log if gnss_log.is_file() else None,
        gnss_payloads=gnss_payloads,
        imu_payloads=imu_payloads,
        elevation_maps=maps.get(ELEVATION_FOLDER, ()),
        volumetric_maps=maps.get(VOLUMETRIC_FOLDER, ()),
        cameras=cameras,
        unrecognised=tuple(unrecognised),
    )


def is_mission_folder(path: str | Path) -> bool:
    """True when ``path`` is a mission folder holding nothing else (what writing a mission
    with overwrite may replace): a folder with any entry the mission layout does not know
    (notes, a thesis, other missions) is not one."""
    root = Path(path)
    if not root.is_dir():
        return False
    layout = discover_layout(root)
    known = {
        *GRAPH_NAMES,
        *POSES_CSV_NAMES,
        "metadata.yaml",
        *PAYLOAD_FOLDERS,
        *LAYER_FOLDERS,
        *(name.split("/")[0] for name in SCAN_FOLDERS),
        "payloads",
        "images_rectified",
        "gnss",
    }
    strangers = [p for p in root.iterdir() if p.name not in known]
    return layout.is_mission and not layout.unrecognised and not strangers


def layer_name(folder: CloudFolder) -> str:
    """The layer key of a layer folder (``ground_clouds`` -> ``ground``)."""
    return LAYER_FOLDERS.get(folder.name, folder.name.removesuffix("_clouds"))
