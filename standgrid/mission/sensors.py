"""GNSS fixes, IMU samples and camera images of a mission."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from standgrid.stamps import Stamp


class FixQuality(IntEnum):
    """NMEA GGA fix quality."""

    INVALID = 0
    GPS = 1
    DGPS = 2
    RTK_FIXED = 4
    RTK_FLOAT = 5


@dataclass(frozen=True, eq=False)
class GnssFixes:
    """A GNSS log as columns. Std columns are NaN where the file has none."""

    stamps_ns: NDArray[np.int64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    alt: NDArray[np.float64]
    quality: NDArray[np.int8]
    h_std: NDArray[np.float64]
    v_std: NDArray[np.float64]
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """An IMU log: linear acceleration (m/s^2) and angular rate (rad/s), base frame."""

    stamps_ns: NDArray[np.int64]
    accel: NDArray[np.float64]
    gyro: NDArray[np.float64]
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True)
class ImageRef:
    """A camera image on disk, loaded only when asked for."""

    camera: str
    stamp: Stamp
    path: Path
