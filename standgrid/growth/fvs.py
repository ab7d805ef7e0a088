"""FVS database input: a catalog's stands and trees as ``FVS_StandInit`` and ``FVS_TreeInit``.

The Forest Vegetation Simulator reads these SQLite tables with its ``DATABASE`` /
``DSNIN`` / ``STANDSQL`` / ``TREESQL`` keywords, in imperial units. docs/FVS.md lists every
column written, its source and unit, and the species choice (LiDAR does not know species:
the user gives a code per stand or one default).
"""

from __future__ import annotations

import datetime as dt
import math
import re
import sqlite3
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from standgrid._atomic import atomic_output
from standgrid.catalog import Catalog, EpochRecord, paths
from standgrid.enrichment.stands import counted_trees
from standgrid.errors import EpochDateError, FormatError
from standgrid.georeference.geoid import GeoidModel, NoGeoidModel, find_geoid
from standgrid.growth.elevation import above_sea_level, epoch_elevation
from standgrid.growth.treelist import (
    catalog_epochs,
    read_stands,
    read_trees,
    stand_area,
    stand_key,
)

M_PER_FT = 0.3048
CM_PER_IN = 2.54
M2_PER_ACRE = 4046.8564224
#: 1 m²/ha in ft²/acre.
BA_M2HA_TO_FT2AC = (1.0 / M_PER_FT**2) / (10_000.0 / M2_PER_ACRE)
#: FVS breakpoint DBH (in) above every tree: one fixed plot size for all trees.
ALL_TREES_BREAK_DBH = 999.0
#: FVS stand ids are at most 26 characters.
MAX_STAND_ID = 26
DEFAULT_VARIANT = "PN"
DEFAULT_SPECIES = "DF"

STAND_COLUMNS = {
    "Stand_ID": "TEXT",
    "Variant": "TEXT",
    "Inv_Year": "INTEGER",
    "Latitude": "REAL",
    "Longitude": "REAL",
    "Slope": "REAL",
    "Aspect": "REAL",
    "ElevFt": "REAL",
    "Basal_Area_Factor": "REAL",
    "Inv_Plot_Size": "REAL",
    "Brk_DBH": "REAL",
    "Num_Plots": "INTEGER",
    "DG_Trans": "INTEGER",
    "DG_Measure": "REAL",
    "HTG_Trans": "INTEGER",
    "HTG_Measure": "REAL",
    "SG_Cell_ID": "TEXT",
    "SG_Epoch": "TEXT",
    "SG_Level": "INTEGER",
    "SG_Area_m2": "REAL",
    "SG_Trees_Without_DBH": "INTEGER",
    "SG_Species_Source": "TEXT",
}
TREE_COLUMNS = {
    "Stand_ID": "TEXT",
    "Plot_ID": "INTEGER",
    "Tree_ID": "INTEGER",
    "Tree_Count": "REAL",
    "History": "INTEGER",
    "Species": "TEXT",
    "DBH": "REAL",
    "DG": "REAL",
    "Ht": "REAL",
    "HTG": "REAL",
    "CrRatio": "INTEGER",
    "SG_Tree_ID": "TEXT",
    "SG_Tree_UID": "INTEGER",
    "SG_DBH_Source": "TEXT",
}


@dataclass
class FvsExport:
    """What :func:`export_fvs` wrote, and what it left out and why."""

    path: Path
    stands: int = 0
    trees: int = 0
    trees_without_dbh: int = 0
    trees_with_increments: int = 0
    stands_skipped: dict[str, str] = field(default_factory=dict)
    species_default_used: bool = False
    #: epoch -> ``ElevFt``'s vertical reference (geoid model, operation, grid file; or the
    #: clouds' own heights), for the epochs whose ``ElevFt`` is written
    elevation_reference: dict[str, str] = field(default_factory=dict)
    #: epoch -> why ``ElevFt`` is NULL for every stand of the epoch
    elev_ft_null_reason: dict[str, str] = field(default_factory=dict)
    #: FVS stand id -> why its ``ElevFt`` is NULL (in an epoch that has a reference)
    elev_ft_null_stands: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.path),
            "stands": self.stands,
            "trees": self.trees,
            "trees_without_dbh_skipped": self.trees_without_dbh,
            "trees_with_dg_htg": self.trees_with_increments,
            "stands_skipped": dict(self.stands_skipped),
            "species_default_used": self.species_default_used,
            "elevation_reference": dict(self.elevation_reference),
            "elev_ft_null_reason": dict(self.elev_ft_null_reason),
            "elev_ft_null_stands": dict(self.elev_ft_null_stands),
            "notes": list(self.notes),
        }


