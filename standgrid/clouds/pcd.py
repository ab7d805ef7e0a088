"""PCD (pypcd4): ascii, binary and binary_compressed, read and written.

A field with COUNT > 1 becomes one ``(N, COUNT)`` field; PCL padding fields (``_``) are
dropped. Truncated data, WIDTH*HEIGHT != POINTS, a wrong ASCII row count and missing
``x y z`` raise :class:`~standgrid.errors.PointCloudFormatError` naming the file and the
header line where there is one. ``VIEWPOINT`` is ``tx ty tz qw qx qy qz`` (w first): the
header gives it as a 4x4 pose, and :func:`write_pcd` takes one.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import DTypeLike, NDArray

from standgrid.clouds.base import XYZ, CloudHeader, CloudReader
from standgrid.errors import PointCloudFormatError
from standgrid.geometry import Matrix4
from standgrid.pointcloud import PointCloud

SUFFIXES = (".pcd",)
#: PCD coordinates are written as float32 only up to this magnitude (base-frame payloads:
#: steps of ~0.06 mm at 1e3 m); anything larger (map or projected frames) as float64.
PCD_FLOAT32_LIMIT = 1e3
_PCD_PAD_PREFIX = "#$%&~~"  # pypcd4's name for PCL "_" padding fields
_PCD_HEADER_KEYS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
)
Encoding = Literal["ascii", "binary", "binary_compressed"]


def sniff(head: bytes) -> bool:
    """Whether a file's first bytes are a PCD header (a comment or a header key first)."""
    first = head.lstrip().split(maxsplit=1)[:1]
    return bool(first) and (
        first[0].startswith(b"#") or first[0].upper() in (b"VERSION", b"FIELDS")
    )


class PcdReader(CloudReader):
    """A PCD file (header parsed and checked on every read; nothing held open)."""

    format = "pcd"

    def _read_header(self) -> CloudHeader:
        return _pcd_header(self.path).to_cloud_header()

    def _read_all(self) -> PointCloud:
        return _read_pcd(self.path)


@dataclass(frozen=True)
class _PcdHeader:
    path: Path
    metadata: Any  # pypcd4.MetaData
    data_offset: int
    viewpoint: Matrix4 | None
    line_of: dict[str, int]

    @property
    def encoding(self) -> str:
        return str(self.metadata.data.value)

    def to_cloud_header(self) -> CloudHeader:
        md = self.metadata
        dtypes: dict[str, np.dtype[Any]] = {}
        names: list[str] = []
        for name, t, size, count in zip(md.fields, md.type, md.size, md.count, strict=True):
            if name.startswith(_PCD_PAD_PREFIX):
                continue
            dtypes[name] = _pcd_numpy_type(t, size, self)
            if name not in XYZ:
                names.append(name)
            del count
        return CloudHeader(
            path=self.path,
            format="pcd",
            points=int(md.points),
            fields=tuple(names),
            dtypes=dtypes,
            viewpoint=self.viewpoint,
            encoding=self.encoding,
            data_bytes=self.data_bytes(),
            data_offset=self.data_offset,
            file_bytes=self.path.stat().st_size,
        )

    def data_bytes(self) -> int | None:
        """Bytes the data section needs: binary from the header; binary_compressed from the
        compressed size stored at its start (8 bytes of sizes + the payload); ASCII None."""
        md = self.metadata
        if self.encoding == "binary":
            row = sum(int(size) * int(count) for size, count in zip(md.size, md.count, strict=True))
            return int(md.points) * row
        if self.encoding == "binary_compressed":
            with self.path.open("rb") as fp:
                fp.seek(self.data_offset)
                sizes = fp.read(8)
            if len(sizes) < 8:
                return 8
            compressed, _ = struct.unpack("<II", sizes)
            return 8 + int(compressed)
        return None


def _pcd_numpy_type(t: str, size: int, header: _PcdHeader) -> np.dtype[Any]:
    from pypcd4.pypcd4 import PCD_TYPE_TO_NUMPY_TYPE

    try:
        return np.dtype(PCD_TYPE_TO_NUMPY_TYPE[(t, size)])
    except KeyError:
        raise PointCloudFormatError(
            f"unsupported PCD TYPE {t} SIZE {size}",
            path=header.path,
            line=header.line_of.get("TYPE"),
        ) from None


