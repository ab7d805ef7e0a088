"""Acceptance tests of ``enrich`` through the real pipeline (``run_pipeline`` on the bundled
simulated pair), checked against the simulator's ground truth and read back with second
readers (laspy, rasterio, pyogrio + sqlite3, pandas)."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

import laspy
import numpy as np
import pandas as pd
import pyogrio
import pytest
import rasterio
import shapely

from standgrid.errors import EpochNotFoundError
from standgrid.partition import CellId
from standgrid.pipeline.enrich import enrich_catalog
from standgrid.simulate import load_truth
from tests.pipeline_fixtures import (
    CRS,
    STAND_BOUNDS,
    EnrichedPair,
    build_small_catalog,
    enriched_pair,
    match_one_to_one,
    small_cell_id,
    standing_truth_trees,
    truth_folder,
)

EPOCHS = ("2024", "2028")
MATCH_RADIUS_M = 1.5
TALL_M = 10.0

#: Columns of ``stand_metrics`` documented in docs/METRICS.md (area + tree metrics) and keys.
DOCUMENTED_METRICS = [
    "cell_id",
    "epoch",
    "level",
    "cell_size",
    "area_m2",
    "observed_m2",
    "observed_fraction",
    "n_points",
    "n_outside_observed",
    "n_no_height",
    "density_pts_m2",
    "zmax",
    "zmean",
    "zsd",
    "zskew",
    "zkurt",
    "zentropy",
    "pzabovezmean",
    "pzabove2",
    *[f"zq{q}" for q in range(5, 100, 5)],
    *[f"zpcum{k}" for k in range(1, 10)],
    "pz_below0p5",
    "pz0p5to2",
    "pz2to5",
    "pz5to10",
    "pz10to20",
    "pz20to30",
    "pz30plus",
    "n_trees",
    "n_dbh_measured",
    "n_dbh_imputed",
    "dbh_measured_share",
    "stems_ha",
    "basal_area_m2_ha",
    "qmd_cm",
    "mean_height_m",
    "dominant_height_m",
    "dominant_by",
    "n_trees_by_stem",
    "stem_detected_share",
    "tree_detection_note",
    "null_reason",
]
DOCUMENTED_TREE_COLUMNS = [
    "cell_id",
    "stand_id",
    "epoch",
    "tree_id",
    "tree_uid",
    "x",
    "y",
    "z_ground",
    "height_m",
    "top_x",
    "top_y",
    "crown_area_m2",
    "n_points",
    "detected_by",
    "dbh_m",
    "dbh_se_m",
    "dbh_reason",
    "stem_x",
    "stem_y",
    "dbh_rmse_m",
    "dbh_n_points",
    "dbh_arc_deg",
    "lean_deg",
    "stem_low_m",
    "stem_high_m",
    "owned",
    "observed",
    "dbh_source",
]


@pytest.fixture(scope="session")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    return enriched_pair(tmp_path_factory)


def _trees(pair: EnrichedPair, epoch: str) -> pd.DataFrame:
    return pd.read_parquet(pair.path / f"tables/tree_list_{epoch}.parquet")


def _metrics(pair: EnrichedPair) -> pd.DataFrame:
    return pd.read_parquet(pair.path / "tables/stand_metrics.parquet")


def _cells(pair: EnrichedPair, epoch: str) -> pd.DataFrame:
    cells = pyogrio.read_dataframe(pair.path / "index.gpkg", layer="cells")
    return cells[cells["epoch"].astype(str) == epoch].reset_index(drop=True)


def _matched(pair: EnrichedPair, epoch: str) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Truth trees standing at the epoch and the detected trees, paired one to one (1.5 m)."""
    truth = standing_truth_trees(epoch)
    found = _trees(pair, epoch)
    t, d = match_one_to_one(
        truth[["x", "y"]].to_numpy(), found[["x", "y"]].to_numpy(), MATCH_RADIUS_M
    )
    return truth.iloc[t].reset_index(drop=True), found.iloc[d].reset_index(drop=True)


