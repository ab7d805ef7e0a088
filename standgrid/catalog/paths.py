"""Catalog-relative paths: the one module that spells where things live in a catalog folder.

::

    catalog.json                              CATALOG_FILE
    index.gpkg                                INDEX
    catalog.qgz                               QGIS_PROJECT
    tiles_<epoch>.vpc                         vpc(epoch)
    tiles/<epoch>/<cell_id>.{laz,las}         tile(epoch, cell_id, laz=)
    rasters/<epoch>/<name>.{tif,qml}          raster(epoch, name), raster_style(epoch, name)
    rasters/<epoch>/elevation_map.{tif,qml}   raster(epoch, ELEVATION_MAP): payloads' maps
    maps/<epoch>/<mission>.elevation.tif      mission_elevation_map(epoch, mission)
    tables/stand_metrics.{csv,parquet}        stand_metrics(ext)
    tables/tree_list_<epoch>.{csv,parquet}    tree_list(epoch, ext)
    compare/<from>__<to>/<file>               comparison(epoch_from, epoch_to, file)
    stac/catalog.json                         STAC_ROOT: the static STAC catalog
    stac/<collection>/collection.json         stac_collection(collection_id)
    stac/<collection>/<item>.json             stac_item(collection_id, item_id)

Every function returns a POSIX relative path (``str``), the form :class:`Transaction` stages,
deletes and journals; ``Catalog.path(rel)`` makes it absolute.
"""

from __future__ import annotations

CATALOG_FILE = "catalog.json"
INDEX = "index.gpkg"
#: The QGIS project showing the catalog (rewritten by enrich and compare).
QGIS_PROJECT = "catalog.qgz"
TABLES = "tables"
#: The stand metrics table without its extension (``.csv`` and ``.parquet`` are written).
METRICS_TABLE = f"{TABLES}/stand_metrics"
TABLE_FORMATS = ("csv", "parquet")


def vpc(epoch: str) -> str:
    """The virtual point cloud (STAC ItemCollection) over one epoch's tiles."""
    return f"tiles_{epoch}.vpc"


def tiles_folder(epoch: str) -> str:
    """The folder of one epoch's tiles."""
    return f"tiles/{epoch}"


def tile(epoch: str, cell_id: str, *, laz: bool = True, copc: bool = False) -> str:
    """One cell's tile in one epoch (``.copc.laz`` for a COPC tile)."""
    suffix = "copc.laz" if copc else "laz" if laz else "las"
    return f"{tiles_folder(epoch)}/{cell_id}.{suffix}"


def rasters_folder(epoch: str) -> str:
    """The folder of one epoch's rasters (DTM, CHM, density, observed) and their styles."""
    return f"rasters/{epoch}"


def raster(epoch: str, name: str) -> str:
    """One epoch's raster ``name`` (``dtm``, ``chm``, ``density``, ``observed``)."""
    return f"{rasters_folder(epoch)}/{name}.tif"


def raster_style(epoch: str, name: str) -> str:
    """The QGIS style sidecar of :func:`raster` (QGIS loads it with the raster)."""
    return f"{rasters_folder(epoch)}/{name}.qml"


#: The raster name of an epoch's mosaic of its payloads' elevation maps (tiled, not enriched).
ELEVATION_MAP = "elevation_map"
#: The folder of the missions' placed elevation maps (the mosaic is made of them).
MAPS = "maps"


def tiled_rasters(epoch: str) -> tuple[str, str]:
    """The rasters of ``rasters/<epoch>/`` that tiling writes (the elevation-map mosaic and
    its style), not enrichment: re-tiling remakes them, invalidation leaves them."""
    return raster(epoch, ELEVATION_MAP), raster_style(epoch, ELEVATION_MAP)


def maps_folder(epoch: str) -> str:
    """The folder of one epoch's per-mission placed elevation maps."""
    return f"{MAPS}/{epoch}"


def mission_elevation_map(epoch: str, mission: str) -> str:
    """One mission's payload elevation maps placed on the raster lattice (their mean)."""
    return f"{maps_folder(epoch)}/{mission}.elevation.tif"


def stand_metrics(ext: str) -> str:
    """The stand metrics table of every epoch (``ext``: ``csv`` or ``parquet``)."""
    return f"{METRICS_TABLE}.{ext}"


def tree_list_stem(epoch: str) -> str:
    """One epoch's tree list without its extension."""
    return f"{TABLES}/tree_list_{epoch}"


def tree_list(epoch: str, ext: str) -> str:
    """One epoch's tree list (``ext``: ``csv`` or ``parquet``)."""
    return f"{tree_list_stem(epoch)}.{ext}"


def comparison_key(epoch_from: str, epoch_to: str) -> str:
    """The key of a comparison in catalog.json's ``comparisons`` and its folder name."""
    return f"{epoch_from}__{epoch_to}"


def comparison_folder(key: str) -> str:
    """The folder of the comparison ``key`` (see :func:`comparison_key`)."""
    return f"compare/{key}"


def comparison(epoch_from: str, epoch_to: str, file: str = "") -> str:
    """A comparison's folder, or the file ``file`` in it."""
    folder = comparison_folder(comparison_key(epoch_from, epoch_to))
    return f"{folder}/{file}" if file else folder


#: The folder of the static STAC catalog (rewritten by every commit) and its root.
STAC = "stac"
STAC_ROOT = f"{STAC}/catalog.json"


def stac_collection(collection_id: str) -> str:
    """A STAC collection (``epoch-<label>``, ``compare-<key>``) of the STAC catalog."""
    return f"{STAC}/{collection_id}/collection.json"


def stac_item(collection_id: str, item_id: str) -> str:
    """A STAC item (a tile, a raster) of a collection, beside it."""
    return f"{STAC}/{collection_id}/{item_id}.json"