def _viewpoint_to_pose(values: Sequence[float]) -> Matrix4:
    """PCD ``tx ty tz qw qx qy qz`` -> T (4x4)."""
    from standgrid.geometry import pose_matrix

    t = np.asarray(values[:3], dtype=np.float64)
    qw, qx, qy, qz = (float(v) for v in values[3:7])
    return pose_matrix(t, [qx, qy, qz, qw])


def _pose_to_viewpoint(pose: Matrix4) -> tuple[float, ...]:
    """T (4x4) -> PCD ``tx ty tz qw qx qy qz``."""
    from standgrid.geometry import translation_quat

    t, q = translation_quat(np.asarray(pose, dtype=np.float64))
    return (*map(float, t), float(q[3]), float(q[0]), float(q[1]), float(q[2]))


def _pcd_header(path: Path) -> _PcdHeader:
    """Read and validate the PCD header lines (up to and including DATA)."""
    from pydantic import ValidationError
    from pypcd4.pypcd4 import MetaData

    lines: list[str] = []
    line_of: dict[str, int] = {}
    offset = 0
    viewpoint: Matrix4 | None = None
    with path.open("rb") as fp:
        lineno = 0
        while True:
            raw = fp.readline(4096)
            lineno += 1
            if not raw:
                what = "empty file" if offset == 0 else "header ends before its DATA line"
                raise PointCloudFormatError(what, path=path, line=lineno if offset else None)
            offset += len(raw)
            try:
                text = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise PointCloudFormatError(
                    "not a PCD header line", path=path, line=lineno
                ) from None
            if not text or text.startswith("#"):
                continue
            key = text.split()[0].upper()
            if key not in (*_PCD_HEADER_KEYS, "DATA"):
                raise PointCloudFormatError(
                    f"unknown PCD header key {key!r}", path=path, line=lineno
                )
            line_of[key] = lineno
            lines.append(text)
            if key == "VIEWPOINT":
                values = text.split()[1:]
                try:
                    numbers = [float(v) for v in values]
                except ValueError:
                    numbers = []
                if len(numbers) != 7 or not np.isfinite(numbers).all():
                    raise PointCloudFormatError("VIEWPOINT needs 7 numbers", path=path, line=lineno)
                if np.linalg.norm(numbers[3:]) < 1e-12:
                    raise PointCloudFormatError(
                        "VIEWPOINT has a zero quaternion", path=path, line=lineno
                    )
                viewpoint = _viewpoint_to_pose(numbers)
            if key == "DATA":
                break
    try:
        metadata = MetaData.parse_header(lines)
    except (ValidationError, ValueError, IndexError) as exc:
        raise PointCloudFormatError(f"invalid PCD header ({_first_error(exc)})", path=path) from exc
    md = metadata
    n_fields = len(md.fields)
    entries: tuple[tuple[str, tuple[Any, ...]], ...] = (
        ("SIZE", md.size),
        ("TYPE", md.type),
        ("COUNT", md.count),
    )
    for key, entry in entries:
        if len(entry) != n_fields:
            raise PointCloudFormatError(
                f"{key} has {len(entry)} entries for {n_fields} fields",
                path=path,
                line=line_of.get(key),
            )
    if md.width * md.height != md.points:
        raise PointCloudFormatError(
            f"WIDTH*HEIGHT = {md.width}*{md.height} != POINTS {md.points}",
            path=path,
            line=line_of.get("POINTS"),
        )
    return _PcdHeader(path, metadata, offset, viewpoint, line_of)


def _first_error(exc: Exception) -> str:
    errors = getattr(exc, "errors", None)
    if callable(errors):
        first = errors()[0]
        return f"{'.'.join(map(str, first.get('loc', ())))}: {first.get('msg')}"
    return str(exc)


