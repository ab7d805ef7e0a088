"""Observed ground, the coverage rule, complete basal area (height-diameter imputation)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd
import pytest
import shapely
import shapely.geometry

from standgrid.enrichment.allometry import MIN_TREES, fit_height_diameter, impute_dbh
from standgrid.enrichment.coverage import (
    cells_mask,
    coverage_from_hits,
    ground_hits,
    polygon_mask_area,
)
from standgrid.enrichment.metrics import tree_metrics
from standgrid.enrichment.stands import (
    CoverageRule,
    StandAggregator,
    StandSample,
    aggregate,
    stand_row,
)
from standgrid.errors import EnrichError
from standgrid.rastergrid import RasterGrid

GRID = RasterGrid(0.0, 0.0, 1.0, 40, 40)


def _full_cells() -> np.ndarray:
    return np.ones(GRID.shape, dtype=bool)


def test_ground_hits_count_returns_per_pixel_and_ignore_outside() -> None:
    xy = np.array([[0.5, 0.5], [0.6, 0.4], [39.5, 39.5], [-1.0, 3.0], [40.0, 1.0]])
    hits = ground_hits(GRID, xy)
    assert hits.sum() == 3
    assert hits[GRID.nrows - 1, 0] == 2  # row 0 is north
    assert hits[0, GRID.ncols - 1] == 1


def test_closing_fills_narrow_gaps_but_not_the_outer_edge() -> None:
    seen = np.zeros(GRID.shape, dtype=np.int64)
    seen[:, :20] = 1
    seen[10:12, 5:7] = 0  # a 2 x 2 m hole behind a stem: closed
    seen[5:35, 10] = 0  # a 1 m stripe between scan lines: closed
    coverage = coverage_from_hits(seen, GRID, _full_cells(), closing_radius=2.0)
    assert coverage.observed[:, :20].all()
    assert not coverage.observed[:, 20:].any()  # the survey's edge does not grow
    assert coverage.near_ground[:, 20:22].all() and not coverage.near_ground[:, 23:].any()


def test_closing_keeps_a_wide_unsurveyed_gap() -> None:
    seen = np.ones(GRID.shape, dtype=np.int64)
    seen[:, 15:25] = 0  # 10 m never surveyed
    coverage = coverage_from_hits(seen, GRID, _full_cells(), closing_radius=2.0)
    assert not coverage.observed[:, 15:25].any()
    assert coverage.observed[:, :15].all() and coverage.observed[:, 25:].all()


def test_observed_is_cut_to_the_cells_and_the_mask_raster_says_so() -> None:
    cells = cells_mask(GRID, [shapely.box(0, 0, 20, 40)])
    coverage = coverage_from_hits(np.ones(GRID.shape, np.int64), GRID, cells)
    assert coverage.observed.sum() == 20 * 40
    raster = coverage.as_mask_raster()
    assert set(np.unique(raster)) == {1, 255}
    assert coverage.observed_m2(shapely.box(10, 0, 30, 20)) == pytest.approx(200.0)
    assert polygon_mask_area(coverage.observed, GRID, shapely.box(0, 0, 40, 40)) == 800.0


def test_observed_area_clips_pixels_to_an_irregular_polygon() -> None:
    """Pixels cut by the polygon's edge count only their part inside it (pixel centres
    counted whole would give 100 m² and 55 m² here)."""
    mask = np.ones(GRID.shape, dtype=bool)
    offset = shapely.box(0.25, 0.25, 10.5, 10.5)
    assert polygon_mask_area(mask, GRID, offset) == pytest.approx(10.25**2, abs=1e-9)
    triangle = shapely.Polygon([(0, 0), (10, 0), (0, 10)])
    assert polygon_mask_area(mask, GRID, triangle) == pytest.approx(50.0, abs=1e-9)
    mask[GRID.nrows - 5 :, :5] = False  # the 5 x 5 m south-west corner unobserved
    assert polygon_mask_area(mask, GRID, triangle) == pytest.approx(50.0 - 25.0, abs=1e-9)


def test_coverage_rule_names_what_is_missing() -> None:
    rule = CoverageRule(min_observed_fraction=0.5, min_density_pts_m2=2.0)
    assert rule.shortfall(0.6, 10.0) is None
    text = rule.shortfall(0.1, 1.0)
    assert text is not None and text.startswith("insufficient_coverage")
    assert "10 %" in text and "points/m2" in text
    with pytest.raises(EnrichError):
        CoverageRule(min_observed_fraction=1.5)


def _trees(n: int, dbh: float = 0.3) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "height_m": np.full(n, 25.0),
            "dbh_m": np.full(n, dbh),
            "dbh_source": pd.array(["measured"] * n, dtype="string"),
        }
    )


def test_one_point_cell_is_null_with_insufficient_coverage_not_zero() -> None:
    sample = StandSample("20m_E0_N0", 0, 20.0, 400.0, 1.0, 1, np.array([27.4]), _trees(0))
    row = stand_row(sample, CoverageRule())
    assert row["null_reason"].startswith("insufficient_coverage")
    assert math.isnan(row["zq95"]) and math.isnan(row["stems_ha"])
    assert math.isnan(row["basal_area_m2_ha"])
    assert row["n_points"] == 1 and row["observed_m2"] == 1.0  # the sample stays visible


def test_per_hectare_values_divide_by_the_observed_area() -> None:
    heights = np.linspace(0, 20, 2000)
    sample = StandSample("20m_E0_N0", 0, 20.0, 400.0, 200.0, 2500, heights, _trees(7))
    row = stand_row(sample, CoverageRule())
    assert row["null_reason"] is None
    assert row["stems_ha"] == pytest.approx(7 / 0.02)
    assert row["basal_area_m2_ha"] == pytest.approx(7 * math.pi * 0.15**2 / 0.02)
    assert row["density_pts_m2"] == pytest.approx(2000 / 200.0)
    assert row["n_outside_observed"] == 500
    assert row["observed_fraction"] == pytest.approx(0.5)


def test_a_stand_aggregates_its_measured_cells_over_the_whole_stand_area() -> None:
    cells = [
        StandSample(f"20m_E{i}_N0", 0, 20.0, 400.0, 400.0, 4000, np.full(4000, 10.0), _trees(14))
        for i in range(20)
    ]
    stand = aggregate("100m_E0_N0", 100.0, 10_000.0, cells)
    row = stand_row(stand, CoverageRule())
    assert row["observed_fraction"] == pytest.approx(0.8)
    assert row["stems_ha"] == pytest.approx(20 * 14 / 0.8)
    assert row["area_m2"] == 10_000.0


def test_stands_measured_as_their_cells_arrive_equal_stands_measured_at_once() -> None:
    rng = np.random.default_rng(7)
    stand_of: dict[str, str | None] = {}
    cells = []
    for s in range(3):  # three stands of 25 cells, one cell without enough coverage
        for i in range(25):
            cell_id = f"20m_E{s * 5 + i % 5}_N{i // 5}"
            stand_of[cell_id] = f"100m_E{s}_N0"
            observed = 10.0 if (s, i) == (1, 3) else 400.0
            heights = rng.gamma(2.0, 4.0, 1000).astype(np.float32)
            cells.append(StandSample(cell_id, 0, 20.0, 400.0, observed, 1200, heights, _trees(2)))
    stand_of["20m_E99_N0"] = None  # a cell outside every stand
    cells.append(StandSample("20m_E99_N0", 0, 20.0, 400.0, 400.0, 9, np.ones(9), _trees(0)))
    rule = CoverageRule()

    def members(stand: str) -> list[StandSample]:
        return [c for c in cells if stand_of[c.stand_id] == stand and c.measured(rule)]

    stand_ids = ("100m_E0_N0", "100m_E1_N0", "100m_E2_N0")
    expected = [stand_row(aggregate(s, 100.0, 10_000.0, members(s)), rule) for s in stand_ids]
    aggregator = StandAggregator(stand_of, 100.0, rule, height_break=2.0)
    order = rng.permutation(len(cells))
    for batch in np.array_split(order, 7):
        aggregator.add([cells[k] for k in batch])
    stands = aggregator.result()
    assert tuple(s.stand_id for s in stands) == stand_ids
    assert sum(len(c.heights) for c in cells) == 0  # every cell's heights released
    assert len(stands[1].members) == 24  # the sparse cell is not part of its stand
    got = [stand_row(s, rule) for s in stands]
    for a, b in zip(got, expected, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            if isinstance(b[key], float):  # sums in another order: equal to round-off
                assert a[key] == pytest.approx(b[key], rel=1e-12, nan_ok=True), key
            else:
                assert a[key] == b[key], key


def test_a_stand_missing_a_cell_is_an_error_not_a_partial_stand() -> None:
    stand_of: dict[str, str | None] = {"20m_E0_N0": "100m_E0_N0", "20m_E1_N0": "100m_E0_N0"}
    aggregator = StandAggregator(stand_of, 100.0, CoverageRule(), height_break=2.0)
    aggregator.add(
        [StandSample("20m_E0_N0", 0, 20.0, 400.0, 400.0, 9, np.ones(9, np.float32), _trees(0))]
    )
    with pytest.raises(EnrichError, match="still miss cells"):
        aggregator.result()


def test_basal_area_is_null_when_a_tree_has_no_dbh_and_reports_the_measured_share() -> None:
    cell = np.zeros(4, dtype=np.int64)
    height = np.array([20.0, 22, 24, 26])
    dbh = np.array([0.2, 0.25, np.nan, 0.3])
    out = tree_metrics(cell, height, dbh, cell_area_m2=400.0).iloc[0]
    assert math.isnan(out["basal_area_m2_ha"]) and "1 of 4 trees" in out["null_reason"]
    full = np.array([0.2, 0.25, 0.28, 0.3])
    measured = np.array([True, True, False, True])
    out = tree_metrics(cell, height, full, cell_area_m2=400.0, dbh_measured=measured).iloc[0]
    assert out["basal_area_m2_ha"] == pytest.approx(np.sum(np.pi * full**2 / 4) / 0.04)
    assert out["n_dbh_measured"] == 3 and out["n_dbh_imputed"] == 1
    assert out["dbh_measured_share"] == pytest.approx(0.75)


def _chapman_richards_forest(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's height-diameter relation, with its height noise."""
    rng = np.random.default_rng(seed)
    dbh = np.clip(0.15 + rng.gamma(2.0, 0.07, n), 0.15, 0.6)
    height = 1.3 + 36.0 * (1 - np.exp(-0.045 * dbh * 100)) ** 1.1 + rng.normal(0, 0.8, n)
    return height, dbh