# --- against the ground truth ------------------------------------------------------------


@pytest.mark.parametrize("epoch", EPOCHS)
def test_tree_detection_f1_for_trees_taller_than_10_m(pair: EnrichedPair, epoch: str) -> None:
    """TP: a true tree > 10 m paired (one to one, <= 1.5 m) with a detection; FN: an
    unpaired true tree > 10 m; FP: an unpaired detection > 10 m (pairing uses every standing
    true tree, so a detected small tree is not a false positive)."""
    truth = standing_truth_trees(epoch)
    found = _trees(pair, epoch)
    t, d = match_one_to_one(
        truth[["x", "y"]].to_numpy(), found[["x", "y"]].to_numpy(), MATCH_RADIUS_M
    )
    tall_truth = truth["height_m"].to_numpy() > TALL_M
    tp = int(tall_truth[t].sum())
    fn = int(tall_truth.sum()) - tp
    unpaired = np.ones(len(found), dtype=bool)
    unpaired[d] = False
    fp = int((unpaired & (found["height_m"].to_numpy() > TALL_M)).sum())
    f1 = 2 * tp / (2 * tp + fp + fn)
    print(f"[{epoch}] trees>10m: truth {tall_truth.sum()}, TP {tp}, FP {fp}, FN {fn}, F1 {f1:.3f}")
    assert f1 >= 0.9


@pytest.mark.parametrize("epoch", EPOCHS)
def test_tree_height_rmse(pair: EnrichedPair, epoch: str) -> None:
    truth, found = _matched(pair, epoch)
    tall = truth["height_m"].to_numpy() > TALL_M
    error = found["height_m"].to_numpy()[tall] - truth["height_m"].to_numpy()[tall]
    rmse = float(np.sqrt(np.mean(error**2)))
    print(f"[{epoch}] height: n {tall.sum()}, RMSE {rmse:.3f} m, bias {error.mean():+.3f} m")
    assert tall.sum() > 150
    assert rmse <= 0.5


@pytest.mark.parametrize("epoch", EPOCHS)
def test_dbh_rmse_where_stems_are_scanned(pair: EnrichedPair, epoch: str) -> None:
    """Over the matched trees whose DBH was measured (the stem was scanned and a circle
    accepted); the others' DBH is imputed from their height, with a larger error."""
    truth, found = _matched(pair, epoch)
    has = (found["dbh_source"] == "measured").to_numpy()
    error_cm = 100 * (found["dbh_m"].to_numpy() - truth["dbh_m"].to_numpy())
    rmse = float(np.sqrt(np.mean(error_cm[has] ** 2)))
    imputed_rmse = float(np.sqrt(np.mean(error_cm[~has] ** 2)))
    all_found = _trees(pair, epoch)
    print(
        f"[{epoch}] DBH: {int((all_found['dbh_source'] == 'measured').sum())} of "
        f"{len(all_found)} detected trees measured ({has.sum()} matched); RMSE {rmse:.2f} cm, "
        f"median |err| {np.median(np.abs(error_cm[has])):.2f} cm, worst "
        f"{np.abs(error_cm[has]).max():.1f} cm; {(~has).sum()} imputed: RMSE "
        f"{imputed_rmse:.2f} cm, bias {np.mean(error_cm[~has]):+.2f} cm"
    )
    assert all_found["dbh_m"].notna().all()
    assert has.sum() >= 50
    assert rmse <= 2.0
    assert imputed_rmse <= 6.0 and abs(np.mean(error_cm[~has])) <= 2.0