def fvs_stand_id(cell_id: str, epoch: str) -> str:
    """``<cell_id>_<epoch>``; an error beyond FVS's 26 characters."""
    stand_id = f"{cell_id}_{epoch}"
    if len(stand_id) > MAX_STAND_ID:
        raise FormatError(f"FVS stand id {stand_id!r} is longer than {MAX_STAND_ID} characters")
    return stand_id


def slope_aspect(dtm: Path, polygon: Any) -> tuple[float, float, float]:
    """Slope (percent), aspect (degrees clockwise from north, the downslope direction; 0
    when flat) and mean elevation (m) of the plane fitted to the DTM pixels in ``polygon``."""
    import rasterio
    from rasterio.features import geometry_mask
    from rasterio.windows import Window, from_bounds

    with rasterio.open(dtm) as src:
        window = (
            from_bounds(*polygon.bounds, transform=src.transform).round_offsets().round_lengths()
        )
        try:  # a stand reaching past the DTM: read (and place) only the overlap
            window = window.intersection(Window(0, 0, src.width, src.height))
        except rasterio.errors.WindowError:
            return math.nan, math.nan, math.nan
        z = src.read(1, window=window, masked=True).astype(np.float64)
        transform = src.window_transform(window)
    inside = ~geometry_mask([polygon], out_shape=z.shape, transform=transform)
    ok = inside & ~np.ma.getmaskarray(z) & np.isfinite(z.filled(np.nan))
    if ok.sum() < 3:
        return math.nan, math.nan, math.nan
    rows, cols = np.nonzero(ok)
    xs, ys = rasterio.transform.xy(transform, rows, cols)
    x, y = np.asarray(xs, float), np.asarray(ys, float)
    a = np.column_stack([x - x.mean(), y - y.mean(), np.ones_like(x)])
    (gx, gy, _), *_ = np.linalg.lstsq(a, z.data[ok], rcond=None)
    slope = 100.0 * math.hypot(gx, gy)
    aspect = (math.degrees(math.atan2(-gx, -gy)) + 360.0) % 360.0 if slope >= 0.5 else 0.0
    return slope, aspect, float(z.data[ok].mean())


def _stand_polygons(catalog: Catalog) -> pd.DataFrame:
    import pyogrio

    frame = pyogrio.read_dataframe(
        catalog.path(paths.INDEX), layer="stand_metrics", columns=["cell_id", "epoch"]
    )
    frame["epoch"] = frame["epoch"].astype(str)
    return frame


def _years_between(catalog: Catalog, first: str, last: str) -> float | None:
    """Years from ``first``'s date to ``last``'s; None when either epoch has no date."""
    first_date, last_date = (catalog.epoch(e).date for e in (first, last))
    if first_date is None or last_date is None:
        return None
    start, end = dt.date.fromisoformat(first_date), dt.date.fromisoformat(last_date)
    return (end - start).days / 365.25


def inventory_year(record: EpochRecord, catalog_root: Path | None = None) -> tuple[int, bool]:
    """FVS ``Inv_Year`` of an epoch: its date's year, else its label when the label is a
    year (then True: taken from the label); an :class:`EpochDateError` naming the epoch
    when it has neither."""
    if record.date:
        return dt.date.fromisoformat(record.date).year, False
    if re.fullmatch(r"[12][0-9]{3}", record.label):
        return int(record.label), True
    raise EpochDateError(
        f"epoch {record.label!r} has no date and its label is not a year: FVS needs an "
        "inventory year (export the other epochs with --epoch, or re-tile its missions "
        "with --epoch YYYY)",
        path=catalog_root,
    )


def _increments(catalog: Catalog, epoch: str, previous: str | None) -> pd.DataFrame | None:
    """Per tree of ``epoch``: past DBH (m; where both epochs measured it) and height
    increment (m) since ``previous``, from ``compare/<previous>__<epoch>/tree_changes``;
    None when the two epochs were not compared."""
    if previous is None:
        return None
    path = catalog.path(paths.comparison(previous, epoch, "tree_changes.parquet"))
    if not path.is_file():
        return None
    changes = pd.read_parquet(path)
    matched = changes[(changes["status"] == "grown") & ~changes["suspicious"].astype(bool)]
    # a past DBH calibrates diameter growth only when both epochs measured the stem, and
    # the stem did not shrink (measurement noise: FVS would drop the record unsaid)
    both = (matched["dbh_source_from"] == "measured") & (matched["dbh_source_to"] == "measured")
    grew = matched["dbh_m_to"] >= matched["dbh_m_from"]
    past_dbh = matched["dbh_m_from"].where(both & grew)
    return pd.DataFrame(
        {
            "past_dbh_m": past_dbh.to_numpy(float),
            "htg_m": matched["height_m_delta"].to_numpy(float),
        },
        index=matched["tree_id_to"].astype(np.int64).to_numpy(),
    )


