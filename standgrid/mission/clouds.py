"""Point-cloud files: PCD (pypcd4), PLY (plyfile) and LAS/LAZ (laspy), read by extension.

Every reader returns a :class:`~standgrid.pointcloud.PointCloud`: ``xyz`` float64 (LAS: the
scaled coordinates) and every other per-point field of the file under its own name and
dtype. A PCD field with COUNT > 1 becomes one ``(N, COUNT)`` field; PCL padding fields
(``_``) are dropped. Only the ``vertex`` element of a PLY is read (faces are not points).

Bad files raise :class:`~standgrid.errors.PointCloudFormatError` naming the file (and the
header line where there is one): truncated data, WIDTH*HEIGHT != POINTS, a wrong ASCII row
count, missing ``x y z`` and NaN/infinite coordinates (NaN in other fields is fine). A
missing file raises :class:`~standgrid.errors.MissionNotFoundError`.

PCD ``VIEWPOINT`` is ``tx ty tz qw qx qy qz`` (w first); :func:`read_cloud_header` returns it
as a 4x4 pose, and :func:`write_cloud` takes one.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import DTypeLike, NDArray

from standgrid.errors import MissionNotFoundError, PointCloudFormatError
from standgrid.geometry import Matrix4
from standgrid.pointcloud import PointCloud

PCD_EXTENSIONS = (".pcd",)
PLY_EXTENSIONS = (".ply",)
LAS_EXTENSIONS = (".las", ".laz")
CLOUD_EXTENSIONS = PCD_EXTENSIONS + PLY_EXTENSIONS + LAS_EXTENSIONS
#: PCD coordinates are written as float32 only up to this magnitude (base-frame payloads:
#: steps of ~0.06 mm at 1e3 m); anything larger (map or projected frames) as float64.
PCD_FLOAT32_LIMIT = 1e3
_XYZ = ("x", "y", "z")
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

_PLY_BYTE_ORDER = {"<": "binary_little_endian", ">": "binary_big_endian"}
Encoding = Literal["ascii", "binary", "binary_compressed"]


@dataclass(frozen=True, eq=False)
class CloudHeader:
    """What a cloud file's header says, read without the points."""

    path: Path
    format: str  # "pcd", "ply", "las" or "laz"
    points: int
    #: Non-coordinate field names, as :func:`read_cloud` returns them.
    fields: tuple[str, ...]
    #: dtype of every stored value, ``x y z`` included (LAS: the scaled float64 coordinates).
    dtypes: dict[str, np.dtype[Any]] = field(default_factory=dict)
    #: PCD VIEWPOINT as T (4x4); None for formats without one or a PCD without the line.
    viewpoint: Matrix4 | None = None
    #: PCD data encoding / PLY format; None for LAS.
    encoding: str | None = None
    #: LAS header bounds ``(mins, maxs)``; None otherwise.
    bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    #: Bytes of point data the header announces (at least), from ``data_offset`` on; None
    #: where the header cannot tell (ASCII PCD/PLY, LAZ).
    data_bytes: int | None = None
    data_offset: int = 0
    #: Size of the file on disk.
    file_bytes: int = 0

    def size_problem(self) -> str | None:
        """Why the file cannot hold what its header announces (truncated), or None."""
        if self.data_bytes is None:
            return None
        present = self.file_bytes - self.data_offset
        if present >= self.data_bytes:
            return None
        return (
            f"truncated: the header announces {self.points:,} points "
            f"({self.data_bytes:,} bytes of {self.encoding or self.format} data), "
            f"the file holds {max(present, 0):,} bytes after its header"
        )


def _suffix(path: Path) -> str:
    return path.suffix.lower()


def check_cloud_file(path: Path) -> None:
    """A typed error unless ``path`` is a file (a folder, or nothing, named like a cloud)."""
    if path.is_dir():
        raise PointCloudFormatError("is a folder, not a point-cloud file", path=path)
    if not path.is_file():
        raise MissionNotFoundError("point cloud not found", path=path)


