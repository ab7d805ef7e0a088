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


# --- reading and writing ---------------------------------------------------------------------
#
# GNSS text: ``# sec, nsec, latitude, longitude, altitude, quality, h_std, v_std`` (commas or
# whitespace; std columns optional -> NaN). IMU text: ``# sec, nsec, ax, ay, az, wx, wy, wz``.
# A header-only file is an empty log; a file with no content at all is an error. Latitude,
# longitude and altitude may be NaN only on rows with quality 0 (invalid fix).

GNSS_HEADER = "# sec, nsec, latitude, longitude, altitude, quality, h_std, v_std"
IMU_HEADER = "# sec, nsec, ax, ay, az, wx, wy, wz"

_GNSS_BASE = ("sec", "nsec", "latitude", "longitude", "altitude", "quality")
_GNSS_ALIASES = {
    "sec": "sec",
    "nsec": "nsec",
    "latitude": "latitude",
    "lat": "latitude",
    "longitude": "longitude",
    "lon": "longitude",
    "altitude": "altitude",
    "alt": "altitude",
    "quality": "quality",
    "h_std": "h_std",
    "v_std": "v_std",
}
_GNSS_LAYOUTS = {6: _GNSS_BASE, 7: (*_GNSS_BASE, "h_std"), 8: (*_GNSS_BASE, "h_std", "v_std")}
_IMU_COLUMNS = ("sec", "nsec", "ax", "ay", "az", "wx", "wy", "wz")
_VALID_QUALITY = np.array([int(q) for q in FixQuality], dtype=np.int64)


def read_gnss(path: str | Path) -> GnssFixes:
    """Read a GNSS text log; bad rows raise SensorLogFormatError with their line."""
    from standgrid.errors import SensorLogFormatError
    from standgrid.mission.poses_csv import read_text_table

    table = read_text_table(
        path,
        aliases=_GNSS_ALIASES,
        layouts=_GNSS_LAYOUTS,
        required=_GNSS_BASE,
        error=SensorLogFormatError,
        what="GNSS log",
    )
    stamps = table.stamps_ns()
    lat, lon, alt = (table.floats(c) for c in ("latitude", "longitude", "altitude"))
    quality = table.ints("quality")
    h_std, v_std = table.floats("h_std"), table.floats("v_std")
    table.fail(~np.isin(quality, _VALID_QUALITY), "fix quality not in {0, 1, 2, 4, 5}")
    valid = quality != FixQuality.INVALID
    table.fail(
        np.isinf(lat) | np.isinf(lon) | np.isinf(alt), "infinite latitude/longitude/altitude"
    )
    table.fail(
        valid & (np.isnan(lat) | np.isnan(lon) | np.isnan(alt)), "NaN position in a valid fix"
    )
    table.fail(np.abs(lat) > 90, "latitude out of [-90, 90]")
    table.fail(np.abs(lon) > 180, "longitude out of [-180, 180]")
    table.fail((h_std < 0) | (v_std < 0) | np.isinf(h_std) | np.isinf(v_std), "invalid std")
    return GnssFixes(
        stamps_ns=stamps,
        lat=lat,
        lon=lon,
        alt=alt,
        quality=quality.astype(np.int8),
        h_std=h_std,
        v_std=v_std,
        source=table.path,
    )


def _fmt_row(values: list[float]) -> str:
    return ", ".join(map(repr, values))


def write_gnss(fixes: GnssFixes, path: str | Path) -> None:
    """Write the canonical GNSS text (all eight columns; NaN stds as ``nan``), exact floats."""
    from standgrid._atomic import write_text_atomic
    from standgrid.stamps import NS_PER_S

    sec, nsec = np.divmod(np.asarray(fixes.stamps_ns, dtype=np.int64), NS_PER_S)
    floats = np.stack([fixes.lat, fixes.lon, fixes.alt], axis=1).astype(np.float64).tolist()
    stds = np.stack([fixes.h_std, fixes.v_std], axis=1).astype(np.float64).tolist()
    out = [GNSS_HEADER]
    for s, n, f, q, sd in zip(
        sec.tolist(), nsec.tolist(), floats, fixes.quality.tolist(), stds, strict=True
    ):
        out.append(f"{s}, {n}, {_fmt_row(f)}, {q}, {_fmt_row(sd)}")
    write_text_atomic(path, "\n".join(out) + "\n")