def _crown_ratio(trees: pd.DataFrame) -> pd.Series:
    """FVS crown ratio (percent of height in live crown) where the tree list measures the
    crown base (``crown_base_m``) or gives ``crown_ratio`` (0-1); else NA (FVS imputes)."""
    if "crown_ratio" in trees.columns:
        ratio = trees["crown_ratio"].astype(float)
    elif "crown_base_m" in trees.columns:
        ratio = 1.0 - trees["crown_base_m"].astype(float) / trees["height_m"].astype(float)
    else:
        return pd.Series(pd.NA, index=trees.index, dtype="Int64")
    return (100.0 * ratio.clip(0.01, 1.0)).round().astype("Int64")


def export_fvs(
    catalog_path: str | Path,
    out: str | Path,
    *,
    level: int = 1,
    epochs: Sequence[str] | None = None,
    variant: str = DEFAULT_VARIANT,
    species: str | None = None,
    species_by_stand: Mapping[str, str] | None = None,
    increments: bool = True,
    overwrite: bool = False,
    geoid_dirs: Sequence[str | Path] | None = None,
    heights_above_sea_level: bool = False,
) -> FvsExport:
    """Write ``FVS_StandInit`` and ``FVS_TreeInit`` (SQLite) for the catalog's stands.

    One FVS stand per stand of ``level`` (1: the 1 ha stands, 0: the tile cells) and epoch,
    with one fixed plot: its size is the stand's observed area. Trees without a DBH are
    left out (FVS needs one) and counted. ``species_by_stand`` maps a standgrid stand id
    (``cell_id``) to an FVS species code; other stands get ``species`` (default
    :data:`DEFAULT_SPECIES`). With ``increments`` and an earlier epoch compared with this
    one, matched trees get DG (past DBH, DG_Trans 1) and HTG (height increment, HTG_Trans 0).
    ``ElevFt`` is the stand's mean DTM height above sea level (:func:`epoch_elevation`):
    for missions placed by GNSS or an anchor, minus the geoid undulation of the grid
    :func:`~standgrid.georeference.geoid.find_geoid` finds in ``geoid_dirs`` (default: its
    usual folders); for already-projected clouds, their heights with
    ``heights_above_sea_level``; else NULL (the report says why, per epoch).
    """
    with Catalog.reading(catalog_path) as catalog:  # one consistent state of every file
        return _export_fvs(
            catalog,
            Path(out),
            level=level,
            epochs=epochs,
            variant=variant,
            species=species,
            species_by_stand=species_by_stand,
            increments=increments,
            overwrite=overwrite,
            geoid=find_geoid(geoid_dirs),
            heights_above_sea_level=heights_above_sea_level,
        )


