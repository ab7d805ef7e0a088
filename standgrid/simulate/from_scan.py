"""A mission cut from a real georeferenced scan, with the true coordinates kept as truth.

A straight path is laid along the long axis of the scan; every point within ``radius`` m
(horizontally) of the path goes to the payload of its nearest node's span, expressed in
the base frame of that span's centre node through the exact chain
``scan CRS -> geodetic -> ECEF -> ENU -> map`` (random map yaw and offset). GNSS fixes
(few cm noise plus outliers) are computed through the same chain. Truth (original CRS
coordinates and source point indices per payload) is written beside the mission.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from standgrid._atomic import atomic_output, check_replaceable
from standgrid.clouds.las_header import check_las_header
from standgrid.crs import CRS
from standgrid.errors import CRSError, FormatError, MissionNotFoundError
from standgrid.geometry import Matrix4, invert_pose, transform_points
from standgrid.mission.layout import is_mission_folder
from standgrid.mission.posegraph import PoseGraph
from standgrid.pointcloud import PointCloud
from standgrid.simulate.chain import FrameChain
from standgrid.simulate.gnss import GnssModel, SimulatedGnss, simulate_gnss
from standgrid.simulate.mission import _graph, _map_frame, write_canonical_parts
from standgrid.simulate.trajectory import (
    Span,
    payload_spans,
    poses_from_positions,
    resample_polyline,
)
from standgrid.simulate.truth import is_truth_folder
from standgrid.stamps import NS_PER_S, Stamp


@dataclass(frozen=True, eq=False)
class ScanMission:
    """What :func:`mission_from_scan` wrote, and the in-memory truth."""

    name: str
    mission_dir: Path
    truth_dir: Path
    crs: str
    chain: FrameChain
    graph: PoseGraph
    true_poses: Matrix4
    stamps_ns: NDArray[np.int64]
    spans: list[Span]
    n_points: int
    gnss: SimulatedGnss

    def summary(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "mission": str(self.mission_dir),
            "truth": str(self.truth_dir),
            "crs": self.crs,
            "nodes": len(self.graph),
            "payloads": len(self.spans),
            "points": self.n_points,
            "gnss_fixes": len(self.gnss.fixes),
            "gnss_outliers": int(self.gnss.outlier.sum()),
        }


def _normalise_crs(crs: str) -> str:
    """A user-given CRS as ``EPSG:XXXX`` or WKT2; PROJ strings and non-projected CRSs refused."""
    from standgrid.georeference.crs import resolve_crs

    try:
        return resolve_crs(crs).text
    except CRSError as exc:
        raise CRSError(f"unusable CRS {crs!r}: {exc.message}") from exc


def _read_scans(
    paths: Sequence[Path], crs: str | None
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.uint8], str, list[dict[str, Any]]]:
    import laspy

    xyz_parts, inten_parts, cls_parts, sources = [], [], [], []
    found_crs: str | None = None
    if crs is not None:
        crs = _normalise_crs(crs)
    for path in paths:
        if not path.is_file():
            raise MissionNotFoundError("scan file not found", path=path)
        check_las_header(path)
        try:
            las = laspy.read(path)
            file_crs = las.header.parse_crs()
        except Exception as exc:  # laspy raises several unrelated types for bad files
            raise FormatError(f"cannot read LAS/LAZ: {exc}", path=path) from exc
        if file_crs is not None:  # the file's EPSG code as pyproj identifies it, else WKT2
            found = CRS.of(file_crs)
            text = f"EPSG:{found.epsg}" if found.epsg else found.wkt2
            if found_crs is not None and text != found_crs and crs is None:
                raise CRSError(f"CRS {text} differs from {found_crs} of the other files", path=path)
            found_crs = found_crs or text
        xyz_parts.append(np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]))
        inten_parts.append(np.asarray(las.intensity, dtype=np.float32))
        cls_parts.append(np.asarray(las.classification, dtype=np.uint8))
        sources.append({"path": str(path), "points": len(las.points)})
    use_crs = crs or found_crs
    if use_crs is None:
        raise CRSError("the scans carry no CRS; pass crs=", path=paths[0])
    try:
        CRS.of(use_crs)
    except CRSError as exc:
        raise CRSError(f"unusable CRS {use_crs!r}: {exc.message}", path=paths[0]) from exc
    return (
        np.concatenate(xyz_parts),
        np.concatenate(inten_parts),
        np.concatenate(cls_parts),
        use_crs,
        sources,
    )


def _centre_line(xy: NDArray[np.float64], inset: float) -> NDArray[np.float64]:
    """Two end points of a straight path along the long (first principal) axis of ``xy``."""
    centre = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy[:: max(1, len(xy) // 200_000)] - centre, full_matrices=False)
    axis = vt[0] if vt[0][np.argmax(np.abs(vt[0]))] > 0 else -vt[0]
    along = (xy - centre) @ axis
    lo, hi = float(along.min()) + inset, float(along.max()) - inset
    return np.array([centre + lo * axis, centre + hi * axis])


def _ground_heights(
    xyz: NDArray[np.float64], classification: NDArray[np.uint8], query: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Ground height under each query point: median of the nearest ground-class points."""
    ground = xyz[classification == 2]
    if len(ground) < 100:
        ground = xyz
    _, idx = cKDTree(ground[:, :2]).query(query, k=min(20, len(ground)))
    return np.asarray(
        np.median(ground[idx, 2], axis=1) if idx.ndim == 2 else ground[idx, 2], np.float64
    )