def read_imu(path: str | Path) -> ImuSamples:
    """Read an IMU text log; bad rows raise SensorLogFormatError with their line."""
    from standgrid.errors import SensorLogFormatError
    from standgrid.mission.poses_csv import read_text_table

    table = read_text_table(
        path,
        aliases={c: c for c in _IMU_COLUMNS},
        layouts={8: _IMU_COLUMNS},
        required=_IMU_COLUMNS,
        error=SensorLogFormatError,
        what="IMU log",
    )
    stamps = table.stamps_ns()
    values = np.stack([table.floats(c) for c in _IMU_COLUMNS[2:]], axis=1).reshape(len(table), 6)
    table.fail(~np.isfinite(values).all(axis=1), "NaN or infinite IMU value")
    return ImuSamples(
        stamps_ns=stamps, accel=values[:, :3].copy(), gyro=values[:, 3:].copy(), source=table.path
    )


def write_imu(samples: ImuSamples, path: str | Path) -> None:
    """Write the canonical IMU text ``# sec, nsec, ax, ay, az, wx, wy, wz``, exact floats."""
    from standgrid._atomic import write_text_atomic
    from standgrid.stamps import NS_PER_S

    sec, nsec = np.divmod(np.asarray(samples.stamps_ns, dtype=np.int64), NS_PER_S)
    values = np.concatenate([samples.accel, samples.gyro], axis=1).astype(np.float64).tolist()
    out = [IMU_HEADER]
    for s, n, row in zip(sec.tolist(), nsec.tolist(), values, strict=True):
        out.append(f"{s}, {n}, {_fmt_row(row)}")
    write_text_atomic(path, "\n".join(out) + "\n")


def concat_gnss(parts: list[GnssFixes], *, drop_exact_duplicates: bool = True) -> GnssFixes:
    """Join per-payload GNSS logs into one, sorted by stamp (stable).

    Rows identical in every column (the same fix logged into two overlapping payload windows)
    are kept once unless ``drop_exact_duplicates`` is False; rows that share a stamp but differ
    are all kept.
    """
    if not parts:
        return GnssFixes(
            np.zeros(0, np.int64),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, np.int8),
            np.zeros(0),
            np.zeros(0),
        )
    cols = {
        name: np.concatenate([getattr(p, name) for p in parts])
        for name in ("stamps_ns", "lat", "lon", "alt", "quality", "h_std", "v_std")
    }
    n = len(cols["stamps_ns"])
    keep_idx = np.arange(n)
    if drop_exact_duplicates and n > 1:
        # Sort on every column (stamp primary; lexsort is stable, so the first logged copy of
        # a row leads its group) so identical rows are neighbours wherever they were logged.
        values = list(cols.values())
        full = np.lexsort(tuple(reversed(values)))
        same = np.ones(n - 1, dtype=bool)
        for v in values:
            a, b = v[full][1:], v[full][:-1]
            eq = a == b
            if v.dtype.kind == "f":
                eq |= np.isnan(a) & np.isnan(b)
            same &= eq
        keep_idx = np.sort(full[np.concatenate([[True], ~same])])
    order = keep_idx[np.argsort(cols["stamps_ns"][keep_idx], kind="stable")]
    cols = {k: v[order] for k, v in cols.items()}
    sources = {p.source for p in parts}
    return GnssFixes(**cols, source=sources.pop() if len(sources) == 1 else None)


def concat_imu(parts: list[ImuSamples]) -> ImuSamples:
    """Join per-payload IMU logs into one, sorted by stamp (stable); every row is kept."""
    if not parts:
        return ImuSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    stamps = np.concatenate([p.stamps_ns for p in parts])
    order = np.argsort(stamps, kind="stable")
    return ImuSamples(
        stamps_ns=stamps[order],
        accel=np.concatenate([p.accel for p in parts])[order],
        gyro=np.concatenate([p.gyro for p in parts])[order],
        source=parts[0].source.parent if parts[0].source is not None else None,
    )


def load_image(ref: ImageRef) -> np.ndarray:
    """Decode the image file of ``ref`` (Pillow, imported on first use) as an array."""
    from PIL import Image, UnidentifiedImageError

    from standgrid.errors import FormatError, MissionNotFoundError

    try:
        with Image.open(ref.path) as img:
            return np.asarray(img)
    except FileNotFoundError as exc:
        raise MissionNotFoundError(
            f"image of camera {ref.camera!r} not found", path=ref.path
        ) from exc
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise FormatError(f"unreadable image ({exc})", path=ref.path) from exc
