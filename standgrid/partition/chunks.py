"""Payloads as chunks for the partition engine: read, into the catalog CRS, snapped, stamped.

:func:`payload_chunk` is a pure function of a :class:`PayloadTask` (plain picklable data), so
an executor may run it in this process or on a dask worker: the result is the same.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import MissionConsistencyError
from standgrid.las_fields import (
    LAS_CHECKED_FIELDS,
    check_finite_gps_time,
    las_dimension_values,
    scan_angle_from_rank,
)
from standgrid.partition.lattice import snap_to_storage
from standgrid.partition.schema import SOURCE_POINT_SOURCE_ID, WITHHELD, Schema, conform
from standgrid.pointcloud import PointCloud

if TYPE_CHECKING:
    from standgrid.georeference.placement import ToCatalog

#: Footprint hulls are taken over at most this many points of a payload (display geometry).
FOOTPRINT_POINTS = 20_000


@dataclass(frozen=True)
class PayloadTask:
    """One payload to read and bring into the catalog CRS."""

    path: Path
    #: ``"base"``/``"map"`` (a node-relative cloud) or ``"utm"`` (already projected).
    frame: str
    #: T_base_file for ``"map"``-frame files, else None.
    file_to_base: NDArray[np.float64] | None
    #: T_map_base of the payload's node (None for projected clouds).
    pose: NDArray[np.float64] | None
    to_catalog: ToCatalog
    lattice_origin: tuple[float, float]
    schema: Schema
    #: Per-point values the tiler sets: GPS time of the payload stamp (kept when the cloud
    #: has its own), the mission number and the payload id.
    gps_time: float
    point_source_id: int
    payload_id: int
    #: The footprint when the payload has fewer than 3 points (its pose point).
    fallback_footprint: Any = None
    #: A part of a plain scan's file: points ``[start, stop)``, GPS times in ``[lo, hi)``.
    span: tuple[int, int] | None = None
    window: tuple[float, float] | None = None
    #: Seconds added to the file's own GPS times (week seconds -> adjusted standard).
    time_offset: float = 0.0
    #: File times below this take a week (604,800 s) more: after the week's rollover.
    time_wrap: float | None = None


@dataclass(frozen=True)
class PayloadChunk:
    """A payload's points in the catalog CRS with the epoch's schema, and its footprint."""

    cloud: PointCloud
    footprint: Any
    #: Points the source file flags ``withheld`` (deleted, LAS 1.4), left out of the tiles.
    withheld: int = 0


def source_fields(cloud: PointCloud, source: Path) -> tuple[PointCloud, int]:
    """A payload's standard LAS fields as the tiles store them, and how many points were
    left out. Only fields of those names cost a pass over the values:

    - ``withheld``: LAS 1.4 says a withheld point "should be considered deleted"; those
      points are left out (counted; the tiles' own withheld flag marks buffer copies).
    - ``scan_angle_rank`` (LAS point formats 0-5, degrees) without a ``scan_angle``:
      stored as the LAS 1.4 ``scan_angle`` (0.006 degree units, off by at most 0.003
      degrees; :func:`~standgrid.las_fields.scan_angle_from_rank`). A ``scan_angle``
      (formats 6-10, or a PLY/PCD field) is taken as given, in 0.006 degree units.
    - ``point_source_id`` (a flight line): the tiler sets the mission number there, so the
      source's values are kept as ``source_point_source_id`` (uint16; every LAS source has
      the dimension, so every payload of a LAS mission carries it, 0 or not). A source that
      has both (a catalog's tile tiled again) keeps its ``source_point_source_id``: its
      ``point_source_id`` is the other catalog's mission number.
    """
    fields = cloud.fields
    if not {WITHHELD, "scan_angle_rank", "point_source_id"} & fields.keys():
        return cloud, 0
    withheld = 0
    if WITHHELD in fields:
        flags = las_dimension_values(WITHHELD, fields[WITHHELD], source).astype(bool)
        withheld = int(np.count_nonzero(flags))
        if withheld:
            cloud = cloud.select(~flags)
    fields = rank_as_scan_angle({k: v for k, v in cloud.fields.items() if k != WITHHELD}, source)
    if "point_source_id" in fields:
        if SOURCE_POINT_SOURCE_ID in fields:
            # a tile of a catalog tiled again: its point_source_id is that catalog's mission
            # number, its source_point_source_id the first source's flight line: kept
            las_dimension_values("point_source_id", fields.pop("point_source_id"), source)
            return PointCloud(cloud.xyz, fields), withheld
        ids = las_dimension_values("point_source_id", fields.pop("point_source_id"), source)
        fields[SOURCE_POINT_SOURCE_ID] = ids.astype(np.uint16, copy=False)
    return PointCloud(cloud.xyz, fields), withheld


def payload_chunk(task: PayloadTask) -> PayloadChunk:
    """Read one payload and bring it into the catalog CRS, snapped to the 1 mm lattice."""
    from standgrid.clouds import read_cloud
    from standgrid.clouds.las import read_las_part

    if task.span is not None:
        raw = read_las_part(task.path, task.span, task.window)
    else:
        raw = read_cloud(task.path)
    cloud, withheld = source_fields(raw, task.path)
    check_las_fields(cloud, task.path)
    if task.to_catalog.fit is None:  # already in a projected CRS
        xyz = task.to_catalog.projected_points(cloud.xyz)
    elif task.frame == "utm":
        raise MissionConsistencyError(
            "a UTM-frame cloud cannot be brought to the base frame without a georeference",
            path=task.path,
        )
    else:
        if task.file_to_base is not None:
            cloud = cloud.transformed(task.file_to_base)
        assert task.pose is not None
        # the points just read are this function's own: projected in place when they can be
        xyz = task.to_catalog.base_points(
            cloud.xyz, task.pose, out=cloud.xyz if _writable_float64(cloud.xyz) else None
        )
    # the projected points are this function's own (never the caller's): snapped in place
    own = _writable_float64(xyz) and (xyz is not cloud.xyz or task.to_catalog.fit is not None)
    xyz = snap_to_storage(xyz, task.lattice_origin, out=xyz if own else None)
    n = len(xyz)
    fields = dict(cloud.fields)
    if task.time_offset and "gps_time" in fields:
        t = np.asarray(fields["gps_time"], dtype=np.float64)
        shifted = t + task.time_offset
        if task.time_wrap is not None:
            shifted += np.where(t < task.time_wrap, 604_800.0, 0.0)
        fields["gps_time"] = shifted
    if "gps_time" not in fields:  # per-point times of the source win over the payload stamp
        fields["gps_time"] = np.full(n, task.gps_time)
    fields["point_source_id"] = np.full(n, task.point_source_id, dtype=np.uint16)
    fields["payload_id"] = np.full(n, task.payload_id, dtype=np.uint32)
    chunk = conform(PointCloud(xyz, fields), task.schema, task.path)
    return PayloadChunk(chunk, footprint(chunk.xyz, task.fallback_footprint), withheld)


def rank_as_scan_angle(fields: Mapping[str, NDArray[Any]], source: Path) -> dict[str, NDArray[Any]]:
    """``fields`` with a ``scan_angle_rank`` (degrees) and no ``scan_angle`` turned into the
    LAS 1.4 ``scan_angle`` (:func:`~standgrid.las_fields.scan_angle_from_rank`); also for the
    points of tiles written before that rule, which kept the rank as an extra dimension."""
    converted = dict(fields)
    if "scan_angle_rank" in converted and "scan_angle" not in converted:
        rank = converted.pop("scan_angle_rank")
        converted["scan_angle"] = scan_angle_from_rank(rank, source)
    return converted


def check_las_fields(cloud: PointCloud, source: Path) -> None:
    """Refuse (naming ``source``) a payload field bound for a standard LAS dimension whose
    values the tiles cannot store exactly (:mod:`standgrid.las_fields`), and non-finite GPS
    times. A field whose dtype cannot hold a bad value (``uint8`` classification) is not
    looked at; the others cost a min/max pass."""
    replaced = {WITHHELD, "point_source_id"}  # set by the partition engine / the tiler
    colours = {"red", "green", "blue"}
    if not colours <= cloud.fields.keys():  # tiles keep lone colour fields as extra bytes
        replaced |= colours
    for name in (LAS_CHECKED_FIELDS - replaced) & cloud.fields.keys():
        las_dimension_values(name, cloud.fields[name], source)
    times = cloud.fields.get("gps_time")
    if times is not None and len(times) and times.dtype.kind == "f":
        check_finite_gps_time(float(times.min()), float(times.max()), [times], source)


def _writable_float64(xyz: NDArray[Any]) -> bool:
    return xyz.dtype == np.float64 and xyz.flags.c_contiguous and xyz.flags.writeable


def footprint(xyz: NDArray[np.float64], fallback: Any) -> Any:
    """The convex hull of a payload's projected points (a polygon; ``fallback`` if < 3)."""
    import shapely
    from scipy.spatial import ConvexHull, QhullError

    stride = max(1, len(xyz) // FOOTPRINT_POINTS)
    xy = xyz[::stride, :2]
    if len(xy) < 3:
        return fallback
    try:
        hull = ConvexHull(xy)
    except QhullError:  # collinear points
        return shapely.MultiPoint(xy[:: max(1, len(xy) // 1000)]).convex_hull
    return shapely.Polygon(xy[hull.vertices])
