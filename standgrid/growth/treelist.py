"""A catalog's tree lists and stand areas as growth simulators read them.

Reads only the catalog's tables (``tables/tree_list_<epoch>.parquet``,
``tables/stand_metrics.parquet``) and the ``stand_metrics`` layer of ``index.gpkg``, as
``standgrid enrich`` writes them (a catalog enriched by an older standgrid is refused with
the command that updates it). Columns: docs/TREES.md.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from standgrid._atomic import atomic_output
from standgrid.catalog import Catalog, paths
from standgrid.enrichment.stands import counted_trees, stem_xy
from standgrid.errors import EpochNotFoundError, FormatError, NotEnrichedError

#: Tree-list formats by file suffix.
FORMATS = {
    ".csv": "csv",
    ".parquet": "parquet",
    ".gpkg": "gpkg",
    ".sqlite": "sqlite",
    ".db": "sqlite",
}
#: The generic tree list, in order (docs/TREES.md describes each column).
TREE_COLUMNS = [
    "epoch",
    "date",
    "stand_id",
    "cell_id",
    "tree_id",
    "tree_uid",
    "detected_by",
    "x",
    "y",
    "stem_x",
    "stem_y",
    "lon",
    "lat",
    "z_ground",
    "height_m",
    "dbh_cm",
    "dbh_source",
    "dbh_se_cm",
    "dbh_reason",
    "basal_area_m2",
    "crown_area_m2",
    "crown_diameter_m",
    "n_points",
    "counted",
    "stand_area_m2",
    "trees_per_ha",
    "crs",
]


def catalog_epochs(catalog: Catalog, epochs: Sequence[str] | None) -> list[str]:
    """The enriched epochs asked for (all enriched ones by default), in catalog order."""
    known = catalog.epoch_records
    wanted = list(epochs) if epochs else [e for e, rec in known.items() if rec.enriched]
    for epoch in wanted:
        if epoch not in known:
            raise EpochNotFoundError(
                f"no epoch {epoch!r} (have {sorted(known)})", path=catalog.path(paths.CATALOG_FILE)
            )
        if not known[epoch].enriched:
            raise NotEnrichedError(_not_enriched(epoch, known[epoch]), path=catalog.root)
    if not wanted:
        stale = [e for e, rec in known.items() if rec.invalidated]
        if stale:
            raise NotEnrichedError(_not_enriched(stale[0], known[stale[0]]), path=catalog.root)
        raise NotEnrichedError("no enriched epoch: run `standgrid enrich` first", path=catalog.root)
    return wanted


def _not_enriched(epoch: str, record: Any) -> str:
    """Why an epoch has no tree list: stale (enriched, then re-tiled: why) or never enriched."""
    if record.invalidated:
        why = record.invalidated.get("reason")
        return (
            f"epoch {epoch!r} is stale: its tiles changed after it was enriched"
            + (f" ({why})" if why else "")
            + "; re-run `standgrid enrich`"
        )
    return f"epoch {epoch!r} is not enriched: run `standgrid enrich` first"


def read_trees(catalog: Catalog, epoch: str) -> pd.DataFrame:
    """The epoch's tree list as ``standgrid enrich`` writes it (``dbh_source``,
    ``dbh_se_m``, ``observed``: docs/METRICS.md)."""
    path = catalog.path(paths.tree_list(epoch, "parquet"))
    if not path.is_file():
        raise NotEnrichedError(
            f"no tree list for epoch {epoch!r}: run `standgrid enrich`", path=path
        )
    trees = pd.read_parquet(path)
    for column in ("tree_id", "x", "y", "height_m", "dbh_m"):
        if column not in trees.columns:
            raise FormatError(f"tree list has no column {column!r}", path=path)
    missing = [c for c in ("dbh_source", "dbh_se_m", "observed") if c not in trees.columns]
    if missing:
        raise NotEnrichedError(
            f"tree list lacks {missing} (written by an older standgrid): run "
            f"`standgrid enrich {catalog.root}` again",
            path=path,
        )
    trees["epoch"] = str(epoch)
    return trees


def read_stands(catalog: Catalog) -> pd.DataFrame:
    """``tables/stand_metrics.parquet`` with ``epoch`` as text."""
    path = catalog.path(paths.stand_metrics("parquet"))
    if not path.is_file():
        raise NotEnrichedError("no stand table: run `standgrid enrich`", path=path)
    stands = pd.read_parquet(path)
    stands["epoch"] = stands["epoch"].astype(str)
    return stands


def stand_area(row: pd.Series) -> float:
    """The ground a stand row was measured over (m²): its observed area."""
    return float(row["observed_m2"])


def stand_key(level: int) -> str:
    """The tree-list column naming a tree's stand at ``level`` (0: tile cell, 1: stand)."""
    if level not in (0, 1):
        raise ValueError(f"level must be 0 or 1, got {level}")
    return "cell_id" if level == 0 else "stand_id"


