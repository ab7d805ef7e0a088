"""Time stamps as the robots write them: integer ``(sec, nsec)``, compared as integers."""

from __future__ import annotations

import re
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

NS_PER_S = 1_000_000_000
#: GPS epoch (1980-01-06) in UNIX seconds.
GPS_EPOCH_UNIX = 315_964_800
#: GPS - UTC leap seconds, constant since 2017-01-01.
GPS_LEAP_SECONDS = 18

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


def unix_ns_to_adjusted_gps_time(ns: NDArray[np.int64] | int) -> NDArray[np.float64]:
    """UNIX nanoseconds -> LAS *adjusted standard GPS time* (GPS seconds - 1e9)."""
    ns_arr = np.asarray(ns, dtype=np.int64)
    sec, rem = np.divmod(ns_arr, NS_PER_S)
    gps_sec = sec - GPS_EPOCH_UNIX + GPS_LEAP_SECONDS - 1_000_000_000
    return gps_sec.astype(np.float64) + rem.astype(np.float64) * 1e-9
