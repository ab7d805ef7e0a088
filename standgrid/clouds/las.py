"""LAS / LAZ / COPC read (laspy, lazrs): every header count checked against the file first.

Coordinates are the scaled float64 ``x y z``; every other point dimension (standard and
extra bytes) is a field under its laspy name. Before laspy allocates anything the header is
checked byte by byte (:mod:`standgrid.clouds.las_header`) and its point count against the
file's size (:func:`check_las_size`); a LAZ file is streamed chunk by chunk by
:meth:`LasReader.chunks` and read from the chunk holding a point by :func:`read_las_part`.
A COPC file is a LAZ 1.4 file (its octree order is not used here). Written by
:mod:`standgrid.clouds.las_write`.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from standgrid.clouds.base import (
    XYZ,
    CloudHeader,
    CloudReader,
    check_cloud_file,
    check_coordinates,
)
from standgrid.clouds.las_header import check_las_header
from standgrid.errors import PointCloudFormatError
from standgrid.pointcloud import PointCloud

LAS_SUFFIXES = (".las",)
LAZ_SUFFIXES = (".laz",)
COPC_SUFFIXES = (".copc.laz",)
#: Where a COPC file's first VLR header starts (right after the 375-byte LAS 1.4 header);
#: its user id (after 2 reserved bytes) is "copc".
_COPC_USER_ID_AT = 377


def sniff_las(head: bytes) -> bool:
    """Whether a file's first bytes are an uncompressed LAS header (``LASF``)."""
    return head[:4] == b"LASF" and len(head) > 104 and not head[104] & 0xC0


def _compressed(head: bytes) -> bool:
    return head[:4] == b"LASF" and len(head) > 104 and bool(head[104] & 0xC0)


def _copc_vlr_first(head: bytes) -> bool:
    return head[_COPC_USER_ID_AT : _COPC_USER_ID_AT + 4] == b"copc"


def sniff_laz(head: bytes) -> bool:
    """Whether a file's first bytes are a LAZ header (``LASF``, compressed point format),
    not a COPC one."""
    return _compressed(head) and not _copc_vlr_first(head)


def sniff_copc(head: bytes) -> bool:
    """Whether a file's first bytes are a COPC header (LAZ whose first VLR is ``copc``)."""
    return _compressed(head) and _copc_vlr_first(head)


class LasReader(CloudReader):
    """A LAS, LAZ or COPC file; :meth:`chunks` streams through laspy (bounded memory)."""

    format = "las"

    def _read_header(self) -> CloudHeader:
        return _las_header(self.path, self.format_name)

    def _read_all(self) -> PointCloud:
        return _read_las(self.path)

    def chunks(self, n_points: int) -> Iterator[PointCloud]:
        """The points as clouds of at most ``n_points``, decompressed chunk by chunk."""
        import laspy

        if n_points < 1:
            raise ValueError("chunk_points must be >= 1")
        src = self.path
        check_las_size(src)
        try:
            with laspy.open(src) as reader:
                done = 0
                for points in reader.chunk_iterator(n_points):
                    cloud = las_points_to_cloud(points)
                    try:
                        check_coordinates(cloud.xyz, src)
                    except PointCloudFormatError as exc:
                        raise PointCloudFormatError(
                            f"{exc.message} in the chunk at point {done}", path=src
                        ) from None
                    done += len(cloud)
                    yield cloud
        except (laspy.errors.LaspyException, ValueError, OSError, EOFError, RuntimeError) as exc:
            if isinstance(exc, PointCloudFormatError):
                raise
            raise PointCloudFormatError(f"unreadable LAS/LAZ ({exc})", path=src) from exc


def las_points_to_cloud(points: Any) -> PointCloud:
    """A laspy point record as a cloud: scaled float64 ``x y z``, every other dimension a
    field under its laspy name."""
    xyz = np.column_stack(
        [
            np.asarray(points.x, np.float64),
            np.asarray(points.y, np.float64),
            np.asarray(points.z, np.float64),
        ]
    )
    fields = {
        name: np.array(points[name])
        for name in points.point_format.dimension_names
        if name not in ("X", "Y", "Z")
    }
    return PointCloud(xyz, fields)


#: Most points one compressed LAZ byte can hold (all-zero points reach ~100; real data < 1).
LAZ_MAX_POINTS_PER_BYTE = 1000


def check_las_size(path: Path) -> int:
    """The header point count of a LAS/LAZ file, checked against the file's size before
    anything is allocated: an uncompressed file must hold ``count x record length`` bytes of
    points; a LAZ file's chunk table must cover the count within the file, and the count may
    not exceed :data:`LAZ_MAX_POINTS_PER_BYTE` per compressed byte."""
    import laspy
    import lazrs

    check_las_header(path)
    try:
        with laspy.open(path) as reader:
            header = reader.header
    except Exception as exc:  # laspy, lazrs and OS errors alike
        raise PointCloudFormatError(f"unreadable LAS/LAZ header ({exc})", path=path) from exc
    count = int(header.point_count)
    size = path.stat().st_size
    offset = int(header.offset_to_point_data)
    record = int(header.point_format.size)
    data = max(0, size - offset)
    if not header.are_points_compressed:
        if count * record > data:
            raise PointCloudFormatError(
                f"header says {count} points ({count * record} bytes of {record}-byte records), "
                f"the file holds {data} bytes of point data ({data // max(record, 1)} whole "
                "points): truncated or a wrong header",
                path=path,
            )
        return count
    if count > data * LAZ_MAX_POINTS_PER_BYTE:
        raise PointCloudFormatError(
            f"header says {count} points, impossible in {data} compressed bytes",
            path=path,
        )
    vlr = next((v for v in header.vlrs if getattr(v, "record_id", None) == 22204), None)
    if vlr is None or count == 0:
        return count
    try:
        laz_vlr = lazrs.LazVlr(vlr.record_data)
        with path.open("rb") as fp:
            fp.seek(offset)
            table = lazrs.read_chunk_table(fp, laz_vlr)
    except Exception as exc:
        what = "unreadable LAZ chunk table"
        if _laz_ends_early(path, offset, size, exc):
            what = "truncated: the file ends before its LAZ chunk table does"
        raise PointCloudFormatError(f"{what} ({exc})", path=path) from exc
    if table:
        if laz_vlr.uses_variable_size_chunks():
            covered = sum(int(points) for points, _ in table)
        else:
            covered = len(table) * int(laz_vlr.chunk_size())
        stored = sum(int(nbytes) for _, nbytes in table)
        if covered < count or stored > data:
            raise PointCloudFormatError(
                f"header says {count} points; the LAZ chunk table covers {covered} points in "
                f"{stored} bytes, the file holds {data}: truncated or a wrong header",
                path=path,
            )
    return count