def generic_tree_list(
    catalog: Catalog, epochs: Sequence[str] | None = None, *, level: int = 1
) -> pd.DataFrame:
    """Every tree of the epochs, one row each, in the columns of :data:`TREE_COLUMNS`.

    ``stand_area_m2`` and ``trees_per_ha`` refer to the stand at ``level`` (0: the 20 m cell,
    1: the 1 ha stand): each tree the stand table counts (``counted``: its stem on observed
    ground, in a measured cell of a measured stand) stands for ``10000 / stand_area_m2``
    trees per hectare, where ``stand_area_m2`` is the stand's observed area; the others are
    listed with null expansion (not counted, not dropped).
    """
    from standgrid.crs import CRS

    key = stand_key(level)
    stands = read_stands(catalog)
    frames = []
    for epoch in catalog_epochs(catalog, epochs):
        trees = read_trees(catalog, epoch)
        if key not in trees.columns:
            raise FormatError(f"tree list has no column {key!r}", path=catalog.root)
        rows = stands[(stands["epoch"] == epoch) & (stands["level"] == level)]
        areas = {
            str(r["cell_id"]): stand_area(r) for _, r in rows.iterrows() if pd.notna(r["stems_ha"])
        }
        counted = counted_trees(trees, stands[stands["epoch"] == epoch])
        area = trees[key].astype(str).map(areas).astype(float).where(counted)
        dbh = trees["dbh_m"].astype(float)
        crown = trees["crown_area_m2"].astype(float) if "crown_area_m2" in trees else np.nan
        out = pd.DataFrame(
            {
                "epoch": epoch,
                "date": catalog.epoch(epoch).date,
                "stand_id": trees.get("stand_id", pd.Series(pd.NA, index=trees.index)),
                "cell_id": trees.get("cell_id", pd.Series(pd.NA, index=trees.index)),
                "tree_id": trees["tree_id"].astype(np.int64),
                "tree_uid": trees.get("tree_uid", pd.Series(pd.NA, index=trees.index)).astype(
                    "Int64"
                ),
                "detected_by": trees.get("detected_by", pd.Series(pd.NA, index=trees.index)).astype(
                    "string"
                ),
                "x": trees["x"].astype(float),
                "y": trees["y"].astype(float),
                "stem_x": trees.get("stem_x", np.nan),
                "stem_y": trees.get("stem_y", np.nan),
                "z_ground": trees.get("z_ground", np.nan),
                "height_m": trees["height_m"].astype(float),
                "dbh_cm": dbh * 100.0,
                "dbh_source": trees["dbh_source"].astype("string"),
                "dbh_se_cm": trees["dbh_se_m"] * 100.0,
                "dbh_reason": trees.get("dbh_reason", pd.Series(pd.NA, index=trees.index)),
                "basal_area_m2": np.pi * (dbh / 2.0) ** 2,
                "crown_area_m2": crown,
                "crown_diameter_m": 2.0 * np.sqrt(crown / np.pi),
                "n_points": trees.get("n_points", pd.Series(pd.NA, index=trees.index)),
                "counted": counted & area.notna(),
                "stand_area_m2": area,
                "trees_per_ha": 10_000.0 / area,
            }
        )
        frames.append(out)
    table = pd.concat(frames, ignore_index=True)
    to_wgs84 = CRS.of(catalog.crs).transformer_to("EPSG:4326")
    lon, lat = to_wgs84.transform(*stem_xy(table))
    table["lon"], table["lat"] = lon, lat
    table["crs"] = catalog.crs
    return table[TREE_COLUMNS]


def tree_list_format(path: Path, fmt: str | None = None) -> str:
    """The output format: ``fmt`` or the one the suffix names."""
    if fmt is not None:
        if fmt not in set(FORMATS.values()):
            raise ValueError(f"format must be one of {sorted(set(FORMATS.values()))}, not {fmt!r}")
        return fmt
    try:
        return FORMATS[path.suffix.lower()]
    except KeyError:
        raise FormatError(
            f"cannot tell the format from the suffix {path.suffix!r} "
            f"(use one of {sorted(FORMATS)} or --format)",
            path=path,
        ) from None


def write_tree_list(
    table: pd.DataFrame,
    out: str | Path,
    *,
    crs: str,
    fmt: str | None = None,
    overwrite: bool = False,
    layer: str = "trees",
) -> Path:
    """Write the tree list atomically as CSV, Parquet, GeoPackage (point layer ``trees`` at
    the stem, or the top without a stem) or a plain SQLite table ``trees``."""
    import sqlite3

    out_path = Path(out)
    kind = tree_list_format(out_path, fmt)
    with atomic_output(out_path, overwrite=overwrite) as tmp:
        if kind == "csv":
            table.to_csv(tmp, index=False)
        elif kind == "parquet":
            table.to_parquet(tmp, index=False)
        elif kind == "gpkg":
            import geopandas as gpd

            frame = gpd.GeoDataFrame(table, geometry=gpd.points_from_xy(*stem_xy(table)), crs=crs)
            with warnings.catch_warnings():  # the temporary name does not end in .gpkg
                warnings.filterwarnings("ignore", "The filename extension should be")
                frame.to_file(tmp, layer=layer, driver="GPKG", engine="pyogrio")
        else:
            with sqlite3.connect(tmp) as conn:
                _sql_ready(table).to_sql(layer, conn, index=False)
            conn.close()
    return out_path


def _sql_ready(table: pd.DataFrame) -> pd.DataFrame:
    """Nullable pandas columns as plain objects (None for NA), so sqlite3 binds them."""
    out = table.copy()
    for column in out.columns:
        if isinstance(out[column].dtype, pd.StringDtype) or out[column].dtype == object:
            out[column] = out[column].astype(object).where(out[column].notna(), None)
    return out


def summary(table: pd.DataFrame) -> dict[str, Any]:
    """Counts for the CLI report: trees, with a DBH, by DBH source, per epoch."""
    out: dict[str, Any] = {}
    for epoch, part in table.groupby("epoch", sort=True):
        sources = part["dbh_source"].fillna("none").value_counts().to_dict()
        out[str(epoch)] = {
            "trees": len(part),
            "with_dbh": int(part["dbh_cm"].notna().sum()),
            "dbh_source": {str(k): int(v) for k, v in sources.items()},
        }
    return out
