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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from standgrid.errors import MetadataError, MissionNameError, MissionNotFoundError
from standgrid.mission.metadata_values import (
    _is_text,
    _parse_gnss,
    _parse_time,
    _parse_when,
    _robot,
    _sensors,
    _tags,
    _text_of,
)
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
