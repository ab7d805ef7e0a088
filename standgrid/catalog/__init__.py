"""The catalog: a folder of tiles, rasters, tables and an index, updated only by transactions.

- :mod:`standgrid.catalog.store`: :class:`Catalog`, :class:`Transaction`, locks, journal,
  crash recovery, ``publish`` of new and replaced catalogs;
- :mod:`standgrid.catalog.paths`: the only module that spells catalog-relative paths;
- :mod:`standgrid.catalog.records`: frozen views of the missions and epochs in catalog.json;
- :mod:`standgrid.catalog.invalidate`: re-tiled epochs lose their enrichment and comparisons.

Stage order: after ``export`` (file writers), before ``enrich``. Only the standard library is
imported here, so opening a catalog stays cheap.
"""

from standgrid.catalog.records import EpochRecord, MissionRecord, TilingSettings
from standgrid.catalog.store import (
    CATALOG_FILE,
    Catalog,
    FileLock,
    Transaction,
    build_folder,
    grid_fingerprint,
    open_catalog,
    publish,
    recover,
    remove_stale_builds,
    writer_lock,
)

__all__ = [
    "CATALOG_FILE",
    "Catalog",
    "EpochRecord",
    "FileLock",
    "MissionRecord",
    "TilingSettings",
    "Transaction",
    "build_folder",
    "grid_fingerprint",
    "open_catalog",
    "publish",
    "recover",
    "remove_stale_builds",
    "writer_lock",
]
