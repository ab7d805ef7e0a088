"""A consistent view of the catalog for one request: its state and an open index connection.

Taken under the catalog's readers lock (:meth:`Catalog.reading`), so no commit is half
visible; the SQLite connection is opened inside it and keeps reading that index file even
when a later commit renames a new one into place. The parsed catalog.json is reused while
the file is unchanged (``reading(reuse=)``): the service only reads it.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from standgrid.catalog import Catalog, paths
from standgrid.serve import features
from standgrid.serve.features import Layer
from standgrid.serve.problems import Problem

_layers_cache: dict[tuple[str, int, int], dict[str, Layer]] = {}
#: The last catalog read per root: reused while its catalog.json is unchanged.
_catalogs: dict[Path, Catalog] = {}
_cache_lock = threading.Lock()


@dataclass
class Snapshot:
    catalog: Catalog
    index: sqlite3.Connection | None
    layers: dict[str, Layer]

    @property
    def epoch_dates(self) -> dict[str, str]:
        return {label: e.date or "" for label, e in self.catalog.epoch_records.items()}

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
    layers: dict[str, Layer] = {}
    with _cache_lock:
        previous = _catalogs.get(root)
    with Catalog.reading(root, reuse=previous) as catalog:
        if catalog is not previous:
            with _cache_lock:
                _catalogs[root] = catalog
        index = catalog.path(paths.INDEX)
        if with_index and index.is_file():
            conn = features.connect(index)
            stat = index.stat()
            key = (str(index), stat.st_ino, stat.st_mtime_ns)
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
        try:
            yield Snapshot(catalog, conn, layers)
        finally:
            if conn is not None:
                conn.close()
