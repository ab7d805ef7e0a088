"""The catalog's GeoPackage index (``index.gpkg``) as one typed object.

:class:`CatalogIndex` owns reading the index's layers and replacing rows of them per epoch
(or per mission) inside a transaction. Layers are read and written whole, in bulk (pyogrio
data frames, never row by row); replaced layers are kept in memory until :meth:`save`, which
writes them all into the transaction's staged copy of the index in one atomic step (the
other layers, and the QGIS styles of layers not replaced, are kept).

::

    index = CatalogIndex(catalog, txn)
    cells = index.read("cells", epoch="2024")          # a GeoDataFrame (empty when absent)
    index.replace("cells", new_cells, epochs={"2024"})  # the epoch's rows -> new_cells
    index.save()                                        # -> txn.stage("index.gpkg")
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths
from standgrid.errors import CatalogError

if TYPE_CHECKING:
    from standgrid.catalog import Catalog, Transaction


class CatalogIndex:
    """The layers of ``index.gpkg`` as one reader (``txn`` None) or one transaction sees them.

    Reads come from the transaction's staged index once it was written, else the catalog's;
    a layer replaced by this object is read back as replaced. Writes need a transaction.
    """

    def __init__(self, catalog: Catalog, txn: Transaction | None = None) -> None:
        self.catalog = catalog
        self.txn = txn
        #: Layers replaced and not yet saved: name -> (frame, QML style or None).
        self._pending: dict[str, tuple[Any, str | None]] = {}
        self._read: dict[str, Any] = {}

    @property
    def path(self) -> Path | None:
        """The index file reads come from (None: the catalog has no index yet)."""
        if self.txn is not None:
            return self.txn.current(paths.INDEX)
        path = self.catalog.path(paths.INDEX)
        return path if path.exists() else None

    def layers(self) -> set[str]:
        """Names of the layers present (replaced ones included)."""
        from standgrid.export.gpkg import index_layer_names

        path = self.path
        present = index_layer_names(path) if path is not None else set()
        return present | set(self._pending)

    def read(self, layer: str, epoch: str | None = None) -> Any:
        """A layer as a (Geo)DataFrame, or only its rows of ``epoch`` (by its ``epoch``
        column). An absent standard layer is an empty frame with its columns; an absent
        other layer an empty frame."""
        frame = self._frame(layer)
        if epoch is None:
            return frame.copy()
        if "epoch" not in frame.columns:
            if not len(frame):
                return frame.copy()
            raise CatalogError(f"layer {layer!r} has no epoch column", path=self.path)
        return frame[frame["epoch"].astype(str) == str(epoch)].reset_index(drop=True)

    def replace(
        self,
        layer: str,
        frame: Any,
        *,
        epochs: Collection[str] = (),
        missions: Collection[str] = (),
        style: str | None = None,
    ) -> None:
        """Replace the layer's rows of ``epochs`` (its ``epoch`` column) and of ``missions``
        (its ``mission`` column) by ``frame`` (a frame or row dicts; appended after the rows
        kept). ``style`` (QML) becomes the layer's default QGIS style; standard layers get
        their own. Written by :meth:`save`."""
        import pandas as pd

        from standgrid.export.gpkg import LAYER_COLUMNS, layer_frame

        if self.txn is None:
            raise CatalogError("replacing index rows needs a transaction", path=self.path)
        new = frame if isinstance(frame, pd.DataFrame) else pd.DataFrame(list(frame))
        if layer in LAYER_COLUMNS:
            new = layer_frame(layer, new, self.catalog.crs)
        current = self._frame(layer)
        drop = pd.Series(False, index=current.index)
        for column, values in (("epoch", epochs), ("mission", missions)):
            if values and column in current.columns:
                drop |= current[column].astype(str).isin({str(v) for v in values})
        kept = current[~drop]
        if len(kept) and len(new):
            if getattr(new, "crs", None) is not None and hasattr(kept, "set_crs"):
                kept = kept.set_crs(new.crs, allow_override=True)  # one CRS: the catalog's
            merged = pd.concat([kept, new], ignore_index=True)
        else:
            merged = (new if len(new) or not len(current.columns) else kept).reset_index(drop=True)
        self._pending[layer] = (merged, style)
        self._read[layer] = merged

    def replace_all(self, layer: str, frame: Any, *, style: str | None = None) -> None:
        """Replace every row of the layer by ``frame`` (``style``: its default QGIS style,
        QML). Written by :meth:`save`."""
        if self.txn is None:
            raise CatalogError("replacing index rows needs a transaction", path=self.path)
        self._pending[layer] = (frame, style)
        self._read[layer] = frame

    def save(self) -> Path | None:
        """Write every replaced layer into the transaction's staged index (one atomic file
        write; other layers kept). Returns the staged path (None: nothing to write)."""
        from standgrid.export.gpkg import LAYER_COLUMNS, IndexWriter, write_standard_layer

        if not self._pending:
            return None
        assert self.txn is not None
        base = self.txn.current(paths.INDEX)
        staged = self.txn.stage(paths.INDEX)
        # staged: the commit fsyncs it (with every staged file, once)
        with IndexWriter(staged, self.catalog.crs, base=base, durable=False) as writer:
            for layer, (frame, style) in self._pending.items():
                if layer in LAYER_COLUMNS and style is None:
                    write_standard_layer(writer, layer, frame)
                else:
                    writer.write_layer(layer, frame, style=style)
        self._pending.clear()
        return staged

    def _frame(self, layer: str) -> Any:
        found = self._read.get(layer)
        if found is not None:
            return found
        import pandas as pd

        from standgrid.export.gpkg import LAYER_COLUMNS, layer_frame, read_index_layer

        path = self.path
        if path is not None and layer in self.layers():
            frame = read_index_layer(path, layer)
        elif layer in LAYER_COLUMNS:
            frame = layer_frame(layer, [], self.catalog.crs)
        else:
            frame = pd.DataFrame()
        self._read[layer] = frame
        return frame
