"""A plain scan's trajectory: reading it, cutting it into segments, and the payload parts
(points of one segment in one file) it makes (see :mod:`standgrid.mission.scan`)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import (
    PointCloudFormatError,
    SensorLogFormatError,
)

if TYPE_CHECKING:
    from standgrid.mission.scan import ScanOptions, _FileFacts

#: Points read at a time when a trajectory's segments are found in the files' GPS times.
TIME_CHUNK = 1_000_000

_TIME_NAMES = ("time", "timestamp", "gps_time", "gpstime", "t", "sec", "seconds")
_AXES = {"x": ("x", "easting", "e"), "y": ("y", "northing", "n"), "z": ("z", "elevation", "h")}
#: A trajectory file bigger than this is refused (a day of 1 kHz poses is ~50 MB of text).
MAX_TRAJECTORY_BYTES = 512 * 1024 * 1024


def read_trajectory(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Times ``(N,)`` and positions ``(N, 3)`` of a scanner's trajectory file: CSV or
    whitespace-separated text, with a header naming ``time``/``timestamp``/``gps_time`` and
    ``x y z`` (or ``easting northing elevation``) columns, or without a header the first four
    columns as time, x, y, z. Times must increase; rows are checked (file and line)."""
    try:
        if path.stat().st_size > MAX_TRAJECTORY_BYTES:
            raise SensorLogFormatError("trajectory file larger than 512 MB", path=path)
        lines = path.read_text(encoding="utf-8", errors="strict").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SensorLogFormatError(f"cannot read the trajectory: {exc}", path=path) from exc
    rows: list[tuple[int, list[str]]] = []
    header: list[str] | None = None
    for number, line in enumerate(lines, 1):
        text = line.strip()
        if not text:
            continue
        tokens = [t for t in re.split(r"[,;\s]+", text.lstrip("#%/ ")) if t]
        comment = text.startswith(("#", "//", "%"))
        if not tokens:
            continue
        if not rows and header is None and not _numeric(tokens[0]):
            names = [t.strip().lower() for t in tokens]
            if not comment or any(n in _TIME_NAMES for n in names):
                header = names  # a comment line before it (an exporter's note) is skipped
            continue
        if comment:
            continue
        rows.append((number, tokens))
    if header is None:
        cols = [0, 1, 2, 3]
    else:
        cols = [_column(header, _TIME_NAMES, "time", path)]
        cols += [_column(header, _AXES[a], a, path) for a in "xyz"]
    values = np.empty((len(rows), 4), dtype=np.float64)
    for i, (number, tokens) in enumerate(rows):
        try:
            values[i] = [float(tokens[c]) for c in cols]
        except (IndexError, ValueError):
            raise SensorLogFormatError(
                f"expected numbers in columns {[c + 1 for c in cols]} (time, x, y, z)",
                path=path,
                line=number,
            ) from None
        if not np.all(np.isfinite(values[i])):
            raise SensorLogFormatError("a value is not finite", path=path, line=number)
        if i and values[i, 0] <= values[i - 1, 0]:
            raise SensorLogFormatError(
                f"time {values[i, 0]!r} does not increase", path=path, line=number
            )
    if len(values) < 2:
        raise SensorLogFormatError("a trajectory needs at least two positions", path=path)
    return values[:, 0], values[:, 1:]


