"""Plain scans: a georeferenced LAS/LAZ/COPC file, a folder of such tiles, or a VPC, as a mission.

A forest GIS analyst's data is a scan a commercial handheld, backpack, terrestrial or
airborne scanner wrote, already in a projected CRS. :func:`open_scan` makes it a
:class:`~standgrid.mission.model.Mission` of projected payloads, so it tiles, enriches and
serves like a robot's mission:

- the mission is named after the file (``las_chablais3.laz`` -> ``las_chablais3``) or the
  folder; a folder of tiles (or a VPC's files) is one mission;
- its CRS is the files' own (one for all; ``crs`` only where the files name none);
- its date is ``date``, else the points' GPS time when the header flags it adjusted
  standard GPS time (told from the values: LAS 1.0/1.1 cannot flag it), else the header's
  creation date; GPS week seconds need ``date`` and are made adjusted standard GPS time
  (what the tiles store and flag) in the week that puts them nearest to it, a time after the
  week's rollover a week later (a warning says so);
- payloads are parts of the files (at most ``part_points`` points each, read with a seek: a
  big file streams through the partition engine part by part); every point is in exactly
  one part, so tiles of a folder conserve their edge points exactly once;
- with a ``trajectory`` (a time-stamped CSV/TXT of positions, as SLAM scanners export),
  each payload is instead the points of one trajectory segment (about ``segment_m`` of
  travel) by GPS time, placed at the trajectory, so footprints and Voronoi cells follow
  the scanner's path. Points before the trajectory's start (after its end) go to the first
  (last) segment.
"""

from __future__ import annotations

import datetime as dt
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.crs import CRS
from standgrid.errors import (
    CRSError,
    MetadataError,
    MissionNotFoundError,
    PointCloudFormatError,
)
from standgrid.mission.scan_trajectory import _trajectory_parts
from standgrid.stamps import NS_PER_S, Stamp

#: Suffixes of a plain scan file (``.copc.laz`` ends in ``.laz``) and of a virtual point cloud.
SCAN_SUFFIXES = (".las", ".laz")
VPC_SUFFIX = ".vpc"
#: Most points in one payload of a plain scan (~40 MB of points and fields as they are
#: converted): fixed, so a scan's payloads (ids, source digests) do not depend on the memory
#: of the machine; the tiler reads ahead by bytes within its budget.
PART_POINTS = 250_000
#: Metres of travel per trajectory segment (a robot mission's payload spacing).
SEGMENT_M = 20.0


@dataclass(frozen=True)
class ScanOptions:
    """How to read plain scans: ``crs`` for files that name none, the ``date`` (else from the
    header), an optional ``trajectory`` file, and the payload sizes."""

    crs: str = "auto"
    date: dt.date | None = None
    trajectory: Path | None = None
    part_points: int = PART_POINTS
    segment_m: float = SEGMENT_M


def scan_name(path: Path) -> str:
    """The mission name of a scan: the file name without ``.copc.laz``/``.laz``/``.las``/
    ``.vpc``, or the folder's name."""
    name = path.name
    for suffix in (".copc.laz", ".laz", ".las", VPC_SUFFIX):
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return name


def _las_files(folder: Path) -> list[Path]:
    return sorted(
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in SCAN_SUFFIXES
    )


def is_scan(path: str | Path) -> bool:
    """Whether ``path`` is a plain scan: a LAS/LAZ/COPC file, a VPC, or a folder of LAS/LAZ
    files that holds no mission (no pose graph, metadata, payload or sensor folder)."""
    from standgrid.mission.layout import discover_layout

    src = Path(path)
    if src.is_file():
        return src.suffix.lower() in (*SCAN_SUFFIXES, VPC_SUFFIX)
    if not src.is_dir() or not _las_files(src):
        return False
    return not discover_layout(src).is_mission


