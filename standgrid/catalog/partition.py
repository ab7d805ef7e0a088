"""The partition a catalog uses, as the one :class:`~standgrid.partition.protocol.Partition`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from standgrid.errors import CatalogError

if TYPE_CHECKING:
    from standgrid.catalog.store import Catalog
    from standgrid.partition.protocol import Partition, VoronoiCells


def catalog_partition(
    catalog: Catalog, epoch: str | None = None, *, payloads: Any = None, coverage: bool = True
) -> Partition:
    """The catalog's cells.

    Grid: the stand grid (``epoch`` and ``payloads`` are not needed). Voronoi: cells around
    the epoch's payload poses (``payloads`` rows with ``mission``, ``stamp_sec``,
    ``stamp_nsec``, ``x``, ``y`` and a footprint ``geometry``; by default the epoch's rows
    of the index's ``payloads`` layer), polygons clipped to the union of the footprints
    when ``coverage``.
    """
    from standgrid.partition import StandGrid
    from standgrid.partition.protocol import GridPartition

    if catalog.scheme == "grid":
        return GridPartition(StandGrid.from_dict(catalog.grid_definition))
    if payloads is None:
        if epoch is None:
            raise CatalogError("Voronoi cells belong to one epoch: name it", path=catalog.root)
        from standgrid.catalog.index import CatalogIndex

        payloads = CatalogIndex(catalog).read("payloads", epoch)
    return voronoi_cells(payloads, coverage=coverage)


def voronoi_cells(payloads: Any, *, coverage: bool = True) -> VoronoiCells:
    """Voronoi cells around payload rows (ids from mission + stamp; :func:`catalog_partition`)."""
    import numpy as np
    import shapely

    from standgrid.partition.protocol import VoronoiCells
    from standgrid.partition.voronoi import site_id
    from standgrid.stamps import Stamp

    xy = np.column_stack([np.asarray(payloads["x"], float), np.asarray(payloads["y"], float)])
    ids = [
        site_id(str(m), Stamp(int(s), int(n)))
        for m, s, n in zip(
            payloads["mission"], payloads["stamp_sec"], payloads["stamp_nsec"], strict=True
        )
    ]
    area = shapely.union_all(list(payloads["geometry"])) if coverage and len(ids) else None
    return VoronoiCells(xy, ids, area)
