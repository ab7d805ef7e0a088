"""The points an epoch keeps from its existing tiles when it is re-tiled.

:func:`kept_points` is a pure function of a :class:`KeptTiles` task (an executor may run it
on a dask worker): one old tile read, the points of re-ingested missions dropped, the rest
snapped to the lattice, without enrichment, in the epoch's schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from standgrid.pointcloud import PointCloud


@dataclass(frozen=True)
class KeptTiles:
    """One existing tile of an epoch being re-tiled."""

    path: Path
    #: Mission numbers whose points are replaced (their old points are dropped).
    renewed: tuple[int, ...]
    lattice_origin: tuple[float, float]
    schema: dict[str, np.dtype]
    #: Payload ids whose old points are dropped too (an in-place re-tile).
    dropped_payloads: tuple[int, ...] = ()


def kept_points(task: KeptTiles) -> PointCloud:
    """The tile's core points of missions not renewed and payloads not dropped, ready for the
    partition engine."""
    from standgrid.catalog.invalidate import without_enrichment
    from standgrid.export.las import read_tile
    from standgrid.partition.chunks import rank_as_scan_angle
    from standgrid.partition.lattice import snap_to_storage
    from standgrid.partition.schema import conform

    cloud = read_tile(task.path)
    keep = ~np.isin(cloud.fields["point_source_id"], task.renewed)
    if task.dropped_payloads:
        keep &= ~np.isin(cloud.fields["payload_id"], task.dropped_payloads)
    kept = cloud.select(keep)
    # heights and tree ids of the old enrichment do not survive a re-tile; a rank kept as
    # an extra dimension (tiles written before it became scan_angle) becomes scan_angle
    fields = rank_as_scan_angle(without_enrichment(kept.fields), task.path)
    kept = PointCloud(snap_to_storage(kept.xyz, task.lattice_origin), fields)
    return conform(kept, task.schema, task.path)