def scan_files(path: Path) -> list[Path]:
    """The LAS/LAZ files of a scan: the file, the folder's files, or the VPC's assets."""
    if path.is_dir():
        files = _las_files(path)
    elif path.suffix.lower() == VPC_SUFFIX:
        files = _vpc_files(path)
    else:
        files = [path]
    if not files:
        raise MissionNotFoundError("no LAS/LAZ file in the scan", path=path)
    for f in files:
        if not f.is_file():
            raise MissionNotFoundError("a file of the scan is missing", path=f)
    return files


def _vpc_files(path: Path) -> list[Path]:
    """The point-cloud assets of a virtual point cloud (a STAC ItemCollection, as PDAL and
    QGIS write it), relative hrefs taken from the VPC's folder."""
    try:
        if path.stat().st_size > 64 * 1024 * 1024:
            raise MetadataError("a VPC of more than 64 MB", path=path)
        doc = json.loads(path.read_text(encoding="utf-8"))
        hrefs = []
        for number, feature in enumerate(doc["features"]):
            # the data asset of each feature; overviews (roles ["overview"], as PDAL wrench
            # and QGIS write them) thin the same points again and are never read
            data = [
                asset["href"]
                for key, asset in feature["assets"].items()
                if "overview" not in (asset.get("roles") or [])
                and (
                    "data" in (asset.get("roles") or []) or key == "data" or not asset.get("roles")
                )
                and str(asset.get("href", "")).lower().endswith(SCAN_SUFFIXES)
            ]
            if len(data) != 1:
                raise MetadataError(
                    f"feature {number} has {len(data)} point-cloud data assets (one expected)",
                    path=path,
                )
            hrefs.append(data[0])
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise MetadataError(
            f"not a virtual point cloud (STAC ItemCollection): {exc}", path=path
        ) from exc
    files = []
    for href in hrefs:
        if re.match(r"^[a-z][a-z0-9+.-]*://", href, re.I):
            raise MetadataError(f"asset {href!r}: only files beside the VPC are read", path=path)
        files.append((path.parent / href).resolve())
    return list(dict.fromkeys(files))


@dataclass(frozen=True)
class _FileFacts:
    path: Path
    points: int
    crs: str | None
    gps_standard: bool
    has_time: bool
    created: dt.date | None
    box: tuple[NDArray[np.float64], NDArray[np.float64]]
    #: The median GPS time of the first thousand points (None without times).
    first_time: float | None


def _facts(path: Path) -> _FileFacts:
    import laspy

    from standgrid.clouds.las import check_las_size

    count = check_las_size(path)
    try:
        with laspy.open(path) as reader:
            header = reader.header
            crs = header.parse_crs()
            created = header.creation_date
            standard = header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
            has_time = "gps_time" in header.point_format.dimension_names
            box = (np.asarray(header.mins, np.float64), np.asarray(header.maxs, np.float64))
            first = None
            if has_time and count:
                t = np.asarray(reader.read_points(min(1000, count))["gps_time"], np.float64)
                t = t[np.isfinite(t) & (t != 0)]
                first = float(np.median(t)) if len(t) else None
    except Exception as exc:  # laspy, pyproj and OS errors alike
        raise PointCloudFormatError(f"unreadable LAS/LAZ header ({exc})", path=path) from exc
    if created is not None and created.year < 1990:
        created = None
    return _FileFacts(
        path,
        count,
        None if crs is None else CRS.of(crs).text,
        bool(standard),
        has_time,
        created,
        box,
        first,
    )


def adjusted_gps_to_date(seconds: float) -> dt.date:
    """The UTC date of an adjusted standard GPS time (GPS seconds - 1e9), leap seconds
    counted."""
    from standgrid.stamps import adjusted_gps_time_to_unix

    return dt.datetime.fromtimestamp(adjusted_gps_time_to_unix(seconds), dt.UTC).date()


