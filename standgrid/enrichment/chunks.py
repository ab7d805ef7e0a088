"""An epoch as buffered chunks, the layout of :func:`~standgrid.enrichment.apply.catalog_apply`
(lidR's): plan, read, rewrite.

A *chunk* owns a block of cells (a square of ``side`` metres of the stand grid, or the
Voronoi cells whose centre falls in it) and sees, besides their tiles, every neighbour's
core points within ``buffer`` metres: what a computation needs to be right at the chunk's
edges; and, given a *reach*, the lowest points of a wider ring (a ground classification
that looks further than the buffer). Each tile is decoded once for its chunk (neighbours are
re-read only for their coordinates). A per-chunk function receives :class:`ChunkPoints` and
returns per-point fields over the block's rows; :func:`write_chunk_tiles` maps them back onto
the owned tiles (their buffer copies included) and writes the new tiles where the transaction
staged them.

Everything here is plain, picklable data, so chunks run on dask workers as well as here.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.partition.lattice import lowest_in_squares

#: Peak bytes a chunk's computation holds per point of its block (the decoded tiles, the
#: block's coordinates, every per-point array a pass keeps, the trees' kd-trees and the
#: rasters), used to size chunks to the budget and to run only as many at once as fit.
#: Measured: the peak RSS a chunk adds over the process's, per block point, was 150-270
#: on simulated forest (20 M points, 20 m cells; more for sparse blocks, whose rasters and
#: trees weigh more per point), so 300.
BYTES_PER_POINT = 300


@dataclass(frozen=True)
class ChunkCell:
    """One cell of the catalog: its id, tile (catalog-relative), polygon and stand."""

    cell_id: str
    tile: str
    bounds: tuple[float, float, float, float]
    polygon_wkb: bytes
    n_points: int
    #: the id of the coarser (1 ha) stand holding the cell, when the grid has one
    stand_id: str | None = None

    @property
    def polygon(self) -> Any:
        import shapely

        return shapely.from_wkb(self.polygon_wkb)


@dataclass(frozen=True)
class Chunk:
    """The cells a chunk owns and the neighbours whose points within ``buffer`` it sees."""

    index: int
    cells: tuple[ChunkCell, ...]
    neighbours: tuple[ChunkCell, ...]
    buffer: float
    #: the wider extent whose lowest points the block's ground classification sees, and the
    #: further cells (not neighbours) that hold some of them
    reach_bounds: tuple[float, float, float, float] | None = None
    far: tuple[ChunkCell, ...] = ()

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """The bounding box of the owned cells."""
        b = np.array([c.bounds for c in self.cells], dtype=np.float64)
        lo, hi = b[:, :2].min(axis=0), b[:, 2:].max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    @property
    def buffered_bounds(self) -> tuple[float, float, float, float]:
        xmin, ymin, xmax, ymax = self.bounds
        h = self.buffer
        return xmin - h, ymin - h, xmax + h, ymax + h

    @property
    def n_points(self) -> int:
        return sum(c.n_points for c in self.cells)

    @property
    def block_points(self) -> int:
        """About how many points the chunk's block holds: its cells' own, and each
        neighbour's in proportion to its area inside the buffered bounds."""
        xmin, ymin, xmax, ymax = self.buffered_bounds
        total = float(self.n_points)
        for c in self.neighbours:
            w = min(xmax, c.bounds[2]) - max(xmin, c.bounds[0])
            h = min(ymax, c.bounds[3]) - max(ymin, c.bounds[1])
            area = (c.bounds[2] - c.bounds[0]) * (c.bounds[3] - c.bounds[1])
            if w > 0 and h > 0 and area > 0:
                total += c.n_points * min(1.0, w * h / area)
        return int(total)


def chunk_side(
    cells: Sequence[ChunkCell], cell_size: float, buffer: float, points_budget: int
) -> float:
    """The largest chunk side (a multiple of ``cell_size``, at most 10 cells) whose buffered
    block holds about ``points_budget`` points at the cells' mean density."""
    area = sum((c.bounds[2] - c.bounds[0]) * (c.bounds[3] - c.bounds[1]) for c in cells)
    points = sum(c.n_points for c in cells)
    density = points / area if area > 0 else 0.0
    side = 10 * cell_size
    while side > cell_size and density * (side + 2 * buffer) ** 2 > points_budget:
        side -= cell_size
    return side


