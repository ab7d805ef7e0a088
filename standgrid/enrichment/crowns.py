"""Crowns grown from their trees' stems and tops: every point above ground goes to the tree
it is nearest to along the vegetation itself.

The points at least ``min_height`` above ground are binned into voxels of ``voxel`` m on a
lattice anchored at the CRS origin (the same voxels in every processing block); voxels
within ``link`` m of each other are joined by two directed edges, each as long as the step,
its vertical part counted ``down_weight`` (3) times going down: a tree grows up and out
from its stem, so a small tree's crown is reached from its own stem below, not from the big
crown above it (:class:`VoxelGraph`). From the voxels of every
tree's sources (its trunk, :func:`standgrid.features.stems.stem_points` of the voxel centres,
and the apex of its canopy top) a multi-source shortest-path search (scipy's Dijkstra)
gives every voxel the tree it is reached from first, up to a path of ``max_path`` m
(:meth:`VoxelGraph.reach`): a crown goes to the tree it grows from, and a small tree under a
big crown keeps its own points, so its height is its own top (FSCT and realtime_trees
assign points to stems by shortest paths too). A voxel no path reaches (a gap in what the
scanner saw, wider than ``link``) takes the tree of the nearest reached voxel within
``bridge`` m; beyond that it belongs to no tree (:meth:`VoxelGraph.labels`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

_NONE = np.iinfo(np.int64).max


@dataclass(frozen=True)
class CrownOptions:
    """Parameters of :class:`VoxelGraph` (documented in docs/METRICS.md, "Trees")."""

    voxel: float = 0.3
    link: float = 0.5
    #: a step's vertical part counts this much going up, and going down
    up_weight: float = 1.0
    down_weight: float = 3.0
    max_path: float = 60.0
    bridge: float = 2.0
    min_height: float = 0.5


class VoxelGraph:
    """The vegetation of a block as a graph of voxels (module doc)."""

    def __init__(
        self,
        xyz: NDArray[np.float64],
        heights: NDArray[np.float64],
        options: CrownOptions | None = None,
    ) -> None:
        """The points at least ``min_height`` above ground."""
        self.options = o = options or CrownOptions()
        self.n_points = len(xyz)
        h = np.asarray(heights, dtype=np.float64)
        self.rows = np.flatnonzero(np.isfinite(h) & (h >= o.min_height))
        self.keys, self.voxel_of = _voxels(xyz, self.rows, o.voxel)
        self.centres = (self.keys.astype(np.float64) + 0.5) * o.voxel
        n = len(self.keys)
        count = np.bincount(self.voxel_of, minlength=n)
        #: each voxel's height above ground: its centre over the mean ground of its points
        ground = np.bincount(self.voxel_of, xyz[self.rows, 2] - h[self.rows], minlength=n)
        self.heights = self.centres[:, 2] - ground / np.maximum(count, 1)
        self.graph = _lattice_graph(self.keys, o)

    def voxels(self, points: NDArray[np.int64]) -> NDArray[np.int64]:
        """The voxel of each of these rows of the points (they must be in the graph)."""
        return self.voxel_of[np.searchsorted(self.rows, points)]

    @property
    def voxel_size(self) -> float:
        return self.options.voxel

    def reach(
        self, source_voxels: NDArray[np.int64], source_trees: NDArray[np.int64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Per voxel, the tree (a value of ``source_trees``) it is reached from first, -1
        where none reaches it within ``max_path``, and the path's length. A voxel that is a
        source of two trees starts the one with the lowest number."""
        from scipy.sparse.csgraph import dijkstra

        n = len(self.keys)
        if not len(source_voxels) or not n:
            return np.full(n, -1, dtype=np.int64), np.full(n, np.inf)
        start = np.full(n, _NONE, dtype=np.int64)
        np.minimum.at(start, source_voxels, source_trees)
        sources = np.flatnonzero(start < _NONE)
        dist, _, reached_from = dijkstra(
            self.graph,
            directed=True,
            indices=sources,
            min_only=True,
            return_predecessors=True,
            limit=self.options.max_path,
        )
        tree = np.where(reached_from >= 0, start[np.maximum(reached_from, 0)], -1)
        tree[sources] = start[sources]
        return tree, dist

    def labels(self, voxel_tree: NDArray[np.int64]) -> NDArray[np.int64]:
        """Per point, the tree of its voxel (-1: none, or not in the graph), after a voxel no
        path reached takes the tree of the nearest reached voxel within ``bridge``."""
        voxel_tree = voxel_tree.copy()
        lost = np.flatnonzero(voxel_tree < 0)
        reached = np.flatnonzero(voxel_tree >= 0)
        if len(lost) and len(reached) and self.options.bridge > 0:
            voxel_tree[lost] = _nearest_tree(
                self.centres[lost],
                self.centres[reached],
                voxel_tree[reached],
                self.options.bridge,
            )
        label = np.full(self.n_points, -1, dtype=np.int64)
        label[self.rows] = voxel_tree[self.voxel_of]
        return label


