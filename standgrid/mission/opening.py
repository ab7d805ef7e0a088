"""Opening a mission folder: its graph, metadata, payloads (with their clouds' CRS), sensor logs.

See :func:`open_mission`.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from standgrid.clouds import read_cloud_header
from standgrid.crs import CRS
from standgrid.errors import (
    DuplicateStampError,
    MetadataError,
    MissionConsistencyError,
    MissionNotFoundError,
    OrphanPayloadError,
    PointCloudFormatError,
    StandgridError,
)
from standgrid.geometry import Matrix4
from standgrid.mission.layout import CloudFolder, MissionLayout, discover_layout, layer_name
from standgrid.mission.metadata import MissionMetadata, metadata_from_folder_name, read_metadata
from standgrid.mission.model import DEFAULT_CACHE_POINTS, CloudCache, Mission
from standgrid.mission.payload import Payload, PayloadKind, _attach, _vertices_by_stamp
from standgrid.mission.posegraph import PoseGraph
from standgrid.mission.poses_csv import read_poses_csv
from standgrid.mission.sensors import (
    GnssFixes,
    ImageRef,
    ImuSamples,
    concat_gnss,
    concat_imu,
    read_gnss,
    read_imu,
)
from standgrid.stamps import Stamp


def _report(exc: StandgridError, strict: bool, problems: list[str]) -> None:
    if strict:
        raise exc
    problems.append(str(exc))


def _read_graph(layout: MissionLayout) -> PoseGraph | None:
    if layout.graph is not None:
        return read_pose_graph_file(layout.graph)
    if layout.poses_csv is not None:
        graph = read_poses_csv(layout.poses_csv).to_pose_graph()
        if graph.source is None:
            graph.source = layout.poses_csv
        return graph
    return None


def read_pose_graph_file(path: Path) -> PoseGraph:
    from standgrid.mission.posegraph import read_pose_graph

    graph = read_pose_graph(path)
    if graph.source is None:
        graph.source = path
    return graph


def _read_metadata(
    layout: MissionLayout, strict: bool, problems: list[str]
) -> MissionMetadata | None:
    if layout.metadata is not None:
        try:
            return read_metadata(layout.metadata)
        except MetadataError as exc:
            _report(exc, strict, problems)
            return None
    try:
        return metadata_from_folder_name(layout.root)
    except StandgridError:
        return None  # an unconventional folder name simply carries no metadata


def _cloud_payloads(
    folder: CloudFolder | None,
    kind: PayloadKind,
    layers: dict[Stamp, dict[str, Path]],
) -> list[Payload]:
    if folder is None:
        return []
    return [
        Payload(f.stamp, None, f.path, folder.frame, dict(layers.get(f.stamp, {})), kind)
        for f in folder.files
    ]


def _las_crs(path: Path) -> CRS | None:
    """The CRS a LAS/LAZ header carries, or None."""
    import laspy

    from standgrid.clouds.las_header import check_las_header

    check_las_header(path)
    try:
        with laspy.open(path) as reader:
            found = reader.header.parse_crs()
    except (laspy.errors.LaspyException, ValueError, OSError, EOFError) as exc:
        raise PointCloudFormatError(f"unreadable LAS/LAZ header ({exc})", path=path) from exc
    return None if found is None else CRS.of(found)


def _projected_las(items: list[Payload]) -> list[Payload]:
    """LAS/LAZ payloads whose header carries a projected CRS are in that CRS (frame ``utm``),
    whatever their folder; a geographic or geocentric CRS is refused (x/y must be metres)."""
    out = []
    for p in items:
        if p.path.suffix.lower() in (".las", ".laz"):
            crs = _las_crs(p.path)
            if crs is not None:
                if not crs.is_projected:
                    raise MissionConsistencyError(
                        f"the cloud's CRS {crs.name!r} is not projected; standgrid reads "
                        "clouds in a projected CRS (metres) or in the robot/map frame",
                        path=p.path,
                    )
                p = replace(p, frame="utm", crs=crs)
        out.append(p)
    return out


def _with_derived_maps(
    payloads: list[Payload], layout: MissionLayout, strict: bool, problems: list[str]
) -> list[Payload]:
    """Each payload with its elevation and volumetric map of the same stamp (a map matching
    no payload is reported as an orphan; two maps of one stamp as duplicates)."""
    if not (layout.elevation_maps or layout.volumetric_maps):
        return payloads
    index = {p.stamp: k for k, p in enumerate(payloads)}
    out = list(payloads)
    for files, key in (
        (layout.elevation_maps, "elevation_map"),
        (layout.volumetric_maps, "volumetric_map"),
    ):
        seen: dict[Stamp, Path] = {}
        for f in files:
            if f.stamp in seen:
                msg = f"two maps share the stamp {f.stamp}: {seen[f.stamp].name}, {f.path.name}"
                _report(DuplicateStampError(msg, path=f.path.parent), strict, problems)
                continue
            seen[f.stamp] = f.path
            k = index.get(f.stamp)
            if k is None:
                msg = f"map matches no payload stamp {f.stamp}"
                _report(OrphanPayloadError(msg, path=f.path), strict, problems)
                continue
            if key == "elevation_map":
                out[k] = replace(out[k], elevation_map=f.path)
            else:
                out[k] = replace(out[k], volumetric_map=f.path)
    return out


def _check_duplicates(items: list[Payload], strict: bool, problems: list[str]) -> list[Payload]:
    """Two files of one folder with the same stamp (e.g. ``.pcd`` and ``.ply``)."""
    seen: dict[Stamp, Payload] = {}
    for p in items:
        if p.stamp in seen:
            exc = DuplicateStampError(
                f"two files share the stamp {p.stamp}: {seen[p.stamp].path.name}, {p.path.name}",
                path=p.path.parent,
            )
            _report(exc, strict, problems)
        else:
            seen[p.stamp] = p
    return items


def _report_unrecognised(layout: MissionLayout, strict: bool, problems: list[str]) -> None:
    """Files in cloud/sensor folders whose names carry no stamp are never read: a strict
    open raises on the first, a non-strict open lists each in ``problems``."""
    msg = "file name carries no stamp (<prefix>_<sec>_<nsec>.<ext>); not read"
    if strict and layout.unrecognised:
        raise MissionConsistencyError(
            f"{msg} (open with strict=False to skip such files)", path=layout.unrecognised[0]
        )
    problems += [f"{extra}: {msg}" for extra in layout.unrecognised]


def open_mission(
    path: str | Path,
    *,
    strict: bool = True,
    cache_points: int = DEFAULT_CACHE_POINTS,
) -> Mission:
    """Open a mission folder of any known layout.

    ``strict`` raises on the first inconsistency (:class:`OrphanPayloadError`,
    :class:`DuplicateStampError`, unreadable metadata, a file in a cloud or sensor folder
    whose name carries no stamp: :class:`MissionConsistencyError`); otherwise each is
    reported in ``Mission.problems`` and the data is kept (orphan payloads with
    ``node_id=None``). Graph files present but not used (a less preferred name) are never an
    error: they are listed in ``Mission.warnings`` (and, non-strict, in ``problems`` too).
    A missing folder, or one without any mission file, raises :class:`MissionNotFoundError`.
    """
    layout = discover_layout(path)
    if not layout.is_mission:
        raise MissionNotFoundError(
            "no mission files (pose graph, pose CSV, metadata.yaml, cloud or sensor folders)",
            path=layout.root,
        )
    problems: list[str] = []
    metadata = _read_metadata(layout, strict, problems)
    graph = _read_graph(layout)

    dups = graph.duplicate_stamps() if graph is not None else {}
    for stamp, ids in dups.items():
        exc = DuplicateStampError(
            f"vertices {ids} share the stamp {stamp}", path=graph.source if graph else None
        )
        _report(exc, strict, problems)
    by_stamp = _vertices_by_stamp(graph)

    layers: dict[Stamp, dict[str, Path]] = {}
    for folder in layout.layer_folders:
        for f in folder.files:
            layers.setdefault(f.stamp, {})[layer_name(folder)] = f.path

    source = layout.payload_source or next(
        (f for f in layout.payload_folders if f.frame == "utm"), None
    )
    payloads = _attach(
        _check_duplicates(
            _projected_las(_cloud_payloads(source, "point_cloud", layers)), strict, problems
        ),
        by_stamp,
        graph,
        strict,
        problems,
    )
    scans = _attach(
        _check_duplicates(_cloud_payloads(layout.scans, "scan", layers), strict, problems),
        by_stamp,
        graph,
        strict,
        problems,
    )
    payloads = _with_derived_maps(payloads, layout, strict, problems)
    attached = {p.stamp for p in payloads} | {p.stamp for p in scans}
    for folder in layout.layer_folders:
        for f in folder.files:
            if f.stamp not in attached:
                msg = f"layer cloud matches no payload or scan stamp {f.stamp}"
                _report(OrphanPayloadError(msg, path=f.path), strict, problems)

    source_poses: dict[Path, Matrix4] = {}
    if source is not None and source.frame == "map":
        for p in payloads:
            vertex = by_stamp.get(p.stamp)
            if vertex is not None:
                source_poses[p.path] = vertex.pose
            else:
                header = read_cloud_header(p.path)
                source_poses[p.path] = np.eye(4) if header.viewpoint is None else header.viewpoint

    gnss: GnssFixes | None = None
    if layout.gnss_log is not None:
        gnss = read_gnss(layout.gnss_log)
    elif layout.gnss_payloads:
        gnss = concat_gnss([read_gnss(f.path) for f in layout.gnss_payloads])
    imu: ImuSamples | None = None
    if layout.imu_payloads:
        imu = concat_imu([read_imu(f.path) for f in layout.imu_payloads])
    images = [
        ImageRef(cam, f.stamp, f.path) for cam, files in layout.cameras.items() for f in files
    ]
    images.sort(key=lambda i: (i.stamp, i.camera))
    _report_unrecognised(layout, strict, problems)
    warnings = [
        f"{g}: graph file present but not used (read {layout.graph})" for g in layout.other_graphs
    ]
    if not strict:
        problems += warnings

    return Mission(
        layout=layout,
        metadata=metadata,
        graph=graph,
        payloads=payloads,
        scans=scans,
        gnss=gnss,
        imu=imu,
        images=images,
        problems=problems,
        strict=strict,
        source_poses=source_poses,
        cache=CloudCache(cache_points),
        warnings=warnings,
    )