def week_start(day: dt.date, seconds_of_week: float) -> float:
    """The adjusted standard GPS time (GPS seconds - 1e9) of the start of the GPS week that
    puts ``seconds_of_week`` nearest to noon UTC of ``day`` (leap seconds counted): week
    seconds + this = adjusted time, right when ``day`` is within 3.5 days of the scan."""
    from standgrid.stamps import unix_ns_to_adjusted_gps_time

    noon = int(dt.datetime(day.year, day.month, day.day, 12, tzinfo=dt.UTC).timestamp())
    gps = float(unix_ns_to_adjusted_gps_time(noon * NS_PER_S)) + 1e9
    return round((gps - seconds_of_week) / 604_800) * 604_800 - 1e9


#: Seconds in a GPS week: GPS week seconds lie in [0, WEEK_S).
WEEK_S = 604_800.0


def _time_kind(facts: _FileFacts) -> tuple[str | None, float | None]:
    """What a file's GPS times are, from their values (the header's flag is not trusted:
    LAS 1.0/1.1 cannot say, writers forget it): ``"week"`` seconds when the first times lie
    within one week, else ``"standard"`` (adjusted standard GPS time); None without times.
    Also the first times' median."""
    first = facts.first_time
    if first is None:
        return None, None
    return ("week" if 0.0 <= first < WEEK_S else "standard"), first


def _week_offset(kind: str | None, first: float | None, day: dt.date) -> tuple[float, float | None]:
    """``(offset, wrap_below)`` making a file's week seconds adjusted standard GPS time: the
    week that puts its first times nearest to ``day``; a time below ``wrap_below`` came after
    the week's rollover (Sunday 0h GPS) and takes a week more."""
    if kind != "week" or first is None:
        return 0.0, None
    return week_start(day, first), first - WEEK_S / 2


def _date(
    facts: list[_FileFacts],
    kinds: list[tuple[str | None, float | None]],
    options: ScanOptions,
    path: Path,
) -> tuple[dt.date, str]:
    if options.date is not None:
        return options.date, "--date"
    for kind, first in kinds:
        if kind == "standard" and first is not None:
            day = adjusted_gps_to_date(first)
            if 1990 <= day.year <= 2100:
                return day, "GPS time"
    if any(kind == "week" for kind, _ in kinds):
        raise MetadataError(
            "the scan's GPS times are week seconds: give its date (option scan_date) "
            "to place them in their week (a header's creation date is often days "
            "later)",
            path=path,
            option="scan_date",
        )
    if facts[0].created is not None:
        return facts[0].created, "header creation date"
    raise MetadataError(
        "the scan's header gives no date (no adjusted standard GPS time, no creation date): "
        "give it (option scan_date)",
        path=path,
        option="scan_date",
    )


def _crs(facts: list[_FileFacts], options: ScanOptions, path: Path) -> str | None:
    """The files' one CRS; None when they name none and ``options.crs`` is given (the
    placement resolves and checks it); an error when neither says."""
    own = {f.crs for f in facts if f.crs is not None}
    if len(own) > 1:
        raise CRSError(f"the scan's files are in several CRSs: {sorted(own)}", path=path)
    if own:
        if any(f.crs is None for f in facts):
            missing = next(f.path for f in facts if f.crs is None)
            raise CRSError(f"names no CRS while the others are in {own.pop()}", path=missing)
        return own.pop()
    if options.crs in ("auto", "", None):
        raise CRSError(
            "the scan names no CRS (no WKT or GeoTIFF VLR): give it (option crs, EPSG:XXXX)",
            path=path,
            option="crs",
        )
    return None