def _numeric(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _column(header: list[str], names: tuple[str, ...], what: str, path: Path) -> int:
    for name in names:
        if name in header:
            return header.index(name)
    raise SensorLogFormatError(f"no {what} column in the header {header}", path=path, line=1)


def segment_times(
    times: NDArray[np.float64], xyz: NDArray[np.float64], segment_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where the trajectory is cut every ``segment_m`` of horizontal travel: the cut times
    (the first segment's start, every cut, the last position's time) and each segment's
    middle position ``(K, 3)``."""
    step = np.hypot(np.diff(xyz[:, 0]), np.diff(xyz[:, 1]))
    travel = np.concatenate([[0.0], np.cumsum(step)])
    n = max(1, math.ceil(travel[-1] / segment_m))
    marks = np.linspace(0.0, travel[-1], n + 1) if travel[-1] > 0 else np.array([0.0, 0.0])
    # the time at each mark of travel (travel is non-decreasing in time)
    cuts = np.interp(marks, travel, times)
    cuts[0], cuts[-1] = times[0], times[-1]
    middle = np.interp(0.5 * (cuts[:-1] + cuts[1:]), times, np.arange(len(times), dtype=float))
    lo = np.floor(middle).astype(int)
    hi = np.minimum(lo + 1, len(times) - 1)
    frac = (middle - lo)[:, None]
    sites = xyz[lo] * (1 - frac) + xyz[hi] * frac
    return cuts, sites


def _trajectory_parts(
    facts: list[_FileFacts], options: ScanOptions, src: Path
) -> tuple[list[tuple[Path, tuple[int, int] | None, Any, Any]], NDArray[np.float64]]:
    """One payload per (trajectory segment, file holding points of it): the file's points
    between the first and last chunk of GPS times that meet the segment, cut to its times."""
    import laspy

    assert options.trajectory is not None
    times, xyz = read_trajectory(options.trajectory)
    cuts, sites = segment_times(times, xyz, options.segment_m)
    lows = cuts[:-1].copy()
    highs = cuts[1:].copy()
    lows[0], highs[-1] = -math.inf, math.inf
    parts: list[tuple[Path, tuple[int, int] | None, Any, Any]] = []
    span_t = [math.inf, -math.inf]
    per_file: list[tuple[_FileFacts, list[tuple[int, int, float, float]]]] = []
    for f in facts:
        if not f.has_time:
            raise PointCloudFormatError(
                "no per-point GPS time: a trajectory cannot be matched to the points", path=f.path
            )
        chunks = []
        with laspy.open(f.path) as reader:
            start = 0
            for points in reader.chunk_iterator(TIME_CHUNK):
                t = np.asarray(points["gps_time"], dtype=np.float64)
                if len(t):
                    chunks.append((start, start + len(t), float(t.min()), float(t.max())))
                    span_t = [min(span_t[0], chunks[-1][2]), max(span_t[1], chunks[-1][3])]
                start += len(t)
        per_file.append((f, chunks))
    for f, chunks in per_file:
        covered = sum(hi - lo for _, _, lo, hi in chunks)
        whole = max(hi for *_, hi in chunks) - min(lo for _, _, lo, _ in chunks) if chunks else 0
        if len(chunks) > 2 and covered > 2.0 * whole:
            raise PointCloudFormatError(
                f"the points are not in GPS-time order (each of its {len(chunks)} chunks of "
                f"{TIME_CHUNK:,} points spans {covered / len(chunks):.0f} s of {whole:.0f} s): "
                "every trajectory segment would read the whole file; sort it by GPS time "
                "(e.g. PDAL filters.sort, LAStools lassort -gps_time) or tile it without "
                "option trajectory",
                path=f.path,
                option="trajectory",
            )
    if span_t[0] > times[-1] or span_t[1] < times[0]:
        raise SensorLogFormatError(
            f"the trajectory's times {times[0]:.3f}..{times[-1]:.3f} s do not meet the points' "
            f"GPS times {span_t[0]:.3f}..{span_t[1]:.3f} s (same time base: adjusted standard "
            "GPS time or GPS week seconds, as the points)",
            path=options.trajectory,
        )
    for k in range(len(lows)):
        site = tuple(float(v) for v in sites[k])
        for f, chunks in per_file:
            meet = [c for c in chunks if c[3] >= lows[k] and c[2] < highs[k]]
            if not meet:
                continue
            window = (float(lows[k]), float(highs[k]))
            # a dense segment is read in parts too (the memory budget), each cut to its times
            for start in range(meet[0][0], meet[-1][1], options.part_points):
                stop = min(start + options.part_points, meet[-1][1])
                parts.append((f.path, (start, stop), window, site))
    return parts, xyz
