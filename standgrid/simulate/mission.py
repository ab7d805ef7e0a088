"""Simulate whole missions: world -> trajectory -> scans, GNSS, IMU -> canonical mission + truth."""

from __future__ import annotations

import datetime as dt
import os
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from standgrid._atomic import check_replaceable, temporary_sibling
from standgrid.crs import CRS
from standgrid.errors import OutputNotWritableError
from standgrid.geometry import Matrix4, invert_pose, transform_points
from standgrid.mission.layout import is_mission_folder
from standgrid.mission.posegraph import Edge, PoseGraph, Vertex
from standgrid.mission.sensors import GnssFixes
from standgrid.pointcloud import PointCloud
from standgrid.simulate.canopy import generate_mixed_forest
from standgrid.simulate.chain import FrameChain
from standgrid.simulate.elevation import ElevationMapModel, elevation_grid
from standgrid.simulate.forest import Shrubs, Trees, generate_forest, grow_forest
from standgrid.simulate.gnss import (
    GnssModel,
    SimulatedGnss,
    simulate_gnss,
    simulate_imu,
)
from standgrid.simulate.raycast import (
    BARK_ROUGHNESS,
    RAYCAST_SCANNERS,
    SHRUB_FOLIAGE_DENSITY,
    raycast_scan,
)
from standgrid.simulate.scanner import ScannerModel, ScanPoints, scan
from standgrid.simulate.terrain import Terrain, random_terrain
from standgrid.simulate.trajectory import (
    Span,
    clip_waypoints,
    drifted_poses,
    information_matrix,
    loop_closure_pairs,
    noisy_relative,
    payload_spans,
    poses_from_positions,
    resample_polyline,
    serpentine_waypoints,
)
from standgrid.stamps import NS_PER_S, Stamp

#: Wytham Woods, Oxford, UK.
SITE_LON, SITE_LAT = -1.3370, 51.7735
SITE_CRS = "EPSG:32630"
PLACE = "wytham"
#: Stands: today's even plantation, or a mixed stand (:mod:`standgrid.simulate.canopy`).
FORESTS = ("plantation", "mixed")
#: Scanners: points sampled on the true surfaces, or a ray caster with occlusion.
SCANNER_KINDS = ("surface", *RAYCAST_SCANNERS)


@dataclass(frozen=True)
class EpochSpec:
    """What differs between the two campaigns: date, robot, sensor height, path direction."""

    date: dt.date
    start: dt.time
    robot: str
    unit: str
    sensor_height: float
    lanes_along: str
    sensors: tuple[str, ...]

    def mission_name(self) -> str:
        return f"{self.date.isoformat()}-{PLACE}-{self.robot}-{self.unit}"


EPOCHS: dict[int, EpochSpec] = {
    1: EpochSpec(
        dt.date(2024, 5, 14),
        dt.time(9, 30),
        "anymal",
        "coyote",
        0.7,
        "y",
        ("velodyne-vlp16", "gnss", "imu"),
    ),
    2: EpochSpec(
        dt.date(2028, 5, 20),
        dt.time(10, 15),
        "frontier",
        "v15",
        1.2,
        "x",
        ("hesai-xt32", "gnss", "imu", "cameras"),
    ),
    # a second robot over the same stand on the first campaign's day (same trees)
    3: EpochSpec(
        dt.date(2024, 5, 14),
        dt.time(13, 40),
        "spot",
        "lynx",
        0.6,
        "x",
        ("ouster-os0", "gnss", "imu"),
    ),
}
#: The mission of ``EPOCHS[k]`` scans the world of this campaign (1: 2024, 2: 2028).
CAMPAIGN_OF = {1: 1, 2: 2, 3: 1}