@pytest.mark.parametrize("epoch", EPOCHS)
def test_dtm_against_the_true_terrain(pair: EnrichedPair, epoch: str) -> None:
    """DTM pixel centres inside the simulated stand vs ``load_truth(...).terrain_height``."""
    truth = load_truth(truth_folder(epoch))
    with rasterio.open(pair.path / f"rasters/{epoch}/dtm.tif") as ds:
        dtm = ds.read(1)
        rows, cols = np.indices(dtm.shape)
        x, y = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
        nodata = ds.nodata
    x, y, z = np.asarray(x), np.asarray(y), dtm.ravel().astype(np.float64)
    xmin, ymin, xmax, ymax = STAND_BOUNDS
    inside = (x > xmin) & (x < xmax) & (y > ymin) & (y < ymax)
    valid = z != nodata
    assert valid[inside].mean() > 0.8  # masked only far from ground returns
    inside &= valid
    error = np.abs(z[inside] - truth.terrain_height(x[inside], y[inside]))
    print(
        f"[{epoch}] DTM vs truth terrain: median |err| {np.median(error):.4f} m, "
        f"p95 {np.percentile(error, 95):.3f} m, max {error.max():.2f} m ({inside.sum()} px)"
    )
    assert np.median(error) < 0.05
    assert np.percentile(error, 95) < 0.3


@pytest.mark.parametrize("epoch", EPOCHS)
def test_rasters_cover_exactly_the_cells_and_dtm_only_near_ground(
    pair: EnrichedPair, epoch: str
) -> None:
    """No raster runs past the cells; a DTM pixel is written only within 2 m of a ground
    return (read back from the tiles' class 2 with laspy), the observed mask only there."""
    from scipy.spatial import cKDTree

    cells = _cells(pair, epoch)
    xmin, ymin, xmax, ymax = shapely.bounds(shapely.union_all(cells.geometry.to_numpy()))
    ground = []
    for rel in cells["tile_path"]:
        las = laspy.read(pair.path / rel)
        keep = (np.asarray(las.classification) == 2) & ~np.asarray(las.withheld, dtype=bool)
        ground.append(np.column_stack([np.asarray(las.x)[keep], np.asarray(las.y)[keep]]))
    tree = cKDTree(np.concatenate(ground))
    for name in ("dtm", "chm", "density", "observed"):
        with rasterio.open(pair.path / f"rasters/{epoch}/{name}.tif") as ds:
            assert tuple(ds.bounds) == pytest.approx((xmin, ymin, xmax, ymax)), name
            data, nodata, transform = ds.read(1), ds.nodata, ds.transform
        if name in ("dtm", "observed"):
            written = data != nodata if name == "dtm" else data == 1
            rows, cols = np.nonzero(written)
            x, y = rasterio.transform.xy(transform, rows, cols)
            distance, _ = tree.query(np.column_stack([x, y]))
            # pixel centre to the nearest return: 2 m plus half a pixel diagonal
            assert distance.max() <= 2.0 + 0.75, name


# --- the enrich outputs ------------------------------------------------------------------


@pytest.mark.parametrize("epoch", EPOCHS)
def test_tiles_rewritten_with_classes_heights_tree_ids_and_buffers(
    pair: EnrichedPair, epoch: str
) -> None:
    cells = _cells(pair, epoch)
    tiling = pair.report["tile"]["epochs"][epoch]
    tree_ids = set(_trees(pair, epoch)["tree_id"].astype(np.int64))
    core_total = withheld_total = labelled = labelled_known = 0
    ground_hag = []
    for rel in cells["tile_path"]:
        las = laspy.read(pair.path / rel)
        assert las.header.parse_crs().to_epsg() == 32630
        dims = set(las.point_format.dimension_names)
        assert {"height_above_ground", "tree_id"} <= dims
        withheld = np.asarray(las.withheld, dtype=bool)
        cls = np.asarray(las.classification)
        hag = np.asarray(las.height_above_ground, dtype=np.float64)
        ids = np.asarray(las.tree_id).astype(np.int64)
        assert set(np.unique(cls)) <= {1, 2}
        assert np.isfinite(hag).all(), f"{rel}: points without a height above ground"
        ground_hag.append(hag[cls == 2])
        core_total += int((~withheld).sum())
        withheld_total += int(withheld.sum())
        labelled += int((ids != 0).sum())
        labelled_known += int(np.isin(ids[ids != 0], list(tree_ids)).sum())
    ground = np.concatenate(ground_hag)
    assert len(ground) > 0.1 * core_total  # class 2 present (bare forest floor is seen a lot)
    assert np.median(np.abs(ground)) < 0.1
    # every tiled point is still there: core and buffer (withheld) counts of the tiling run
    assert core_total == tiling["points_out"]
    assert withheld_total == tiling["buffer_points"] > 0
    # tree_id labels name trees of the epoch's tree list
    print(f"[{epoch}] labelled points {labelled}, with an id of the tree list {labelled_known}")
    assert labelled > 0.2 * core_total
    assert labelled_known >= 0.99 * labelled