def plan_chunks(
    cells: Sequence[ChunkCell],
    *,
    side: float,
    origin: tuple[float, float],
    buffer: float,
    reach: Callable[[tuple[float, float, float, float]], tuple[float, float, float, float]]
    | None = None,
) -> list[Chunk]:
    """Group ``cells`` into square chunks of ``side`` metres (by the cell's centre, on the
    lattice of ``origin``), each with the neighbours within ``buffer`` of its cells; and,
    given ``reach`` (buffered bounds -> wider bounds), the further cells within those."""
    import shapely

    if not cells:
        return []
    ordered = sorted(cells, key=lambda c: c.cell_id)
    centres = np.array(
        [((c.bounds[0] + c.bounds[2]) / 2, (c.bounds[1] + c.bounds[3]) / 2) for c in ordered]
    )
    keys = np.floor((centres - np.asarray(origin, dtype=np.float64)) / side).astype(np.int64)
    groups: dict[tuple[int, int], list[ChunkCell]] = {}
    for key, cell in zip(map(tuple, keys.tolist()), ordered, strict=True):
        groups.setdefault(key, []).append(cell)
    boxes = shapely.box(*np.array([c.bounds for c in ordered]).T)
    tree = shapely.STRtree(boxes)
    chunks = []
    for index, key in enumerate(sorted(groups, key=lambda k: (-k[1], k[0]))):  # north first
        own = tuple(groups[key])
        owned_ids = {c.cell_id for c in own}
        probe = Chunk(index, own, (), buffer)
        near = tree.query(shapely.box(*probe.buffered_bounds))
        neighbours = tuple(
            ordered[j] for j in sorted(int(j) for j in near) if ordered[j].cell_id not in owned_ids
        )
        reach_bounds, far = None, tuple[ChunkCell, ...]()
        if reach is not None:
            reach_bounds = reach(probe.buffered_bounds)
            seen = owned_ids | {c.cell_id for c in neighbours}
            further = sorted(int(j) for j in tree.query(shapely.box(*reach_bounds)))
            far = tuple(ordered[j] for j in further if ordered[j].cell_id not in seen)
        chunks.append(Chunk(index, own, neighbours, buffer, reach_bounds, far))
    return chunks


@dataclass
class OwnedTile:
    """A chunk's own tile as stored (rewritten with the chunk's fields) and its buffer copies."""

    path: str
    #: the ``laspy.LasData`` read
    record: Any
    withheld: NDArray[np.bool_]
    #: coordinates of the withheld points (copies of other cells' points), on the lattice
    buffer_xyz: NDArray[np.float64]


@dataclass
class ChunkPoints:
    """A chunk's points: the owned tiles' core points first (in ``chunk.cells`` order), then
    the neighbours' core points inside the buffered bounds.

    ``cell_rows[k]`` is the slice of ``xyz`` holding owned cell k's core points; ``tiles``
    the owned tiles as read (withheld buffer copies included, flagged by ``withheld``).
    """

    chunk: Chunk
    xyz: NDArray[np.float64]
    cell_rows: list[slice]
    tiles: list[OwnedTile]
    #: the lowest point of every ``ring_square`` square within ``chunk.reach_bounds`` and
    #: outside the buffered bounds (empty without a reach)
    ring_xyz: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def n_core(self) -> int:
        return self.cell_rows[-1].stop if self.cell_rows else 0