def test_naslund_model_imputes_dbh_within_its_stated_uncertainty() -> None:
    height, dbh = _chapman_richards_forest(1, 400)
    model = fit_height_diameter(height[:200], dbh[:200])
    assert model is not None and model.n_trees == 200
    predicted, limited = model.predict_dbh_m(height[200:])
    error = predicted - dbh[200:]
    rmse = float(np.sqrt(np.mean(error**2)))
    assert rmse < 0.06
    assert abs(float(np.mean(error))) < 0.01  # unbiased on average
    se = model.dbh_se_m(predicted)
    assert 0.5 < rmse / float(np.sqrt(np.mean(se**2))) < 1.6  # the stated SE is honest
    ba_true = np.sum(np.pi * dbh[200:] ** 2 / 4)
    assert np.sum(np.pi * predicted**2 / 4) == pytest.approx(ba_true, rel=0.06)
    assert not limited.all()


def test_too_few_measured_trees_give_no_model_and_no_guess() -> None:
    height, dbh = _chapman_richards_forest(2, MIN_TREES - 1)
    assert fit_height_diameter(height, dbh) is None
    table = pd.DataFrame(
        {
            "height_m": [20.0, 25.0],
            "dbh_m": [0.3, np.nan],
            "dbh_reason": pd.array([None, "no stem points at 1.3 m near the tree"], "string"),
        }
    )
    out = impute_dbh(table, None)
    assert list(out["dbh_source"]) == ["measured", "none"]
    assert math.isnan(out["dbh_m"].iloc[1]) and "no height-diameter model" in out["dbh_reason"][1]