def _default_place(paths: Sequence[Path]) -> str:
    stem = re.sub(r"[^a-z]+", "-", paths[0].stem.lower()).strip("-")
    return stem or "scan"


def mission_from_scan(
    las_paths: Sequence[str | Path],
    out_root: str | Path,
    *,
    seed: int,
    crs: str | None = None,
    payload_spacing: float = 20.0,
    radius: float = 20.0,
    node_spacing: float = 1.5,
    speed: float = 1.0,
    sensor_height: float = 1.0,
    gnss_noise_m: float = 0.03,
    outlier_fraction: float = 0.05,
    gnss_rate_hz: float = 2.0,
    date: dt.date = dt.date(2023, 6, 1),
    place: str | None = None,
    robot: str = "handheld",
    inset: float = 10.0,
    write_georef: bool = False,
    overwrite: bool = False,
) -> ScanMission:
    """Cut a real georeferenced scan into a mission along a path; truth written beside it.

    Writes ``<out_root>/missions/<name>/`` (canonical layout) and ``<out_root>/truth/<name>/``
    with ``payload_points/points_<stamp>.npy`` (original CRS coordinates, float64) and
    ``index_<stamp>.npy`` (indices into the concatenated input files, in order). The graph
    holds the true poses (no drift). A given ``crs`` (overriding the files') is stored as
    ``EPSG:XXXX`` or WKT2; a PROJ string or a geographic CRS raises :class:`CRSError`.
    """
    from standgrid.simulate.mission import SimulationConfig
    from standgrid.simulate.truth import write_gnss_truth, write_truth_json

    paths = [Path(p) for p in las_paths]
    if not paths:
        raise ValueError("no scan files given")
    name = f"{date.isoformat()}-{place or _default_place(paths)}-{robot}"
    root = Path(out_root)
    mission_dir, truth_dir = root / "missions" / name, root / "truth" / name
    check_replaceable(
        mission_dir, overwrite=overwrite, replaces=is_mission_folder, what="a mission folder"
    )
    check_replaceable(
        truth_dir, overwrite=overwrite, replaces=is_truth_folder, what="a simulator truth folder"
    )
    xyz, intensity, classification, use_crs, sources = _read_scans(paths, crs)
    rng = np.random.default_rng([int(seed), 7])

    # Path, nodes (sensor above the ground), stamps.
    xy_nodes, arc = resample_polyline(_centre_line(xyz[:, :2], inset), node_spacing)
    node_crs = np.column_stack(
        [xy_nodes, _ground_heights(xyz, classification, xy_nodes) + sensor_height]
    )
    start = dt.datetime.combine(date, dt.time(10, 0), tzinfo=dt.UTC)
    t0_ns = int(start.timestamp()) * NS_PER_S + int(rng.integers(0, 600 * NS_PER_S))
    stamps_ns = t0_ns + np.round(arc / speed * 1e9).astype(np.int64)

    # Chain: GNSS first (ENU origin = first fix), then a random map frame.
    mid = node_crs[len(node_crs) // 2 : len(node_crs) // 2 + 1]
    probe = FrameChain(use_crs, (0.0, 0.0, 0.0), np.eye(4))
    provisional = FrameChain(use_crs, tuple(probe.crs_to_lla(mid)[0]), np.eye(4))
    model = GnssModel(
        rate_hz=gnss_rate_hz,
        rtk_h_std=(gnss_noise_m, gnss_noise_m),
        rtk_windows=0,
        dropouts=0,
        outlier_fraction=outlier_fraction,
        open_sky=True,
    )
    gnss = simulate_gnss(rng, provisional, stamps_ns, node_crs, model)
    fixes = gnss.fixes
    lla_ref = (float(fixes.lat[0]), float(fixes.lon[0]), float(fixes.alt[0]))
    enu = FrameChain(use_crs, lla_ref, np.eye(4))
    chain = FrameChain(
        use_crs, lla_ref, _map_frame(rng, enu.lla_to_enu(enu.crs_to_lla(node_crs[:1]))[0])
    )
    true_poses = poses_from_positions(rng, chain.crs_to_map(node_crs), tilt_std_deg=0.0)
    config = SimulationConfig(write_georef=write_georef)
    graph = _graph(rng, stamps_ns, true_poses, true_poses, chain, config)

    # Points -> nearest node within radius -> that node's span.
    spans = payload_spans(arc, payload_spacing)
    dist, nearest = cKDTree(xy_nodes).query(xyz[:, :2], distance_upper_bound=radius)
    keep = np.isfinite(dist)
    span_of_node = np.empty(len(xy_nodes), dtype=np.int64)
    for k, span in enumerate(spans):
        span_of_node[span.first : span.last + 1] = k
    point_index = np.flatnonzero(keep)
    point_span = span_of_node[nearest[keep]]
    order = np.argsort(point_span, kind="stable")
    point_index, point_span = point_index[order], point_span[order]
    cuts = np.searchsorted(point_span, np.arange(len(spans) + 1))
    payloads: list[PointCloud] = []
    per_payload_index: list[NDArray[np.int64]] = []
    for k, span in enumerate(spans):
        idx = point_index[cuts[k] : cuts[k + 1]]
        base = transform_points(invert_pose(true_poses[span.centre]), chain.crs_to_map(xyz[idx]))
        payloads.append(PointCloud(base, {"intensity": intensity[idx]}))
        per_payload_index.append(idx.astype(np.int64))

    from standgrid.mission.metadata import MissionMetadata

    metadata = MissionMetadata(
        name=name,
        date=date,
        time=dt.time(10, 0),
        place=place or _default_place(paths),
        robot=robot,
        unit=None,
        gnss=lla_ref,
        sensors=["lidar", "gnss", "imu"],
        tags=["simulated", "from-scan"],
        notes=f"cut from {', '.join(p.name for p in paths)} (CRS {use_crs}), seed {seed}",
        extra={"simulator": {"seed": int(seed), "source_crs": use_crs}},
    )
    with atomic_output(
        mission_dir, overwrite=overwrite, replaces=is_mission_folder, what="a mission folder"
    ) as tmp:
        tmp.mkdir()
        write_canonical_parts(
            tmp,
            metadata=metadata,
            graph=graph,
            stamps_ns=stamps_ns,
            true_poses=true_poses,
            spans=spans,
            payloads=payloads,
            fixes=fixes,
            rng=rng,
            imu_rate_hz=10.0,
        )
    with atomic_output(
        truth_dir, overwrite=overwrite, replaces=is_truth_folder, what="a simulator truth folder"
    ) as tmp:
        from standgrid.mission.poses_csv import PoseTable, write_poses_csv

        (tmp / "payload_points").mkdir(parents=True)
        for span, idx in zip(spans, per_payload_index, strict=True):
            stamp = Stamp.from_ns(int(stamps_ns[span.centre]))
            np.save(tmp / "payload_points" / stamp.filename("points", "npy"), xyz[idx])
            np.save(tmp / "payload_points" / stamp.filename("index", "npy"), idx)
        write_poses_csv(PoseTable.from_arrays(stamps_ns, true_poses), tmp / "true_poses.csv")
        write_gnss_truth(fixes.stamps_ns, gnss.true_xyz, gnss.outlier, tmp / "gnss_truth.csv")
        kept = xyz[point_index]
        write_truth_json(
            {
                "kind": "from_scan",
                "mission": name,
                "crs": use_crs,
                "crs_to_geodetic": chain.description,
                "chain": "CRS (x, y, h as ellipsoidal) -> EPSG:4979 -> EPSG:4978 -> ENU(lla_ref) "
                "-> T_map_enu",
                "lla_ref": list(lla_ref),
                "T_map_enu": chain.T_map_enu.tolist(),
                "seed": int(seed),
                "epoch": 1,
                "date": date.isoformat(),
                "bounds": [
                    float(kept[:, 0].min()),
                    float(kept[:, 1].min()),
                    float(kept[:, 0].max()),
                    float(kept[:, 1].max()),
                ],
                "sources": sources,
                "points_kept": len(point_index),
                "radius_m": radius,
                "payload_spacing_m": payload_spacing,
                "gnss_noise_m": gnss_noise_m,
                "outlier_fraction": outlier_fraction,
            },
            tmp / "truth.json",
        )
    return ScanMission(
        name=name,
        mission_dir=mission_dir,
        truth_dir=truth_dir,
        crs=use_crs,
        chain=chain,
        graph=graph,
        true_poses=true_poses,
        stamps_ns=stamps_ns,
        spans=spans,
        n_points=len(point_index),
        gnss=gnss,
    )