def read_chunk(
    root: str | Path,
    chunk: Chunk,
    lattice_origin: tuple[float, float],
    *,
    cache_bytes: int = 0,
    ring_square: float | None = None,
    ring_lattice: tuple[float, float] = (0.0, 0.0),
) -> ChunkPoints:
    """Decode the chunk's own tiles and its neighbours' points in the buffer; tiles' core
    coordinates stay in this process's cache (up to ``cache_bytes``) for later chunks.
    Given ``ring_square``, also the lowest point of each such square (on ``ring_lattice``)
    in the ring out to ``chunk.reach_bounds``."""
    # 3/4 of the cache for neighbours' coordinates, 1/4 for tiles' lowest points (about 1/20
    # of a tile's points: the whole epoch's fit, for the chunks' rings)
    _CORES.resize(cache_bytes * 3 // 4 // CACHED_BYTES_PER_POINT)
    _LOWEST.resize(cache_bytes // 4 // CACHED_BYTES_PER_POINT)
    from standgrid.export.las import read_tile_record, snap_to_storage

    tiles, parts, rows, start = [], [], [], 0
    for cell in chunk.cells:
        path = Path(root) / cell.tile
        record = read_tile_record(path)
        withheld = np.asarray(record.withheld, dtype=bool)
        stored = snap_to_storage(_xyz(record), lattice_origin)
        core = stored[~withheld]
        _CORES.put(path, core)  # a later chunk's neighbour
        tiles.append(OwnedTile(str(path), record, withheld, stored[withheld]))
        parts.append(core)
        rows.append(slice(start, start + len(core)))
        start += len(core)
    xmin, ymin, xmax, ymax = chunk.buffered_bounds
    ring = []
    for cell in chunk.neighbours:
        xyz = _neighbour_xyz(Path(root) / cell.tile, lattice_origin)
        x, y = xyz[:, 0], xyz[:, 1]
        parts.append(xyz[(x >= xmin) & (x < xmax) & (y >= ymin) & (y < ymax)])
    if ring_square is not None and chunk.reach_bounds is not None:
        squares = (ring_square, *ring_lattice)
        neighbours = {c.cell_id for c in chunk.neighbours}
        for cell in (*chunk.neighbours, *chunk.far):
            path = Path(root) / cell.tile
            lowest = _LOWEST.get(path, squares)
            if lowest is None:  # (a far tile's coordinates are not kept: only its lowest)
                xyz = _neighbour_xyz(path, lattice_origin, keep=cell.cell_id in neighbours)
                lowest = xyz[lowest_in_squares(xyz, ring_square, ring_lattice)]
                _LOWEST.put(path, lowest, squares)
            # (a square cut by the tile's edge has a lowest point in each tile: the block's
            # ground classification keeps the lowest of them)
            ring.append(_in_ring(lowest, chunk.buffered_bounds, chunk.reach_bounds))
    xyz = np.concatenate(parts) if parts else np.zeros((0, 3))
    ring_xyz = np.concatenate(ring) if ring else np.zeros((0, 3))
    return ChunkPoints(chunk, xyz, rows, tiles, ring_xyz)


def _neighbour_xyz(
    path: Path, lattice_origin: tuple[float, float], *, keep: bool = True
) -> NDArray[np.float64]:
    """A tile's core coordinates, from this process's cache or decoded (and cached when
    ``keep``)."""
    from standgrid.export.las import snap_to_storage

    xyz = _CORES.get(path)
    if xyz is None:
        xyz = snap_to_storage(_core_xyz(path), lattice_origin)
        if keep:
            _CORES.put(path, xyz)
    return xyz


def _in_ring(
    xyz: NDArray[np.float64],
    inner: tuple[float, float, float, float],
    outer: tuple[float, float, float, float],
) -> NDArray[np.float64]:
    """The points inside ``outer`` and outside ``inner`` (both half-open boxes)."""
    x, y = xyz[:, 0], xyz[:, 1]
    in_outer = (x >= outer[0]) & (x < outer[2]) & (y >= outer[1]) & (y < outer[3])
    in_inner = (x >= inner[0]) & (x < inner[2]) & (y >= inner[1]) & (y < inner[3])
    return xyz[in_outer & ~in_inner]


class _CoreCache:
    """Tiles' core coordinates, most recent first, up to ``max_points``: chunks planned north
    first, row by row, meet again the tiles of the chunks before them as neighbours. Keyed by
    path, inode, size and mtime, so a rewritten tile is never served stale."""

    def __init__(self, max_points: int) -> None:
        self.max_points = max_points
        self._items: OrderedDict[tuple[Any, ...], NDArray[np.float64]] = OrderedDict()
        self._points = 0
        self._lock = threading.Lock()  # a dask worker may run tasks on several threads

    @staticmethod
    def _key(path: Path, tag: Any) -> tuple[Any, ...]:
        st = path.stat()
        return (str(path), st.st_ino, st.st_size, st.st_mtime_ns, tag)

    def get(self, path: Path, tag: Any = None) -> NDArray[np.float64] | None:
        key = self._key(path, tag)
        with self._lock:
            found = self._items.get(key)
            if found is not None:
                self._items.move_to_end(key)
        return found

    def put(self, path: Path, xyz: NDArray[np.float64], tag: Any = None) -> None:
        key = self._key(path, tag)
        with self._lock:
            if key not in self._items and len(xyz) <= self.max_points:
                self._items[key] = xyz
                self._points += len(xyz)
            self._shrink()

    def resize(self, max_points: int) -> None:
        with self._lock:
            self.max_points = max_points
            self._shrink()

    def _shrink(self) -> None:
        while self._points > self.max_points and self._items:
            _, dropped = self._items.popitem(last=False)
            self._points -= len(dropped)


#: Bytes a cached point takes (x, y, z as float64).
CACHED_BYTES_PER_POINT = 24
#: This process's cache of tiles' core coordinates (sized by each read_chunk call) ...
_CORES = _CoreCache(0)
#: ... and of their lowest points per square (keyed by the squares' side and lattice).
_LOWEST = _CoreCache(0)


def _core_xyz(path: Path) -> NDArray[np.float64]:
    """A tile's core (not withheld) coordinates, decompressing only the coordinate and flag
    layers of a LAZ 1.4 tile (a neighbour lends its points to the buffer, nothing else)."""
    import laspy

    from standgrid.export.las import read_tile_record

    layers = (
        laspy.DecompressionSelection.XY_RETURNS_CHANNEL
        | laspy.DecompressionSelection.Z
        | laspy.DecompressionSelection.FLAGS
    )
    las = read_tile_record(path, decompression_selection=layers)
    return _xyz(las)[~np.asarray(las.withheld, dtype=bool)]


def _xyz(las: Any) -> NDArray[np.float64]:
    """The scaled coordinates of a ``laspy.LasData`` as one (N, 3) float64 array."""
    xyz = np.empty((len(las.points), 3), dtype=np.float64)
    for k, (stored, scale, offset) in enumerate(
        zip((las.X, las.Y, las.Z), las.header.scales, las.header.offsets, strict=True)
    ):
        np.multiply(stored, scale, out=xyz[:, k])
        xyz[:, k] += offset
    return xyz


def tile_rows(points: ChunkPoints, k: int) -> NDArray[np.int64]:
    """For every point of owned tile ``k`` (withheld included), its row in the block, or -1
    for a buffer copy whose original lies outside the block."""
    from scipy.spatial import cKDTree

    tile = points.tiles[k]
    withheld = tile.withheld
    rows = np.empty(len(withheld), dtype=np.int64)
    span = points.cell_rows[k]
    rows[~withheld] = np.arange(span.start, span.stop)
    if withheld.any():
        wanted = tile.buffer_xyz
        lo, hi = wanted.min(axis=0) - 1e-3, wanted.max(axis=0) + 1e-3
        inside = np.flatnonzero(((points.xyz >= lo) & (points.xyz <= hi)).all(axis=1))
        rows[withheld] = -1
        if len(inside):
            dist, nearest = cKDTree(points.xyz[inside]).query(wanted)
            rows[withheld] = np.where(dist < 1e-6, inside[np.minimum(nearest, len(inside) - 1)], -1)
    return rows


def write_chunk_tiles(
    points: ChunkPoints,
    fields: Mapping[str, NDArray[Any]],
    missing: Mapping[str, Any],
    targets: Sequence[str],
) -> None:
    """Write every owned tile again with ``fields`` (per block row) set on its points.

    A buffer copy whose original is outside the block gets ``missing[name]``. ``targets[k]``
    is where tile k goes (the transaction's staged path). Other fields are kept as read.
    """
    from standgrid.export.copc import is_copc, rewrite_copc_tile
    from standgrid.export.las import rewrite_tile

    for k, (tile, target) in enumerate(zip(points.tiles, targets, strict=True)):
        rows = tile_rows(points, k)
        found = rows >= 0
        new = {}
        for name, values in fields.items():
            out = np.full(len(rows), missing[name], dtype=values.dtype)
            out[found] = values[rows[found]]
            new[name] = out
        rewrite = rewrite_copc_tile if is_copc(target) else rewrite_tile
        rewrite(tile.record, target, new, source=tile.path, durable=False)


def cells_of(records: Any, stand_of: Any = None) -> list[ChunkCell]:
    """:class:`ChunkCell` records from rows of the index's ``cells`` layer (a GeoDataFrame
    with ``cell_id``, ``tile_path``, ``point_count`` and polygons); ``stand_of(cell_id)`` names
    a cell's coarser stand."""
    import shapely

    out = []
    for row in records.itertuples():
        polygon = row.geometry
        out.append(
            ChunkCell(
                cell_id=str(row.cell_id),
                tile=str(row.tile_path),
                bounds=tuple(float(v) for v in polygon.bounds),  # type: ignore[arg-type]
                polygon_wkb=shapely.to_wkb(polygon),
                n_points=int(row.point_count),
                stand_id=stand_of(str(row.cell_id)) if stand_of is not None else None,
            )
        )
    return out
