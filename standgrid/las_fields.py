"""The per-point fields stored in a standard LAS 1.4 dimension, and the check of their values.

Shared by the payload reader (a bad field names the payload file) and the tile writers (a
bad field names the tile). The rule, the same for every integer dimension: a value is
stored only when it is exactly representable; nothing is rounded, wrapped, clipped or
truncated.

- Integer and bool dtypes: every value must lie in the dimension's range. A dtype whose
  whole range fits the dimension (``uint8`` classification, ``uint16`` colours, ``bool``
  flags) is taken without looking at the values.
- Float dtypes: accepted when every value is integral and in range (``1.0, 2.0`` is stored
  as ``1, 2``); NaN, infinities and fractions are refused.
- ``gps_time`` (a LAS double): any real dtype whose values convert to float64 exactly
  (integers beyond 2**53 and floats wider than 64 bits are refused); finiteness is checked
  by the writers from the extremes they compute anyway.
- One value per point (a 1-D array); anything else (complex, text, objects) is refused.

Every refusal is a :class:`~standgrid.errors.PointCloudFormatError` naming the field, the
file and the first offending value with its point index.

The one conversion: a LAS 1.0-1.3 ``scan_angle_rank`` (point formats 0-5, whole degrees) is
stored as the LAS 1.4 ``scan_angle`` (:func:`scan_angle_from_rank`: units of
:data:`SCAN_ANGLE_UNIT_DEG`, off by at most 0.003 degrees).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import PointCloudFormatError

#: Integer LAS dimensions: (dtype the values are stored as, lowest value, highest value).
LAS_INTEGER_DIMENSIONS: dict[str, tuple[np.dtype[Any], int, int]] = {
    "point_source_id": (np.dtype(np.uint16), 0, 65535),
    "classification": (np.dtype(np.uint8), 0, 255),
    "return_number": (np.dtype(np.uint8), 0, 15),
    "number_of_returns": (np.dtype(np.uint8), 0, 15),
    "user_data": (np.dtype(np.uint8), 0, 255),
    "scan_angle": (np.dtype(np.int16), -32768, 32767),
    "scan_direction_flag": (np.dtype(np.uint8), 0, 1),
    "edge_of_flight_line": (np.dtype(np.uint8), 0, 1),
    "synthetic": (np.dtype(np.uint8), 0, 1),
    "key_point": (np.dtype(np.uint8), 0, 1),
    "withheld": (np.dtype(np.uint8), 0, 1),
    "overlap": (np.dtype(np.uint8), 0, 1),
    "scanner_channel": (np.dtype(np.uint8), 0, 3),
    "red": (np.dtype(np.uint16), 0, 65535),
    "green": (np.dtype(np.uint16), 0, 65535),
    "blue": (np.dtype(np.uint16), 0, 65535),
}
#: Every field stored in a LAS dimension of its own name by these rules.
LAS_CHECKED_FIELDS = frozenset({*LAS_INTEGER_DIMENSIONS, "gps_time"})
#: The LAS intensity, where a writer stores it by the same rule (a payload written as LAS;
#: tiles keep other intensities exactly beside a scaled one, ``standgrid.export.las``).
LAS_INTENSITY: tuple[np.dtype[Any], int, int] = (np.dtype(np.uint16), 0, 65535)
#: Degrees per unit of the LAS 1.4 ``scan_angle`` (point formats 6-10).
SCAN_ANGLE_UNIT_DEG = 0.006
#: Integers up to this magnitude convert to float64 exactly.
_FLOAT64_EXACT = 2**53


def las_dimension_values(
    name: str, values: NDArray[Any], path: str | os.PathLike[str], *, first_point: int = 0
) -> NDArray[Any]:
    """``values`` of field ``name``, checked, ready for its LAS dimension: the same array
    when it is of an integer or bool dtype (every value fits: assigning it casts exactly),
    floats converted to the stored dtype; else a :class:`PointCloudFormatError` naming the
    field, ``path`` and the first offending value (point indices start at ``first_point``).
    ``name`` must be in :data:`LAS_CHECKED_FIELDS` or be ``intensity``."""
    if values.ndim != 1:
        raise PointCloudFormatError(
            f"field {name!r} has shape {values.shape[1:]} per point; its LAS dimension holds "
            "one value per point",
            path=path,
        )
    kind = values.dtype.kind
    if kind not in "biuf":
        raise PointCloudFormatError(
            f"field {name!r} of dtype {values.dtype} cannot be stored in its LAS dimension "
            "(a real number is needed)",
            path=path,
        )
    if name == "gps_time":
        return _gps_times(values, path, first_point)
    stored, lo, hi = LAS_INTENSITY if name == "intensity" else LAS_INTEGER_DIMENSIONS[name]
    if kind == "b" or not values.size:
        return values if kind != "f" else values.astype(stored)
    if kind in "ui":
        info = np.iinfo(values.dtype)
        # dtype first: no pass over the values when the dtype cannot hold a bad one
        low_ok = info.min >= lo or values.min() >= lo
        if not (low_ok and (info.max <= hi or values.max() <= hi)):
            _refuse_range(name, values, lo, hi, path, first_point)
        return values
    # floats: min and max propagate NaN, so in-range extremes mean finite values in range
    if not (values.min() >= lo and values.max() <= hi):
        _refuse_range(name, values, lo, hi, path, first_point)
    converted = values.astype(stored)
    inexact = converted != values
    if inexact.any():
        k = int(np.argmax(inexact))
        raise PointCloudFormatError(
            f"field {name!r} value {values[k]} (point {first_point + k}) is not an integer: "
            f"its LAS dimension stores integers (nothing is rounded)",
            path=path,
        )
    return converted


def scan_angle_from_rank(
    rank: NDArray[Any], path: str | os.PathLike[str], *, first_point: int = 0
) -> NDArray[np.int16]:
    """A LAS 1.0-1.3 ``scan_angle_rank`` (degrees, int8 in point formats 0-5) as the LAS 1.4
    ``scan_angle``: ``round(rank / 0.006)`` in int16 units of 0.006 degrees. The stored
    angle is off by at most half a unit, 0.003 degrees (15 degrees is exactly 2500 units,
    1 degree 167 units = 1.002 degrees). A non-integer dtype must hold finite angles within
    the int16 range (+-196.6 degrees), else a :class:`PointCloudFormatError` names the field,
    ``path`` and the first offending value."""
    if rank.ndim != 1 or rank.dtype.kind not in "biuf":
        raise PointCloudFormatError(
            f"field 'scan_angle_rank' of dtype {rank.dtype} and shape {rank.shape[1:]} per "
            "point is not one angle in degrees per point",
            path=path,
        )
    units = rank.astype(np.float64) / SCAN_ANGLE_UNIT_DEG
    if rank.dtype.itemsize > 1 and len(units):  # int8 ranks always fit int16 units
        low, high = LAS_INTEGER_DIMENSIONS["scan_angle"][1:]
        if not (units.min() >= low - 0.5 and units.max() < high + 0.5):
            inside = (units >= low - 0.5) & (units < high + 0.5)
            k = int(np.argmin(inside))
            raise PointCloudFormatError(
                f"field 'scan_angle_rank' value {rank[k]} (point {first_point + k}) is not an "
                f"angle the LAS scan_angle can hold ({low * SCAN_ANGLE_UNIT_DEG:.3f} to "
                f"{high * SCAN_ANGLE_UNIT_DEG:.3f} degrees)",
                path=path,
            )
    return np.rint(units).astype(np.int16)


def check_finite_gps_time(
    low: float, high: float, values: list[NDArray[Any]], path: str | os.PathLike[str]
) -> None:
    """Refuse GPS times (given in parts, with their extremes ``low``, ``high`` as min and max
    give them: NaN when any is NaN) that are not all finite."""
    if np.isfinite(low) and np.isfinite(high):
        return
    start = 0
    for part in values:
        bad = ~np.isfinite(part)
        if bad.any():
            k = int(np.argmax(bad))
            raise PointCloudFormatError(
                f"field 'gps_time' value {part[k]} (point {start + k}) is not a finite time",
                path=path,
            )
        start += len(part)


def _gps_times(
    values: NDArray[Any], path: str | os.PathLike[str], first_point: int
) -> NDArray[Any]:
    kind, size = values.dtype.kind, values.dtype.itemsize
    if values.size and ((kind in "ui" and size == 8) or (kind == "f" and size > 8)):
        if kind == "f":
            converted = values.astype(np.float64)
            inexact = (converted != values) & ~np.isnan(values)
        else:
            inexact = values > _FLOAT64_EXACT
            if kind == "i":
                inexact |= values < -_FLOAT64_EXACT
        if inexact.any():
            k = int(np.argmax(inexact))
            raise PointCloudFormatError(
                f"field 'gps_time' value {values[k]} (point {first_point + k}) has no exact "
                "float64 value (LAS GPS times are doubles)",
                path=path,
            )
    return values.astype(np.float64, copy=False)


def _refuse_range(
    name: str,
    values: NDArray[Any],
    lo: int,
    hi: int,
    path: str | os.PathLike[str],
    first_point: int,
) -> None:
    """Raise for the first value of ``values`` outside ``[lo, hi]`` (or NaN)."""
    inside = (values >= lo) & (values <= hi)
    k = int(np.argmin(inside))
    what = "is not a number" if values[k] != values[k] else "is outside the LAS range"
    raise PointCloudFormatError(
        f"field {name!r} value {values[k]} (point {first_point + k}) {what} [{lo}, {hi}]",
        path=path,
    )
