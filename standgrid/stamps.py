"""Time stamps as the robots write them: integer ``(sec, nsec)``, compared as integers."""

from __future__ import annotations

import re
from datetime import UTC, date, datetime
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

NS_PER_S = 1_000_000_000
#: GPS epoch (1980-01-06) in UNIX seconds.
GPS_EPOCH_UNIX = 315_964_800
#: UTC dates from which GPS - UTC grew by one more leap second (IERS Bulletin C).
GPS_LEAP_SECOND_DATES = (
    date(1981, 7, 1),
    date(1982, 7, 1),
    date(1983, 7, 1),
    date(1985, 7, 1),
    date(1988, 1, 1),
    date(1990, 1, 1),
    date(1991, 1, 1),
    date(1992, 7, 1),
    date(1993, 7, 1),
    date(1994, 7, 1),
    date(1996, 1, 1),
    date(1997, 7, 1),
    date(1999, 1, 1),
    date(2006, 1, 1),
    date(2009, 1, 1),
    date(2012, 7, 1),
    date(2015, 7, 1),
    date(2017, 1, 1),
)
#: Those dates in UNIX seconds (ascending).
_LEAP_UNIX = np.array(
    [int(datetime(d.year, d.month, d.day, tzinfo=UTC).timestamp()) for d in GPS_LEAP_SECOND_DATES],
    dtype=np.int64,
)
#: GPS - UTC leap seconds now (since 2017-01-01).
GPS_LEAP_SECONDS = len(GPS_LEAP_SECOND_DATES)

_NAME_RE = re.compile(
    r"^(?P<prefix>[A-Za-z]+)_(?P<sec>\d+)_(?P<nsec>\d{1,9})\.(?P<ext>[A-Za-z0-9]+)$"
)


class Stamp(NamedTuple):
    """A UNIX time stamp ``(sec, nsec)``; ordering and equality are exact integers."""

    sec: int
    nsec: int

    @classmethod
    def from_ns(cls, ns: int) -> Stamp:
        sec, nsec = divmod(int(ns), NS_PER_S)
        return cls(sec, nsec)

    @classmethod
    def parse(cls, sec: str | int, nsec: str | int) -> Stamp:
        """From the two integer tokens of a graph line or CSV row (``nsec`` may be unpadded)."""
        s, n = int(sec), int(nsec)
        if s < 0 or not 0 <= n < NS_PER_S:
            raise ValueError(f"invalid stamp ({sec}, {nsec})")
        return cls(s, n)

    @property
    def ns(self) -> int:
        """Nanoseconds since the UNIX epoch (exact Python int)."""
        return self.sec * NS_PER_S + self.nsec

    @property
    def seconds(self) -> float:
        """Float seconds (for display and arithmetic that tolerates ~0.1 us)."""
        return self.sec + self.nsec * 1e-9

    def filename(self, prefix: str, ext: str) -> str:
        """The canonical file name: ``<prefix>_<sec>_<nsec:09d>.<ext>``."""
        return f"{prefix}_{self.sec}_{self.nsec:09d}.{ext.lstrip('.')}"

    def __str__(self) -> str:
        return f"{self.sec}.{self.nsec:09d}"


def stamp_from_filename(name: str) -> tuple[str, Stamp, str] | None:
    """``cloud_1583840261_039995392.pcd`` -> ``("cloud", Stamp, "pcd")``; None if no match."""
    m = _NAME_RE.match(name)
    if m is None:
        return None
    return m["prefix"], Stamp(int(m["sec"]), int(m["nsec"])), m["ext"].lower()


def gps_leap_seconds(unix_sec: NDArray[np.int64] | int) -> NDArray[np.int64]:
    """GPS - UTC leap seconds in force at UNIX second(s) ``unix_sec`` (0 before 1981-07-01)."""
    return np.searchsorted(_LEAP_UNIX, np.asarray(unix_sec, dtype=np.int64), side="right")


def adjusted_gps_time_to_unix(seconds: float) -> float:
    """LAS *adjusted standard GPS time* -> UNIX seconds (the inverse of
    :func:`unix_ns_to_adjusted_gps_time`; the leap seconds in force about then)."""
    unix = seconds + 1_000_000_000 + GPS_EPOCH_UNIX
    return unix - float(gps_leap_seconds(int(unix)))


def unix_ns_to_adjusted_gps_time(ns: NDArray[np.int64] | int) -> NDArray[np.float64]:
    """UNIX nanoseconds -> LAS *adjusted standard GPS time* (GPS seconds - 1e9), with the
    leap seconds in force at each stamp."""
    ns_arr = np.asarray(ns, dtype=np.int64)
    sec, rem = np.divmod(ns_arr, NS_PER_S)
    gps_sec = sec - GPS_EPOCH_UNIX + gps_leap_seconds(sec) - 1_000_000_000
    return gps_sec.astype(np.float64) + rem.astype(np.float64) * 1e-9