def test_imputation_fills_only_missing_dbh_and_says_so() -> None:
    height, dbh = _chapman_richards_forest(3, 60)
    known = dbh.copy()
    known[::3] = np.nan
    table = pd.DataFrame(
        {
            "height_m": height,
            "dbh_m": known,
            "dbh_reason": pd.array(
                [None if np.isfinite(d) else "stem fit rejected: arc" for d in known], "string"
            ),
            "dbh_rmse_m": np.where(np.isfinite(known), 0.004, np.nan),
            "dbh_n_points": np.where(np.isfinite(known), 40, 0),
        }
    )
    model = fit_height_diameter(height[np.isfinite(known)], known[np.isfinite(known)])
    out = impute_dbh(table, model)
    imputed = out["dbh_source"] == "imputed"
    assert imputed.sum() == 20 and out["dbh_m"].notna().all()
    np.testing.assert_array_equal(out.loc[~imputed, "dbh_m"], known[np.isfinite(known)])
    assert out.loc[~imputed, "dbh_se_m"].to_numpy() == pytest.approx(2 * 0.004 / np.sqrt(40))
    assert out.loc[imputed, "dbh_reason"].str.startswith("imputed from height").all()


# --- observed area of irregular cells (Voronoi) --------------------------------------------


@pytest.fixture(scope="module")
def voronoi_enriched(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any]:
    """The bundled missions tiled into Voronoi cells and enriched: (catalog root, result)."""
    from standgrid.pipeline.enrich import enrich_catalog
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions
    from tests.conftest import BUNDLED_MISSIONS

    root = tmp_path_factory.mktemp("voronoi") / "catalog"
    tile_missions(sorted(BUNDLED_MISSIONS.iterdir()), root, TileOptions(scheme="voronoi"))
    return root, enrich_catalog(root)


