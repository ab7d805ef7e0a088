"""What the index records about an ingested mission: its payloads, trajectory, GNSS fixes,
and its row of the ``missions`` layer (all geometry in the catalog CRS)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from standgrid.errors import CatalogError, GeoreferenceError

if TYPE_CHECKING:
    from standgrid.catalog.store import Catalog
    from standgrid.crs import CRSLike
    from standgrid.georeference.placement import Placement, ToCatalog
    from standgrid.mission.model import Mission
    from standgrid.mission.payload import Payload
    from standgrid.partition.schema import Schema


class PlacedMission(Protocol):
    """A mission on its way into the catalog, with its number and recipe into the CRS."""

    mission: Mission
    number: int
    to_catalog: ToCatalog | None


#: Payload ids are ``mission_number << 16 | payload index``: stable on re-ingest, no registry.
PAYLOAD_INDEX_BITS = 16


def payload_id(number: int, index: int, mission: Mission) -> int:
    """The id of the mission's ``index``-th cloud payload (``payload_id`` field and column)."""
    if index >= 1 << PAYLOAD_INDEX_BITS:
        raise CatalogError(
            f"more than {1 << PAYLOAD_INDEX_BITS} payloads in one mission", path=mission.path
        )
    return (number << PAYLOAD_INDEX_BITS) | index


def payload_row(
    mission: Mission, to_catalog: ToCatalog, ident: int, payload: Payload, epoch: str
) -> dict[str, Any]:
    """A ``payloads`` row: the pose point and heading (``point_count``,
    ``withheld_left_out`` and the footprint geometry are filled in once the points were
    read)."""
    import shapely

    from standgrid.export.gpkg import iso_time

    if to_catalog.fit is None:  # projected clouds: the centre of their box, no heading
        x, y, z = _projected_centre(mission, to_catalog, payload)
        heading = math.nan
    else:
        pose = mission.pose_of(payload)
        ends = to_catalog.projector.exact(np.array([pose[:3, 3], pose[:3, 3] + pose[:3, 0]]))
        x, y, z = ends[0]
        heading = math.degrees(math.atan2(ends[1, 1] - y, ends[1, 0] - x))
    return {
        "payload_id": ident,
        "mission": mission.name,
        "stamp_sec": payload.stamp.sec,
        "stamp_nsec": payload.stamp.nsec,
        "time": iso_time(payload.stamp.sec, payload.stamp.nsec),
        "node_id": payload.node_id,
        "point_count": 0,
        "withheld_left_out": 0,
        "x": float(x),
        "y": float(y),
        "z": float(z),
        "yaw": heading,
        "epoch": epoch,
        "geometry": shapely.Point(x, y),
    }


def _projected_centre(
    mission: Mission, to_catalog: ToCatalog, payload: Payload
) -> tuple[float, float, float]:
    """Centre of a projected cloud's bounding box, in the catalog CRS (LAS: from the header)."""
    from standgrid.clouds import read_cloud_header

    if payload.site is not None:
        site = np.asarray(payload.site, dtype=np.float64)[None, :]
        x, y, z = to_catalog.projected_points(site)[0]
        return float(x), float(y), float(z)
    header = read_cloud_header(payload.path)
    if header.bounds is not None:
        lo, hi = header.bounds
    else:
        xyz = mission.load_projected(payload).xyz
        lo = np.array([xyz[:, k].min() for k in range(3)])
        hi = np.array([xyz[:, k].max() for k in range(3)])
    centre = to_catalog.projected_points((0.5 * (np.asarray(lo) + np.asarray(hi)))[None, :])[0]
    return float(centre[0]), float(centre[1]), float(centre[2])


def trajectory_rows(mission: Mission, to_catalog: ToCatalog, epoch: str) -> list[dict[str, Any]]:
    """The ``trajectories`` row of a fitted mission with a graph of 2+ nodes, or of a plain
    scan with its trajectory (else none)."""
    import shapely

    if to_catalog.fit is None and mission.scan_path is not None and len(mission.scan_path) > 1:
        xyz = to_catalog.projected_points(mission.scan_path)  # a plain scan's trajectory
        return [
            {"mission": mission.name, "epoch": epoch, "geometry": shapely.LineString(xyz[:, :2])}
        ]
    if to_catalog.fit is None or mission.graph is None or len(mission.graph) < 2:
        return []
    xyz = to_catalog.projector.exact(mission.graph.positions)
    return [{"mission": mission.name, "epoch": epoch, "geometry": shapely.LineString(xyz[:, :2])}]


def gnss_rows(mission: Mission, placement: Placement, crs: CRSLike) -> Any:
    """One ``gnss_fixes`` row per fix (a frame): projected position, residuals, inlier flag."""
    import pandas as pd
    import shapely

    from standgrid.crs import CRS

    gnss, fit = mission.gnss, placement.fit
    if fit is None or gnss is None or len(gnss) == 0 or len(fit.fix_stamps_ns) == 0:
        return pd.DataFrame()
    if len(fit.fix_stamps_ns) != len(gnss) or not np.array_equal(fit.fix_stamps_ns, gnss.stamps_ns):
        raise GeoreferenceError(
            "the georeference fit does not list the mission's GNSS fixes in order",
            path=mission.path,
        )
    to_crs = CRS.of("EPSG:4979").transformer_to(crs)
    valid = np.isfinite(gnss.lat) & np.isfinite(gnss.lon)
    x, y = to_crs.transform(gnss.lon[valid], gnss.lat[valid])
    stamps = np.asarray(fit.fix_stamps_ns, dtype=np.int64)[valid]
    residuals = np.asarray(fit.residuals_m, dtype=np.float64)[valid]
    e, n, u = residuals[:, 0], residuals[:, 1], residuals[:, 2]
    status = np.asarray(fit.status_names, dtype=object)[valid]
    return pd.DataFrame(
        {
            "mission": mission.name,
            "stamp_sec": stamps // 1_000_000_000,
            "stamp_nsec": stamps % 1_000_000_000,
            "quality": np.asarray(gnss.quality)[valid].astype(int),
            "residual_e": e,
            "residual_n": n,
            "residual_u": u,
            "residual_h": [math.hypot(a, b) for a, b in zip(e.tolist(), n.tolist(), strict=True)],
            "inlier": np.asarray(fit.inliers, dtype=bool)[valid],
            "status": status,
            "geometry": shapely.points(np.asarray(x, float), np.asarray(y, float)),
        }
    )