def _nearest_tree(
    lost: NDArray[np.float64],
    reached: NDArray[np.float64],
    trees: NDArray[np.int64],
    reach: float,
) -> NDArray[np.int64]:
    """Per ``lost`` voxel centre, the tree of the nearest ``reached`` one within ``reach``
    (-1: none); of equally near ones (a lattice has many), the lowest tree number."""
    from scipy.spatial import cKDTree

    out = np.full(len(lost), -1, dtype=np.int64)
    dist, nearest = cKDTree(reached).query(lost, k=32, distance_upper_bound=reach)
    found = np.isfinite(dist[:, 0])
    # every voxel as near as the first is among the 32 nearest (a lattice shell holds fewer
    # within the bridge's few voxels)
    tie = np.isfinite(dist) & (dist <= dist[:, :1] + 1e-9)
    candidates = np.where(tie, trees[np.minimum(nearest, len(trees) - 1)], _NONE)
    out[found] = candidates[found].min(axis=1)
    return out


def _lattice_graph(keys: NDArray[np.int64], o: CrownOptions) -> Any:
    """The directed graph (scipy CSR) of the (sorted, unique) voxel ``keys``: an edge to
    every occupied voxel within ``o.link``, as long as the step with its vertical part
    counted ``up_weight`` or ``down_weight`` times, times ``1 + 1e-7 x`` a fraction hashed
    from the CRS-anchored key of the voxel it enters (lattice paths tie; this breaks the ties
    the same way in every block). Each lattice offset within reach is looked up for all
    voxels at once (half of them: the other half are the same pairs reversed); the rows are
    laid out by counting, without a sort."""
    from scipy.sparse import csr_matrix

    n = len(keys)
    if not n:
        return csr_matrix((0, 0))
    reach = o.link / o.voxel
    r = int(np.floor(reach + 1e-9))
    grid = np.arange(-r, r + 1)
    offsets = np.stack(np.meshgrid(grid, grid, grid, indexing="ij"), -1).reshape(-1, 3)
    offsets = offsets[(offsets**2).sum(axis=1) <= reach * reach + 1e-9]
    positive = (offsets[:, 0] > 0) | (
        (offsets[:, 0] == 0) & ((offsets[:, 1] > 0) | ((offsets[:, 1] == 0) & (offsets[:, 2] > 0)))
    )
    offsets = offsets[positive]
    across = np.hypot(offsets[:, 0], offsets[:, 1])
    rise = offsets[:, 2].astype(np.float64)
    up = np.where(rise > 0, o.up_weight, o.down_weight)  # the step i -> i + offset
    down = np.where(rise > 0, o.down_weight, o.up_weight)  # and back
    forward = np.hypot(across, up * rise) * o.voxel
    backward = np.hypot(across, down * rise) * o.voxel
    low = keys.min(axis=0) - r
    span = keys.max(axis=0) - low + r + 1
    packed = ((keys[:, 0] - low[0]) * span[1] + (keys[:, 1] - low[1])) * span[2] + (
        keys[:, 2] - low[2]
    )  # sorted as the keys are (row-major), no offset wraps around
    shifts = (offsets[:, 0] * span[1] + offsets[:, 1]) * span[2] + offsets[:, 2]
    mix = (keys[:, 0] * 73856093) ^ (keys[:, 1] * 19349663) ^ (keys[:, 2] * 83492791)
    entering = 1.0 + 1e-7 / 1000003.0 * (mix % 1000003)
    pairs = []
    count = np.zeros(n, dtype=np.int64)
    for shift in shifts.tolist():
        target = packed + shift
        where = np.searchsorted(packed, target)
        np.minimum(where, n - 1, out=where)
        hit = np.flatnonzero(packed[where] == target)
        j = where[hit]
        pairs.append((hit, j))
        count[hit] += 1
        count[j] += 1
    indptr = np.concatenate([[0], np.cumsum(count)])
    fill = indptr[:-1].copy()
    indices = np.empty(int(indptr[-1]), dtype=np.int64)
    data = np.empty(int(indptr[-1]))
    for (i, j), ahead, back in zip(pairs, forward.tolist(), backward.tolist(), strict=True):
        for rows, columns, step in ((i, j, ahead), (j, i, back)):
            at = fill[rows]
            indices[at] = columns
            data[at] = step * entering[columns]
            fill[rows] += 1
    return csr_matrix((data, indices, indptr), shape=(n, n))


def _voxels(
    xyz: NDArray[np.float64], rows: NDArray[np.int64], size: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The occupied voxels of a CRS-anchored lattice (integer keys, sorted) and the voxel of
    each of the ``rows`` of ``xyz``."""
    if not len(rows):
        return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    cell = np.empty((len(rows), 3), dtype=np.int64)
    for axis in range(3):
        cell[:, axis] = np.floor(xyz[rows, axis] * (1.0 / size))
    low = cell.min(axis=0)
    cell -= low
    span = cell.max(axis=0) + 1
    packed = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    del cell
    unique, voxel_of = np.unique(packed, return_inverse=True)
    keys = np.column_stack(
        [
            unique // (span[1] * span[2]) + low[0],
            unique // span[2] % span[1] + low[1],
            unique % span[2] + low[2],
        ]
    )
    return keys, voxel_of.ravel()