@dataclass(frozen=True)
class SimulationConfig:
    """Knobs of a simulated mission (defaults: a ~120 m stand, ~30 k points per payload)."""

    area: float = 120.0
    points_per_payload: int = 30_000
    node_spacing: float = 1.5
    payload_spacing: float = 20.0
    speed: float = 0.8
    density_ha: float = 350.0
    years_between: float = 4.0
    drift_m: float = 0.03
    imu_rate_hz: float = 5.0
    write_georef: bool = False
    #: The polygon the robot walks (stand-local metres from the stand's lower-left corner;
    #: None: the whole stand). Lanes are cut to it, so coverage has its irregular edges.
    survey_polygon: tuple[tuple[float, float], ...] | None = None
    #: Share of the trees harvested by epoch 2, and where (stand-local box; None: anywhere).
    harvest_fraction: float = 0.12
    harvest_box: tuple[float, float, float, float] | None = None
    new_trees: int = 3
    scanner: ScannerModel = field(default_factory=ScannerModel)
    gnss: GnssModel = field(default_factory=GnssModel)
    #: "plantation" (evenly spaced, vertical stems) or "mixed" (overstorey, understorey,
    #: snags, leaning and forked stems; ``density_ha`` applies to the plantation only).
    forest: str = "plantation"
    #: "surface" (``scanner``: points on the true surfaces, no occlusion) or a ray-casting
    #: scanner of :data:`~standgrid.simulate.raycast.RAYCAST_SCANNERS`.
    scanner_kind: str = "surface"
    #: Largest spacing (m) of the serpentine lanes (under-canopy surveys: ~15 m).
    lane_spacing: float = 32.0
    #: Write an elevation map per payload (``payloads/elevation``): the terrain truth plus
    #: the model's known error (stated in truth.json); None: none.
    elevation_maps: ElevationMapModel | None = None

    def __post_init__(self) -> None:
        if self.forest not in FORESTS:
            raise ValueError(f"forest must be one of {', '.join(FORESTS)}, got {self.forest!r}")
        if self.scanner_kind not in SCANNER_KINDS:
            raise ValueError(
                f"scanner must be one of {', '.join(SCANNER_KINDS)}, got {self.scanner_kind!r}"
            )
        if self.forest == "mixed" and self.scanner_kind == "surface":
            raise ValueError(
                "the surface scanner draws only vertical plantation stems: scan the mixed "
                f"forest with a ray-casting scanner ({', '.join(RAYCAST_SCANNERS)})"
            )
        if self.lane_spacing <= 0:
            raise ValueError(f"lane spacing must be positive, got {self.lane_spacing}")


@dataclass(frozen=True, eq=False)
class World:
    """The stand at one epoch (CRS coordinates)."""

    bounds: tuple[float, float, float, float]
    terrain: Terrain
    trees: Trees
    shrubs: Shrubs


@dataclass(frozen=True, eq=False)
class SimulatedMission:
    """A simulated mission in memory, and where it was written."""

    name: str
    epoch: int
    seed: int
    mission_dir: Path | None
    truth_dir: Path | None
    world: World
    chain: FrameChain
    stamps_ns: NDArray[np.int64]
    true_poses: Matrix4
    graph: PoseGraph
    spans: list[Span]
    node_crs: NDArray[np.float64]
    config: SimulationConfig
    gnss: SimulatedGnss
    path_length_m: float
    #: Points written (0 until the payloads have been generated by a writer).
    n_points: int = 0

    def payload(self, k: int) -> tuple[PointCloud, ScanPoints]:
        """Payload ``k``: the base-frame cloud, and its points in the CRS with class and tree.

        Generated on demand from its own random stream (deterministic, order-independent),
        so missions of tens of millions of points stream through bounded memory.
        """
        span = self.spans[k]
        rng = np.random.default_rng([self.seed, self.epoch, 3000 + k])
        w, config = self.world, self.config
        sensors = self.node_crs[span.first : span.last + 1]
        world = (w.trees, w.shrubs, w.terrain, w.bounds, config.points_per_payload)
        if config.scanner_kind == "surface":
            pts = scan(rng, sensors, *world, config.scanner)
        else:
            pts = raycast_scan(rng, sensors, *world, RAYCAST_SCANNERS[config.scanner_kind])
        base = transform_points(
            invert_pose(self.true_poses[span.centre]), self.chain.crs_to_map(pts.xyz)
        )
        return PointCloud(base, {"intensity": pts.intensity}), pts

    def iter_payloads(self) -> Iterator[PointCloud]:
        """The base-frame payload clouds in span order."""
        for k in range(len(self.spans)):
            yield self.payload(k)[0]

    def summary(self) -> dict[str, Any]:
        counts = self.graph.edge_counts()
        return {
            "name": self.name,
            "epoch": self.epoch,
            "seed": self.seed,
            "mission": str(self.mission_dir) if self.mission_dir else None,
            "truth": str(self.truth_dir) if self.truth_dir else None,
            "nodes": len(self.graph),
            "payloads": len(self.spans),
            "points": self.n_points,
            "odometry_edges": int(counts.get("odometry", 0)),  # type: ignore[call-overload]
            "loop_closures": int(counts.get("loop_closure", 0)),  # type: ignore[call-overload]
            "gnss_fixes": len(self.gnss.fixes),
            "gnss_outliers": int(self.gnss.outlier.sum()),
            "trees_standing": int(self.world.trees.standing.sum()),
            "path_length_m": round(self.path_length_m, 2),
        }


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), stream])


