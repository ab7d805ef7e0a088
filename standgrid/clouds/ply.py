"""PLY (plyfile): the ``vertex`` element read (faces are not points), binary written.

A header whose element counts the file cannot hold, a missing ``x y z`` and list
properties on the vertex raise :class:`~standgrid.errors.PointCloudFormatError` naming the
file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from standgrid.clouds.base import XYZ, CloudHeader, CloudReader
from standgrid.errors import PointCloudFormatError
from standgrid.pointcloud import PointCloud

SUFFIXES = (".ply",)
_PLY_BYTE_ORDER = {"<": "binary_little_endian", ">": "binary_big_endian"}


def sniff(head: bytes) -> bool:
    """Whether a file's first bytes are a PLY header."""
    return head[:4] in (b"ply\n", b"ply\r")


class PlyReader(CloudReader):
    """A PLY file (header parsed and checked on every read; nothing held open)."""

    format = "ply"

    def _read_header(self) -> CloudHeader:
        return _ply_header(self.path)

    def _read_all(self) -> PointCloud:
        return _read_ply(self.path)


def _ply_error(path: Path, exc: Exception) -> PointCloudFormatError:
    return PointCloudFormatError(f"unreadable PLY ({exc})", path=path)


def _ply_vertex_element(ply: Any, path: Path) -> Any:
    try:
        return ply["vertex"]
    except KeyError:
        raise PointCloudFormatError("PLY has no 'vertex' element", path=path) from None


def _ply_header(path: Path) -> CloudHeader:
    from plyfile import PlyData, PlyListProperty, PlyParseError

    offset = 0
    try:
        with path.open("rb") as fp:
            parse = getattr(PlyData, "_parse_header", None)
            ply = parse(fp) if parse is not None else PlyData.read(fp)
            offset = fp.tell() if parse is not None else 0
    except (PlyParseError, ValueError, UnicodeDecodeError) as exc:
        raise _ply_error(path, exc) from exc
    vertex = _ply_vertex_element(ply, path)
    data_bytes: int | None = None
    if not ply.text and parse is not None:  # a lower bound: elements up to the first list
        data_bytes = 0
        for element in ply.elements:
            if any(isinstance(p, PlyListProperty) for p in element.properties):
                break
            row = sum(np.dtype(p.val_dtype).itemsize for p in element.properties)
            data_bytes += int(element.count) * row
    dtypes = {
        p.name: np.dtype(p.val_dtype).newbyteorder("=")
        for p in vertex.properties
        if not isinstance(p, PlyListProperty)
    }
    return CloudHeader(
        path=path,
        format="ply",
        points=int(vertex.count),
        fields=tuple(n for n in dtypes if n not in XYZ),
        dtypes=dtypes,
        encoding="ascii" if ply.text else _PLY_BYTE_ORDER.get(ply.byte_order, "binary"),
        data_bytes=data_bytes,
        data_offset=offset,
        file_bytes=path.stat().st_size,
    )


def _check_ply_size(path: Path) -> None:
    """Element counts of a PLY header checked against the file size before reading: every
    row needs at least its fixed-size values (binary) or two bytes per value (ascii)."""
    from plyfile import PlyData, PlyListProperty, PlyParseError

    try:
        with path.open("rb") as fp:
            ply = PlyData._parse_header(fp)
            start = fp.tell()
    except (PlyParseError, ValueError, UnicodeDecodeError, EOFError) as exc:
        raise _ply_error(path, exc) from exc
    available = path.stat().st_size - start
    need = 0
    for element in ply.elements:
        row = 0
        for prop in element.properties:
            if ply.text:
                row += 2  # a digit and a separator at least (a list: its count)
            elif isinstance(prop, PlyListProperty):
                row += np.dtype(prop.len_dtype).itemsize
            else:
                row += np.dtype(prop.val_dtype).itemsize
        need += int(element.count) * row
        if need > available:
            raise PointCloudFormatError(
                f"header says {element.count} {element.name} rows, which need at least "
                f"{need} bytes; the file holds {available} after its header: truncated or a "
                "wrong header",
                path=path,
            )


def _read_ply(path: Path) -> PointCloud:
    from plyfile import PlyData, PlyListProperty, PlyParseError

    _check_ply_size(path)
    try:
        ply = PlyData.read(str(path), mmap=False)
    except (PlyParseError, ValueError, EOFError, UnicodeDecodeError) as exc:
        raise _ply_error(path, exc) from exc
    vertex = _ply_vertex_element(ply, path)
    names = [p.name for p in vertex.properties]
    for p in vertex.properties:
        if isinstance(p, PlyListProperty):
            raise PointCloudFormatError(
                f"PLY vertex list property {p.name!r} is not supported", path=path
            )
    for axis in XYZ:
        if axis not in names:
            raise PointCloudFormatError(f"PLY vertex element has no {axis!r} property", path=path)
    data = vertex.data
    xyz = np.empty((len(data), 3), dtype=np.float64)
    for k, axis in enumerate(XYZ):
        xyz[:, k] = data[axis]
    fields = {
        n: np.array(data[n], dtype=data.dtype[n].newbyteorder("=")) for n in names if n not in XYZ
    }
    return PointCloud(xyz, fields)


def write_ply(cloud: PointCloud, dst: Path) -> None:
    """Write ``cloud`` as a binary PLY (plyfile), float64 ``x y z``, atomically."""
    from plyfile import PlyData, PlyElement

    from standgrid._atomic import atomic_output

    descr: list[tuple[str, str]] = [(a, "f8") for a in XYZ]
    for name, values in cloud.fields.items():
        if values.ndim != 1:
            raise PointCloudFormatError(f"PLY field {name!r} must be one value per point", path=dst)
        dt = np.dtype(np.uint8) if values.dtype == np.bool_ else values.dtype.newbyteorder("=")
        descr.append((name, dt.str))
    try:
        data = np.empty(len(cloud), dtype=descr)
        for k, axis in enumerate(XYZ):
            data[axis] = cloud.xyz[:, k]
        for name, values in cloud.fields.items():
            data[name] = values
        element = PlyElement.describe(data, "vertex")
    except (ValueError, TypeError) as exc:
        raise PointCloudFormatError(f"cannot write PLY ({exc})", path=dst) from exc
    with atomic_output(dst) as tmp:
        try:
            PlyData([element], text=False).write(str(tmp))
        except (ValueError, TypeError) as exc:
            raise PointCloudFormatError(f"cannot write PLY ({exc})", path=dst) from exc