#: No coordinate of a real cloud (base frame, map or projected CRS) is this far from 0 (m);
#: garbled binary data is.
MAX_COORDINATE_M = 1e9


def _check_coordinates(xyz: NDArray[np.float64], path: Path) -> None:
    if not len(xyz) or (xyz.min() >= -MAX_COORDINATE_M and xyz.max() <= MAX_COORDINATE_M):
        return  # two passes over the data; NaN fails both comparisons and is found below
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise PointCloudFormatError(
            f"{int(bad.sum())} of {len(xyz)} points have NaN or infinite coordinates "
            f"(first at index {first})",
            path=path,
        )
    huge = (np.abs(xyz) > MAX_COORDINATE_M).any(axis=1)
    if huge.any():
        first = int(np.argmax(huge))
        raise PointCloudFormatError(
            f"{int(huge.sum())} of {len(xyz)} points have coordinates beyond "
            f"{MAX_COORDINATE_M:g} m (first at index {first}: {xyz[first].tolist()}); the "
            "point data is garbled or not in metres",
            path=path,
        )


def _select(fields: dict[str, NDArray[Any]], wanted: Sequence[str] | None, path: Path) -> dict:
    if wanted is None:
        return fields
    missing = [n for n in wanted if n not in fields]
    if missing:
        raise PointCloudFormatError(
            f"no field(s) {missing}; the file has {sorted(fields)}", path=path
        )
    return {n: fields[n] for n in wanted}


# --- public entry points ---------------------------------------------------------------------


def read_cloud(path: str | Path, *, fields: Sequence[str] | None = None) -> PointCloud:
    """Read a ``.pcd``, ``.ply``, ``.las`` or ``.laz`` file (``fields``: keep only these)."""
    src = Path(path)
    check_cloud_file(src)
    ext = _suffix(src)
    if ext in PCD_EXTENSIONS:
        cloud = _read_pcd(src)
    elif ext in PLY_EXTENSIONS:
        cloud = _read_ply(src)
    elif ext in LAS_EXTENSIONS:
        cloud = _read_las(src)
    else:
        raise PointCloudFormatError(f"unknown point-cloud extension {ext!r}", path=src)
    _check_coordinates(cloud.xyz, src)
    if fields is not None:
        cloud = PointCloud(cloud.xyz, _select(dict(cloud.fields), fields, src))
    return cloud


def read_cloud_header(path: str | Path) -> CloudHeader:
    """Point count, field names and viewpoint of a cloud file, from its header only."""
    src = Path(path)
    check_cloud_file(src)
    ext = _suffix(src)
    if ext in PCD_EXTENSIONS:
        return _pcd_header(src).to_cloud_header()
    if ext in PLY_EXTENSIONS:
        return _ply_header(src)
    if ext in LAS_EXTENSIONS:
        return _las_header(src)
    raise PointCloudFormatError(f"unknown point-cloud extension {ext!r}", path=src)