def stand_bounds(area: float) -> tuple[float, float, float, float]:
    """A square stand of side ``area`` m centred on the site, corners on a 10 m grid."""
    to_utm = CRS.of("EPSG:4326").transformer_to(SITE_CRS)
    cx, cy = to_utm.transform(SITE_LON, SITE_LAT)
    x0 = round((cx - area / 2) / 10.0) * 10.0
    y0 = round((cy - area / 2) / 10.0) * 10.0
    return (x0, y0, x0 + area, y0 + area)


def build_world(seed: int, epoch: int, config: SimulationConfig) -> World:
    """The stand at ``epoch``; epoch 2 is epoch 1 grown, thinned and with ingrowth."""
    bounds = stand_bounds(config.area)
    rng = _rng(seed, 0)
    terrain = random_terrain(rng, bounds)
    if config.forest == "mixed":
        trees, shrubs = generate_mixed_forest(rng, bounds, terrain)
    else:
        trees, shrubs = generate_forest(rng, bounds, terrain, density_ha=config.density_ha)
    if epoch == 2:
        box = None
        if config.harvest_box is not None:
            bx0, by0, bx1, by1 = config.harvest_box
            box = (bounds[0] + bx0, bounds[1] + by0, bounds[0] + bx1, bounds[1] + by1)
        trees = grow_forest(
            _rng(seed, 100),
            trees,
            terrain,
            years=config.years_between,
            harvest_fraction=config.harvest_fraction,
            harvest_box=box,
            new_trees=config.new_trees,
        )
    elif epoch != 1:
        raise ValueError(f"campaign must be 1 or 2, got {epoch}")
    return World(bounds, terrain, trees, shrubs)


def _node_stamps(
    rng: np.random.Generator, spec: EpochSpec, n: int, config: SimulationConfig
) -> NDArray[np.int64]:
    start = dt.datetime.combine(spec.date, spec.start, tzinfo=dt.UTC)
    t0_ns = int(start.timestamp()) * NS_PER_S + int(rng.integers(0, 600 * NS_PER_S))
    dt_s = config.node_spacing / config.speed * rng.uniform(0.85, 1.15, n)
    dt_s[0] = 0.0
    return t0_ns + np.cumsum(np.round(dt_s * 1e9).astype(np.int64))


def _map_frame(rng: np.random.Generator, chain_start_enu: NDArray[np.float64]) -> Matrix4:
    """T_map_enu: random yaw; the map origin sits near the robot's start (as SLAM maps do)."""
    yaw = rng.uniform(-np.pi, np.pi)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    T[:3, 3] = -T[:3, :3] @ chain_start_enu + rng.normal(0.0, [0.5, 0.5, 0.1])
    return T


