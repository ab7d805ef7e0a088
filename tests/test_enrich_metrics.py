"""Stand metrics: hand-checked tiny clouds, lidR definitions on the real MixedConifer plot."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from standgrid.enrichment.metrics import (
    QUANTILE_PERCENTS,
    REASON_NO_DBH,
    REASON_NO_HEIGHT,
    REASON_NO_POINTS,
    REASON_NO_TREES,
    area_metrics,
    cell_index,
    strata_columns,
    tree_metrics,
)
from standgrid.errors import EnrichError
from tests.conftest import real_file


def test_five_points_by_hand() -> None:
    z = np.array([1.0, 2.0, 3.0, 4.0, 10.0])
    row = area_metrics(np.zeros(5, dtype=np.int64), z, cell_area_m2=400.0).iloc[0]
    assert row["n_points"] == 5 and row["density_pts_m2"] == pytest.approx(5 / 400)
    assert row["zmax"] == 10.0 and row["zmean"] == 4.0
    assert row["zsd"] == pytest.approx(math.sqrt(50 / 4))  # sample sd (R sd)
    assert row["zskew"] == pytest.approx(36 / 10**1.5)  # m3 / m2^1.5, population moments
    assert row["zkurt"] == pytest.approx(278.8 / 100)  # m4 / m2^2 (not excess)
    assert row["zq50"] == 3.0 and row["zq25"] == 2.0
    assert row["zq95"] == pytest.approx(8.8)  # type 7: 4 + 0.8 * (10 - 4)
    assert row["pzabove2"] == 60.0  # strictly above
    assert row["pzabovezmean"] == 20.0
    # zpcum: breaks 0,1,..,10 over the 4 points below the top break (z = 10 is left out)
    assert [row[f"zpcum{k}"] for k in range(1, 10)] == [0, 25, 50, 75, 100, 100, 100, 100, 100]
    assert row["zentropy"] == pytest.approx(math.log(4) / math.log(10))
    strata = dict(zip(strata_columns(), [0, 20, 60, 0, 20, 0, 0], strict=True))
    for name, value in strata.items():
        assert row[name] == pytest.approx(value), name
    assert sum(row[name] for name in strata) == pytest.approx(100.0)
    assert (
        row["null_reason"] is None
        or row["null_reason"] is np.nan
        or str(row["null_reason"]) == "<NA>"
    )


def reference_zpcum(z: np.ndarray, zmin: float = 0.0) -> list[float]:
    """lidR stdmetrics_z zpcum, written out with findInterval semantics."""
    zmax = z.max()
    if zmax <= zmin:
        return [0.0] * 9
    breaks = zmin + np.arange(11) * ((zmax - zmin) / 10)
    interval = np.searchsorted(breaks, z[z > zmin], side="right")  # R findInterval
    table = np.array([(interval == i).sum() for i in range(1, 11)], dtype=float)
    return list(np.cumsum(table / table.sum() * 100)[:9])


@pytest.mark.realdata
def test_real_mixed_conifer_matches_direct_numpy() -> None:
    import laspy

    las = laspy.read(real_file("als/lidR/MixedConifer.laz"))
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    col, row = cell_index(x, y, origin=(481_260.0, 3_812_920.0), cell_size=20.0)
    key = row * 100 + col
    table = area_metrics(key, z, cell_area_m2=400.0)
    assert table["n_points"].sum() == len(z)
    assert table["null_reason"].isna().all()
    for cell, got in table.iterrows():
        zz = z[key == cell]
        assert got["n_points"] == len(zz)
        assert got["zmax"] == pytest.approx(zz.max(), abs=1e-9)  # heights exact to ~1e-8 m
        assert got["zmean"] == pytest.approx(zz.mean(), rel=1e-12)
        assert got["zsd"] == pytest.approx(zz.std(ddof=1), rel=1e-9)
        assert got["zskew"] == pytest.approx(stats.skew(zz, bias=True), rel=1e-9)
        assert got["zkurt"] == pytest.approx(stats.kurtosis(zz, fisher=False, bias=True), rel=1e-9)
        for p in QUANTILE_PERCENTS:
            assert got[f"zq{p}"] == pytest.approx(np.percentile(zz, p), abs=1e-7)
        assert got["pzabove2"] == pytest.approx(100 * np.mean(zz > 2))
        assert got["pzabovezmean"] == pytest.approx(100 * np.mean(zz > zz.mean()))
        assert [got[f"zpcum{k}"] for k in range(1, 10)] == pytest.approx(reference_zpcum(zz))
        assert got["pz10to20"] == pytest.approx(100 * np.mean((zz >= 10) & (zz < 20)))
        assert got["density_pts_m2"] == pytest.approx(len(zz) / 400)


def test_null_cells_have_a_reason_never_a_silent_zero() -> None:
    keys = np.array([1, 1, 1, 2, 2, 3, 3], dtype=np.int64)
    h = np.array([5.0, 6.0, np.nan, np.nan, np.nan, 1.0, 3.0])
    table = area_metrics(keys, h, cells=[1, 2, 3, 9], cell_area_m2=100.0)
    assert list(table.index) == [1, 2, 3, 9]
    assert table.loc[9, "null_reason"] == REASON_NO_POINTS and table.loc[9, "n_points"] == 0
    assert table.loc[2, "null_reason"] == REASON_NO_HEIGHT and table.loc[2, "n_no_height"] == 2
    metric_columns = [c for c in table.columns if c.startswith(("z", "pz"))]
    assert table.loc[[2, 9], metric_columns].isna().all().all()
    assert table.loc[1, "zmean"] == 5.5 and table.loc[1, "n_no_height"] == 1
    assert table.loc[1, "density_pts_m2"] == pytest.approx(0.03)  # all returns count
    assert table.loc[3, "pzabove2"] == 50.0 and pd_isna(table.loc[3, "null_reason"])
    single = area_metrics(np.array([4]), np.array([7.0])).iloc[0]
    assert math.isnan(single["zsd"]) and math.isnan(single["zskew"]) and single["zq95"] == 7.0


def test_constant_heights_have_zero_sd_and_no_skew_or_kurtosis() -> None:
    keys = np.array([1, 1, 1, 2, 2, 2, 2, 3, 3], dtype=np.int64)
    h = np.array([0.1, 0.1, 0.1, 7.3, 7.3, 7.3, 7.3, 0.1, 0.2])
    table = area_metrics(keys, h)
    for cell in (1, 2):  # 0.1 * 3 leaves round-off in m2 from the floating mean
        assert table.loc[cell, "zsd"] == 0.0
        assert math.isnan(table.loc[cell, "zskew"]) and math.isnan(table.loc[cell, "zkurt"])
        assert table.loc[cell, "zq50"] == table.loc[cell, "zmax"]
    assert table.loc[3, "zsd"] == pytest.approx(np.std([0.1, 0.2], ddof=1))
    assert table.loc[3, "zskew"] == pytest.approx(0.0, abs=1e-9)
    assert table.loc[3, "zkurt"] == pytest.approx(1.0)


def pd_isna(value: object) -> bool:
    import pandas as pd

    return bool(pd.isna(value))


def test_large_cell_keys_and_random_clouds_match_direct_computation() -> None:
    rng = np.random.default_rng(3)
    small = rng.integers(0, 50, 20_000)
    huge = small * 7_919_000_000_003 + 12  # CellId-style sparse 64-bit keys
    h = rng.gamma(2.0, 6.0, 20_000) - 1.0
    a = area_metrics(small, h)
    b = area_metrics(huge, h)
    assert np.allclose(
        a.drop(columns="null_reason").to_numpy(),
        b.drop(columns="null_reason").to_numpy(),
        equal_nan=True,
    )
    for cell in (0, 17, 49):
        zz = h[small == cell]
        assert a.loc[cell, "zq35"] == pytest.approx(np.quantile(zz, 0.35), abs=1e-7)
        # heights below 0 (ground noise) fall in no bin (lidR would give NA for the cell)
        kept = zz[zz >= 0]
        bins = int(np.ceil(kept.max()))
        p = np.histogram(kept, bins=bins, range=(0, bins))[0] / len(kept)
        p = p[p > 0]
        assert a.loc[cell, "zentropy"] == pytest.approx(-(p * np.log(p)).sum() / np.log(bins))
        assert a.loc[cell, "pz_below0p5"] == pytest.approx(100 * np.mean(zz < 0.5))


def test_first_return_cover_and_custom_break() -> None:
    h = np.array([0.1, 3.0, 4.0, 1.0, 6.0])
    first = np.array([True, True, False, True, True])
    row = area_metrics(np.zeros(5, dtype=np.int64), h, first_return=first, height_break=3.0).iloc[0]
    assert row["cover_first_above3"] == 25.0  # first returns: 0.1, 3.0, 1.0, 6.0 -> one > 3
    assert row["pzabove3"] == 40.0


def test_bad_input_raises() -> None:
    with pytest.raises(EnrichError):
        area_metrics(np.zeros(3, dtype=np.int64), np.zeros(4))
    with pytest.raises(EnrichError):
        area_metrics(np.zeros(3), np.zeros(3))
    with pytest.raises(EnrichError):
        area_metrics(np.zeros(3, dtype=np.int64), np.zeros(3), strata=(2.0, 1.0))
    with pytest.raises(EnrichError):
        tree_metrics([1], [10.0], [0.2], cell_area_m2=0.0)


def test_tree_metrics_by_hand() -> None:
    cells = np.array([7, 7, 7, 7, 8, 8])
    height = np.array([20.0, 25.0, 18.0, 30.0, 12.0, 14.0])
    dbh = np.array([0.30, 0.40, 0.20, 0.50, np.nan, 0.25])
    table = tree_metrics(cells, height, dbh, cell_area_m2=200.0, cells=[7, 8, 9])
    area_ha = 0.02
    a = table.loc[7]
    assert a["stems_ha"] == pytest.approx(4 / area_ha) and a["n_dbh_measured"] == 4
    ba = sum(math.pi * (d / 2) ** 2 for d in (0.3, 0.4, 0.2, 0.5))
    assert a["basal_area_m2_ha"] == pytest.approx(ba / area_ha)
    assert a["qmd_cm"] == pytest.approx(100 * math.sqrt((0.09 + 0.16 + 0.04 + 0.25) / 4))
    assert a["mean_height_m"] == pytest.approx(23.25)
    # 100 trees/ha on 0.02 ha = the 2 largest-DBH trees: 30 m (0.50) and 25 m (0.40)
    assert a["dominant_height_m"] == pytest.approx(27.5) and a["dominant_by"] == "dbh"
    assert pd_isna(a["null_reason"])
    b = table.loc[8]  # one tree lacks a DBH: dominant by height, no partial basal area
    assert b["n_dbh_measured"] == 1 and b["dominant_by"] == "height"
    assert b["dominant_height_m"] == pytest.approx(13.0)
    assert math.isnan(b["basal_area_m2_ha"]) and math.isnan(b["qmd_cm"])
    assert b["null_reason"] == f"{REASON_NO_DBH}: 1 of 2 trees"
    c = table.loc[9]
    assert (
        c["stems_ha"] == 0
        and c["null_reason"] == REASON_NO_TREES
        and math.isnan(c["mean_height_m"])
    )
    only_height = tree_metrics([1, 1], [10.0, 12.0], [np.nan, np.nan], cell_area_m2=400.0)
    assert only_height.loc[1, "null_reason"] == f"{REASON_NO_DBH}: 2 of 2 trees"
    assert math.isnan(only_height.loc[1, "basal_area_m2_ha"])
    assert only_height.loc[1, "dominant_height_m"] == pytest.approx(11.0)  # k = 4 > 2 trees


@pytest.mark.realdata
def test_stand_grid_cell_keys_work_as_metric_keys() -> None:
    """The partition stage's int64 cell keys group points exactly like plain indices."""
    import laspy

    from standgrid.partition.grid import StandGrid, key_to_index

    las = laspy.read(real_file("als/lidR/MixedConifer.laz"))
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    grid = StandGrid(crs="EPSG:26912", cell_size=20.0, origin=(481_000.0, 3_812_000.0))
    by_key = area_metrics(grid.cell_keys(x, y), z, cell_area_m2=400.0)
    col, row = cell_index(x, y, origin=grid.origin, cell_size=grid.cell_size)
    by_index = area_metrics(col * 1000 + row, z, cell_area_m2=400.0)
    ix, iy = key_to_index(by_key.index.to_numpy())
    assert np.array_equal(np.sort(ix * 1000 + iy), by_index.index.to_numpy())
    reordered = by_index.loc[ix * 1000 + iy]
    assert np.array_equal(reordered["n_points"].to_numpy(), by_key["n_points"].to_numpy())
    assert np.allclose(reordered["zq95"].to_numpy(), by_key["zq95"].to_numpy())