def test_voronoi_cells_observe_at_most_their_area_exactly(
    voronoi_enriched: tuple[Any, Any],
) -> None:
    """observed_m2 = area of (observed pixel squares ∩ the cell), computed independently from
    observed.tif polygonised by rasterio (pixel centres counted whole gave up to 5 % more
    than the cell's own area)."""
    import rasterio
    from rasterio import features

    from standgrid.catalog import Catalog, paths
    from standgrid.catalog.index import CatalogIndex

    root, result = voronoi_enriched
    catalog = Catalog.open(root)
    metrics = pd.read_parquet(root / paths.stand_metrics("parquet"))
    checked = 0
    for epoch in catalog.epochs:
        with rasterio.open(root / paths.raster(epoch, "observed")) as src:
            mask = src.read(1)
            transform = src.transform
        observed = shapely.union_all(
            [
                shapely.geometry.shape(geometry)
                for geometry, value in features.shapes(mask, transform=transform)
                if value == 1
            ]
        )
        cells = CatalogIndex(catalog).read("cells", epoch)
        rows = metrics[(metrics["epoch"].astype(str) == epoch) & (metrics["level"] == 0)]
        rows = rows.set_index("cell_id").loc[cells["cell_id"]]
        assert rows.index.str.startswith("V_").all()
        expected = shapely.area(shapely.intersection(cells.geometry.to_numpy(), observed))
        got = rows["observed_m2"].to_numpy()
        assert (got <= cells.geometry.area.to_numpy() + 1e-6).all()
        assert (rows["observed_fraction"] <= 1.0).all()
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
        # the epoch's summary is the observed area of its cells
        assert result.epochs[epoch]["observed_m2"] == pytest.approx(got.sum(), abs=1e-6)
        checked += len(rows)
    assert checked == len(metrics[metrics["level"] == 0]) > 0