def _graph(
    rng: np.random.Generator,
    stamps_ns: NDArray[np.int64],
    true_poses: Matrix4,
    estimate: Matrix4,
    chain: FrameChain,
    config: SimulationConfig,
) -> PoseGraph:
    vertices = {i: Vertex(i, Stamp.from_ns(int(s)), estimate[i]) for i, s in enumerate(stamps_ns)}
    odo_t, odo_r, lc_t, lc_r = 0.01, 0.002, 0.02, 0.003
    edges = [
        Edge(
            i,
            i + 1,
            noisy_relative(rng, true_poses[i], true_poses[i + 1], odo_t, odo_r),
            information_matrix(odo_t, odo_r),
        )
        for i in range(len(stamps_ns) - 1)
    ]
    for i, j in loop_closure_pairs(true_poses[:, :3, 3]):
        edges.append(
            Edge(
                i,
                j,
                noisy_relative(rng, true_poses[i], true_poses[j], lc_t, lc_r),
                information_matrix(lc_t, lc_r),
            )
        )
    return PoseGraph(
        vertices=vertices,
        edges=edges,
        platform_id=0,
        gnss_lla_ref=chain.lla_ref if config.write_georef else None,
        gnss_lla_to_map=chain.T_map_enu if config.write_georef else None,
    )


def run_simulation(
    seed: int, epoch: int = 1, config: SimulationConfig | None = None
) -> SimulatedMission:
    """Simulate one mission in memory (nothing written)."""
    config = config or SimulationConfig()
    spec = EPOCHS[epoch]
    world = build_world(seed, CAMPAIGN_OF[epoch], config)
    rng = _rng(seed, epoch)
    # Trajectory in the CRS: nodes every ~1.5 m, sensor above the true ground.
    waypoints = serpentine_waypoints(
        rng, world.bounds, along=spec.lanes_along, max_line_spacing=config.lane_spacing
    )
    if config.survey_polygon is not None:
        x0, y0 = world.bounds[:2]
        outline = [(x0 + u, y0 + v) for u, v in config.survey_polygon]
        waypoints = clip_waypoints(waypoints, outline)
    xy, arc = resample_polyline(waypoints, config.node_spacing)
    node_crs = np.column_stack([xy, world.terrain.height(xy[:, 0], xy[:, 1]) + spec.sensor_height])
    stamps_ns = _node_stamps(rng, spec, len(xy), config)
    # Exact chain: a provisional ENU origin for the GNSS noise, then the first fix as reference.
    provisional = FrameChain(SITE_CRS, tuple(world_lla(node_crs[:1])[0]), np.eye(4))
    gnss = simulate_gnss(rng, provisional, stamps_ns, node_crs, config.gnss)
    fixes = gnss.fixes
    lla_ref = (float(fixes.lat[0]), float(fixes.lon[0]), float(fixes.alt[0]))
    enu_chain = FrameChain(SITE_CRS, lla_ref, np.eye(4))
    start_enu = enu_chain.lla_to_enu(enu_chain.crs_to_lla(node_crs[:1]))[0]
    chain = FrameChain(SITE_CRS, lla_ref, _map_frame(rng, start_enu))
    true_poses = poses_from_positions(rng, chain.crs_to_map(node_crs))
    estimate = drifted_poses(rng, true_poses, config.drift_m)
    graph = _graph(rng, stamps_ns, true_poses, estimate, chain, config)
    spans = payload_spans(arc, config.payload_spacing)
    return SimulatedMission(
        name=spec.mission_name(),
        epoch=epoch,
        seed=seed,
        mission_dir=None,
        truth_dir=None,
        world=world,
        chain=chain,
        stamps_ns=stamps_ns,
        true_poses=true_poses,
        graph=graph,
        spans=spans,
        node_crs=node_crs,
        config=config,
        gnss=gnss,
        path_length_m=float(arc[-1]),
    )


def world_lla(xyz_crs: NDArray[np.float64]) -> NDArray[np.float64]:
    """CRS points of the site -> (lat, lon, h)."""
    return FrameChain(SITE_CRS, (SITE_LAT, SITE_LON, 0.0), np.eye(4)).crs_to_lla(xyz_crs)


# --- writing ------------------------------------------------------------------------------


def _metadata(sim: SimulatedMission, spec: EpochSpec) -> Any:
    from standgrid.mission.metadata import MissionMetadata

    first = Stamp.from_ns(int(sim.stamps_ns[0]))
    start = dt.datetime.fromtimestamp(first.sec, tz=dt.UTC)
    return MissionMetadata(
        name=sim.name,
        date=spec.date,
        time=start.time().replace(microsecond=0),
        place=PLACE,
        robot=spec.robot,
        unit=spec.unit,
        gnss=sim.chain.lla_ref,
        sensors=list(spec.sensors),
        tags=["simulated", "forest", f"epoch-{sim.epoch}"],
        notes=f"standgrid simulator, seed {sim.seed}; ground truth in truth/{sim.name}/",
        extra={"simulator": {"seed": sim.seed, "epoch": sim.epoch}},
    )