def _export_fvs(
    catalog: Catalog,
    out: Path,
    *,
    level: int,
    epochs: Sequence[str] | None,
    variant: str,
    species: str | None,
    species_by_stand: Mapping[str, str] | None,
    increments: bool,
    overwrite: bool,
    geoid: GeoidModel | NoGeoidModel,
    heights_above_sea_level: bool = False,
) -> FvsExport:
    from standgrid.crs import CRS

    key = stand_key(level)
    wanted = catalog_epochs(catalog, epochs)
    records = catalog.epoch_records
    order = sorted(records, key=lambda e: (records[e].date or "", e))
    years_of: dict[str, int] = {}
    report_notes: list[str] = []
    for epoch in wanted:  # every epoch refused before anything is read or written
        years_of[epoch], from_label = inventory_year(records[epoch], catalog.root)
        if from_label:
            report_notes.append(f"{epoch}: no date; Inv_Year {years_of[epoch]} is its label")
    stands = read_stands(catalog)
    polygons = _stand_polygons(catalog)
    to_wgs84 = CRS.of(catalog.crs).transformer_to("EPSG:4326")
    report = FvsExport(Path(out), species_default_used=False, notes=report_notes)
    elevations = {e: epoch_elevation(catalog, e, geoid, heights_above_sea_level) for e in wanted}
    for epoch, elevation in elevations.items():
        if elevation.null_reason is not None:
            report.elev_ft_null_reason[epoch] = elevation.null_reason
        else:
            assert elevation.reference is not None
            report.elevation_reference[epoch] = elevation.reference
    if heights_above_sea_level and not any(
        e.user_says_above_sea_level for e in elevations.values()
    ):
        report.notes.append(
            "--heights-above-sea-level changed nothing: no exported epoch is made only of "
            "already-projected clouds"
        )
    species_by_stand = dict(species_by_stand or {})
    stand_rows: list[dict[str, Any]] = []
    tree_frames: list[pd.DataFrame] = []
    for epoch in wanted:
        trees = read_trees(catalog, epoch)
        position = order.index(epoch)
        previous = order[position - 1] if increments and position > 0 else None
        if previous is not None and not records[previous].enriched:
            previous = None
        incr = _increments(catalog, epoch, previous)
        if previous is not None and incr is None:
            report.notes.append(
                f"{epoch}: no DG/HTG (epochs {previous} and {epoch} not compared: run "
                f"`standgrid compare {catalog.root} --from {previous} --to {epoch}`)"
            )
            previous = None
        years = _years_between(catalog, previous, epoch) if previous is not None else None
        if previous is not None and years is None:
            report.notes.append(
                f"{epoch}: no DG/HTG (epoch {epoch if records[previous].date else previous} "
                "has no date: the years between the two measurements are unknown)"
            )
            incr = None
        year = years_of[epoch]
        level_rows = stands[(stands["epoch"] == epoch) & (stands["level"] == level)]
        dtm = catalog.path(paths.raster(epoch, "dtm"))
        counted = trees[counted_trees(trees, stands[stands["epoch"] == epoch])]
        for _, row in level_rows.sort_values("cell_id").iterrows():
            cell_id = str(row["cell_id"])
            if pd.isna(row["stems_ha"]):  # not measured: nothing to grow, said why
                report.stands_skipped[cell_id + "_" + epoch] = str(row["null_reason"])
                continue
            mine = counted[counted[key].astype(str) == cell_id]
            area = stand_area(row)
            with_dbh = mine[np.isfinite(mine["dbh_m"].to_numpy(float))]
            if not len(mine) or not area > 0:
                report.stands_skipped[cell_id + "_" + epoch] = "no trees detected"
                continue
            if not len(with_dbh):
                report.stands_skipped[cell_id + "_" + epoch] = "no tree with a DBH"
                report.trees_without_dbh += len(mine)
                continue
            report.trees_without_dbh += len(mine) - len(with_dbh)
            stand_id = fvs_stand_id(cell_id, epoch)
            poly = polygons[(polygons["cell_id"] == cell_id) & (polygons["epoch"] == epoch)]
            geom = poly.geometry.iloc[0] if len(poly) else None
            slope, aspect, elev = (
                slope_aspect(dtm, geom) if geom is not None and dtm.is_file() else (math.nan,) * 3
            )
            cx, cy = (
                (geom.centroid.x, geom.centroid.y)
                if geom is not None
                else (float(mine["x"].mean()), float(mine["y"].mean()))
            )
            lon, lat = to_wgs84.transform(cx, cy)
            elev, why = above_sea_level(elevations[epoch], lon, lat, elev)
            if why is not None:
                report.elev_ft_null_stands[stand_id] = why
            acres = area / M2_PER_ACRE
            code = species_by_stand.get(cell_id)
            if code is None:
                code = species or DEFAULT_SPECIES
                report.species_default_used = report.species_default_used or species is None
            stand_rows.append(
                {
                    "Stand_ID": stand_id,
                    "Variant": variant.upper(),
                    "Inv_Year": year,
                    "Latitude": lat,
                    "Longitude": lon,
                    "Slope": _opt(slope),
                    "Aspect": _opt(aspect),
                    "ElevFt": _opt(elev / M_PER_FT),
                    "Basal_Area_Factor": -1.0 / acres,
                    "Inv_Plot_Size": 1.0 / acres,
                    "Brk_DBH": ALL_TREES_BREAK_DBH,
                    "Num_Plots": 1,
                    "DG_Trans": 1 if years else None,
                    "DG_Measure": years,
                    "HTG_Trans": 0 if years else None,
                    "HTG_Measure": years,
                    "SG_Cell_ID": cell_id,
                    "SG_Epoch": epoch,
                    "SG_Level": level,
                    "SG_Area_m2": area,
                    "SG_Trees_Without_DBH": len(mine) - len(with_dbh),
                    "SG_Species_Source": "per-stand"
                    if cell_id in species_by_stand
                    else ("user default" if species else "placeholder default"),
                }
            )
            tree_frames.append(
                _tree_rows(stand_id, with_dbh.sort_values("tree_id"), code, incr, years)
            )
    tree_table = (
        pd.concat(tree_frames, ignore_index=True)
        if tree_frames
        else pd.DataFrame(columns=list(TREE_COLUMNS))
    )
    report.stands = len(stand_rows)
    report.trees = len(tree_table)
    report.trees_with_increments = int((tree_table["DG"].notna() | tree_table["HTG"].notna()).sum())
    _write_database(
        Path(out), pd.DataFrame(stand_rows, columns=list(STAND_COLUMNS)), tree_table, overwrite
    )
    return report