@pytest.mark.parametrize("name", ["dtm", "chm", "density"])
def test_rasters_are_cogs_aligned_to_the_grid_and_overlay(pair: EnrichedPair, name: str) -> None:
    catalog = json.loads((pair.path / "catalog.json").read_text())
    x0, y0 = catalog["grid"]["origin"]
    frames = []
    for epoch in EPOCHS:
        with rasterio.open(pair.path / f"rasters/{epoch}/{name}.tif") as ds:
            assert ds.driver == "GTiff"
            assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
            assert ds.profile["tiled"] and ds.block_shapes[0] == (256, 256)
            if max(ds.width, ds.height) > 256:  # GDAL adds overviews only above one block
                assert ds.overviews(1)
            assert ds.crs.to_epsg() == 32630
            t = ds.transform
            assert t.b == 0 and t.d == 0 and t.a == -t.e == 1.0
            for offset in (t.c - x0, t.f - y0):
                assert offset / t.a == pytest.approx(round(offset / t.a), abs=1e-9)
            data = ds.read(1, masked=True)
            rows, cols = np.indices(data.shape)
            x, y = rasterio.transform.xy(t, rows.ravel(), cols.ravel())
            x, y = np.asarray(x), np.asarray(y)
            xmin, ymin, xmax, ymax = STAND_BOUNDS
            inside = (x > xmin) & (x < xmax) & (y > ymin) & (y < ymax)
            assert (~np.ma.getmaskarray(data).ravel()[inside]).mean() > 0.95  # the stand is mapped
            frames.append(t)
    a, b = frames
    assert a.a == b.a and a.e == b.e
    assert (a.c - b.c) / a.a == pytest.approx(round((a.c - b.c) / a.a), abs=1e-9)
    assert (a.f - b.f) / a.a == pytest.approx(round((a.f - b.f) / a.a), abs=1e-9)


def test_stand_metrics_tables_keyed_documented_and_identical(pair: EnrichedPair) -> None:
    parquet = _metrics(pair)
    csv = pd.read_csv(pair.path / "tables/stand_metrics.csv", dtype={"epoch": str})
    assert list(parquet.columns) == DOCUMENTED_METRICS
    assert list(csv.columns) == DOCUMENTED_METRICS
    assert not parquet.duplicated(["cell_id", "epoch"]).any()
    for epoch in EPOCHS:
        rows = parquet[parquet["epoch"] == epoch]
        cell_ids = sorted(_cells(pair, epoch)["cell_id"])
        assert sorted(rows.loc[rows["level"] == 0, "cell_id"]) == cell_ids
        # level 1: the 1 ha stands holding those cells
        stands = {str(CellId.parse(c).parent(100.0)) for c in cell_ids}
        assert sorted(rows.loc[rows["level"] == 1, "cell_id"]) == sorted(stands)
    assert len(csv) == len(parquet)
    for column in DOCUMENTED_METRICS:
        a, b = parquet[column], csv[column]
        if pd.api.types.is_numeric_dtype(a) and not pd.api.types.is_bool_dtype(a):
            np.testing.assert_array_equal(a.to_numpy(np.float64), b.to_numpy(np.float64))
        else:
            assert a.fillna("").astype(str).tolist() == b.fillna("").astype(str).tolist(), column
    # the stands of the simulated forest are measured: canopy heights and trees
    inside = parquet[parquet["n_trees"] > 0]
    assert len(inside) >= 30
    assert inside["zq95"].between(10, 40).all()
    assert inside["stems_ha"].gt(0).all()


