"""Partitioning the map: the fixed stand grid, Voronoi cells, and the streaming partition engine."""

from standgrid.partition.engine import (
    CellPoints,
    ChunkSchemaError,
    GridBuffer,
    PartitionEngine,
    PartitionStats,
)
from standgrid.partition.grid import CellId, StandGrid, index_to_key, key_to_index
from standgrid.partition.voronoi import (
    VoronoiPartition,
    coverage_from_points,
    coverage_from_trajectory,
    site_id,
)

__all__ = [
    "CellId",
    "CellPoints",
    "ChunkSchemaError",
    "GridBuffer",
    "PartitionEngine",
    "PartitionStats",
    "StandGrid",
    "VoronoiPartition",
    "coverage_from_points",
    "coverage_from_trajectory",
    "index_to_key",
    "key_to_index",
    "site_id",
]