def metadata_extra(mission: Mission) -> dict[str, Any]:
    """robot, place, unit and sensors of the mission's metadata (empty without)."""
    meta = mission.metadata
    if meta is None:
        return {"robot": "", "place": "", "unit": "", "sensors": []}
    return {
        "robot": meta.robot or "",
        "place": meta.place or "",
        "unit": meta.unit or "",
        "sensors": list(meta.sensors),
    }


def mission_row(
    mission: Mission,
    placement: Placement,
    number: int,
    epoch: str,
    date: str,
    catalog: Any,
    *,
    placement_offset_m: float = 0.0,
) -> dict[str, Any]:
    """The mission's row of the ``missions`` layer (``placement_offset_m``: how far the
    placement used may put a point from the mission's fresh fit, 0 when it is that fit)."""
    from standgrid.georeference.placement import finite_or_none

    fit = placement.fit
    meta = metadata_extra(mission)
    aligned = placement.alignment or {}
    return {
        "mission": mission.name,
        "number": number,
        "epoch": epoch,
        "date": date,
        "robot": meta["robot"],
        "place": meta["place"],
        "unit": meta["unit"],
        "sensors": ",".join(meta["sensors"]),
        "fit_method": "projected" if fit is None else fit.method,
        "rmse_m": None if fit is None else finite_or_none(fit.rmse_m),
        "n_used": 0 if fit is None else int(fit.n_used),
        "n_rejected": 0 if fit is None else int(fit.n_rejected),
        "placement_offset_m": float(placement_offset_m),
        # alignment (standgrid.alignment): DRMS 1-sigma, absolute and relative to the missions
        # it was registered with; null when not aligned
        "aligned": bool(aligned.get("aligned", False)),
        "registered_with": ",".join(aligned.get("registered_with", ())),
        "sigma_h_m": aligned.get("sigma_h_m"),
        "sigma_rel_m": aligned.get("sigma_rel_m"),
        "grid_fingerprint": catalog.fingerprint,
        "crs": catalog.crs,
    }


def epoch_sites(others: Any, rows: list[dict[str, Any]]) -> Any:
    """The epoch's payload rows: those of missions not re-ingested, then this run's."""
    import pandas as pd

    new = pd.DataFrame(rows, columns=["mission", "stamp_sec", "stamp_nsec", "x", "y", "geometry"])
    if not len(others):
        return new
    return pd.concat([pd.DataFrame(others[list(new.columns)]), new], ignore_index=True)


def payload_rows(
    group: Sequence[PlacedMission], epoch: str
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One ``payloads`` row and one payload task's arguments (but the epoch's lattice origin
    and schema) per cloud payload of the group's missions."""
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.stamps import unix_ns_to_adjusted_gps_time

    rows, sources = [], []
    for ingest in group:
        mission, to_catalog = ingest.mission, ingest.to_catalog
        assert to_catalog is not None
        for k, payload in enumerate(cloud_payloads(mission)):
            ident = payload_id(ingest.number, k, mission)
            row = payload_row(mission, to_catalog, ident, payload, epoch)
            fitted = to_catalog.fit is not None
            sources.append(
                {
                    "path": payload.path,
                    "span": payload.span,
                    "window": payload.window,
                    "time_offset": payload.time_offset,
                    "time_wrap": payload.time_wrap,
                    "frame": payload.frame,
                    "file_to_base": mission.file_to_base(payload),
                    "pose": mission.pose_of(payload) if fitted else None,
                    "to_catalog": to_catalog,
                    "gps_time": float(unix_ns_to_adjusted_gps_time(payload.stamp.ns)),
                    "point_source_id": ingest.number,
                    "payload_id": ident,
                    "fallback_footprint": row["geometry"],
                }
            )
            rows.append(row)
    return rows, sources


def tiling_schema(catalog: Catalog, previous: list[str], group: Sequence[PlacedMission]) -> Schema:
    """The epoch's field schema: from its first existing tile and each mission's first payload
    (its fields as the tiles store them: :func:`~standgrid.partition.chunks.source_fields`)."""
    from standgrid.export.las import read_tile
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.partition.chunks import rank_as_scan_angle, source_fields
    from standgrid.partition.schema import epoch_schema
    from standgrid.pointcloud import PointCloud

    samples = []
    if previous:  # tiles written before scan_angle_rank became scan_angle: as they are now
        tile_path = catalog.path(previous[0])
        tile = read_tile(tile_path)
        samples.append(PointCloud(tile.xyz, rank_as_scan_angle(tile.fields, tile_path)))
    for ingest in group:
        payloads = cloud_payloads(ingest.mission)
        if payloads:
            first = payloads[0]
            mission = ingest.mission
            load = mission.load_projected if first.frame == "utm" else mission.load_base
            samples.append(source_fields(load(first), first.path)[0])
    return epoch_schema(samples, catalog.root)
