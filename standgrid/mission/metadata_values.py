"""Reading ``metadata.yaml`` values leniently: dates and times, robot, sensors, tags, GNSS."""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

#: Keys of a sensor mapping that hold the model / the kind.
_SENSOR_MODEL_KEYS = ("model", "name", "type", "id")
_SENSOR_KIND_KEYS = ("kind", "type", "category")


def _is_text(value: Any) -> bool:
    return isinstance(value, str | int | float) and not isinstance(value, bool) and value != ""


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