def write_mission_folder(sim: SimulatedMission, folder: Path, config: SimulationConfig) -> int:
    """Write the canonical mission layout of ``sim`` into an existing empty ``folder`` (and,
    with ``config.elevation_maps``, an elevation map per payload).

    Returns the number of points written.
    """
    n_points = write_canonical_parts(
        folder,
        metadata=_metadata(sim, EPOCHS[sim.epoch]),
        graph=sim.graph,
        stamps_ns=sim.stamps_ns,
        true_poses=sim.true_poses,
        spans=sim.spans,
        payloads=sim.iter_payloads(),
        fixes=sim.gnss.fixes,
        rng=_rng(sim.seed, 1000 + sim.epoch),
        imu_rate_hz=config.imu_rate_hz,
    )
    if config.elevation_maps is not None:
        write_elevation_maps(sim, folder, config.elevation_maps)
    return n_points


def write_elevation_maps(sim: SimulatedMission, folder: Path, model: ElevationMapModel) -> None:
    """One elevation map per payload (``payloads/elevation/elevation_<stamp>.npz``), in its
    base frame at the true pose (as its cloud), each from its own random stream."""
    from standgrid.mission.derived_maps import (
        ELEVATION_FOLDER,
        ELEVATION_PREFIX,
        write_elevation_npz,
    )

    for k, span in enumerate(sim.spans):
        rng = np.random.default_rng([sim.seed, sim.epoch, 5000 + k])
        heights, origin = elevation_grid(
            model, sim.world.terrain, sim.chain, sim.true_poses[span.centre], rng
        )
        stamp = Stamp.from_ns(int(sim.stamps_ns[span.centre]))
        target = folder / ELEVATION_FOLDER / stamp.filename(ELEVATION_PREFIX, "npz")
        write_elevation_npz(target, heights, model.resolution, origin)


def write_canonical_parts(
    folder: Path,
    *,
    metadata: Any,
    graph: PoseGraph,
    stamps_ns: NDArray[np.int64],
    true_poses: Matrix4,
    spans: list[Span],
    payloads: Iterable[PointCloud],
    fixes: GnssFixes,
    rng: np.random.Generator,
    imu_rate_hz: float,
) -> int:
    """Metadata, graph, pose CSV, payload clouds (VIEWPOINT = graph pose), GNSS log and
    per-payload GNSS and IMU files, with the format writers of :mod:`standgrid.mission`.

    The IMU is simulated once over the whole mission; the GNSS and IMU logs are cut into
    contiguous per-payload windows by the canonical writer
    (:func:`standgrid.mission.writer.write_payload_logs`)."""
    from standgrid.clouds import write_cloud
    from standgrid.mission.metadata import write_metadata
    from standgrid.mission.posegraph import write_pose_graph
    from standgrid.mission.poses_csv import PoseTable, write_poses_csv
    from standgrid.mission.sensors import write_gnss
    from standgrid.mission.writer import write_payload_logs

    write_metadata(metadata, folder / "metadata.yaml")
    write_pose_graph(graph, folder / "slam_pose_graph.g2o")
    write_poses_csv(PoseTable.from_pose_graph(graph), folder / "slam_poses.csv")
    for sub in ("payload_clouds", "gnss", "payloads/gnss", "payloads/imu"):
        (folder / sub).mkdir(parents=True)
    write_gnss(fixes, folder / "gnss" / "fixes.txt")
    n_points = 0
    payload_stamps: list[Stamp] = []
    for span, cloud in zip(spans, payloads, strict=True):
        n_points += len(cloud)
        stamp = Stamp.from_ns(int(stamps_ns[span.centre]))
        payload_stamps.append(stamp)
        write_cloud(
            cloud,
            folder / "payload_clouds" / stamp.filename("cloud", "pcd"),
            viewpoint=graph.vertices[span.centre].pose,
        )
    imu = simulate_imu(
        rng, stamps_ns, true_poses, int(stamps_ns[0]), int(stamps_ns[-1]), imu_rate_hz
    )
    write_payload_logs(folder, payload_stamps, fixes, imu)
    return n_points