def test_stand_metrics_null_only_with_a_reason(pair: EnrichedPair) -> None:
    """Every null metric has a ``null_reason``; every stand with enough coverage is measured."""
    metrics = _metrics(pair)
    for column in ("zmax", "zmean", "zq95", "pzabove2", "stems_ha", "basal_area_m2_ha"):
        missing = metrics[column].isna()
        assert metrics.loc[missing, "null_reason"].notna().all(), column
    covered = metrics["observed_fraction"] >= 0.25
    assert covered.sum() >= 20
    assert metrics.loc[covered, ["zq95", "stems_ha", "basal_area_m2_ha"]].notna().all().all()


def test_zentropy_null_has_a_reason(pair: EnrichedPair) -> None:
    metrics = _metrics(pair)
    silent = metrics["zentropy"].isna() & metrics["null_reason"].fillna("").eq("")
    assert not silent.any(), f"{int(silent.sum())} stands with zentropy null and no reason"


@pytest.mark.parametrize("epoch", EPOCHS)
def test_tree_lists(pair: EnrichedPair, epoch: str) -> None:
    parquet = _trees(pair, epoch)
    csv = pd.read_csv(pair.path / f"tables/tree_list_{epoch}.csv", dtype={"epoch": str})
    assert list(parquet.columns) == DOCUMENTED_TREE_COLUMNS
    assert list(csv.columns) == DOCUMENTED_TREE_COLUMNS
    np.testing.assert_array_equal(csv["tree_id"].to_numpy(), parquet["tree_id"].to_numpy())
    np.testing.assert_array_equal(csv["height_m"].to_numpy(), parquet["height_m"].to_numpy())
    assert not parquet["tree_id"].duplicated().any()
    assert parquet["owned"].all()
    summary = pair.report["enrich"]["epochs"][epoch]
    assert summary["trees"] == len(parquet)
    assert summary["trees_dbh_measured"] == int((parquet["dbh_source"] == "measured").sum())
    assert summary["trees_dbh_imputed"] == int((parquet["dbh_source"] == "imputed").sum())
    assert summary["trees_dbh_none"] == int((parquet["dbh_source"] == "none").sum())
    # each tree lies in its cell (top inside the cell polygon) and cell counts agree
    cells = _cells(pair, epoch).set_index("cell_id")
    polygons = cells.loc[parquet["cell_id"], "geometry"].to_numpy()
    assert shapely.contains_xy(polygons, parquet["x"], parquet["y"]).all()
    metrics = _metrics(pair)
    rows = metrics[metrics["epoch"] == epoch]
    # counted: trees on observed ground, in the cells whose metrics are reported
    measured = set(rows.loc[(rows["level"] == 0) & rows["n_trees"].notna(), "cell_id"])
    counted = parquet[parquet["observed"] & parquet["cell_id"].isin(measured)]
    for level, key in ((0, "cell_id"), (1, "stand_id")):  # cells, and their 1 ha stands
        reported = rows[(rows["level"] == level) & rows["n_trees"].notna()]
        counts = reported.set_index("cell_id")["n_trees"]
        per_stand = counted.groupby(key).size().reindex(counts.index, fill_value=0)
        np.testing.assert_array_equal(per_stand.to_numpy(), counts.to_numpy())
        assert rows.loc[rows["level"] == level, "n_trees"].isna().sum() < len(rows) / 2


