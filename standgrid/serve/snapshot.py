"""A consistent view of the catalog for one request: its state and an open index connection.

Taken under the catalog's readers lock (:meth:`Catalog.reading`), so no commit is half
visible. The parsed catalog.json is reused while the file is unchanged (``reading(reuse=)``):
the service only reads it. Index connections are pooled per index file (path, inode, mtime,
size, as seen under the lock): a request takes an idle connection to the file now at the
path, or opens one, and gives it back when it ends; a connection keeps reading its file
even when a later commit renames a new one into place, and connections to a replaced file
are closed. Opening one costs ~2 ms (SQLite parses the GeoPackage schema); reusing it, none.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
import weakref
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from standgrid.catalog import Catalog, paths
from standgrid.serve import features
from standgrid.serve.features import Layer
from standgrid.serve.problems import Problem

_IndexKey = tuple[str, int, int, int]  # path, inode, mtime (ns), size
_layers_cache: dict[_IndexKey, dict[str, Layer]] = {}
#: The last catalog read per root: reused while its catalog.json is unchanged.
_catalogs: dict[Path, Catalog] = {}
#: Idle connections by index file, and the newest file seen per index path.
_idle: dict[_IndexKey, list[sqlite3.Connection]] = {}
_newest: dict[str, _IndexKey] = {}
#: Idle connections kept per index file (more are closed when given back).
MAX_IDLE = 16
#: Epoch label -> date per catalog read (the service never changes a Catalog it read).
_epoch_dates: weakref.WeakKeyDictionary[Catalog, dict[str, str]] = weakref.WeakKeyDictionary()
_cache_lock = threading.Lock()


def _take(index: Path) -> tuple[_IndexKey, sqlite3.Connection]:
    """A connection to the file now at ``index`` (call under the readers lock)."""
    stat = index.stat()
    key = (str(index), stat.st_ino, stat.st_mtime_ns, stat.st_size)
    stale: list[sqlite3.Connection] = []
    with _cache_lock:
        if _newest.get(key[0]) != key:
            old = _newest.get(key[0])
            if old is not None:
                stale = _idle.pop(old, [])
            _newest[key[0]] = key
        pool = _idle.get(key)
        conn = pool.pop() if pool else None
    for dead in stale:
        dead.close()
    return key, conn if conn is not None else features.connect(index)


def _give_back(key: _IndexKey, conn: sqlite3.Connection) -> None:
    with _cache_lock:
        pool = _idle.setdefault(key, []) if _newest.get(key[0]) == key else None
        if pool is not None and len(pool) < MAX_IDLE:
            pool.append(conn)
            return
    conn.close()


@dataclass
class Snapshot:
    catalog: Catalog
    index: sqlite3.Connection | None
    layers: dict[str, Layer]

    @property
    def epoch_dates(self) -> Mapping[str, str]:
        with _cache_lock:
            dates = _epoch_dates.get(self.catalog)
        if dates is None:
            dates = {label: e.date or "" for label, e in self.catalog.epoch_records.items()}
            with _cache_lock:
                _epoch_dates[self.catalog] = dates
        return dates

    def layer(self, collection_id: str) -> Layer:
        """The layer of a collection id from a request (404 unless the index has it)."""
        layer = self.layers.get(collection_id)
        if layer is None:
            raise Problem(404, f"no collection {collection_id!r}; collections: "
                          f"{sorted(self.layers)}")  # fmt: skip
        return layer


@contextlib.contextmanager
def snapshot(root: Path, *, with_index: bool = True) -> Iterator[Snapshot]:
    """The catalog at ``root`` as of its last commit (and its index, when it has one), with
    the catalog's readers lock held until the block ends."""
    conn: sqlite3.Connection | None = None
    key: _IndexKey | None = None
    layers: dict[str, Layer] = {}
    with _cache_lock:
        previous = _catalogs.get(root)
    with Catalog.reading(root, reuse=previous) as catalog:
        if catalog is not previous:
            with _cache_lock:
                _catalogs[root] = catalog
        index = catalog.path(paths.INDEX)
        try:
            if with_index and index.is_file():
                key, conn = _take(index)
                with _cache_lock:
                    cached = _layers_cache.get(key)
                if cached is None:
                    cached = features.read_layers(conn)
                    with _cache_lock:
                        _layers_cache.clear()
                        _layers_cache[key] = cached
                layers = cached
            # yielded under the readers lock: no commit renames a file in while the request
            # reads (files opened here stay the snapshot's even after it)
            yield Snapshot(catalog, conn, layers)
        except BaseException:
            if conn is not None:  # a request that failed mid-read may leave a statement open
                conn.close()
                conn = None
            raise
        finally:
            if conn is not None and key is not None:
                _give_back(key, conn)