def write_truth_folder(sim: SimulatedMission, folder: Path, config: SimulationConfig) -> None:
    """Write the ground truth of ``sim`` into an existing empty ``folder``."""
    from standgrid.mission.poses_csv import PoseTable, write_poses_csv
    from standgrid.simulate.truth import (
        write_gnss_truth,
        write_shrubs_csv,
        write_trees_csv,
        write_truth_json,
    )

    spec = EPOCHS[sim.epoch]
    write_trees_csv(sim.world.trees, folder / "trees.csv")
    write_shrubs_csv(sim.world.shrubs, folder / "shrubs.csv")
    write_poses_csv(PoseTable.from_arrays(sim.stamps_ns, sim.true_poses), folder / "true_poses.csv")
    write_gnss_truth(
        sim.gnss.fixes.stamps_ns, sim.gnss.true_xyz, sim.gnss.outlier, folder / "gnss_truth.csv"
    )
    info = {
        "kind": "simulated",
        "mission": sim.name,
        "crs": SITE_CRS,
        "crs_to_geodetic": sim.chain.description,
        "chain": "CRS (x, y, ellipsoidal h) -> EPSG:4979 -> EPSG:4978 -> ENU(lla_ref) -> T_map_enu",
        "lla_ref": list(sim.chain.lla_ref),
        "T_map_enu": sim.chain.T_map_enu.tolist(),
        "seed": sim.seed,
        "epoch": sim.epoch,
        "date": spec.date.isoformat(),
        "years_since_epoch_1": config.years_between if sim.epoch == 2 else 0.0,
        "bounds": list(sim.world.bounds),
        "terrain": sim.world.terrain.to_dict(),
        "sensor_height_m": spec.sensor_height,
        "scanner": {
            "max_range_m": config.scanner.max_range,
            "noise_std_m": config.scanner.noise_std,
        },
        "slam_drift_m": config.drift_m,
        "payload_spacing_m": config.payload_spacing,
        "points_per_payload": config.points_per_payload,
        "gnss_h_std_meaning": "horizontal RMS error; per axis h_std / sqrt(2)",
        "trees_dbh_height": "DBH at 1.3 m above ground; stems taper linearly to the tree top",
    }
    if (config.forest, config.scanner_kind, config.lane_spacing) != ("plantation", "surface", 32.0):
        info.update(_opt_in_truth(config))
    if config.elevation_maps is not None:
        info["elevation_maps"] = config.elevation_maps.truth()
    if config.gnss != GnssModel():
        info["gnss_model"] = {k: v for k, v in vars(config.gnss).items()}
    write_truth_json(info, folder / "truth.json")


def _opt_in_truth(config: SimulationConfig) -> dict[str, Any]:
    """Truth of the opt-in knobs (forest, ray-casting scanner, lanes); left out of a default
    simulation's truth.json, which stays as it was."""
    info: dict[str, Any] = {"forest": config.forest, "lane_spacing_m": config.lane_spacing}
    if config.scanner_kind == "surface":
        info["scanner"] = {
            "kind": "surface",
            "max_range_m": config.scanner.max_range,
            "noise_std_m": config.scanner.noise_std,
        }
        return info
    model = RAYCAST_SCANNERS[config.scanner_kind]
    info["scanner"] = {
        "kind": model.kind,
        "max_range_m": model.max_range,
        "min_range_m": model.min_range,
        "noise_std_m": model.noise_std,
        "noise": "Gaussian, along the ray",
        "elevation_deg": list(model.elevation_deg),
        "rings": model.rings,
        "altitude_above_nodes_m": list(model.altitude),
        "bark_roughness_std_m": BARK_ROUGHNESS,
        "shrub_foliage_density_per_m": SHRUB_FOLIAGE_DENSITY,
        "occlusion": "first hit per ray; crowns and shrubs porous (foliage_density)",
    }
    info["trees_dbh_height"] = (
        "DBH at 1.3 m along the stem axis, perpendicular to it; heights vertical above "
        "z_ground; stem taper, forks and crowns as in standgrid.simulate.canopy"
    )
    return info


