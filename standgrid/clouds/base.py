"""What every point-cloud format shares: the header, the reader, the checks of what is read.

A :class:`CloudReader` is one open file, in the manner of ``laspy.open``: its
:attr:`~CloudReader.header` (read on first use, without the points), :meth:`~CloudReader.read`
for every point and :meth:`~CloudReader.chunks` for bounded pieces. Readers return a
:class:`~standgrid.pointcloud.PointCloud`: ``xyz`` float64 and every other per-point field of
the file under its own name and dtype.

Bad files raise :class:`~standgrid.errors.PointCloudFormatError` naming the file; a missing
file :class:`~standgrid.errors.MissionNotFoundError`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import MissionNotFoundError, PointCloudFormatError
from standgrid.geometry import Matrix4
from standgrid.pointcloud import PointCloud

XYZ = ("x", "y", "z")
#: No coordinate of a real cloud (base frame, map or projected CRS) is this far from 0 (m);
#: garbled binary data is.
MAX_COORDINATE_M = 1e9


@dataclass(frozen=True, eq=False)
class CloudHeader:
    """What a cloud file's header says, read without the points."""

    path: Path
    format: str  # a registry name: "pcd", "ply", "las", "laz" or "copc"
    points: int
    #: Non-coordinate field names, as :meth:`CloudReader.read` returns them.
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
    #: Parses the CRS the file carries (LAS); None for formats that carry none.
    crs_reader: Callable[[], Any] | None = field(default=None, repr=False)

    @cached_property
    def crs(self) -> Any:
        """The CRS the file carries (a ``pyproj.CRS``, parsed on first use), or None."""
        return self.crs_reader() if self.crs_reader is not None else None

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


class CloudReader:
    """One cloud file, opened: ``header``, ``read()`` and ``chunks(n_points)``.

    A format subclasses it with ``_read_header`` and ``_read_all``; ``chunks`` reads the whole
    file and slices it unless the format streams (LAS/LAZ). Usable as a context manager.
    """

    #: The registry name of the format.
    format: ClassVar[str] = ""

    def __init__(self, path: Path, format_name: str | None = None) -> None:
        self.path = path
        self.format_name = format_name or self.format

    @cached_property
    def header(self) -> CloudHeader:
        """Point count, fields, bounds and CRS where known, from the header only."""
        return self._read_header()

    def read(self, fields: Sequence[str] | None = None) -> PointCloud:
        """Every point (``fields``: keep only these), coordinates checked."""
        cloud = self._read_all()
        check_coordinates(cloud.xyz, self.path)
        if fields is not None:
            cloud = PointCloud(cloud.xyz, select_fields(dict(cloud.fields), fields, self.path))
        return cloud

    def chunks(self, n_points: int) -> Iterator[PointCloud]:
        """The points as clouds of at most ``n_points`` (here: read whole, then sliced)."""
        if n_points < 1:
            raise ValueError("chunk_points must be >= 1")
        cloud = self.read()
        for start in range(0, len(cloud), n_points):
            stop = start + n_points
            yield PointCloud(
                cloud.xyz[start:stop], {k: v[start:stop] for k, v in cloud.fields.items()}
            )

    def _read_header(self) -> CloudHeader:
        raise NotImplementedError

    def _read_all(self) -> PointCloud:
        raise NotImplementedError

    def close(self) -> None:
        """Nothing is held open between calls; kept for the ``with`` form."""

    def __enter__(self) -> CloudReader:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.format_name} {self.path}>"


def check_cloud_file(path: Path) -> None:
    """A typed error unless ``path`` is a file (a folder, or nothing, named like a cloud)."""
    if path.is_dir():
        raise PointCloudFormatError("is a folder, not a point-cloud file", path=path)
    if not path.is_file():
        raise MissionNotFoundError("point cloud not found", path=path)


def check_coordinates(xyz: NDArray[np.float64], path: Path) -> None:
    """Refuse NaN, infinite and garbled (beyond :data:`MAX_COORDINATE_M`) coordinates."""
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


def select_fields(
    fields: dict[str, NDArray[Any]], wanted: Sequence[str] | None, path: Path
) -> dict[str, NDArray[Any]]:
    """``fields`` reduced to ``wanted`` (all when None); a missing one is an error."""
    if wanted is None:
        return fields
    missing = [n for n in wanted if n not in fields]
    if missing:
        raise PointCloudFormatError(
            f"no field(s) {missing}; the file has {sorted(fields)}", path=path
        )
    return {n: fields[n] for n in wanted}
