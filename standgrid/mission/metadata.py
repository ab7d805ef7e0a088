"""Mission metadata: ``metadata.yaml`` (its schema, lenient reading, safe YAML) and the
metadata a folder name gives (:mod:`standgrid.mission.mission_name`).

``metadata.yaml`` is read leniently (:func:`read_metadata`): the keys other tools write are
mapped through :data:`KEY_SYNONYMS` (``robot_id`` -> robot, ``start_time`` -> date and time,
``site`` / ``location`` -> place, ...), sensors may be a list (of names or of mappings) or a
mapping, values that are missing are derived from the mission folder's name when it follows
a convention, and unknown keys are kept in ``extra``. ``MissionMetadata.sources`` says where
each value came from. Only a date that can be neither read nor derived is an error
(:class:`MetadataError` naming the key and the file); place and robot may stay unknown
(None).
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from standgrid.errors import MetadataError, MissionNameError, MissionNotFoundError
from standgrid.mission.mission_name import MissionName, parse_mission_name


@dataclass
class MissionMetadata:
    """The contents of ``metadata.yaml`` (place and robot None when unknown)."""

    name: str
    date: dt.date
    place: str | None
    robot: str | None
    unit: str | None = None
    time: dt.time | None = None
    #: ``(lat, lon, alt)`` WGS84 degrees / ellipsoidal metres, if known.
    gnss: tuple[float, float, float] | None = None
    sensors: list[str] = field(default_factory=list)
    tags: list[str] = field(default_factory=list)
    notes: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    #: Where each value came from: the metadata.yaml key read (``robot_id``), or
    #: ``folder name``. Not written to metadata.yaml and not compared.
    sources: dict[str, str] = field(default_factory=dict, compare=False)

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


#: metadata.yaml keys read for each field, first present wins. A synonym present but not used
#: (``platform`` beside ``robot_id``) is kept in ``extra``. ``location`` is a place when it is
#: text and a GNSS position when it is a mapping or a list.
KEY_SYNONYMS: dict[str, tuple[str, ...]] = {
    "name": ("name", "mission_name", "mission"),
    "date": (
        "date",
        "start_time",
        "start",
        "datetime",
        "date_time",
        "start_datetime",
        "timestamp",
        "start_date",
        "recording_date",
        "recorded_at",
        "recorded",
    ),
    "time": ("time", "time_of_day", "start_clock"),
    "place": ("place", "site", "location", "site_name", "place_name", "location_name"),
    "robot": ("robot", "robot_id", "robot_name", "robot_type", "vehicle", "platform"),
    "unit": ("unit", "unit_id", "robot_unit", "serial", "serial_number"),
    "gnss": ("gnss", "gps", "gnss_origin", "origin", "start_position", "lla", "location"),
    "sensors": ("sensors", "sensor", "sensor_list", "sensor_suite"),
    "tags": ("tags", "tag", "labels", "keywords"),
    "notes": ("notes", "note", "description", "comment", "comments", "remarks"),
}
FOLDER_NAME = "folder name"
ROS2_BAG_KEY = "rosbag2_bagfile_information"
#: Keys of a sensor mapping that hold the model / the kind.
_SENSOR_MODEL_KEYS = ("model", "name", "type", "id")
_SENSOR_KIND_KEYS = ("kind", "type", "category")


#: The largest metadata.yaml read (bytes): a mission's metadata is a few hundred bytes.
MAX_METADATA_BYTES = 1 << 20


def _no_alias_loader() -> type:
    """A ``yaml.SafeLoader`` that refuses aliases (``*name``): metadata never needs them, and
    nested aliases expand exponentially (a "billion laughs" file of a few hundred bytes)."""
    import yaml

    class NoAliasLoader(yaml.SafeLoader):
        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.AliasEvent):
                event = self.peek_event()
                raise _AliasRefused(event.anchor, event.start_mark.line + 1)
            return super().compose_node(parent, index)

    return NoAliasLoader


class _AliasRefused(Exception):
    """A YAML alias met while composing (becomes a :class:`MetadataError`)."""

    def __init__(self, anchor: str, line: int) -> None:
        super().__init__(anchor, line)
        self.anchor, self.line = anchor, line


def _key_lines(text: str) -> dict[str, int]:
    """1-based line of each top-level key (for error messages)."""
    import yaml

    try:
        node = yaml.compose(text, Loader=_no_alias_loader())
    except (yaml.YAMLError, _AliasRefused):
        return {}
    if not isinstance(node, yaml.MappingNode):
        return {}
    return {
        str(k.value): k.start_mark.line + 1 for k, _ in node.value if isinstance(k, yaml.ScalarNode)
    }


def _load_yaml(src: Path) -> tuple[dict[Any, Any], str]:
    import yaml

    try:
        with open(src, "rb") as handle:
            data = handle.read(MAX_METADATA_BYTES + 1)
        if len(data) > MAX_METADATA_BYTES:
            raise MetadataError(
                f"larger than {MAX_METADATA_BYTES // 1024} KiB: not mission metadata", path=src
            )
        text = data.decode("utf-8")
    except FileNotFoundError as exc:
        raise MissionNotFoundError("metadata file not found", path=src) from exc
    except UnicodeDecodeError as exc:
        raise MetadataError(f"not a text file ({exc.reason})", path=src) from exc
    except OSError as exc:  # a folder, no permission, ...
        raise MetadataError(f"cannot read: {exc.strerror or exc}", path=src) from exc
    if not text.strip():
        raise MetadataError("empty metadata file", path=src, line=1)
    try:
        doc = yaml.load(text, Loader=_no_alias_loader())  # a SafeLoader
    except _AliasRefused as exc:
        raise MetadataError(
            f"YAML alias *{exc.anchor} refused: metadata needs no anchors or aliases (nested "
            "aliases can expand without bound)",
            path=src,
            line=exc.line,
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise MetadataError(
            f"invalid YAML ({getattr(exc, 'problem', exc)})", path=src, line=line
        ) from exc
    except ValueError as exc:  # e.g. a date-shaped scalar that is no date (2023-13-45)
        lines = _key_lines(text)
        key = next((k for k in KEY_SYNONYMS["date"] if k in lines), None)
        raise MetadataError(
            f"invalid value ({exc})", path=src, line=lines.get(key or ""), key=key
        ) from exc
    if not isinstance(doc, dict):
        raise MetadataError("metadata must be a YAML mapping", path=src, line=1)
    if ROS2_BAG_KEY in doc:
        raise MetadataError(
            f"this is a ROS 2 bag's metadata ({ROS2_BAG_KEY}), not mission metadata", path=src
        )
    return doc, text


def _is_text(value: Any) -> bool:
    return isinstance(value, str | int | float) and not isinstance(value, bool) and value != ""


def read_metadata(path: str | Path, *, folder_name: str | None = None) -> MissionMetadata:
    """Read ``metadata.yaml`` leniently (module docstring); errors name the key and the file.

    ``folder_name`` (default: the name of the folder holding the file) supplies what the
    file lacks when it follows a naming convention.
    """
    src = Path(path)
    doc, text = _load_yaml(src)
    lines = _key_lines(text)

    def fail(key: str, message: str) -> MetadataError:
        return MetadataError(f"{key}: {message}", path=src, line=lines.get(key), key=key)

    used: set[Any] = set()
    sources: dict[str, str] = {}

    def pick(fieldname: str, accept: Any = _is_text) -> tuple[str, Any] | None:
        for key in KEY_SYNONYMS[fieldname]:
            value = doc.get(key)
            if key in used or value is None or value == "" or not accept(value):
                continue
            used.add(key)
            sources[fieldname] = key
            return key, value
        return None

    date: dt.date | None = None
    time: dt.time | None = None
    found = pick("date", lambda v: v is not None)
    if found is not None:
        date, time = _parse_when(found[1], lambda m, k=found[0]: fail(k, m))
        if date is None:  # a time of day only (YAML reads 10:33:05 as a base-60 integer)
            sources.pop("date")
            sources["time"] = found[0]
    found_time = pick("time", lambda v: v is not None)
    if found_time is not None:
        time = _parse_time(found_time[1], lambda m, k=found_time[0]: fail(k, m))
    robot = unit = None
    found = pick("robot", lambda v: _is_text(v) or isinstance(v, dict))
    if found is not None:
        robot, unit = _robot(found[1])
        if unit is not None:
            sources["unit"] = found[0]
    place = _text_of(pick("place"))
    found = pick("unit")
    if found is not None:
        unit = str(found[1])
    found = pick("gnss", lambda v: isinstance(v, dict | list | tuple))
    gnss = None if found is None else _parse_gnss(found[1], lambda m, k=found[0]: fail(k, m))
    found = pick("sensors", lambda v: v is not None)
    sensors = [] if found is None else _sensors(found[1], lambda m, k=found[0]: fail(k, m))
    found = pick("tags", lambda v: v is not None)
    tags = [] if found is None else _tags(found[1], lambda m, k=found[0]: fail(k, m))
    notes = _text_of(pick("notes")) or ""
    name = _text_of(pick("name"))

    folder = Path(folder_name) if folder_name is not None else src.absolute().parent
    try:
        parsed: MissionName | None = parse_mission_name(folder.name)
    except MissionNameError:
        parsed = None
    if parsed is not None:

        def derive(key: str, own: Any, from_name: Any) -> Any:
            if own is None and from_name is not None:
                sources[key] = FOLDER_NAME
                return from_name
            return own

        date = derive("date", date, parsed.date)
        time = derive("time", time, parsed.time)
        place = derive("place", place, parsed.place)
        robot = derive("robot", robot, parsed.robot)
        unit = derive("unit", unit, parsed.unit)
        if name is None:
            name, sources["name"] = folder.name, FOLDER_NAME
    if date is None:
        tried = ", ".join(KEY_SYNONYMS["date"])
        why = (
            "carries no date"
            if parsed is not None
            else "does not follow a naming convention (YYYY-MM-DD-<place>-<robot>...)"
        )
        raise MetadataError(
            f"missing key 'date': none of {tried} is set, and the folder name "
            f"{folder.name!r} {why}",
            path=src,
            key="date",
        )

    extra = doc.get("extra") if "extra" not in used else None
    if extra is not None and not isinstance(extra, dict):
        raise fail("extra", "must be a mapping")
    extra = dict(extra or {})
    synonyms = {key for keys in KEY_SYNONYMS.values() for key in keys}
    for key, value in doc.items():
        if key in used or key == "extra":
            continue
        if key in synonyms and value in (None, "", [], {}):
            continue  # an empty known key (``gnss: null``) carries nothing
        extra[key] = value
    if name is None:
        name = str(MissionName(date, place, robot, unit))
    return MissionMetadata(
        name=name,
        date=date,
        place=place,
        robot=robot,
        unit=unit,
        time=time,
        gnss=gnss,
        sensors=sensors,
        tags=tags,
        notes=notes,
        extra=extra,
        sources=sources,
    )


def _text_of(found: tuple[str, Any] | None) -> str | None:
    return None if found is None else str(found[1])


def _robot(value: Any) -> tuple[str | None, str | None]:
    """A robot text, or a mapping ``{type|platform|model|name: ..., id|unit|serial: ...}``."""
    if not isinstance(value, dict):
        return str(value), None
    robot = next((value[k] for k in ("type", "platform", "model", "name") if value.get(k)), None)
    unit = next((value[k] for k in ("id", "unit", "serial", "name") if value.get(k)), None)
    if unit == robot:
        unit = None
    return (None if robot is None else str(robot)), (None if unit is None else str(unit))


_DATETIME_FORMATS = (
    "%Y%m%d",
    "%Y%m%dT%H%M%S",
    "%Y%m%d_%H%M%S",
    "%Y-%m-%d_%H-%M-%S",
    "%Y-%m-%d-%H-%M-%S",
    "%Y/%m/%d",
    "%Y/%m/%d %H:%M:%S",
    "%d.%m.%Y",
    "%d.%m.%Y %H:%M:%S",
)


def _from_epoch(seconds: float) -> tuple[dt.date, dt.time]:
    moment = dt.datetime.fromtimestamp(seconds, tz=dt.UTC)
    return moment.date(), moment.time()


def _epoch_seconds(number: float) -> float | None:
    """A UNIX time in s, ms, us or ns (by magnitude) as seconds; None if not plausible."""
    for scale in (1.0, 1e3, 1e6, 1e9):
        seconds = number / scale
        if 1e8 <= seconds < 1e10:  # 1973 .. 2286
            return seconds
    return None


def _parse_when(value: Any, fail: Any) -> tuple[dt.date | None, dt.time | None]:
    """A date, datetime, ISO text, common date formats or a UNIX time (UTC) -> (date, time).

    Dates and times with a time zone are taken as written (no conversion); UNIX times give
    the UTC date and time.
    """
    if isinstance(value, dt.datetime):
        return value.date(), value.time().replace(tzinfo=None)
    if isinstance(value, dt.date):
        return value, None
    if isinstance(value, dict):  # {sec, nsec} as ROS writes stamps
        sec = value.get("sec", value.get("secs"))
        nsec = value.get("nsec", value.get("nanosec", value.get("nsecs", 0)))
        try:
            return _from_epoch(float(sec) + float(nsec) * 1e-9)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise fail(f"not a date or a {{sec, nsec}} stamp: {value!r}") from None
    if isinstance(value, bool):
        raise fail(f"not a date: {value!r}")
    if isinstance(value, int) and 0 <= value < 86400:  # YAML 1.1 base-60 time of day
        return None, _parse_time(value, fail)
    if isinstance(value, int) and 19000101 <= value <= 21001231:
        value = str(value)
    if isinstance(value, int | float):
        seconds = _epoch_seconds(float(value))
        if seconds is None:
            raise fail(f"not a date or a plausible UNIX time: {value!r}")
        return _from_epoch(seconds)
    text = str(value).strip()
    try:
        moment = dt.datetime.fromisoformat(text)
    except ValueError:
        pass
    else:
        if len(text) <= 10:
            return moment.date(), None
        return moment.date(), moment.time().replace(tzinfo=None)
    for fmt in _DATETIME_FORMATS:
        try:
            moment = dt.datetime.strptime(text, fmt)
        except ValueError:
            continue
        return moment.date(), (None if "%H" not in fmt else moment.time())
    try:
        number = float(text)
    except ValueError:
        raise fail(f"not a date (YYYY-MM-DD, ISO 8601 or a UNIX time): {value!r}") from None
    seconds = _epoch_seconds(number)
    if seconds is None:
        raise fail(f"not a date or a plausible UNIX time: {value!r}")
    return _from_epoch(seconds)


def _sensors(value: Any, fail: Any) -> list[str]:
    """Sensor names from a list (of names or of mappings), a mapping or a comma-separated text.

    A mapping entry ``lidar: velodyne-vlp16`` (or ``lidar: {model: velodyne-vlp16}``) gives the
    model; the key is kept as well when it is a sensor kind the model's name does not reveal.
    """
    from standgrid.mission.sensor_models import sensor_kinds

    def entry(key: str | None, item: Any) -> list[str]:
        model: Any = item
        kind: Any = key
        if isinstance(item, dict):
            model = next((item[k] for k in _SENSOR_MODEL_KEYS if _is_text(item.get(k))), None)
            kind = next((item[k] for k in _SENSOR_KIND_KEYS if _is_text(item.get(k))), key)
        elif item is None or item is True:
            model = key
        elif not _is_text(item):
            raise fail(f"cannot read a sensor from {item!r}")
        names = [str(model)] if model is not None else []
        if kind is not None and (model is None or str(kind) != str(model)):
            known = sensor_kinds(str(kind))
            if not names or not known <= sensor_kinds(names[0]):
                names.append(str(kind))
        return names

    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    out: list[str] = []
    if isinstance(value, dict):
        for key, item in value.items():
            out += entry(str(key), item)
    elif isinstance(value, list):
        for item in value:
            out += entry(None, item)
    else:
        raise fail("must be a list or a mapping of sensors")
    return list(dict.fromkeys(out))


def _tags(value: Any, fail: Any) -> list[str]:
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    if isinstance(value, list):
        return [str(v) for v in value]
    raise fail("must be a list (or a comma-separated text)")


def _parse_time(value: Any, fail: Any) -> dt.time | None:
    if value in (None, ""):
        return None
    if isinstance(value, dt.datetime):
        return value.time().replace(tzinfo=None)
    if isinstance(value, dt.time):
        return value
    if isinstance(value, int) and 0 <= value < 86400:  # YAML 1.1 reads 10:33:05 as base-60 int
        return dt.time(value // 3600, value % 3600 // 60, value % 60)
    try:
        return dt.time.fromisoformat(str(value))
    except ValueError as exc:
        raise fail(f"not a HH:MM:SS time: {value!r}") from exc


_LAT_KEYS = ("latitude", "lat")
_LON_KEYS = ("longitude", "lon", "lng", "long")
_ALT_KEYS = ("altitude", "alt", "height", "h", "ellipsoidal_height")


def _parse_gnss(value: Any, fail: Any) -> tuple[float, float, float] | None:
    if value is None:
        return None
    if isinstance(value, dict):
        triple = []
        for names in (_LAT_KEYS, _LON_KEYS, _ALT_KEYS):
            key = next((k for k in names if k in value), None)
            if key is None:
                raise fail(f"missing {names[0]!r}")
            triple.append(value[key])
    elif isinstance(value, list | tuple) and len(value) == 3:
        triple = list(value)
    else:
        raise fail("must be {latitude, longitude, altitude} or [lat, lon, alt]")
    try:
        lat, lon, alt = (float(v) for v in triple)
    except (TypeError, ValueError) as exc:
        raise fail(f"non-numeric value in {triple!r}") from exc
    if not all(math.isfinite(v) for v in (lat, lon, alt)):
        raise fail(f"latitude, longitude and altitude must be finite: {lat}, {lon}, {alt}")
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise fail(f"latitude/longitude out of range: {lat}, {lon}")
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
        sources={k: FOLDER_NAME for k, v in _name_parts(path.name, parsed) if v is not None},
    )


def _name_parts(name: str, parsed: MissionName) -> list[tuple[str, Any]]:
    return [
        ("name", name),
        ("date", parsed.date),
        ("time", parsed.time),
        ("place", parsed.place),
        ("robot", parsed.robot),
        ("unit", parsed.unit),
    ]


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