def write_cloud(
    cloud: PointCloud,
    path: str | Path,
    *,
    viewpoint: Matrix4 | None = None,
    encoding: Encoding = "binary",
    xyz_dtype: DTypeLike | None = None,
    las_scale: float = 0.001,
    crs: str | None = None,
) -> None:
    """Write ``cloud`` by extension, atomically.

    PCD (pypcd4): ``encoding`` ascii / binary / binary_compressed; ``x y z`` float32 (the
    convention for base-frame payloads) unless a coordinate exceeds 1e3 m in magnitude
    (:data:`PCD_FLOAT32_LIMIT`: map-frame clouds keep float64) or ``xyz_dtype=np.float64``;
    ``viewpoint`` T (default identity) is written as ``tx ty tz qw qx qy qz``. Bool fields
    are stored as uint8. pypcd4 writes ASCII floats with 10 decimals and falls back to
    ``binary`` when LZF cannot shrink the data.
    PLY (plyfile): binary, float64 ``x y z``.
    LAS/LAZ (laspy, 1.4, PDRF 6 or 7 with ``red green blue``): ``las_scale`` quantum,
    offset at the floor of the minimum, standard dimensions filled from same-named fields
    when the cast is lossless (else an error), other fields as extra bytes; ``crs``
    ("EPSG:XXXX" or WKT) as a WKT VLR. A ``gps_time`` field is taken as adjusted standard
    GPS time and flagged so in the header's global encoding.
    """
    from standgrid._atomic import atomic_output

    dst = Path(path)
    ext = _suffix(dst)
    if ext not in CLOUD_EXTENSIONS:
        raise ValueError(f"{dst}: unknown point-cloud extension {ext!r}")
    if viewpoint is not None and ext not in PCD_EXTENSIONS:
        raise ValueError(f"{dst}: only PCD stores a viewpoint")
    with atomic_output(dst) as tmp:
        if ext in PCD_EXTENSIONS:
            _write_pcd(cloud, tmp, viewpoint, encoding, xyz_dtype, dst)
        elif ext in PLY_EXTENSIONS:
            _write_ply(cloud, tmp, dst)
        else:
            _write_las(cloud, tmp, las_scale, crs, dst, compressed=ext == ".laz")


def iter_cloud_chunks(path: str | Path, chunk_points: int) -> Iterator[PointCloud]:
    """Yield a cloud file as clouds of at most ``chunk_points`` points.

    LAS/LAZ stream through laspy's chunk iterator (bounded memory); PCD and PLY are read
    whole and sliced.
    """
    if chunk_points < 1:
        raise ValueError("chunk_points must be >= 1")
    src = Path(path)
    check_cloud_file(src)
    if _suffix(src) in LAS_EXTENSIONS:
        import laspy

        check_las_size(src)
        try:
            with laspy.open(src) as reader:
                done = 0
                for points in reader.chunk_iterator(chunk_points):
                    cloud = _las_points_to_cloud(points)
                    try:
                        _check_coordinates(cloud.xyz, src)
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
        return
    cloud = read_cloud(src)
    for start in range(0, len(cloud), chunk_points):
        stop = start + chunk_points
        yield PointCloud(cloud.xyz[start:stop], {k: v[start:stop] for k, v in cloud.fields.items()})


