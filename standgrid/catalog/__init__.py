"""The catalog: a folder of tiles, rasters, tables and an index, updated only by transactions.

- :mod:`standgrid.catalog.store`: :class:`Catalog`, opening, creating and reading a catalog;
- :mod:`standgrid.catalog.transaction`: :class:`Transaction`, staged changes and their commit;
- :mod:`standgrid.catalog.lock`: the writer and readers locks (:class:`FileLock`);
- :mod:`standgrid.catalog.journal`: the commit journal, crash points and crash recovery;
- :mod:`standgrid.catalog.publish`: ``publish`` of new and replaced catalogs;
- :mod:`standgrid.catalog.state`: ``catalog.json`` read and checked, ``grid_fingerprint``;
- :mod:`standgrid.catalog.paths`: the only module that spells catalog-relative paths;
- :mod:`standgrid.catalog.records`: frozen views of the missions and epochs in catalog.json;
- :mod:`standgrid.catalog.invalidate`: re-tiled epochs lose their enrichment and comparisons.

Stage order: after ``export`` (file writers), before ``tiling``. Only the standard library is
imported here, so opening a catalog stays cheap.
"""

from standgrid.catalog.journal import recover
from standgrid.catalog.lock import FileLock, writer_lock
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.publish import build_folder, publish, remove_stale_builds
from standgrid.catalog.records import EpochRecord, MissionRecord, TilingSettings
from standgrid.catalog.state import grid_fingerprint
from standgrid.catalog.store import Catalog, open_catalog
from standgrid.catalog.transaction import Transaction

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
