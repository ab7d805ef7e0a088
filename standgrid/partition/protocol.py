"""One partition protocol: what the stages need of a catalog's cells, grid or Voronoi alike.

A cell has an integer ``key`` (what :meth:`Partition.assign` returns and the partition engine
groups by) and a text id (the tile's name and the ``cell_id`` column). :class:`GridPartition`
(the fixed stand grid) and :class:`VoronoiCells` (cells around payload poses) implement it;
``standgrid.catalog.partition.catalog_partition`` returns the one a catalog uses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import CatalogError
from standgrid.partition.engine import BufferFunction, GridBuffer
from standgrid.partition.grid import CellId, StandGrid
from standgrid.partition.voronoi import VoronoiPartition

#: Rasters of a Voronoi catalog align to a 10 m lattice from (0, 0).
VORONOI_RASTER_SIZE = 10.0


@runtime_checkable
class Partition(Protocol):
    """The cells of a catalog."""

    #: ``"grid"`` or ``"voronoi"`` (what catalog.json records).
    scheme: Literal["grid", "voronoi"]
    #: Origin of the tiles' 1 mm storage lattice (and of tile offsets).
    lattice_origin: tuple[float, float]
    #: True when a cell holds ``xmin <= x < xmax`` (grid); False: closed polygons (Voronoi).
    half_open: bool

    def assign(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
        """The cell key of each point (every point of the plane has one)."""
        ...

    def cell_id(self, key: int) -> str:
        """The text id of a cell key (tile file name, ``cell_id`` column)."""
        ...

    def polygon(self, key: int) -> Any:
        """The cell's polygon (shapely); None when it is not known (Voronoi without coverage)."""
        ...

    def cell_size(self, cell_id: str) -> float:
        """Edge length in metres of a cell (NaN: Voronoi cells have none)."""
        ...

    def stand_of(self, cell_id: str) -> str | None:
        """The id of the stand (next coarser grid level) holding the cell; None without one."""
        ...

    def raster_alignment(self) -> tuple[tuple[float, float], float]:
        """Origin and pixel lattice size rasters of the catalog align to."""
        ...

    def buffer(self, distance: float) -> BufferFunction:
        """Which points are copied into neighbouring cells' buffers (:class:`CatalogError`
        when the scheme has no buffers)."""
        ...


class GridPartition:
    """The stand grid's finest level as a :class:`Partition` (keys: :attr:`CellId.key`)."""

    scheme: Literal["grid", "voronoi"] = "grid"
    half_open = True

    def __init__(self, grid: StandGrid) -> None:
        self.grid = grid
        self.lattice_origin = (float(grid.origin[0]), float(grid.origin[1]))

    def assign(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
        return self.grid.cell_keys(x, y)

    def cell_id(self, key: int) -> str:
        return str(self.grid.key_to_cell(key))

    def polygon(self, key: int) -> Any:
        return self.grid.polygon(self.grid.key_to_cell(key))

    def cell_size(self, cell_id: str) -> float:
        return float(CellId.parse(cell_id).size)

    def stand_of(self, cell_id: str) -> str | None:
        if len(self.grid.levels) < 2:
            return None
        return str(CellId.parse(cell_id).parent(self.grid))

    def raster_alignment(self) -> tuple[tuple[float, float], float]:
        return self.lattice_origin, float(self.grid.cell_size)

    def buffer(self, distance: float) -> BufferFunction:
        return GridBuffer(self.grid, distance)


class VoronoiCells:
    """Voronoi cells around sites (payload poses) as a :class:`Partition` (keys: site index).

    Assignment covers the whole plane; polygons are known once a ``coverage`` is given
    (:meth:`with_coverage`; before that, the sites' hull grown by 1 m stands in).
    """

    scheme: Literal["grid", "voronoi"] = "voronoi"
    half_open = False
    lattice_origin = (0.0, 0.0)

    def __init__(self, xy: ArrayLike, ids: Sequence[str], coverage: Any = None) -> None:
        import shapely

        if len(ids) == 0:
            raise CatalogError("no payloads to build Voronoi cells around")
        pts = np.asarray(xy, dtype=np.float64)
        self._has_coverage = coverage is not None
        area = (
            coverage if coverage is not None else (shapely.MultiPoint(pts).convex_hull.buffer(1.0))
        )
        self.cells = VoronoiPartition(pts, ids, area)
        self._polygons: dict[str, Any] | None = None

    def with_coverage(self, coverage: Any) -> VoronoiCells:
        """The same sites, polygons clipped to ``coverage``."""
        return VoronoiCells(self.cells.xy, self.cells.ids, coverage)

    def assign(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
        return self.cells.assign(x, y)

    def cell_id(self, key: int) -> str:
        return self.cells.ids[int(key)]

    def polygon(self, key: int) -> Any:
        if not self._has_coverage:
            return None
        if self._polygons is None:
            self._polygons = self.cells.polygons()
        return self._polygons.get(self.cell_id(key))

    def cell_size(self, cell_id: str) -> float:
        return math.nan

    def stand_of(self, cell_id: str) -> str | None:
        return None

    def raster_alignment(self) -> tuple[tuple[float, float], float]:
        return self.lattice_origin, VORONOI_RASTER_SIZE

    def buffer(self, distance: float) -> BufferFunction:
        raise CatalogError("buffers are available for the grid scheme only")