# --- PCD ---------------------------------------------------------------------------------------


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
            if name not in _XYZ:
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
    for axis in _XYZ:
        if axis not in names:
            raise PointCloudFormatError(
                f"PCD has no {axis!r} field (fields: {list(md.fields)})",
                path=header.path,
                line=header.line_of.get("FIELDS"),
            )
    xyz = np.empty((len(data), 3), dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # garbage is caught by the checks
        for k, axis in enumerate(_XYZ):
            xyz[:, k] = data[axis]
    fields: dict[str, NDArray[Any]] = {}
    for name, count in zip(md.fields, md.count, strict=True):
        if name in _XYZ or name.startswith(_PCD_PAD_PREFIX):
            continue
        if count == 1:
            fields[name] = np.array(data[name])
        else:
            fields[name] = np.stack([data[f"{name}__{c:04d}"] for c in range(count)], axis=1)
    return PointCloud(xyz, fields)


def _pcd_value_dtype(values: NDArray[Any], name: str) -> np.dtype[Any]:
    from pypcd4.pypcd4 import NUMPY_TYPE_TO_PCD_TYPE

    dt = values.dtype
    if dt == np.bool_:
        return np.dtype(np.uint8)
    if dt == np.float16:
        return np.dtype(np.float32)
    if dt.newbyteorder("=") in NUMPY_TYPE_TO_PCD_TYPE:
        return dt.newbyteorder("=")
    raise ValueError(f"field {name!r}: dtype {dt} cannot be stored in a PCD")


def _write_pcd(
    cloud: PointCloud,
    tmp: Path,
    viewpoint: Matrix4 | None,
    encoding: str,
    xyz_dtype: DTypeLike | None,
    dst: Path,
) -> None:
    from pypcd4 import Encoding as PcdEncoding
    from pypcd4 import PointCloud as PcdCloud
    from pypcd4.pypcd4 import NUMPY_TYPE_TO_PCD_TYPE, MetaData

    if xyz_dtype is None:
        big = len(cloud) and float(np.nanmax(np.abs(cloud.xyz))) > PCD_FLOAT32_LIMIT
        coord_dtype = np.dtype(np.float64 if big else np.float32)
    else:
        coord_dtype = np.dtype(xyz_dtype)
        if coord_dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
            raise ValueError(f"{dst}: xyz_dtype must be float32 or float64")
    names: list[str] = list(_XYZ)
    types: list[np.dtype[Any]] = [coord_dtype] * 3
    counts: list[int] = [1, 1, 1]
    columns: list[NDArray[Any]] = [cloud.xyz[:, k] for k in range(3)]
    for name, values in cloud.fields.items():
        if name in _XYZ or not name or any(c.isspace() for c in name):
            raise ValueError(f"{dst}: field name {name!r} cannot be written to a PCD")
        dt = _pcd_value_dtype(values, name)
        cols = values.reshape(len(values), -1)
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
    pcd = PcdCloud(metadata, data)
    try:
        pcd_encoding = PcdEncoding(encoding)
    except ValueError:
        raise ValueError(f"{dst}: unknown PCD encoding {encoding!r}") from None
    pcd.save(tmp, encoding=pcd_encoding)


# --- PLY ---------------------------------------------------------------------------------------


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
        fields=tuple(n for n in dtypes if n not in _XYZ),
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
    for axis in _XYZ:
        if axis not in names:
            raise PointCloudFormatError(f"PLY vertex element has no {axis!r} property", path=path)
    data = vertex.data
    xyz = np.empty((len(data), 3), dtype=np.float64)
    for k, axis in enumerate(_XYZ):
        xyz[:, k] = data[axis]
    fields = {
        n: np.array(data[n], dtype=data.dtype[n].newbyteorder("=")) for n in names if n not in _XYZ
    }
    return PointCloud(xyz, fields)


def _write_ply(cloud: PointCloud, tmp: Path, dst: Path) -> None:
    from plyfile import PlyData, PlyElement

    descr: list[tuple[str, str]] = [(a, "f8") for a in _XYZ]
    for name, values in cloud.fields.items():
        if values.ndim != 1:
            raise ValueError(f"{dst}: PLY field {name!r} must be one value per point")
        dt = np.dtype(np.uint8) if values.dtype == np.bool_ else values.dtype.newbyteorder("=")
        descr.append((name, dt.str))
    data = np.empty(len(cloud), dtype=descr)
    for k, axis in enumerate(_XYZ):
        data[axis] = cloud.xyz[:, k]
    for name, values in cloud.fields.items():
        data[name] = values
    try:
        PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(tmp))
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{dst}: cannot write PLY ({exc})") from exc


# --- LAS / LAZ -----------------------------------------------------------------------------


def _las_points_to_cloud(points: Any) -> PointCloud:
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

    from standgrid.mission.las_header import check_las_header

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
    return _las_points_to_cloud(las.points)


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
    cloud = _las_points_to_cloud(points)
    if window is not None:
        if "gps_time" not in cloud.fields:
            raise PointCloudFormatError("no GPS time: points cannot be cut by time", path=src)
        t = np.asarray(cloud.fields["gps_time"], dtype=np.float64)
        cloud = cloud.select((t >= window[0]) & (t < window[1]))
    _check_coordinates(cloud.xyz, src)
    return cloud


