"""Mission metadata: folder-name convention, rosbag names and ``metadata.yaml``.

Folder names follow ``YYYY-MM-DD-<place>-<robot>[-<unit>]`` (places may contain hyphens);
an optional ``HH-MM-SS`` time may follow the date (``-`` or ``_`` after the date).

How the robot token is found:

1. The last token that names a known robot platform (:data:`KNOWN_ROBOTS`, extend it with
   :func:`register_robot`) with at least one place token before it and at most one token
   (the unit) after it.
2. Otherwise, when three or more tokens remain and the last one looks like a unit id
   (letters then digits, e.g. ``v15``, ``frn015``, ``unit3``, or digits only), the
   second-to-last token is the robot and the last the unit.
3. Otherwise the last token is the robot and there is no unit. (A *named* unit such as
   ``coyote`` is only recognised after a known robot.)

``metadata.yaml`` keys: ``name``, ``date`` (YYYY-MM-DD), ``time`` ("HH:MM:SS", optional),
``place``, ``robot``, ``unit``, ``gnss`` (``{latitude, longitude, altitude}`` or null),
``sensors``, ``tags``, ``notes``, ``extra``. ``date``, ``place`` and ``robot`` are required;
``name`` defaults to the composed folder name. Unknown top-level keys are kept in ``extra``.
"""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from standgrid.errors import MetadataError, MissionNameError, MissionNotFoundError

#: Robot platforms recognised in folder names (lower case). Extend with :func:`register_robot`.
KNOWN_ROBOTS: set[str] = {
    "anymal",
    "frontier",
    "spot",
    "husky",
    "jackal",
    "warthog",
    "dingo",
    "ridgeback",
    "moose",
    "heron",
    "go1",
    "go2",
    "aliengo",
    "handheld",
    "backpack",
}

_DATE_RE = re.compile(r"^(\d{4})-(\d{2})-(\d{2})(?:[-_](.*))?$")
_TIME_RE = re.compile(r"^(\d{2})-(\d{2})-(\d{2})(?:[-_](.*))?$")
_UNIT_RE = re.compile(r"^(?:[a-z]{0,5}\d+[a-z]?|\d+)$")
ROS2_BAG_KEY = "rosbag2_bagfile_information"


def register_robot(name: str) -> None:
    """Add a robot platform name to :data:`KNOWN_ROBOTS`."""
    KNOWN_ROBOTS.add(name.strip().lower())


@dataclass(frozen=True)
class MissionName:
    """The parts of a mission folder name."""

    date: dt.date
    place: str
    robot: str
    unit: str | None = None
    time: dt.time | None = None

    def __str__(self) -> str:
        parts = [self.date.isoformat()]
        if self.time is not None:
            parts.append(self.time.strftime("%H-%M-%S"))
        parts += [self.place, self.robot]
        if self.unit:
            parts.append(self.unit)
        return "-".join(parts)


def _parse_date(y: str, m: str, d: str, name: str) -> dt.date:
    try:
        return dt.date(int(y), int(m), int(d))
    except ValueError as exc:
        raise MissionNameError(f"invalid date {y}-{m}-{d} in {name!r} ({exc})") from exc


def parse_mission_name(name: str) -> MissionName:
    """Split ``YYYY-MM-DD[-HH-MM-SS]-<place>-<robot>[-<unit>]`` (rules in the module docstring)."""
    base = Path(str(name)).name
    m = _DATE_RE.match(base)
    if m is None:
        raise MissionNameError(f"{base!r} does not start with a YYYY-MM-DD date")
    date = _parse_date(m[1], m[2], m[3], base)
    rest = m[4] or ""
    time: dt.time | None = None
    t = _TIME_RE.match(rest)
    if t is not None:
        try:
            time = dt.time(int(t[1]), int(t[2]), int(t[3]))
        except ValueError as exc:
            raise MissionNameError(f"invalid time in {base!r} ({exc})") from exc
        rest = t[4] or ""
    tokens = [tok for tok in re.split(r"[-_]", rest) if tok]
    if len(tokens) < 2:
        raise MissionNameError(f"{base!r} lacks a place and a robot after the date")
    lowered = [tok.lower() for tok in tokens]
    for k in range(len(tokens) - 1, 0, -1):
        if lowered[k] in KNOWN_ROBOTS and len(tokens) - k <= 2:
            unit = tokens[k + 1] if k + 1 < len(tokens) else None
            return MissionName(date, "-".join(tokens[:k]), tokens[k], unit, time)
    if len(tokens) >= 3 and _UNIT_RE.match(lowered[-1]):
        return MissionName(date, "-".join(tokens[:-2]), tokens[-2], tokens[-1], time)
    return MissionName(date, "-".join(tokens[:-1]), tokens[-1], None, time)


@dataclass(frozen=True)
class RosbagName:
    """``RobotID-Date-Time-AdditionalTag.bag``."""

    robot_id: str
    date: dt.date
    time: dt.time
    tag: str | None
    extension: str


