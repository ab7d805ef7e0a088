"""The catalog's QGIS project, ``catalog.qgz``: what the catalog holds, ready to look at.

:func:`write_catalog_project` stages it in a transaction from what that transaction will
commit (its state, its GeoPackage index, rasters and their ``.qml`` sidecars), so the
project and the outputs it shows land together. Legend, top first:

- one group per comparison, ``change <from>→<to>`` (unchecked): tree changes by status,
  the ``stand_changes`` choropleth of the cells (its default diverging style), the CHM
  difference (diverging ramp, m);
- one group per epoch, newest first (only the newest checked): tree crowns coloured by
  height with DBH labels (cm), trajectories, the coarse stands (1 ha) as outlines labelled
  with their basal area, the cells as a choropleth of basal area (m²/ha, one range for
  every epoch), then, unchecked: GNSS fixes, payload footprints, tiles, observed ground,
  point density, and at the bottom the CHM (checked) and the DTM.

Every GeoPackage layer is filtered to its epoch (or comparison) by a subset string, and a
layer is listed only when its file exists and its filter selects rows.
"""

from __future__ import annotations

import contextlib
import sqlite3
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths

if TYPE_CHECKING:
    from standgrid.catalog.transaction import Transaction
    from standgrid.export.qgis_project import ProjectGroup, ProjectLayer

#: The cell metric of the choropleth: column, legend text.
CHOROPLETH = ("basal_area_m2_ha", "Basal area (m²/ha)")
#: The change choropleth of the cells (diverging around 0): column, legend text.
CHANGE_CHOROPLETH = ("basal_area_m2_ha_delta", "Basal area change (m²/ha)")
#: Legend text of the columns the default ``stand_changes`` style may use (else the column).
CHANGE_LABELS = {
    "tree_height_growth_m_per_year": "Tree height growth (m/yr)",
    "zq95_per_year": "Canopy height p95 change (m/yr)",
}


def _quote(value: str) -> str:
    return "'" + value.replace("'", "''") + "'"


