"""File writers: LAS/LAZ tiles, the GeoPackage index (+ QGIS styles), VPC.

The catalog folder they are written into is :mod:`standgrid.catalog`.
"""

from standgrid.export.gpkg import (
    LAYER_COLUMNS,
    IndexWriter,
    VpcTile,
    cell_row,
    iso_time,
    layer_frame,
    write_index,
    write_vpc,
)
from standgrid.export.las import TileInfo, read_tile, write_tile
from standgrid.export.styles import (
    add_layer_style,
    categorized_style,
    density_style,
    diverging_style,
    graduated_style,
    load_qml,
    single_style,
    stand_metric_style,
)

__all__ = [
    "LAYER_COLUMNS",
    "IndexWriter",
    "TileInfo",
    "VpcTile",
    "add_layer_style",
    "categorized_style",
    "cell_row",
    "density_style",
    "diverging_style",
    "graduated_style",
    "iso_time",
    "layer_frame",
    "load_qml",
    "read_tile",
    "single_style",
    "stand_metric_style",
    "write_index",
    "write_tile",
    "write_vpc",
]