def _opt(value: float) -> float | None:
    return None if not math.isfinite(value) else float(value)


def _tree_rows(
    stand_id: str,
    trees: pd.DataFrame,
    species: str,
    incr: pd.DataFrame | None,
    years: float | None,
) -> pd.DataFrame:
    dbh_in = trees["dbh_m"].to_numpy(float) * 100.0 / CM_PER_IN
    dg = pd.Series(np.nan, index=trees.index)
    htg = pd.Series(np.nan, index=trees.index)
    if incr is not None and years:
        ids = trees["tree_id"].astype(np.int64)
        found = ids.isin(incr.index)
        matched = incr.reindex(ids[found].to_numpy())
        dg[found] = matched["past_dbh_m"].to_numpy() * 100.0 / CM_PER_IN  # NaN: not measured
        htg[found] = matched["htg_m"].to_numpy() / M_PER_FT
    return pd.DataFrame(
        {
            "Stand_ID": stand_id,
            "Plot_ID": 1,
            "Tree_ID": np.arange(1, len(trees) + 1),
            "Tree_Count": 1.0,
            "History": 1,
            "Species": species,
            "DBH": dbh_in,
            "DG": dg.to_numpy(),
            "Ht": trees["height_m"].to_numpy(float) / M_PER_FT,
            "HTG": htg.to_numpy(),
            "CrRatio": _crown_ratio(trees).to_numpy(),
            "SG_Tree_ID": trees["tree_id"].astype(np.int64).astype(str).to_numpy(),
            "SG_Tree_UID": (
                trees["tree_uid"].astype("Int64").to_numpy()
                if "tree_uid" in trees.columns
                else pd.array([pd.NA] * len(trees), dtype="Int64")
            ),
            "SG_DBH_Source": trees["dbh_source"].astype(object).to_numpy(),
        }
    )


def _sql_value(value: Any) -> Any:
    if value is None or value is pd.NA:
        return None
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _sql_value(value.item())
    return value


def _write_database(out: Path, stands: pd.DataFrame, trees: pd.DataFrame, overwrite: bool) -> None:
    with atomic_output(out, overwrite=overwrite) as tmp:
        conn = sqlite3.connect(tmp)
        try:
            for name, columns, frame in (
                ("FVS_StandInit", STAND_COLUMNS, stands),
                ("FVS_TreeInit", TREE_COLUMNS, trees),
            ):
                spec = ", ".join(f"{c} {t}" for c, t in columns.items())
                conn.execute(f"CREATE TABLE {name} ({spec})")
                marks = ", ".join("?" for _ in columns)
                rows = (
                    tuple(_sql_value(v) for v in rec)
                    for rec in frame[list(columns)].itertuples(index=False, name=None)
                )
                conn.executemany(f"INSERT INTO {name} VALUES ({marks})", rows)
            conn.commit()
        finally:
            conn.close()


def keyword_file(
    database: str | Path,
    stand_ids: Sequence[str],
    *,
    cycles: int = 1,
    cycle_years: int = 10,
    output_database: str | Path | None = None,
) -> str:
    """An FVS keyword file running each stand of ``database`` for ``cycles`` cycles.

    With ``output_database``, FVS also writes its summary table (``FVS_Summary``) there.
    """
    blocks = []
    for stand_id in stand_ids:
        out_db = f"DSNOUT\n{output_database}\nSUMMARY\n" if output_database is not None else ""
        blocks.append(
            f"STDIDENT\n{stand_id}\n"
            f"DATABASE\nDSNIN\n{database}\n{out_db}"
            "STANDSQL\nSELECT * FROM FVS_StandInit WHERE Stand_ID = '%StandID%'\nENDSQL\n"
            "TREESQL\nSELECT * FROM FVS_TreeInit WHERE Stand_ID = '%StandID%'\nENDSQL\nEND\n"
            f"{'TIMEINT':<10}{0.0:>10.1f}{float(cycle_years):>10.1f}\n"
            f"{'NUMCYCLE':<10}{float(cycles):>10.1f}\n"
            "PROCESS\n"
        )
    return "".join(blocks) + "STOP\n"