class _Index:
    """The GeoPackage as the transaction sees it: its layers, row counts, default styles."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def _query(self, sql: str, *args: object) -> list[Any]:
        with contextlib.closing(sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)) as db:
            return db.execute(sql, args).fetchall()

    def has(self, table: str) -> bool:
        return bool(self._query("SELECT 1 FROM gpkg_contents WHERE table_name = ?", table))

    def rows(self, table: str, where: str) -> int:
        """Rows the filter selects; 0 when the layer lacks a column it names (older layer)."""
        if not self.has(table):
            return 0
        try:
            return int(self._query(f'SELECT count(*) FROM "{table}" WHERE {where}')[0][0])
        except sqlite3.OperationalError:  # "no such column"
            return 0

    def default_style(self, table: str) -> str | None:
        if not self.has("layer_styles"):
            return None
        found = self._query(
            "SELECT styleQML FROM layer_styles WHERE f_table_name = ? AND useAsDefault "
            "ORDER BY id DESC LIMIT 1",
            table,
        )
        return str(found[0][0]) if found else None

    def range(self, table: str, column: str, where: str) -> tuple[float, float] | None:
        if not self.has(table) or column not in {
            row[1] for row in self._query(f'PRAGMA table_info("{table}")')
        }:
            return None
        lo, hi = self._query(
            f'SELECT min("{column}"), max("{column}") FROM "{table}" WHERE {where}'
        )[0]
        return None if lo is None else (float(lo), float(hi))

    def extent(self) -> tuple[float, float, float, float]:
        import pyogrio

        xmin, ymin, xmax, ymax = pyogrio.read_info(self.path, layer="cells")["total_bounds"]
        pad = 0.05 * max(xmax - xmin, ymax - ymin, 1.0)
        return xmin - pad, ymin - pad, xmax + pad, ymax + pad


class _Layers:
    """Collects the layers of one group whose files exist and whose filters select rows."""

    def __init__(self, txn: Transaction, index: _Index) -> None:
        self.txn, self.index = txn, index
        self.layers: list[ProjectLayer] = []

    def vector(
        self,
        name: str,
        table: str,
        geometry: str,
        where: str,
        visible: bool,
        qml: str | None = None,
    ) -> None:
        from standgrid.export.qgis_project import ProjectLayer

        style = qml or self.index.default_style(table)
        if style is None or self.index.rows(table, where) == 0:
            return
        self.layers.append(
            ProjectLayer(
                name,
                paths.INDEX,
                style,
                table=table,
                geometry=geometry,
                subset=where,
                visible=visible,
            )
        )

    def raster(
        self, name: str, tif: str, style: str, visible: bool, qml_text: str | None = None
    ) -> None:
        """A raster layer styled by its sidecar ``style`` (or by ``qml_text`` when given)."""
        from standgrid.export.qgis_project import ProjectLayer

        qml = self.txn.current(style)
        if self.txn.current(tif) is None or qml is None:
            return
        text = qml_text if qml_text is not None else qml.read_text("utf-8")
        self.layers.append(ProjectLayer(name, tif, text, provider="gdal", visible=visible))


def _grid_words(state: dict[str, Any]) -> tuple[str, str | None]:
    """How the legend names the cells (``20 m cells``) and the coarse stands (``1 ha``)."""
    grid = state.get("grid", {})
    if state.get("scheme") != "grid":
        return "Voronoi cells", None
    levels = [float(v) for v in grid.get("levels", [grid.get("cell_size", 0.0)])]
    cells = f"{levels[0]:g} m cells"
    return cells, (f"{levels[1] ** 2 / 10_000:g} ha" if len(levels) > 1 else None)


def _epoch_group(
    txn: Transaction,
    index: _Index,
    epoch: str,
    visible: bool,
    choropleth: Callable[[str], str | None],
    chm_style: str | None = None,
) -> ProjectGroup:
    from standgrid.export import styles
    from standgrid.export.qgis_project import ProjectGroup

    state = txn.state
    cells_words, stand_words = _grid_words(state)
    this = f'"epoch" = {_quote(epoch)}'
    missions = state["epochs"][epoch].get("missions", [])
    layers = _Layers(txn, index)
    height = index.range("trees", "height_m", "1") if index.has("trees") else None
    if height is not None:
        crowns = styles.graduated_style(
            "height_m",
            *height,
            ramp=styles.VIRIDIS,
            precision=1,
            outline_only=True,
            width=0.6,
            unit="m",
        )
        labelled = styles.with_labels(
            crowns, "round(\"dbh_m\" * 100) || ' cm'", geometry="polygon", size=7
        )
        layers.vector(
            "Trees: crown by height (m), DBH (cm)", "trees", "polygon", this, True, labelled
        )
    layers.vector("Trajectories", "trajectories", "line", this, True)
    metric, metric_words = CHOROPLETH
    if stand_words is not None and index.has("stand_metrics"):
        outline = styles.single_style(
            "polygon", "#000000", no_fill=True, outline="#000000", width=0.8
        )
        outline = styles.with_labels(
            outline,
            f"format_number(\"{metric}\", 1) || ' m²/ha'",
            geometry="polygon",
            size=10,
            priority=10,
        )
        layers.vector(
            f"Stands {stand_words}: {metric_words.lower()}",
            "stand_metrics",
            "polygon",
            f'{this} AND "level" = 1',
            True,
            outline,
        )
    cell_style = choropleth(metric)
    if cell_style is not None:
        layers.vector(
            f"{metric_words}, {cells_words}",
            "stand_metrics",
            "polygon",
            f'{this} AND "level" = 0',
            True,
            cell_style,
        )
    if missions:
        names = ", ".join(_quote(m) for m in missions)
        layers.vector("GNSS fixes", "gnss_fixes", "point", f'"mission" IN ({names})', False)
    layers.vector("Payload footprints", "payloads", "polygon", this, False)
    enriched = bool(state["epochs"][epoch].get("enriched"))
    layers.vector(f"Tiles ({cells_words}, points)", "cells", "polygon", this, not enriched)
    for name, label, on in (
        ("observed", "Observed ground", False),
        ("density", "Point density (pts/m²)", False),
        ("chm", "CHM (m)", True),
        ("dtm", "DTM (m)", False),
    ):
        shared = chm_style if name == "chm" else None
        layers.raster(label, paths.raster(epoch, name), paths.raster_style(epoch, name), on, shared)
    return ProjectGroup(epoch, tuple(layers.layers), visible)


def _change_group(txn: Transaction, index: _Index, epoch_from: str, epoch_to: str) -> ProjectGroup:
    from xml.etree import ElementTree as ET

    from standgrid.export import styles
    from standgrid.export.qgis_project import ProjectGroup

    cells_words, _ = _grid_words(txn.state)
    pair = f'"epoch_from" = {_quote(epoch_from)} AND "epoch_to" = {_quote(epoch_to)}'
    layers = _Layers(txn, index)
    layers.vector("Tree changes (grown, new, removed)", "tree_changes", "point", pair, True)
    where = f'{pair} AND "level" = 0'
    column, words = CHANGE_CHOROPLETH
    found = index.range("stand_changes", column, where)
    if found is not None:  # loss red, gain blue, one colour strength either side
        style = styles.diverging_style(column, *found, alpha=170, precision=1, unit="m²/ha")
    else:  # the layer's default style (its own column)
        style = index.default_style("stand_changes") or ""
        renderer = ET.fromstring(style.split("\n", 1)[1]).find("renderer-v2") if style else None
        column = renderer.get("attr", "") if renderer is not None else ""
        words = CHANGE_LABELS.get(column, column)
    if style:
        layers.vector(f"{words}, {cells_words}", "stand_changes", "polygon", where, True, style)
    layers.raster(
        "CHM change (m)",
        paths.comparison(epoch_from, epoch_to, "chm_diff.tif"),
        paths.comparison(epoch_from, epoch_to, "chm_diff.qml"),
        True,
    )
    return ProjectGroup(f"change {epoch_from}→{epoch_to}", tuple(layers.layers), False)


def project_groups(txn: Transaction, index_path: Path) -> list[ProjectGroup]:
    """The legend of the catalog's project: change groups, then epochs newest first."""
    from standgrid.export import styles

    index = _Index(index_path)
    state = txn.state
    epochs = sorted(
        state.get("epochs", {}),
        key=lambda e: (str(state["epochs"][e].get("date", "")), e),
        reverse=True,
    )
    level0 = '"level" = 0'

    def choropleth(metric: str) -> str | None:  # one range over every epoch: comparable
        if not index.has("stand_metrics"):
            return None
        found = index.range("stand_metrics", metric, level0)
        if found is None:
            return None
        return styles.graduated_style(
            metric, *found, ramp=styles.YLGN, alpha=190, precision=1, unit="m²/ha"
        )

    groups = [
        _change_group(txn, index, str(c["from"]), str(c["to"]))
        for _, c in sorted(state.get("comparisons", {}).items())
    ]
    chm_style = _shared_chm_style(txn, epochs)
    groups += [
        _epoch_group(txn, index, epoch, i == 0, choropleth, chm_style)
        for i, epoch in enumerate(epochs)
    ]
    return [g for g in groups if g.layers]