_BAG_RE = re.compile(
    r"^(?P<robot>.+?)[-_](?P<y>\d{4})-?(?P<mo>\d{2})-?(?P<d>\d{2})[-_]"
    r"(?P<h>\d{2})-?(?P<mi>\d{2})-?(?P<s>\d{2})(?:[-_](?P<tag>.+?))?\.(?P<ext>bag|mcap|db3)$",
    re.IGNORECASE,
)


def parse_rosbag_name(name: str) -> RosbagName:
    """Parse ``anymal-2023-01-13-10-33-05-lidar.bag`` (also ``.mcap`` / ``.db3``, compact dates)."""
    base = Path(str(name)).name
    m = _BAG_RE.match(base)
    if m is None:
        raise MissionNameError(f"{base!r} does not follow RobotID-Date-Time-AdditionalTag.bag")
    date = _parse_date(m["y"], m["mo"], m["d"], base)
    try:
        time = dt.time(int(m["h"]), int(m["mi"]), int(m["s"]))
    except ValueError as exc:
        raise MissionNameError(f"invalid time in {base!r} ({exc})") from exc
    return RosbagName(m["robot"], date, time, m["tag"], m["ext"].lower())


@dataclass
class MissionMetadata:
    """The contents of ``metadata.yaml``."""

    name: str
    date: dt.date
    place: str
    robot: str
    unit: str | None = None
    time: dt.time | None = None
    #: ``(lat, lon, alt)`` WGS84 degrees / ellipsoidal metres, if known.
    gnss: tuple[float, float, float] | None = None
    sensors: list[str] = field(default_factory=list)
    tags: list[str] = field(default_factory=list)
    notes: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain YAML-safe mapping (the layout of ``metadata.yaml``)."""
        gnss = None
        if self.gnss is not None:
            lat, lon, alt = self.gnss
            gnss = {"latitude": float(lat), "longitude": float(lon), "altitude": float(alt)}
        return {
            "name": self.name,
            "date": self.date,
            "time": None if self.time is None else self.time.isoformat(),
            "place": self.place,
            "robot": self.robot,
            "unit": self.unit,
            "gnss": gnss,
            "sensors": list(self.sensors),
            "tags": list(self.tags),
            "notes": self.notes,
            "extra": dict(self.extra),
        }


_KNOWN_KEYS = (
    "name",
    "date",
    "time",
    "place",
    "robot",
    "unit",
    "gnss",
    "sensors",
    "tags",
    "notes",
    "extra",
)


def _key_lines(text: str) -> dict[str, int]:
    """1-based line of each top-level key (for error messages)."""
    import yaml

    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return {}
    if not isinstance(node, yaml.MappingNode):
        return {}
    return {
        str(k.value): k.start_mark.line + 1 for k, _ in node.value if isinstance(k, yaml.ScalarNode)
    }


def read_metadata(path: str | Path) -> MissionMetadata:
    """Read ``metadata.yaml`` (yaml.safe_load); problems raise MetadataError naming the file."""
    import yaml

    src = Path(path)
    try:
        text = src.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise MissionNotFoundError("metadata file not found", path=src) from exc
    except UnicodeDecodeError as exc:
        raise MetadataError(f"not a text file ({exc.reason})", path=src) from exc
    except OSError as exc:  # a folder, no permission, ...
        raise MetadataError(f"cannot read: {exc.strerror or exc}", path=src) from exc
    if not text.strip():
        raise MetadataError("empty metadata file", path=src, line=1)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise MetadataError(
            f"invalid YAML ({getattr(exc, 'problem', exc)})", path=src, line=line
        ) from exc
    except ValueError as exc:  # e.g. a date-shaped scalar that is no date (2023-13-45)
        lines = _key_lines(text)
        raise MetadataError(f"invalid value ({exc})", path=src, line=lines.get("date")) from exc
    if not isinstance(doc, dict):
        raise MetadataError("metadata must be a YAML mapping", path=src, line=1)
    if ROS2_BAG_KEY in doc:
        raise MetadataError(
            f"this is a ROS 2 bag's metadata ({ROS2_BAG_KEY}), not mission metadata", path=src
        )
    lines = _key_lines(text)

    def fail(key: str, message: str) -> MetadataError:
        return MetadataError(f"{key}: {message}", path=src, line=lines.get(key))

    for key in ("date", "place", "robot"):
        if doc.get(key) in (None, ""):
            raise MetadataError(f"missing required key {key!r}", path=src)
    date = doc["date"]
    if isinstance(date, dt.datetime):
        date = date.date()
    elif isinstance(date, str):
        try:
            date = dt.date.fromisoformat(date)
        except ValueError as exc:
            raise fail("date", f"not a YYYY-MM-DD date: {date!r}") from exc
    elif not isinstance(date, dt.date):
        raise fail("date", f"not a YYYY-MM-DD date: {date!r}")
    time = _parse_time(doc.get("time"), fail)
    place, robot = str(doc["place"]), str(doc["robot"])
    unit = doc.get("unit")
    unit = None if unit in (None, "") else str(unit)
    gnss = _parse_gnss(doc.get("gnss"), fail)
    lists: dict[str, list[str]] = {}
    for key in ("sensors", "tags"):
        value = doc.get(key) or []
        if not isinstance(value, list):
            raise fail(key, "must be a list")
        lists[key] = [str(v) for v in value]
    notes = doc.get("notes") or ""
    extra = doc.get("extra") or {}
    if not isinstance(extra, dict):
        raise fail("extra", "must be a mapping")
    extra = dict(extra)
    for key, value in doc.items():
        if key not in _KNOWN_KEYS:
            extra[key] = value
    name = doc.get("name") or str(MissionName(date, place, robot, unit))
    return MissionMetadata(
        name=str(name),
        date=date,
        place=place,
        robot=robot,
        unit=unit,
        time=time,
        gnss=gnss,
        sensors=lists["sensors"],
        tags=lists["tags"],
        notes=str(notes),
        extra=extra,
    )


def _parse_time(value: Any, fail: Any) -> dt.time | None:
    if value in (None, ""):
        return None
    if isinstance(value, dt.time):
        return value
    if isinstance(value, int) and 0 <= value < 86400:  # YAML 1.1 reads 10:33:05 as base-60 int
        return dt.time(value // 3600, value % 3600 // 60, value % 60)
    try:
        return dt.time.fromisoformat(str(value))
    except ValueError as exc:
        raise fail("time", f"not a HH:MM:SS time: {value!r}") from exc


def _parse_gnss(value: Any, fail: Any) -> tuple[float, float, float] | None:
    if value is None:
        return None
    if isinstance(value, dict):
        try:
            triple = [value["latitude"], value["longitude"], value["altitude"]]
        except KeyError as exc:
            raise fail("gnss", f"missing {exc.args[0]!r}") from exc
    elif isinstance(value, list | tuple) and len(value) == 3:
        triple = list(value)
    else:
        raise fail("gnss", "must be {latitude, longitude, altitude} or [lat, lon, alt]")
    try:
        lat, lon, alt = (float(v) for v in triple)
    except (TypeError, ValueError) as exc:
        raise fail("gnss", f"non-numeric value in {triple!r}") from exc
    if not all(math.isfinite(v) for v in (lat, lon, alt)):
        raise fail("gnss", f"latitude, longitude and altitude must be finite: {lat}, {lon}, {alt}")
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise fail("gnss", f"latitude/longitude out of range: {lat}, {lon}")
    return (lat, lon, alt)


def write_metadata(meta: MissionMetadata, path: str | Path) -> None:
    """Write ``metadata.yaml`` atomically; :func:`read_metadata` gives back an equal object."""
    import yaml

    from standgrid._atomic import write_text_atomic

    try:
        text = yaml.safe_dump(
            meta.to_dict(), sort_keys=False, allow_unicode=True, default_flow_style=False
        )
    except yaml.YAMLError as exc:  # e.g. numpy scalars in ``extra``
        raise ValueError(f"{path}: metadata holds a value YAML cannot store ({exc})") from exc
    write_text_atomic(path, text)


def metadata_from_folder_name(
    path_or_name: str | Path, sensors: list[str] | None = None
) -> MissionMetadata:
    """Metadata from a folder name that follows the convention (no GNSS, no tags).

    ``sensors`` defaults to what an existing folder shows: ``lidar`` (any ``*clouds*``
    folder), ``gnss`` (``gnss/`` or ``payloads/gnss/``), ``imu`` (``payloads/imu/``) and one
    entry per camera folder under ``payloads/cameras/`` or ``images_rectified/``.
    """
    path = Path(path_or_name)
    parsed = parse_mission_name(path.name)
    if sensors is None:
        sensors = _sensors_in(path) if path.is_dir() else []
    return MissionMetadata(
        name=path.name,
        date=parsed.date,
        place=parsed.place,
        robot=parsed.robot,
        unit=parsed.unit,
        time=parsed.time,
        sensors=list(sensors),
    )


def _sensors_in(folder: Path) -> list[str]:
    found: list[str] = []
    if any(p.is_dir() and "clouds" in p.name for p in folder.iterdir()):
        found.append("lidar")
    if (folder / "gnss").is_dir() or (folder / "payloads" / "gnss").is_dir():
        found.append("gnss")
    if (folder / "payloads" / "imu").is_dir():
        found.append("imu")
    for cams in (folder / "payloads" / "cameras", folder / "images_rectified"):
        if cams.is_dir():
            found += sorted(p.name for p in cams.iterdir() if p.is_dir() and p.name not in found)
    return found