def _las_header(path: Path) -> CloudHeader:
    """The header of a LAS/LAZ file. An uncompressed file shorter than its header announces
    is not an error here: :meth:`CloudHeader.size_problem` says so (readers raise); a LAZ
    file's count is checked against its chunk table (it has no ``data_bytes``)."""
    import laspy

    from standgrid.mission.las_header import check_las_header

    check_las_header(path, points=False)
    try:
        with laspy.open(path) as reader:
            header = reader.header
    except (laspy.errors.LaspyException, ValueError, OSError, EOFError, struct.error) as exc:
        raise PointCloudFormatError(f"unreadable LAS/LAZ header ({exc})", path=path) from exc
    if header.are_points_compressed:
        check_las_size(path)
    pf = header.point_format
    dtypes: dict[str, np.dtype[Any]] = {a: np.dtype(np.float64) for a in _XYZ}
    names: list[str] = []
    for dim in pf.dimensions:
        if dim.name in ("X", "Y", "Z"):
            continue
        names.append(dim.name)
        dtypes[dim.name] = np.dtype(dim.dtype) if dim.dtype is not None else np.dtype(np.uint8)
    return CloudHeader(
        path=path,
        format=_suffix(path).lstrip("."),
        points=int(header.point_count),
        fields=tuple(names),
        dtypes=dtypes,
        bounds=(np.asarray(header.mins, np.float64), np.asarray(header.maxs, np.float64)),
        data_bytes=None if header.are_points_compressed else int(header.point_count) * int(pf.size),
        data_offset=int(header.offset_to_point_data),
        file_bytes=path.stat().st_size,
    )


def _lossless_cast(values: NDArray[Any], dtype: np.dtype[Any]) -> NDArray[Any] | None:
    with np.errstate(invalid="ignore", over="ignore"):
        cast = values.astype(dtype)
        back = cast.astype(values.dtype)
    return cast if np.array_equal(back, values) else None


def _write_las(
    cloud: PointCloud, tmp: Path, scale: float, crs: str | None, dst: Path, *, compressed: bool
) -> None:
    import laspy

    pf_id = 7 if all(c in cloud.fields for c in ("red", "green", "blue")) else 6
    header = laspy.LasHeader(point_format=pf_id, version="1.4")
    header.scales = np.full(3, scale)
    header.offsets = np.floor(cloud.xyz.min(axis=0)) if len(cloud) else np.zeros(3)
    if "gps_time" in cloud.fields:
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    if crs is not None:
        import pyproj

        header.add_crs(pyproj.CRS.from_user_input(crs))
    standard = set(laspy.PointFormat(pf_id).dimension_names)
    extra: list[laspy.ExtraBytesParams] = []
    for name, values in cloud.fields.items():
        if name in standard:
            continue
        if values.ndim != 1:
            raise ValueError(f"{dst}: LAS extra field {name!r} must be one value per point")
        dt = np.dtype(np.uint8) if values.dtype == np.bool_ else values.dtype.newbyteorder("=")
        extra.append(laspy.ExtraBytesParams(name=name, type=dt))
    if extra:
        header.add_extra_dims(extra)
    las = laspy.LasData(header)
    las.points = laspy.ScaleAwarePointRecord.zeros(len(cloud), header=header)
    try:
        las.x = cloud.xyz[:, 0]
        las.y = cloud.xyz[:, 1]
        las.z = cloud.xyz[:, 2]
    except (OverflowError, ValueError) as exc:
        raise ValueError(
            f"{dst}: coordinates do not fit LAS integers at scale {scale} ({exc})"
        ) from exc
    for name, values in cloud.fields.items():
        if name in standard:
            target = np.asarray(las[name]).dtype
            cast = _lossless_cast(np.asarray(values), target)
            if cast is None:
                raise ValueError(
                    f"{dst}: field {name!r} ({values.dtype}) does not fit LAS dimension "
                    f"{name!r} ({target}) without loss; convert or rename it"
                )
            las[name] = cast
        else:
            las[name] = values.astype(np.uint8) if values.dtype == np.bool_ else values
    with tmp.open("wb") as stream:  # a path's suffix (.tmp) would override do_compress
        las.write(stream, do_compress=compressed)