def _shared_chm_style(txn: Transaction, epochs: Sequence[str]) -> str | None:
    """One CHM colour range (0 to the highest epoch's p98) for every epoch, so the same colour
    is the same height in each; None without a CHM. The sidecar ``chm.qml`` beside each
    raster keeps its own range (a raster dragged in alone)."""
    from standgrid.export import styles

    tops = [
        styles.raster_range(found, "chm")[1]
        for found in (txn.current(paths.raster(epoch, "chm")) for epoch in epochs)
        if found is not None
    ]
    return styles.raster_style("chm", 0.0, max(tops)) if tops else None


def write_catalog_project(txn: Transaction) -> Path | None:
    """Stage ``catalog.qgz`` in ``txn`` (None, and nothing staged, before the first tiles)."""
    from standgrid.export.qgis_project import write_qgis_project

    index_path = txn.current(paths.INDEX)
    crs = txn.state.get("crs")
    if index_path is None or not crs or not _Index(index_path).has("cells"):
        return None
    groups: Sequence[ProjectGroup] = project_groups(txn, index_path)
    return write_qgis_project(
        txn.stage(paths.QGIS_PROJECT),
        groups,
        crs=str(crs),
        extent=_Index(index_path).extent(),
        title=txn.catalog.root.name,
    )