def test_geopackage_layers_with_crs_and_default_styles(pair: EnrichedPair) -> None:
    gpkg = pair.path / "index.gpkg"
    stands = pyogrio.read_dataframe(gpkg, layer="stand_metrics")
    trees = pyogrio.read_dataframe(gpkg, layer="trees")
    assert stands.crs.to_epsg() == 32630 and trees.crs.to_epsg() == 32630
    metrics = _metrics(pair)
    assert len(stands) == len(metrics)
    merged = stands.merge(metrics, on=["cell_id", "epoch"], suffixes=("_gpkg", ""))
    assert len(merged) == len(metrics)
    np.testing.assert_allclose(merged["zq95_gpkg"], merged["zq95"], equal_nan=True)
    assert len(trees) == sum(len(_trees(pair, e)) for e in EPOCHS)
    assert set(trees.geom_type) <= {"Polygon", "MultiPolygon"}
    # crowns hold their tree tops
    crowns = trees.geometry.buffer(0.5).to_numpy()
    assert shapely.contains_xy(crowns, trees["x"], trees["y"]).mean() > 0.95
    with sqlite3.connect(gpkg) as db:
        srs = dict(db.execute("SELECT table_name, srs_id FROM gpkg_geometry_columns").fetchall())
        styles = db.execute(
            "SELECT f_table_name, styleQML FROM layer_styles WHERE useAsDefault = 1"
        ).fetchall()
    assert srs["stand_metrics"] == srs["trees"] == 32630
    default = {name: qml for name, qml in styles}
    assert "zq95" in default["stand_metrics"] and "<qgis" in default["stand_metrics"]
    assert "height_m" in default["trees"]


def test_catalog_marks_epochs_enriched(pair: EnrichedPair) -> None:
    state = json.loads((pair.path / "catalog.json").read_text())
    for epoch in EPOCHS:
        entry = state["epochs"][epoch]
        assert entry["enriched"] is True
        assert entry["enrichment"]["cells"] == len(_cells(pair, epoch))
    assert state["crs"] == CRS


@pytest.mark.parametrize("epoch", EPOCHS)
def test_metrics_of_a_cell_recomputed_from_its_tile(pair: EnrichedPair, epoch: str) -> None:
    metrics = _metrics(pair)
    rows = metrics[(metrics["epoch"] == epoch) & (metrics["level"] == 0) & (metrics["n_trees"] > 5)]
    cells = _cells(pair, epoch).set_index("cell_id")
    with rasterio.open(pair.path / f"rasters/{epoch}/observed.tif") as ds:
        observed = ds.read(1) == 1
        transform = ds.transform
    for cell_id in rows["cell_id"].iloc[:3]:
        row = rows.set_index("cell_id").loc[cell_id]
        las = laspy.read(pair.path / cells.loc[cell_id, "tile_path"])
        core = ~np.asarray(las.withheld, dtype=bool)
        # the metrics are over the points on observed ground
        r, c = rasterio.transform.rowcol(
            transform, np.asarray(las.x)[core], np.asarray(las.y)[core]
        )
        on = observed[np.asarray(r), np.asarray(c)]
        h = np.asarray(las.height_above_ground, dtype=np.float64)[core][on]
        assert row["n_points"] == core.sum()
        assert row["n_outside_observed"] == core.sum() - on.sum()
        assert row["zmax"] == pytest.approx(h.max(), abs=1e-5)
        assert row["zmean"] == pytest.approx(h.mean(), abs=1e-5)
        assert row["zq95"] == pytest.approx(np.percentile(h, 95), abs=1e-5)
        assert row["pzabove2"] == pytest.approx(100 * np.mean(h > 2.0), abs=1e-9)
        assert row["area_m2"] == pytest.approx(400.0)


def test_unknown_epoch_is_refused_before_any_work(pair: EnrichedPair) -> None:
    before = (pair.path / "catalog.json").read_bytes()
    with pytest.raises(EpochNotFoundError, match="1999"):
        from standgrid.enrichment.options import EnrichOptions

        enrich_catalog(pair.path, EnrichOptions(epochs=("1999",)))
    assert (pair.path / "catalog.json").read_bytes() == before


