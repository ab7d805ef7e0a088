"""Voronoi cells around payload poses, clipped to the ground a mission actually covered.

Sites are stored sorted by their id (``V_<mission>_<sec>_<nsec:09d>``), so a site's index —
what :meth:`VoronoiPartition.assign` returns and what the partition engine groups by — depends
only on the payloads, never on the order a geometry library returns polygons.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import GridError
from standgrid.stamps import Stamp

#: How many neighbours are compared when the two nearest sites are at exactly equal distance.
_TIE_NEIGHBOURS = 16


def site_id(mission: str, stamp: Stamp) -> str:
    """The Voronoi cell id of a payload: ``V_<mission>_<sec>_<nsec:09d>``."""
    return f"V_{mission}_{stamp.sec}_{stamp.nsec:09d}"


def coverage_from_points(xy: ArrayLike, radius: float) -> Any:
    """The union of discs of ``radius`` around each point (e.g. payload footprints)."""
    pts = _as_xy(xy)
    if radius <= 0:
        raise GridError(f"coverage radius must be positive, got {radius}")
    return shapely.union_all(shapely.buffer(shapely.points(pts), radius))


def coverage_from_trajectory(xy: ArrayLike, radius: float) -> Any:
    """The corridor of ``radius`` around a trajectory polyline."""
    pts = _as_xy(xy)
    if radius <= 0:
        raise GridError(f"coverage radius must be positive, got {radius}")
    if len(pts) == 1:
        return shapely.Point(pts[0]).buffer(radius)
    return shapely.LineString(pts).buffer(radius)


def _as_xy(xy: ArrayLike) -> NDArray[np.float64]:
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0:
        raise GridError(f"sites must be a non-empty (N, 2) array, got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise GridError("sites must have finite coordinates")
    return pts


class VoronoiPartition:
    """Nearest-site partition of the plane; polygons clipped to ``coverage``.

    ``assign`` covers the whole plane (nothing is dropped outside the coverage); ties are
    broken towards the lower site id. ``polygons`` are the same cells as shapely polygons.
    """

    def __init__(self, xy: ArrayLike, ids: Sequence[str], coverage: Any) -> None:
        from scipy.spatial import cKDTree

        pts = _as_xy(xy)
        id_list = [str(i) for i in ids]
        if len(id_list) != len(pts):
            raise GridError(f"{len(id_list)} site ids for {len(pts)} sites")
        if len(set(id_list)) != len(id_list):
            dupes = sorted({i for i in id_list if id_list.count(i) > 1})
            raise GridError(f"duplicate Voronoi site ids: {dupes[:5]}")
        if coverage is None or shapely.is_empty(coverage):
            raise GridError("Voronoi coverage must be a non-empty geometry")
        order = np.argsort(np.array(id_list, dtype=object), kind="stable")
        self.ids: tuple[str, ...] = tuple(id_list[i] for i in order)
        self.xy: NDArray[np.float64] = pts[order]
        self.coverage = coverage
        self._tree = cKDTree(self.xy)
        self._index = {site: i for i, site in enumerate(self.ids)}

    @classmethod
    def from_payloads(
        cls, mission: str, stamps: Sequence[Stamp], xy: ArrayLike, coverage: Any
    ) -> VoronoiPartition:
        return cls(xy, [site_id(mission, s) for s in stamps], coverage)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def keys(self) -> NDArray[np.int64]:
        """The int key of each site (its index in :attr:`ids`)."""
        return np.arange(len(self.ids), dtype=np.int64)

    def key_of(self, site: str) -> int:
        try:
            return self._index[site]
        except KeyError:
            raise GridError(f"no Voronoi site {site!r}") from None

    def assign(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
        """Index (into :attr:`ids`) of the nearest site of each point; ties -> lower id."""
        q = np.column_stack([np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)])
        if not np.isfinite(q).all():
            raise GridError("cannot assign non-finite coordinates to Voronoi cells")
        n = len(self.ids)
        if n == 1 or len(q) == 0:
            return np.zeros(len(q), dtype=np.int64)
        dist, idx = self._tree.query(q, k=2)
        result = idx[:, 0].astype(np.int64)
        tied = np.flatnonzero(dist[:, 0] == dist[:, 1])
        if tied.size:
            k = min(n, _TIE_NEIGHBOURS)
            d_t, i_t = self._tree.query(q[tied], k=k)
            candidates = np.where(d_t == d_t[:, :1], i_t, n)
            result[tied] = candidates.min(axis=1)
        return result

    def __call__(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
        return self.assign(x, y)

    def polygons(self) -> dict[str, Any]:
        """Each site's cell clipped to the coverage, matched to its site by containment.

        Sites sharing a position: the lowest id gets the cell, the others an empty polygon.
        """
        unique_xy, first = np.unique(self.xy, axis=0, return_index=True)
        result: dict[str, Any] = {site: shapely.Polygon() for site in self.ids}
        if len(unique_xy) == 1:
            result[self.ids[int(first[0])]] = self.coverage
            return result
        sites = shapely.points(unique_xy)
        xmin, ymin, xmax, ymax = shapely.bounds(
            shapely.union(shapely.envelope(self.coverage), shapely.multipoints(unique_xy))
        )
        pad = max(xmax - xmin, ymax - ymin, 1.0)
        extent = shapely.box(xmin - pad, ymin - pad, xmax + pad, ymax + pad)
        cells = shapely.get_parts(
            shapely.voronoi_polygons(shapely.multipoints(unique_xy), extend_to=extent)
        )
        cell_idx, site_idx = shapely.STRtree(sites).query(cells, predicate="contains")
        if len(np.unique(site_idx)) != len(unique_xy) or len(cell_idx) != len(unique_xy):
            raise GridError("Voronoi polygons do not match their sites one to one")
        for c, s in zip(cell_idx.tolist(), site_idx.tolist(), strict=True):
            # the lowest id at this position: np.unique's first index in id-sorted order
            result[self.ids[int(first[s])]] = shapely.intersection(cells[c], self.coverage)
        return result