def _read_pcd(path: Path) -> PointCloud:
    from pypcd4 import PointCloud as PcdCloud

    header = _pcd_header(path)
    md = header.metadata
    dtype = md.build_dtype()
    size = path.stat().st_size
    encoding = header.encoding
    if encoding == "binary":
        need = header.data_offset + md.points * dtype.itemsize
        if size < need:
            raise PointCloudFormatError(
                f"truncated binary PCD: header says {md.points} points ({need} bytes), "
                f"file has {size} bytes "
                f"({(size - header.data_offset) // dtype.itemsize} whole points)",
                path=path,
            )
        if size - need >= dtype.itemsize > 0:
            raise PointCloudFormatError(
                f"binary PCD holds {(size - header.data_offset) // dtype.itemsize} whole points, "
                f"header says POINTS {md.points}",
                path=path,
                line=header.line_of.get("POINTS"),
            )
    elif encoding in ("binary_compressed", "binaryscompressed") and md.points > 0:
        with path.open("rb") as fp:
            fp.seek(header.data_offset)
            sizes = fp.read(8)
        if len(sizes) < 8:
            raise PointCloudFormatError("truncated compressed PCD: no size words", path=path)
        compressed, uncompressed = struct.unpack("II", sizes)
        if size < header.data_offset + 8 + compressed:
            raise PointCloudFormatError(
                f"truncated compressed PCD: {compressed} compressed bytes expected, "
                f"file has {size - header.data_offset - 8}",
                path=path,
            )
        if uncompressed != md.points * dtype.itemsize:
            raise PointCloudFormatError(
                f"compressed PCD holds {uncompressed} bytes, header says "
                f"{md.points} points x {dtype.itemsize} bytes",
                path=path,
            )
    try:
        pcd = PcdCloud.from_path(path)
    except Exception as exc:  # pypcd4 / lzf / numpy raise assorted generic errors
        if encoding == "ascii":
            _raise_bad_ascii_row(header, exc)
        raise PointCloudFormatError(f"unreadable {encoding} PCD data ({exc})", path=path) from exc
    data = np.atleast_1d(pcd.pc_data)
    if len(data) != md.points:
        line = None
        if encoding == "ascii":
            line = _data_first_line(header) + len(data)
        raise PointCloudFormatError(
            f"header says POINTS {md.points}, data holds {len(data)}", path=path, line=line
        )
    return _structured_to_cloud(data, md, header)


def _data_first_line(header: _PcdHeader) -> int:
    return header.line_of["DATA"] + 1


def _raise_bad_ascii_row(header: _PcdHeader, exc: Exception) -> None:
    """Find the first ASCII data row that does not parse and raise with its line."""
    width = int(sum(header.metadata.count))
    with header.path.open("rb") as fp:
        fp.seek(header.data_offset)
        for lineno, raw in enumerate(fp, start=_data_first_line(header)):
            tokens = raw.split()
            if not tokens:
                continue
            if len(tokens) != width:
                raise PointCloudFormatError(
                    f"ASCII row has {len(tokens)} values, fields need {width}",
                    path=header.path,
                    line=lineno,
                ) from exc
            try:
                [float(t) for t in tokens]
            except ValueError:
                raise PointCloudFormatError(
                    f"ASCII row has a non-numeric value: {raw.decode(errors='replace').strip()!r}",
                    path=header.path,
                    line=lineno,
                ) from exc
    raise PointCloudFormatError(f"unreadable ascii PCD data ({exc})", path=header.path) from exc


