"""Exporting: LAS/LAZ tiles, the GeoPackage index (+ QGIS styles), VPC, the catalog folder."""

from standgrid.export.catalog import Catalog, Transaction, grid_fingerprint, recover
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
    "Catalog",
    "IndexWriter",
    "TileInfo",
    "Transaction",
    "VpcTile",
    "add_layer_style",
    "categorized_style",
    "cell_row",
    "density_style",
    "diverging_style",
    "graduated_style",
    "grid_fingerprint",
    "iso_time",
    "layer_frame",
    "load_qml",
    "read_tile",
    "recover",
    "single_style",
    "stand_metric_style",
    "write_index",
    "write_tile",
    "write_vpc",
]