def scan_summary(path: str | Path) -> dict[str, Any]:
    """What ``standgrid info`` says of a plain scan, from its headers (one read of the first
    points for a GPS-time date): files, points, CRS, date and where it would come from,
    extent; what tiling it would still need (``needs``)."""
    src = Path(path).absolute()
    facts = [_facts(f) for f in scan_files(src)]
    needs = []
    crs: str | None = None
    date: dict[str, str] | None = None
    try:
        crs = _crs(facts, ScanOptions(), src)
    except CRSError as exc:
        needs.append(exc.message)
    kinds = [_time_kind(f) for f in facts]
    try:
        day, source = _date(facts, kinds, ScanOptions(), src)
        date = {"date": day.isoformat(), "from": source}
    except MetadataError as exc:
        needs.append(exc.message)
    lo = np.min([f.box[0] for f in facts], axis=0)
    hi = np.max([f.box[1] for f in facts], axis=0)
    return {
        "name": scan_name(src),
        "path": str(src),
        "kind": "plain scan",
        "files": [{"file": f.path.name, "points": f.points, "crs": f.crs} for f in facts],
        "points": sum(f.points for f in facts),
        "crs": crs,
        "date": date,
        "gps_time": "none"
        if not any(k for k, _ in kinds)
        else ("week seconds" if any(k == "week" for k, _ in kinds) else "adjusted standard"),
        "extent_crs": {"min": lo.tolist(), "max": hi.tolist()},
        "needs": needs,
    }


def open_scan(path: str | Path, options: ScanOptions = ScanOptions()) -> Any:
    """A plain scan (file, folder of tiles, VPC) as a mission of projected payloads (module
    doc). Raises a typed error naming the file for anything it cannot use."""
    from standgrid.mission.layout import MissionLayout
    from standgrid.mission.metadata import MissionMetadata
    from standgrid.mission.model import CloudCache, Mission
    from standgrid.mission.payload import Payload

    src = Path(path).absolute()
    if not src.exists():
        raise MissionNotFoundError("scan not found", path=src)
    if options.part_points < 1:
        raise ValueError("part_points must be >= 1")
    facts = [_facts(f) for f in scan_files(src)]
    crs = _crs(facts, options, src)
    kinds = [_time_kind(f) for f in facts]
    day, date_source = _date(facts, kinds, options, src)
    name = scan_name(src)
    base = int(dt.datetime(day.year, day.month, day.day, tzinfo=dt.UTC).timestamp())
    parts: list[tuple[Path, tuple[int, int] | None, Any, Any]] = []
    path_xyz = None
    if options.trajectory is not None:
        parts, path_xyz = _trajectory_parts(facts, options, src)
    else:
        for f in facts:
            centre = tuple(float(v) for v in 0.5 * (f.box[0] + f.box[1]))
            if f.points <= options.part_points:
                parts.append((f.path, None, None, centre))
                continue
            for start in range(0, f.points, options.part_points):
                stop = min(start + options.part_points, f.points)
                parts.append((f.path, (start, stop), None, centre))
    offsets = {f.path: _week_offset(*kind, day) for f, kind in zip(facts, kinds, strict=True)}
    crs_value = None if crs is None else CRS.of(crs)
    payloads = [
        Payload(
            Stamp.from_ns(base * NS_PER_S + k),
            None,
            file,
            "utm",
            {},
            "point_cloud",
            crs=crs_value,
            span=span,
            window=window,
            site=site,
            time_offset=offsets[file][0],
            time_wrap=offsets[file][1],
        )
        for k, (file, span, window, site) in enumerate(parts)
    ]
    warnings = []
    for f, (kind, _) in zip(facts, kinds, strict=True):
        if kind is not None and (kind == "standard") != f.gps_standard:
            flagged = "adjusted standard" if f.gps_standard else "week seconds"
            warnings.append(
                f"{f.path.name}: the header flags its GPS times {flagged}, their "
                f"values are {kind} time: read as {kind} time"
            )
    if any(offset for offset, _ in offsets.values()):
        warnings.append(
            f"GPS times in week seconds: made adjusted standard GPS time in the GPS week that "
            f"puts them nearest to {day.isoformat()} (the date from the {date_source})"
        )
    metadata = MissionMetadata(
        name=name, date=day, place=None, robot=None, sources={"date": date_source}
    )
    mission = Mission(
        layout=MissionLayout(root=src),
        metadata=metadata,
        graph=None,
        payloads=payloads,
        scans=[],
        gnss=None,
        imu=None,
        images=[],
        problems=[],
        strict=True,
        source_poses={},
        cache=CloudCache(0),
        warnings=warnings,
    )
    mission.name = name
    mission.scan_path = path_xyz
    return mission
