"""A LAS/LAZ header checked byte by byte against the file's size before laspy reads it.

laspy trusts the header's counts: a ``number_of_vlrs`` of 0xFFFFFFFF makes it loop for
hours while its memory grows, random bytes after ``LASF`` do the same or end in
``struct.error``. :func:`check_las_header` reads the fixed header (at most 375 bytes) and
walks the VLR headers (54 bytes each, at most :data:`MAX_VLRS`) and the EVLR headers
(60 bytes each), so every count, offset and length is bounded by the file before anything
is allocated: a hostile file costs a few reads and ends in a
:class:`~standgrid.errors.PointCloudFormatError` naming it and the header field.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

from standgrid.errors import PointCloudFormatError

#: Header sizes by LAS 1.x minor version (1.0-1.2: 227, 1.3: 235, 1.4: 375 bytes).
HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
#: Smallest record length of each point data record format (LAS 1.4 R15 table).
POINT_RECORD_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
#: No real file holds more variable-length records than this (scanners write < 20); a header
#: announcing more is refused rather than walked (bounded time).
MAX_VLRS = 10_000
VLR_HEADER = 54
EVLR_HEADER = 60


@dataclass(frozen=True)
class LasHeaderFacts:
    """What the pre-check read: version, counts and where things are."""

    version: tuple[int, int]
    header_size: int
    offset_to_points: int
    vlrs: int
    point_format: int
    compressed: bool
    record_length: int
    point_count: int
    evlrs: int
    file_size: int


def _bad(path: Path, what: str) -> PointCloudFormatError:
    return PointCloudFormatError(f"not a readable LAS/LAZ header: {what}", path=path)


def check_las_header(path: Path, *, points: bool = True) -> LasHeaderFacts:
    """The header of the LAS/LAZ file ``path``, every count checked against the file size
    (``points=False``: all but an uncompressed file's point records, for a header reader
    that reports a truncated file rather than refusing it); raises
    :class:`PointCloudFormatError` (naming the field) on the first that cannot hold."""
    try:
        size = path.stat().st_size
        with path.open("rb") as fp:
            head = fp.read(375)
            if len(head) < 227 or head[:4] != b"LASF":
                what = "no LASF signature" if head[:4] != b"LASF" else f"{len(head)} bytes"
                raise _bad(path, f"{what} (a LAS header is at least 227 bytes from 'LASF')")
            major, minor = head[24], head[25]
            if major != 1 or minor not in HEADER_SIZES:
                raise _bad(path, f"version {major}.{minor} (LAS 1.0 to 1.4 are read)")
            (header_size, offset, n_vlrs, fmt_byte, record) = struct.unpack_from("<HIIBH", head, 94)
            need = HEADER_SIZES[minor]
            if header_size < need or header_size > size or len(head) < min(need, 375):
                raise _bad(
                    path,
                    f"header size {header_size} (LAS 1.{minor}: at least {need}, "
                    f"file of {size} bytes)",
                )
            if not header_size <= offset <= size:
                raise _bad(
                    path,
                    f"offset to point data {offset} outside the header's end "
                    f"{header_size} and the file's {size} bytes",
                )
            point_format = fmt_byte & 0x3F
            compressed = bool(fmt_byte & 0xC0)
            if point_format not in POINT_RECORD_SIZES:
                raise _bad(path, f"point data format {point_format} (0 to 10 exist)")
            if record < POINT_RECORD_SIZES[point_format]:
                raise _bad(
                    path,
                    f"point record length {record} below format {point_format}'s "
                    f"{POINT_RECORD_SIZES[point_format]} bytes",
                )
            scales = struct.unpack_from("<3d", head, 131)
            offsets = struct.unpack_from("<3d", head, 155)
            if not all(math.isfinite(s) and s != 0.0 for s in scales):
                raise _bad(path, f"scale factors {scales} (finite, non-zero)")
            if not all(math.isfinite(o) for o in offsets):
                raise _bad(path, f"offsets {offsets} (finite)")
            room = offset - header_size
            if n_vlrs > MAX_VLRS or n_vlrs * VLR_HEADER > room:
                most = min(room // VLR_HEADER, MAX_VLRS)
                raise _bad(
                    path,
                    f"{n_vlrs} VLRs announced, {room} bytes between the header "
                    f"and the points hold at most {most}",
                )
            at = header_size
            for i in range(n_vlrs):
                fp.seek(at)
                vlr = fp.read(VLR_HEADER)
                if len(vlr) < VLR_HEADER:
                    raise _bad(path, f"VLR {i} at byte {at} runs past the end of the file")
                (length,) = struct.unpack_from("<H", vlr, 20)
                at += VLR_HEADER + length
                if at > offset:
                    raise _bad(
                        path, f"VLR {i} ends at byte {at}, past the point data's offset {offset}"
                    )
            count = int(struct.unpack_from("<I", head, 107)[0])
            n_evlrs = 0
            if minor >= 4:
                (evlr_start, n_evlrs, count64) = struct.unpack_from("<QIQ", head, 235)
                count = int(count64) or count
                if n_evlrs:
                    if n_evlrs > MAX_VLRS or not offset <= evlr_start <= size:
                        raise _bad(
                            path, f"{n_evlrs} EVLRs at byte {evlr_start} (file of {size} bytes)"
                        )
                    at = evlr_start
                    for i in range(n_evlrs):
                        fp.seek(at)
                        evlr = fp.read(EVLR_HEADER)
                        if len(evlr) < EVLR_HEADER:
                            raise _bad(path, f"EVLR {i} at byte {at} runs past the end of the file")
                        (length,) = struct.unpack_from("<Q", evlr, 20)
                        at += EVLR_HEADER + int(length)
                        if at > size:
                            raise _bad(
                                path, f"EVLR {i} ends at byte {at}, past the file's {size} bytes"
                            )
            end = evlr_start if minor >= 4 and n_evlrs else size
            if points and not compressed and count * record > end - offset:
                raise PointCloudFormatError(
                    f"header says {count} points ({count * record} bytes of {record}-byte "
                    f"records), the file holds {max(end - offset, 0)} bytes of point data "
                    f"({max(end - offset, 0) // record} whole points): truncated or a wrong "
                    "header",
                    path=path,
                )
    except OSError as exc:
        raise PointCloudFormatError(f"cannot read the LAS/LAZ header ({exc})", path=path) from exc
    return LasHeaderFacts(
        version=(major, minor),
        header_size=header_size,
        offset_to_points=offset,
        vlrs=n_vlrs,
        point_format=point_format,
        compressed=compressed,
        record_length=record,
        point_count=count,
        evlrs=n_evlrs,
        file_size=size,
    )