def _prepare(final: Path, overwrite: bool, replaces: Any, what: str) -> None:
    check_replaceable(final, overwrite=overwrite, replaces=replaces, what=what)


def _install_together(moves: list[tuple[Path, Path]]) -> None:
    """Rename each new folder onto its final path, all or none.

    The old folders are moved aside first; if any rename fails, the new folders already in
    place are moved back and the old ones restored (the pair stays consistent), then
    :class:`OutputNotWritableError` is raised. On success the old folders are deleted.
    """
    aside: list[tuple[Path, Path]] = []  # (final, old moved aside)
    placed: list[tuple[Path, Path]] = []  # (new, final)
    current = moves[0][1]
    try:
        for _, final in moves:
            current = final
            if final.exists():
                old = temporary_sibling(final)
                os.replace(final, old)
                aside.append((final, old))
        for new, final in moves:
            current = final
            os.replace(new, final)
            placed.append((new, final))
    except OSError as exc:
        for new, final in reversed(placed):
            os.replace(final, new)
        for final, old in reversed(aside):
            os.replace(old, final)
        raise OutputNotWritableError(
            f"cannot move the new output into place: {exc.strerror}", path=current
        ) from exc
    for _, old in aside:
        shutil.rmtree(old, ignore_errors=True)


def simulate_mission(
    out_root: str | Path,
    *,
    seed: int,
    epoch: int = 1,
    overwrite: bool = False,
    config: SimulationConfig | None = None,
    **overrides: Any,
) -> SimulatedMission:
    """Simulate one mission into ``<out_root>/missions/<name>/``, truth into ``truth/<name>/``.

    Both are written to temporary siblings and renamed into place together: a failure
    leaves the previous mission and truth (or neither) as they were.

    ``overrides`` set :class:`SimulationConfig` fields (``area=100``, ``points_per_payload=...``).
    """
    if epoch not in EPOCHS:
        raise ValueError(f"epoch must be one of {sorted(EPOCHS)}, got {epoch}")
    base = config or SimulationConfig()
    if overrides:
        base = SimulationConfig(**{**base.__dict__, **overrides})
    root = Path(out_root)
    name = EPOCHS[epoch].mission_name()
    mission_dir, truth_dir = root / "missions" / name, root / "truth" / name
    _prepare(mission_dir, overwrite, is_mission_folder, "a mission folder")
    from standgrid.simulate.truth import is_truth_folder

    _prepare(truth_dir, overwrite, is_truth_folder, "a simulator truth folder")
    sim = run_simulation(seed, epoch, base)
    tmp_mission, tmp_truth = temporary_sibling(mission_dir), temporary_sibling(truth_dir)
    try:
        for tmp in (tmp_mission, tmp_truth):
            try:
                tmp.mkdir(parents=True)
            except OSError as exc:
                raise OutputNotWritableError(
                    f"cannot create folder: {exc.strerror}", path=tmp.parent
                ) from exc
        n_points = write_mission_folder(sim, tmp_mission, base)
        write_truth_folder(sim, tmp_truth, base)
        _install_together([(tmp_mission, mission_dir), (tmp_truth, truth_dir)])
    finally:
        for tmp in (tmp_mission, tmp_truth):
            shutil.rmtree(tmp, ignore_errors=True)
    return replace(sim, mission_dir=mission_dir, truth_dir=truth_dir, n_points=n_points)


def simulate_pair(
    out_root: str | Path, seed: int, *, overwrite: bool = False, **overrides: Any
) -> list[SimulatedMission]:
    """Both epochs of one stand (same terrain and trees, four years apart)."""
    return [
        simulate_mission(out_root, seed=seed, epoch=e, overwrite=overwrite, **overrides)
        for e in (1, 2)
    ]


__all__ = [
    "EPOCHS",
    "SimulatedMission",
    "SimulationConfig",
    "World",
    "build_world",
    "run_simulation",
    "simulate_mission",
    "simulate_pair",
    "stand_bounds",
]