def _laz_ends_early(path: Path, offset: int, size: int, error: Exception) -> bool:
    """Whether a LAZ chunk table could not be read because the file is cut short: its
    pointer (the first 8 bytes of the point data) is missing or points past the end, or
    reading it ran out of bytes (Rust's UnexpectedEof)."""
    with path.open("rb") as fp:
        fp.seek(offset)
        pointer = fp.read(8)
    if len(pointer) < 8:
        return True
    table = int.from_bytes(pointer, "little", signed=True)
    return table + 8 > size or "failed to fill whole buffer" in str(error)


def _read_las(path: Path) -> PointCloud:
    import laspy

    check_las_size(path)
    try:
        las = laspy.read(path)
    except Exception as exc:  # laspy, lazrs (a RuntimeError), OS errors
        raise PointCloudFormatError(f"unreadable LAS/LAZ ({exc})", path=path) from exc
    if len(las.points) != las.header.point_count:
        raise PointCloudFormatError(
            f"header says {las.header.point_count} points, file holds {len(las.points)}", path=path
        )
    return las_points_to_cloud(las.points)


def read_las_part(
    path: str | Path, span: tuple[int, int], window: tuple[float, float] | None = None
) -> PointCloud:
    """Points ``[start, stop)`` of a LAS/LAZ file (a LAZ file is decompressed from the chunk
    holding ``start``), and of those only the GPS times in ``window`` ``[lo, hi)``."""
    import laspy

    src = Path(path)
    check_cloud_file(src)
    count = check_las_size(src)
    start, stop = span
    if not 0 <= start <= stop <= count:
        raise PointCloudFormatError(f"points {start}..{stop} of a file of {count}", path=src)
    try:
        with laspy.open(src) as reader:
            reader.seek(start)
            points = reader.read_points(stop - start)
    except Exception as exc:  # laspy, lazrs (a RuntimeError), OS errors
        raise PointCloudFormatError(f"unreadable LAS/LAZ ({exc})", path=src) from exc
    if len(points) != stop - start:
        raise PointCloudFormatError(
            f"points {start}..{stop}: the file holds {start + len(points)}", path=src
        )
    cloud = las_points_to_cloud(points)
    if window is not None:
        if "gps_time" not in cloud.fields:
            raise PointCloudFormatError("no GPS time: points cannot be cut by time", path=src)
        t = np.asarray(cloud.fields["gps_time"], dtype=np.float64)
        cloud = cloud.select((t >= window[0]) & (t < window[1]))
    check_coordinates(cloud.xyz, src)
    return cloud


def _las_header(path: Path, format_name: str) -> CloudHeader:
    """The header of a LAS/LAZ file. An uncompressed file shorter than its header announces
    is not an error here: :meth:`CloudHeader.size_problem` says so (readers raise); a LAZ
    file's count is checked against its chunk table (it has no ``data_bytes``)."""
    import laspy

    check_las_header(path, points=False)
    try:
        with laspy.open(path) as reader:
            header = reader.header
    except (laspy.errors.LaspyException, ValueError, OSError, EOFError, struct.error) as exc:
        raise PointCloudFormatError(f"unreadable LAS/LAZ header ({exc})", path=path) from exc
    if header.are_points_compressed:
        check_las_size(path)
    pf = header.point_format
    dtypes: dict[str, np.dtype[Any]] = {a: np.dtype(np.float64) for a in XYZ}
    names: list[str] = []
    for dim in pf.dimensions:
        if dim.name in ("X", "Y", "Z"):
            continue
        names.append(dim.name)
        dtypes[dim.name] = np.dtype(dim.dtype) if dim.dtype is not None else np.dtype(np.uint8)
    return CloudHeader(
        path=path,
        format=format_name,
        points=int(header.point_count),
        fields=tuple(names),
        dtypes=dtypes,
        bounds=(np.asarray(header.mins, np.float64), np.asarray(header.maxs, np.float64)),
        data_bytes=None if header.are_points_compressed else int(header.point_count) * int(pf.size),
        data_offset=int(header.offset_to_point_data),
        file_bytes=path.stat().st_size,
        crs_reader=lambda: _parse_crs(header, path),
    )


def _parse_crs(header: Any, path: Path) -> Any:
    """The CRS a LAS header's VLRs carry (``pyproj.CRS``), or None."""
    try:
        return header.parse_crs()
    except Exception as exc:  # laspy and pyproj errors alike
        raise PointCloudFormatError(
            f"unreadable CRS in the LAS/LAZ header ({exc})", path=path
        ) from exc
