"""Deprecated location of the catalog store: use :mod:`standgrid.catalog` (kept one release)."""

from standgrid.catalog.store import *  # noqa: F403
from standgrid.catalog.store import (  # noqa: F401  (private names some callers used)
    CATALOG_FILE,
    Catalog,
    FileLock,
    Transaction,
    apply_journal,
    build_folder,
    crash_point,
    grid_fingerprint,
    lock_paths,
    publish,
    recover,
    remove_stale_builds,
    writer_lock,
)