def test_float32_heights_give_the_float64_metrics_to_the_bit_and_their_sorted_order() -> None:
    from standgrid.enrichment.metrics import area_metrics_sorted

    rng = np.random.default_rng(11)
    h32 = (rng.gamma(2.0, 6.0, 30_000) - 1.0).astype(np.float32)
    h32[rng.choice(30_000, 50, replace=False)] = np.nan  # no height there
    grouped = np.repeat(np.arange(5, dtype=np.int64), 6_000)  # cell after cell: sorted per cell
    scattered = rng.integers(0, 2_000, 30_000)  # many small cells: one sort by (cell, height)
    for keys in (grouped, scattered):
        wide = area_metrics(keys, h32.astype(np.float64))
        table, ordered = area_metrics_sorted(keys, h32)
        assert list(table.columns) == list(wide.columns) and table.index.equals(wide.index)
        for column in wide.columns.drop("null_reason"):
            a, b = wide[column].to_numpy(np.float64), table[column].to_numpy(np.float64)
            assert a.tobytes() == b.tobytes(), column
        assert ordered.dtype == np.float32
        finite = np.isfinite(h32)
        expected = np.concatenate(
            [np.sort(h32[finite & (keys == cell)]) for cell in np.unique(keys[finite])]
        )
        assert ordered.tobytes() == expected.tobytes()


def test_measured_heights_left_sorted_measure_the_same_stand() -> None:
    import pandas as pd

    from standgrid.enrichment.stands import StandSample, measure_heights

    def cells(seed: int) -> list[StandSample]:
        rng = np.random.default_rng(seed)
        out = []
        for k in range(4):
            h = (rng.gamma(2.0, 6.0, 5_000) - 1.0).astype(np.float32)
            h[[3, 17]] = np.nan
            trees = pd.DataFrame({"height_m": [], "dbh_m": []})
            out.append(StandSample(f"c{k}", 0, 20.0, 400.0, 400.0, 5_000, h, trees))
        return out

    plain, kept = cells(12), cells(12)
    measure_heights(plain)
    measure_heights(kept, sort_heights=True)
    for a, b in zip(plain, kept, strict=True):
        assert a.area is not None and repr(a.area) == repr(b.area)
        finite = np.isfinite(a.heights)
        n = int(finite.sum())
        assert b.heights.dtype == np.float32 and len(b.heights) == len(a.heights)
        assert b.heights[:n].tobytes() == np.sort(a.heights[finite]).tobytes()
        assert np.isnan(b.heights[n:]).all()
