"""The point-cloud formats, in one table: name, suffixes, magic-bytes sniff, reader, writer.

:func:`open_cloud` finds a file's format by its suffix (a longer one first: ``.copc.laz``
before ``.laz``) or, for a suffix no format has, by its first bytes, and returns the
format's :class:`~standgrid.clouds.base.CloudReader`, as ``laspy.open`` does for LAS.
:func:`read_cloud`, :func:`read_cloud_header`, :func:`iter_cloud_chunks` and
:func:`write_cloud` are thin functions over it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from numpy.typing import DTypeLike

from standgrid.clouds import las, pcd, ply
from standgrid.clouds.base import CloudHeader, CloudReader, check_cloud_file
from standgrid.clouds.las_write import write_las_cloud
from standgrid.errors import PointCloudFormatError
from standgrid.geometry import Matrix4
from standgrid.pointcloud import PointCloud

#: Bytes read from a file's start to sniff its format.
SNIFF_BYTES = 512


@dataclass(frozen=True)
class WriteOptions:
    """What :func:`write_cloud` may be told; each format takes what it can store."""

    viewpoint: Matrix4 | None = None
    encoding: pcd.Encoding = "binary"
    xyz_dtype: DTypeLike | None = None
    las_scale: float = 0.001
    crs: str | None = None


@dataclass(frozen=True)
class CloudFormat:
    """One point-cloud format."""

    name: str
    #: File-name endings, lower case (``.copc.laz``: more than one suffix).
    suffixes: tuple[str, ...]
    reader: Callable[[Path, str], CloudReader]
    #: Whether a file's first :data:`SNIFF_BYTES` are of this format; None: not told apart.
    sniff: Callable[[bytes], bool] | None = None
    #: Writes a cloud to a path atomically; None: read only.
    writer: Callable[[PointCloud, Path, WriteOptions], None] | None = None
    #: Whether the format stores a viewpoint (a sensor pose).
    viewpoint: bool = False


def _write_pcd(cloud: PointCloud, dst: Path, options: WriteOptions) -> None:
    pcd.write_pcd(
        cloud,
        dst,
        viewpoint=options.viewpoint,
        encoding=options.encoding,
        xyz_dtype=options.xyz_dtype,
    )


def _write_ply(cloud: PointCloud, dst: Path, options: WriteOptions) -> None:
    ply.write_ply(cloud, dst)


def _write_las(cloud: PointCloud, dst: Path, options: WriteOptions) -> None:
    write_las_cloud(cloud, dst, laz=False, scale=options.las_scale, crs=options.crs)


def _write_laz(cloud: PointCloud, dst: Path, options: WriteOptions) -> None:
    write_las_cloud(cloud, dst, laz=True, scale=options.las_scale, crs=options.crs)


#: Every format. COPC is LAZ read alike (its suffix ends in ``.laz``: the longest suffix
#: that fits wins); it is written by the tile writer (``standgrid.export.copc``) only.
FORMATS: tuple[CloudFormat, ...] = (
    CloudFormat("pcd", pcd.SUFFIXES, pcd.PcdReader, pcd.sniff, _write_pcd, viewpoint=True),
    CloudFormat("ply", ply.SUFFIXES, ply.PlyReader, ply.sniff, _write_ply),
    CloudFormat("las", las.LAS_SUFFIXES, las.LasReader, las.sniff_las, _write_las),
    CloudFormat("laz", las.LAZ_SUFFIXES, las.LasReader, las.sniff_laz, _write_laz),
    CloudFormat("copc", las.COPC_SUFFIXES, las.LasReader, las.sniff_copc),
)
#: The last suffix (``Path.suffix``) of every format's files.
CLOUD_EXTENSIONS: tuple[str, ...] = tuple(
    dict.fromkeys("." + s.rsplit(".", 1)[1] for f in FORMATS for s in f.suffixes)
)


def format_by_suffix(path: Path) -> CloudFormat | None:
    """The format whose suffix ``path``'s name ends in (the longest that fits), or None."""
    name = path.name.lower()
    fits = [(len(s), f) for f in FORMATS for s in f.suffixes if name.endswith(s)]
    return max(fits, key=lambda fit: fit[0])[1] if fits else None


def sniff_format(path: Path) -> CloudFormat | None:
    """The format a file's first bytes say, or None."""
    try:
        with path.open("rb") as fp:
            head = fp.read(SNIFF_BYTES)
    except OSError as exc:
        raise PointCloudFormatError(f"cannot read the file ({exc})", path=path) from exc
    return next((f for f in FORMATS if f.sniff is not None and f.sniff(head)), None)


def open_cloud(path: str | Path) -> CloudReader:
    """The reader of a cloud file, its format told by its suffix, else by its first bytes.

    Nothing but the file's existence is checked here: the header is read on first use of
    ``.header``, the points by ``.read()`` and ``.chunks(n)``."""
    src = Path(path)
    check_cloud_file(src)
    found = format_by_suffix(src) or sniff_format(src)
    if found is None:
        raise PointCloudFormatError(
            f"unknown point-cloud extension {src.suffix.lower()!r}", path=src
        )
    return found.reader(src, found.name)


def read_cloud(path: str | Path, *, fields: Sequence[str] | None = None) -> PointCloud:
    """Every point of a ``.pcd``, ``.ply``, ``.las``/``.laz`` or COPC file (``fields``: keep
    only these)."""
    return open_cloud(path).read(fields)


def read_cloud_header(path: str | Path) -> CloudHeader:
    """Point count, field names, viewpoint, bounds and CRS of a cloud file, from its header."""
    return open_cloud(path).header


def iter_cloud_chunks(path: str | Path, chunk_points: int) -> Iterator[PointCloud]:
    """A cloud file as clouds of at most ``chunk_points`` points: LAS/LAZ stream through
    laspy's chunk iterator (bounded memory); PCD and PLY are read whole and sliced."""
    if chunk_points < 1:
        raise ValueError("chunk_points must be >= 1")
    return open_cloud(path).chunks(chunk_points)


def write_cloud(
    cloud: PointCloud,
    path: str | Path,
    *,
    viewpoint: Matrix4 | None = None,
    encoding: pcd.Encoding = "binary",
    xyz_dtype: DTypeLike | None = None,
    las_scale: float = 0.001,
    crs: str | None = None,
) -> None:
    """Write ``cloud`` in the format of ``path``'s suffix, atomically.

    PCD (:func:`~standgrid.clouds.pcd.write_pcd`): ``encoding``, ``xyz_dtype`` and the
    ``viewpoint`` T. PLY (:func:`~standgrid.clouds.ply.write_ply`): binary, float64 ``x y z``.
    LAS/LAZ (:func:`~standgrid.clouds.las_write.write_las_cloud`, the one LAS encoder):
    ``las_scale`` quantum, ``crs`` ("EPSG:XXXX" or WKT) as a WKT VLR. A format that cannot
    store what is asked raises :class:`~standgrid.errors.PointCloudFormatError` naming
    ``path``.
    """
    dst = Path(path)
    found = format_by_suffix(dst)
    if found is None:
        raise PointCloudFormatError(
            f"unknown point-cloud extension {dst.suffix.lower()!r}", path=dst
        )
    if found.writer is None:
        raise PointCloudFormatError(f"{found.name} files are not written here", path=dst)
    if viewpoint is not None and not found.viewpoint:
        raise PointCloudFormatError("only PCD stores a viewpoint", path=dst)
    options = WriteOptions(viewpoint, encoding, xyz_dtype, las_scale, crs)
    found.writer(cloud, dst, options)
