"""Mission folder-name conventions and rosbag names.

Folder names (every form of docs/MISSION_FORMAT.md parses, see :func:`parse_mission_name`):

- ``YYYY-MM-DD-<place>-<robot>[-<unit>]`` (places may contain hyphens), optionally with an
  ``HH-MM-SS`` time after the date (``-`` or ``_`` after the date):
  ``2023-04-21-stein-am-rhein-frontier-v15``, ``2024-03-26_13-47-27-wytham-spot``;
- the VILENS logger's ``YYYY-MM-DD-HH-MM-SS`` (date and time only): ``2023-05-01-14-01-05``;
- the ROS 2 VILENS / Frontier ``YYYY-MM-DD_HH-MM-SS_rec<NNN>_<site>``:
  ``2024-03-26_13-47-27_rec004_site`` (recording ``rec004``, place ``site``, no robot);
- a bag-like ``<robot>-YYYY-MM-DD-HH-MM-SS[-<tag>]`` (a folder named like its rosbag).

How the robot token is found in the ``<place>-<robot>[-<unit>]`` part:

1. The last token that names a known robot platform (:data:`KNOWN_ROBOTS`, extend it with
   :func:`register_robot`) with at least one place token before it and at most one token
   (the unit) after it.
2. Otherwise, when three or more tokens remain and the last one looks like a unit id
   (letters then digits, e.g. ``v15``, ``frn015``, ``unit3``, or digits only), the
   second-to-last token is the robot and the last the unit.
3. Otherwise the last token is the robot and there is no unit. (A *named* unit such as
   ``coyote`` is only recognised after a known robot.)

A ``rec<NNN>`` token is a recording id (``MissionName.tag``). After a time or a recording
id a single remaining token is the place; after a bare date it is an error (place or robot?).
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from pathlib import Path

from standgrid.errors import MissionNameError

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


def register_robot(name: str) -> None:
    """Add a robot platform name to :data:`KNOWN_ROBOTS`."""
    KNOWN_ROBOTS.add(name.strip().lower())


@dataclass(frozen=True)
class MissionName:
    """The parts of a mission folder name (place and robot None where the name has none)."""

    date: dt.date
    place: str | None
    robot: str | None
    unit: str | None = None
    time: dt.time | None = None
    #: A recording id (``rec004``) or a bag-like name's additional tag.
    tag: str | None = None

    def __str__(self) -> str:
        parts = [self.date.isoformat()]
        if self.time is not None:
            parts.append(self.time.strftime("%H-%M-%S"))
        parts += [p for p in (self.tag, self.place, self.robot, self.unit) if p]
        return "-".join(parts)


def _parse_date(y: str, m: str, d: str, name: str) -> dt.date:
    try:
        return dt.date(int(y), int(m), int(d))
    except ValueError as exc:
        raise MissionNameError(f"invalid date {y}-{m}-{d} in {name!r} ({exc})") from exc


def _parse_clock(h: str, m: str, s: str, name: str) -> dt.time:
    try:
        return dt.time(int(h), int(m), int(s))
    except ValueError as exc:
        raise MissionNameError(f"invalid time in {name!r} ({exc})") from exc


_REC_RE = re.compile(r"^rec\d+$", re.IGNORECASE)
_BAG_FOLDER_RE = re.compile(
    r"^(?P<robot>[A-Za-z][A-Za-z0-9]*)[-_](?P<y>\d{4})-(?P<mo>\d{2})-(?P<d>\d{2})[-_]"
    r"(?P<h>\d{2})-(?P<mi>\d{2})-(?P<s>\d{2})(?:[-_](?P<tag>.+))?$"
)


def parse_mission_name(name: str) -> MissionName:
    """Split a mission folder name of any form of docs/MISSION_FORMAT.md (module docstring)."""
    base = Path(str(name)).name
    m = _DATE_RE.match(base)
    if m is None:
        bag = _BAG_FOLDER_RE.match(base)
        if bag is None:
            raise MissionNameError(f"{base!r} does not start with a YYYY-MM-DD date")
        return MissionName(
            _parse_date(bag["y"], bag["mo"], bag["d"], base),
            None,
            bag["robot"],
            None,
            _parse_clock(bag["h"], bag["mi"], bag["s"], base),
            bag["tag"],
        )
    date = _parse_date(m[1], m[2], m[3], base)
    rest = m[4] or ""
    time: dt.time | None = None
    t = _TIME_RE.match(rest)
    if t is not None:
        time = _parse_clock(t[1], t[2], t[3], base)
        rest = t[4] or ""
    tokens = [tok for tok in re.split(r"[-_]", rest) if tok]
    recs = [i for i, tok in enumerate(tokens) if _REC_RE.match(tok)]
    tag = tokens.pop(recs[0]) if recs else None
    if not tokens:
        if rest and tag is None:
            raise MissionNameError(f"{base!r} lacks a place and a robot after the date")
        return MissionName(date, None, None, None, time, tag)
    lowered = [tok.lower() for tok in tokens]
    if tag is not None:  # ROS 2 VILENS / Frontier: <date>_<time>_rec<NNN>_<site>
        robots = [i for i, tok in enumerate(lowered) if tok in KNOWN_ROBOTS]
        robot = tokens.pop(robots[-1]) if robots else None
        return MissionName(date, "-".join(tokens) or None, robot, None, time, tag)
    if len(tokens) == 1:
        if time is None:
            raise MissionNameError(f"{base!r} lacks a place and a robot after the date")
        return MissionName(date, tokens[0], None, None, time)
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