def _structured_to_cloud(data: NDArray[Any], md: Any, header: _PcdHeader) -> PointCloud:
    names = data.dtype.names or ()
    for axis in XYZ:
        if axis not in names:
            raise PointCloudFormatError(
                f"PCD has no {axis!r} field (fields: {list(md.fields)})",
                path=header.path,
                line=header.line_of.get("FIELDS"),
            )
    xyz = np.empty((len(data), 3), dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # garbage is caught by the checks
        for k, axis in enumerate(XYZ):
            xyz[:, k] = data[axis]
    fields: dict[str, NDArray[Any]] = {}
    for name, count in zip(md.fields, md.count, strict=True):
        if name in XYZ or name.startswith(_PCD_PAD_PREFIX):
            continue
        if count == 1:
            fields[name] = np.array(data[name])
        else:
            fields[name] = np.stack([data[f"{name}__{c:04d}"] for c in range(count)], axis=1)
    return PointCloud(xyz, fields)


def _pcd_value_dtype(values: NDArray[Any], name: str, dst: Path) -> np.dtype[Any]:
    from pypcd4.pypcd4 import NUMPY_TYPE_TO_PCD_TYPE

    dt = values.dtype
    if dt == np.bool_:
        return np.dtype(np.uint8)
    if dt == np.float16:
        return np.dtype(np.float32)
    if dt.newbyteorder("=") in NUMPY_TYPE_TO_PCD_TYPE:
        return dt.newbyteorder("=")
    raise PointCloudFormatError(f"field {name!r}: dtype {dt} cannot be stored in a PCD", path=dst)


def write_pcd(
    cloud: PointCloud,
    dst: Path,
    *,
    viewpoint: Matrix4 | None = None,
    encoding: str = "binary",
    xyz_dtype: DTypeLike | None = None,
) -> None:
    """Write ``cloud`` as a PCD (pypcd4), atomically.

    ``encoding`` ascii / binary / binary_compressed; ``x y z`` float32 (the convention for
    base-frame payloads) unless a coordinate exceeds 1e3 m in magnitude
    (:data:`PCD_FLOAT32_LIMIT`: map-frame clouds keep float64) or ``xyz_dtype=np.float64``;
    ``viewpoint`` T (default identity) is written as ``tx ty tz qw qx qy qz``. Bool fields
    are stored as uint8. pypcd4 writes ASCII floats with 10 decimals and falls back to
    ``binary`` when LZF cannot shrink the data.
    """
    from pypcd4 import Encoding as PcdEncoding
    from pypcd4 import PointCloud as PcdCloud
    from pypcd4.pypcd4 import NUMPY_TYPE_TO_PCD_TYPE, MetaData

    from standgrid._atomic import atomic_output

    if xyz_dtype is None:
        big = len(cloud) and float(np.nanmax(np.abs(cloud.xyz))) > PCD_FLOAT32_LIMIT
        coord_dtype = np.dtype(np.float64 if big else np.float32)
    else:
        coord_dtype = np.dtype(xyz_dtype)
        if coord_dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
            raise PointCloudFormatError("xyz_dtype must be float32 or float64", path=dst)
    try:
        pcd_encoding = PcdEncoding(encoding)
    except ValueError:
        raise PointCloudFormatError(f"unknown PCD encoding {encoding!r}", path=dst) from None
    names: list[str] = list(XYZ)
    types: list[np.dtype[Any]] = [coord_dtype] * 3
    counts: list[int] = [1, 1, 1]
    columns: list[NDArray[Any]] = [cloud.xyz[:, k] for k in range(3)]
    for name, values in cloud.fields.items():
        if name in XYZ or not name or any(c.isspace() for c in name):
            raise PointCloudFormatError(f"field name {name!r} cannot be written to a PCD", path=dst)
        dt = _pcd_value_dtype(values, name, dst)
        cols = values.reshape(len(values), int(np.prod(values.shape[1:])))  # 0 points too
        names.append(name)
        types.append(dt)
        counts.append(cols.shape[1])
        columns.extend(cols[:, c] for c in range(cols.shape[1]))
    vp = (
        _pose_to_viewpoint(viewpoint)
        if viewpoint is not None
        else (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    )
    pcd_types = [NUMPY_TYPE_TO_PCD_TYPE[t] for t in types]
    metadata = MetaData.model_validate(
        {
            "fields": tuple(names),
            "size": tuple(size for _, size in pcd_types),
            "type": tuple(kind for kind, _ in pcd_types),
            "count": tuple(counts),
            "points": len(cloud),
            "width": len(cloud),
            "height": 1,
            "viewpoint": vp,
        }
    )
    data = np.empty(len(cloud), dtype=metadata.build_dtype())
    for column_name, column in zip(data.dtype.names or (), columns, strict=True):
        data[column_name] = column
    with atomic_output(dst) as tmp:
        PcdCloud(metadata, data).save(tmp, encoding=pcd_encoding)
