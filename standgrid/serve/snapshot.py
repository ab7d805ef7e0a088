"""A consistent view of the catalog for one request: its state and a provider of its index.

Taken under the catalog's readers lock (:meth:`Catalog.reading`), so no commit is half
visible. The parsed catalog.json is reused while the file is unchanged (``reading(reuse=)``):
the service only reads it. Index providers (:class:`GeoPackageProvider`, one connection
each) are pooled per index file (path, inode, mtime, size, as seen under the lock): a
request takes an idle one for the file now at the path, or opens one, and gives it back when
it ends; a provider keeps reading its file even when a later commit renames a new one into
place, and those of a replaced file are closed. Opening one costs ~2 ms (SQLite parses the
GeoPackage schema); reusing it, none. A :class:`QueryError` of the provider is a 400 problem.
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from standgrid.catalog import Catalog, paths
from standgrid.serve.problems import Problem
from standgrid.serve.provider import GeoPackageProvider, Layer, QueryError

_IndexKey = tuple[str, int, int, int]  # path, inode, mtime (ns), size
_layers_cache: dict[_IndexKey, dict[str, Layer]] = {}
#: The last catalog read per root: reused while its catalog.json is unchanged.
_catalogs: dict[Path, Catalog] = {}
#: Idle providers by index file, and the newest file seen per index path.
_idle: dict[_IndexKey, list[GeoPackageProvider]] = {}
_newest: dict[str, _IndexKey] = {}
#: Idle providers kept per index file (more are closed when given back).
MAX_IDLE = 16
#: Epoch label -> date per catalog read (the service never changes a Catalog it read).
_epoch_dates: weakref.WeakKeyDictionary[Catalog, dict[str, str]] = weakref.WeakKeyDictionary()
_cache_lock = threading.Lock()


def _take(index: Path) -> tuple[_IndexKey, GeoPackageProvider]:
    """A provider of the file now at ``index`` (call under the readers lock)."""
    stat = index.stat()
    key = (str(index), stat.st_ino, stat.st_mtime_ns, stat.st_size)
    stale: list[GeoPackageProvider] = []
    with _cache_lock:
        if _newest.get(key[0]) != key:
            old = _newest.get(key[0])
            if old is not None:
                stale = _idle.pop(old, [])
            _newest[key[0]] = key
        pool = _idle.get(key)
        provider = pool.pop() if pool else None
        layers = _layers_cache.get(key)
    for dead in stale:
        dead.close()
    if provider is None:
        provider = GeoPackageProvider.open(index, layers)
        if layers is None:
            with _cache_lock:
                _layers_cache.clear()
                _layers_cache[key] = provider.layers
    return key, provider


def _give_back(key: _IndexKey, provider: GeoPackageProvider) -> None:
    with _cache_lock:
        pool = _idle.setdefault(key, []) if _newest.get(key[0]) == key else None
        if pool is not None and len(pool) < MAX_IDLE:
            pool.append(provider)
            return
    provider.close()


@dataclass
class Snapshot:
    catalog: Catalog
    #: the index's provider (None: the catalog has no index yet, or it was not asked for)
    provider: GeoPackageProvider | None

    @property
    def layers(self) -> dict[str, Layer]:
        return self.provider.layers if self.provider is not None else {}

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
            raise Problem(
                404, f"no collection {collection_id!r}; collections: {sorted(self.layers)}"
            )
        return layer


@contextlib.contextmanager
def snapshot(root: Path, *, with_index: bool = True) -> Iterator[Snapshot]:
    """The catalog at ``root`` as of its last commit (and its index, when it has one), with
    the catalog's readers lock held until the block ends."""
    provider: GeoPackageProvider | None = None
    key: _IndexKey | None = None
    with _cache_lock:
        previous = _catalogs.get(root)
    with Catalog.reading(root, reuse=previous) as catalog:
        if catalog is not previous:
            with _cache_lock:
                _catalogs[root] = catalog
        index = catalog.path(paths.INDEX)
        try:
            if with_index and index.is_file():
                key, provider = _take(index)
            # yielded under the readers lock: no commit renames a file in while the request
            # reads (files opened here stay the snapshot's even after it)
            yield Snapshot(catalog, provider)
        except BaseException as exc:
            if provider is not None:  # a request that failed mid-read may leave a statement
                provider.close()  # open
                provider = None
            if isinstance(exc, QueryError):
                raise Problem(400, str(exc)) from exc
            raise
        finally:
            if provider is not None and key is not None:
                _give_back(key, provider)