# --- a stand without ground --------------------------------------------------------------


def test_stand_without_ground_has_null_metrics_with_a_reason(tmp_path: Path) -> None:
    catalog = build_small_catalog(tmp_path / "small")
    report = enrich_catalog(catalog)
    assert report.epochs["2024"]["cells_without_ground"] == 1
    assert report.epochs["2028"]["cells_without_ground"] == 0
    metrics = pd.read_parquet(catalog / "tables/stand_metrics.parquet").set_index(
        ["epoch", "cell_id"]
    )
    bare = metrics.loc[("2024", small_cell_id("C"))]
    assert bare["n_points"] == 2
    for column in ("zmax", "zmean", "zq95", "pzabove2", "mean_height_m"):
        assert math.isnan(bare[column]), column
    assert "no ground" in bare["null_reason"]
    # its points keep no made-up height, and no tree is listed there
    las = laspy.read(catalog / f"tiles/2024/{small_cell_id('C')}.laz")
    assert np.isnan(np.asarray(las.height_above_ground)).all()
    trees = pd.read_parquet(catalog / "tables/tree_list_2024.parquet")
    assert small_cell_id("C") not in set(trees["cell_id"])
    # neighbours with ground are measured: the 15 m cone tree is found
    ok = metrics.loc[("2024", small_cell_id("A"))]
    assert ok["zmax"] == pytest.approx(15.0, abs=0.3)
    assert ok["n_trees"] == 1


def test_enrich_summary_counts_the_trees_left_without_a_dbh(tmp_path: Path) -> None:
    """Cone trees have no stem to fit: with fewer than 15 measured stems in the catalog no
    height-diameter model, so no tree gets a DBH, and both summaries say so (not "0
    measured, 0 imputed" alone)."""
    from click.testing import CliRunner

    from standgrid.cli import cli

    catalog = build_small_catalog(tmp_path / "small")
    result = CliRunner().invoke(cli, ["enrich", str(catalog), "--json", "-q"])
    assert result.exit_code == 0, result.output
    summaries = json.loads(result.stdout)["epochs"]
    recorded = json.loads((catalog / "catalog.json").read_text())["epochs"]
    for epoch, summary in summaries.items():
        trees = pd.read_parquet(catalog / f"tables/tree_list_{epoch}.parquet")
        without = int(trees["dbh_m"].isna().sum())
        assert without == len(trees) > 0 and summary["height_diameter_model"] is None
        assert summary["trees_dbh_none"] == without
        assert summary["trees_dbh_measured"] + summary["trees_dbh_imputed"] + without == len(trees)
        assert recorded[epoch]["enrichment"]["trees_dbh_none"] == without
    human = CliRunner().invoke(cli, ["enrich", str(catalog), "-q"])
    assert human.exit_code == 0, human.output
    for epoch, summary in summaries.items():
        line = next(x for x in human.stdout.splitlines() if x.startswith(f"epoch {epoch}:"))
        assert f"{summary['trees_dbh_none']} without a DBH" in line
        assert "no height-diameter model: fewer than 15 measured stems" in line


def test_stand_without_ground_has_no_zero_stem_count(tmp_path: Path) -> None:
    catalog = build_small_catalog(tmp_path / "small")
    enrich_catalog(catalog)
    metrics = pd.read_parquet(catalog / "tables/stand_metrics.parquet").set_index(
        ["epoch", "cell_id"]
    )
    bare = metrics.loc[("2024", small_cell_id("C"))]
    assert pd.isna(bare["stems_ha"]) and pd.isna(bare["n_trees"])


def test_stand_without_ground_labels_no_tree_points(tmp_path: Path) -> None:
    catalog = build_small_catalog(tmp_path / "small")
    enrich_catalog(catalog)
    las = laspy.read(catalog / f"tiles/2024/{small_cell_id('C')}.laz")
    assert (np.asarray(las.tree_id) == 0).all()
