"""Tree matching between epochs: synthetic forests with known growth, harvest and ingrowth."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from standgrid.comparison.trees import ChangeInputError, interval_years, match_trees
from standgrid.errors import FormatError, StandgridError
from tests.conftest import real_file

DATE_FROM = dt.date(2020, 6, 1)
DATE_TO = dt.date(2024, 6, 1)  # 1461 days = exactly 4.0 years of 365.25 days
YEARS = 4.0
GROWTH_PER_YEAR = 0.5


def _trees(ids, xy, height, dbh=None, crown=None) -> pd.DataFrame:
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    height = np.asarray(height, dtype=np.float64)
    frame = pd.DataFrame(
        {
            "tree_id": np.asarray(ids, dtype=np.uint32),
            "x": xy[:, 0] + 500_000.0,
            "y": xy[:, 1] + 6_700_000.0,
            "z_ground": np.full(len(xy), 120.0),
            "height_m": height,
        }
    )
    frame["dbh_m"] = height / 80.0 if dbh is None else dbh
    frame["crown_area_m2"] = height * 0.8 if crown is None else crown
    return frame


def _synthetic_pair(seed: int = 7, n: int = 400, noise: float = 0.4):
    """A 100 x 100 m forest; 10 % harvested, 40 ingrowth trees, +0.5 m/yr, position noise."""
    rng = np.random.default_rng(seed)
    # jittered grid with 4-5 m spacing: neighbours within 2 m of each other's noisy positions
    side = int(np.sqrt(n))
    gx, gy = np.meshgrid(np.arange(side) * 5.0, np.arange(side) * 5.0)
    xy = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-1.0, 1.0, (side * side, 2))
    height = rng.uniform(8.0, 30.0, len(xy))
    before = _trees(np.arange(1, len(xy) + 1), xy, height)

    harvested = rng.choice(len(xy), size=len(xy) // 10, replace=False)
    kept = np.setdiff1d(np.arange(len(xy)), harvested)
    angle = rng.uniform(0, 2 * np.pi, len(kept))
    shift = noise * np.column_stack([np.cos(angle), np.sin(angle)])
    grown_height = height[kept] + GROWTH_PER_YEAR * YEARS + rng.normal(0, 0.05, len(kept))
    # ingrowth: small trees far (> 2.5 m) from every old tree
    from scipy.spatial import cKDTree

    tree = cKDTree(xy)
    ingrowth: list[np.ndarray] = []
    while len(ingrowth) < 40:
        p = rng.uniform(0, side * 5.0, 2)
        if tree.query(p)[0] > 2.5 and all(np.hypot(*(p - q)) > 2.5 for q in ingrowth):
            ingrowth.append(p)
    new_xy = np.vstack([xy[kept] + shift, np.array(ingrowth)])
    new_height = np.concatenate([grown_height, rng.uniform(2.0, 4.0, len(ingrowth))])
    # ids are re-assigned per epoch (segmentation does not keep ids): shuffle them
    new_ids = rng.permutation(np.arange(1000, 1000 + len(new_xy)))
    after = _trees(new_ids, new_xy, new_height)
    truth_pairs = dict(zip(before["tree_id"].to_numpy()[kept], new_ids[: len(kept)], strict=True))
    return (
        before,
        after,
        truth_pairs,
        set(before["tree_id"].to_numpy()[harvested]),
        set(new_ids[len(kept) :]),
    )


def test_interval_years_is_days_over_365_25():
    assert interval_years(DATE_FROM, DATE_TO) == pytest.approx(4.0, abs=1e-12)
    assert interval_years("2023-01-01", "2024-01-01") == pytest.approx(365 / 365.25)
    assert interval_years(dt.datetime(2024, 1, 1, 0), dt.datetime(2024, 1, 1, 12)) == pytest.approx(
        0.5 / 365.25
    )
    with pytest.raises(ChangeInputError, match="must be after"):
        interval_years(DATE_TO, DATE_FROM)
    with pytest.raises(StandgridError, match="not a date"):
        interval_years("yesterday-ish", DATE_TO)


def test_synthetic_forest_growth_harvest_and_ingrowth_recovered():
    before, after, truth_pairs, harvested, ingrowth = _synthetic_pair()
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    table = result.table

    assert result.years == pytest.approx(YEARS)
    assert result.counts() == {
        "grown": len(truth_pairs),
        "new": len(ingrowth),
        "removed": len(harvested),
    }
    # every tree appears exactly once
    assert table["tree_id_from"].dropna().is_unique
    assert table["tree_id_to"].dropna().is_unique
    assert table["tree_id_from"].notna().sum() == len(before)
    assert table["tree_id_to"].notna().sum() == len(after)
    # correct partners, harvest and ingrowth all found
    grown = result.grown
    found_pairs = dict(
        zip(grown["tree_id_from"].astype(int), grown["tree_id_to"].astype(int), strict=True)
    )
    assert found_pairs == {int(k): int(v) for k, v in truth_pairs.items()}
    assert set(result.removed["tree_id_from"].astype(int)) == {int(t) for t in harvested}
    assert set(result.new["tree_id_to"].astype(int)) == {int(t) for t in ingrowth}
    # annualised growth: +0.5 m/yr over 4 years
    assert grown["height_m_delta"].mean() == pytest.approx(2.0, abs=0.02)
    assert grown["height_m_per_year"].mean() == pytest.approx(0.5, abs=0.005)
    assert grown["height_m_per_year"].between(0.4, 0.6).all()
    assert grown["distance_m"].max() == pytest.approx(0.4, abs=1e-9)
    assert not grown["suspicious"].any()
    # derived attributes follow the height (dbh = h / 80)
    assert grown["dbh_m_delta"].to_numpy() == pytest.approx(
        grown["height_m_delta"].to_numpy() / 80.0
    )
    # removed and new rows carry no change values, and their own position
    assert result.removed["height_m_delta"].isna().all()
    assert result.new["height_m_per_year"].isna().all()
    assert result.removed["x"].to_numpy() == pytest.approx(result.removed["x_from"].to_numpy())
    assert result.new["y"].to_numpy() == pytest.approx(result.new["y_to"].to_numpy())


def test_dense_neighbours_resolved_optimally_not_greedily():
    # Greedy nearest-first would pair B with A' (0.4 m) and leave A with B' (1.7 m).
    before = _trees([1, 2], [[0.0, 0.0], [1.0, 0.0]], [20.0, 20.0])
    after = _trees([11, 12], [[0.6, 0.0], [1.7, 0.0]], [21.0, 21.0])
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    pairs = dict(zip(result.grown["tree_id_from"], result.grown["tree_id_to"], strict=True))
    assert pairs == {1: 11, 2: 12}
    assert result.counts() == {"grown": 2, "new": 0, "removed": 0}


def test_height_breaks_ties_between_equidistant_neighbours():
    # Two trees 1 m apart, the re-observed positions both in the middle: heights decide.
    before = _trees([1, 2], [[0.0, 0.0], [1.0, 0.0]], [10.0, 25.0])
    after = _trees([11, 12], [[0.5, 0.1], [0.5, -0.1]], [26.0, 11.0])
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    pairs = dict(zip(result.grown["tree_id_from"], result.grown["tree_id_to"], strict=True))
    assert pairs == {1: 12, 2: 11}
    assert result.grown["height_m_delta"].to_numpy() == pytest.approx([1.0, 1.0])


def test_tree_that_shrank_too_much_is_removed_plus_new():
    before = _trees([1, 2], [[0.0, 0.0], [10.0, 0.0]], [20.0, 20.0])
    # tree 1 -> 12 m (-40 %): broken/fallen, a different tree; tree 2 -> 19 m: suspicious
    after = _trees([11, 12], [[0.3, 0.0], [10.3, 0.0]], [12.0, 19.0])
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert result.counts() == {"grown": 1, "new": 1, "removed": 1}
    assert int(result.removed["tree_id_from"].iloc[0]) == 1
    assert int(result.new["tree_id_to"].iloc[0]) == 11
    assert result.grown["suspicious"].tolist() == [True]
    loose = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO, max_height_loss=0.5)
    assert loose.counts() == {"grown": 2, "new": 0, "removed": 0}


def test_beyond_max_distance_is_not_a_match():
    before = _trees([1], [[0.0, 0.0]], [20.0])
    after = _trees([2], [[2.5, 0.0]], [21.0])
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert result.counts() == {"grown": 0, "new": 1, "removed": 1}
    wide = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO, max_distance=3.0)
    assert wide.counts() == {"grown": 1, "new": 0, "removed": 0}
    assert wide.grown["distance_m"].iloc[0] == pytest.approx(2.5)


def test_exact_same_position_is_matched():
    before = _trees([1], [[0.0, 0.0]], [20.0])
    after = _trees([2], [[0.0, 0.0]], [20.0])
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert result.counts() == {"grown": 1, "new": 0, "removed": 0}
    assert result.grown["height_m_per_year"].iloc[0] == 0.0


@pytest.mark.parametrize("side", ["from", "to", "both"])
def test_empty_tree_sets(side):
    some = _trees([1, 2, 3], [[0, 0], [5, 0], [10, 0]], [10.0, 12.0, 14.0])
    empty = some.iloc[0:0]
    before = empty if side in ("from", "both") else some
    after = empty if side in ("to", "both") else some
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    expected = {
        "from": {"grown": 0, "new": 3, "removed": 0},
        "to": {"grown": 0, "new": 0, "removed": 3},
        "both": {"grown": 0, "new": 0, "removed": 0},
    }[side]
    assert result.counts() == expected
    assert len(result.table) == sum(expected.values())
    assert "height_m_per_year" in result.table.columns


def test_optional_attribute_columns_may_be_absent():
    before = _trees([1], [[0, 0]], [10.0]).drop(columns=["dbh_m", "crown_area_m2"])
    after = _trees([2], [[0.2, 0]], [11.0]).drop(columns=["dbh_m"])
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    row = result.grown.iloc[0]
    assert np.isnan(row["dbh_m_delta"]) and np.isnan(row["crown_area_m2_delta"])
    assert row["crown_area_m2_to"] == pytest.approx(8.8)
    assert row["height_m_per_year"] == pytest.approx(0.25)


def test_dbh_growth_only_between_two_stem_fits():
    """Four matched trees: fitted twice, imputed twice, fit then model, no DBH in one epoch;
    only the first gets a diameter growth."""
    xy = [[0, 0], [10, 0], [20, 0], [30, 0]]
    before = _trees([1, 2, 3, 4], xy, [20.0, 21.0, 22.0, 23.0], dbh=[0.30, 0.31, 0.32, np.nan])
    after = _trees([5, 6, 7, 8], xy, [21.0, 22.0, 23.0, 24.0], dbh=[0.32, 0.30, 0.33, 0.35])
    before["dbh_source"] = ["measured", "imputed", "measured", "none"]
    after["dbh_source"] = ["measured", "imputed", "imputed", "imputed"]
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    grown = result.grown.sort_values("tree_id_from")
    assert list(grown["dbh_growth_source"]) == ["measured", "imputed", "mixed", "none"]
    assert list(grown["dbh_mixed_sources"]) == [False, False, True, False]
    assert grown["dbh_m_delta"].iloc[0] == pytest.approx(0.02)
    assert grown["dbh_m_per_year"].iloc[0] == pytest.approx(0.02 / result.years)
    assert grown[["dbh_m_delta", "dbh_m_per_year"]].iloc[1:].isna().all().all()
    assert grown["dbh_m_to"].notna().all()


def test_bad_tree_tables_are_refused():
    good = _trees([1], [[0, 0]], [10.0])
    with pytest.raises(FormatError, match=r"trees_to.*height_m"):
        match_trees(good, good.drop(columns=["height_m"]), date_from=DATE_FROM, date_to=DATE_TO)
    bad = good.copy()
    bad.loc[0, "x"] = np.nan
    with pytest.raises(FormatError, match=r"trees_from.*non-finite"):
        match_trees(bad, good, date_from=DATE_FROM, date_to=DATE_TO)
    twice = pd.concat([good, good])
    with pytest.raises(FormatError, match="duplicate tree_id"):
        match_trees(twice, good, date_from=DATE_FROM, date_to=DATE_TO)


def _brute_force_cost(before: pd.DataFrame, after: pd.DataFrame) -> float:
    """Minimum total cost over every partial one-to-one matching (the documented objective)."""
    from standgrid.enrichment.identity import UNMATCHED_COST
    from standgrid.enrichment.identity import pair_costs as _pair_costs

    n, m = len(before), len(after)
    cost = np.full((n, m), np.inf)
    for i in range(n):
        for j in range(m):
            d = np.hypot(after.x.iloc[j] - before.x.iloc[i], after.y.iloc[j] - before.y.iloc[i])
            c, ok = _pair_costs(
                np.array([before.height_m.iloc[i]]),
                np.array([after.height_m.iloc[j]]),
                np.array([d]),
                max_distance=2.0,
                max_height_loss=0.3,
                max_height_gain=1.0,
            )
            if d <= 2.0 and ok[0]:
                cost[i, j] = c[0]

    def best(i: int, used: frozenset[int]) -> float:
        if i == n:
            return UNMATCHED_COST * (m - len(used))
        options = [UNMATCHED_COST + best(i + 1, used)]
        options += [
            cost[i, j] + best(i + 1, used | {j})
            for j in range(m)
            if j not in used and np.isfinite(cost[i, j])
        ]
        return min(options)

    return best(0, frozenset())


def _result_cost(result) -> float:
    from standgrid.enrichment.identity import UNMATCHED_COST
    from standgrid.enrichment.identity import pair_costs as _pair_costs

    grown = result.grown
    costs, _ = _pair_costs(
        grown["height_m_from"].to_numpy(),
        grown["height_m_to"].to_numpy(),
        grown["distance_m"].to_numpy(),
        max_distance=2.0,
        max_height_loss=0.3,
        max_height_gain=1.0,
    )
    unmatched = len(result.table) - len(grown)
    return float(costs.sum()) + UNMATCHED_COST * unmatched


_tree = st.tuples(st.floats(0, 4), st.floats(0, 2), st.floats(5, 20))


@settings(max_examples=80, deadline=None, derandomize=True)
@given(st.lists(_tree, max_size=5), st.lists(_tree, max_size=5))
def test_assignment_is_optimal_against_brute_force(trees_a, trees_b):
    def frame(trees, first_id):
        xy = [[t[0], t[1]] for t in trees] or np.empty((0, 2))
        return _trees(np.arange(first_id, first_id + len(trees)), xy, [t[2] for t in trees])

    before, after = frame(trees_a, 1), frame(trees_b, 100)
    result = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert _result_cost(result) == pytest.approx(_brute_force_cost(before, after), abs=1e-9)
    assert result.table["tree_id_from"].notna().sum() == len(before)
    assert result.table["tree_id_to"].notna().sum() == len(after)
    grown = result.grown
    assert (grown["distance_m"] <= 2.0).all()
    assert (grown["height_m_to"] >= 0.7 * grown["height_m_from"] - 1e-9).all()


@pytest.mark.realdata
def test_real_tree_positions_with_simulated_second_epoch():
    """Tree tops of a real ALS plot (lidR MixedConifer, lidR's segmentation) as epoch 1;
    epoch 2 = 0.4 m/yr growth over 5 years, 0.5 m position noise, 15 % harvest, ingrowth."""
    import laspy
    from scipy.spatial import cKDTree

    las = laspy.read(real_file("als/lidR/MixedConifer.laz"))
    points = pd.DataFrame(
        {
            "tree": np.asarray(las["treeID"]),
            "x": np.asarray(las.x),
            "y": np.asarray(las.y),
            "z": np.asarray(las.z),
        }
    )
    points = points[(points["tree"] > 0) & (points["tree"] < 1e9)]  # NA is stored as DBL_MAX
    tops = points.loc[points.groupby("tree")["z"].idxmax()].reset_index(drop=True)
    assert len(tops) > 150
    before = _trees(
        np.arange(1, len(tops) + 1),
        tops[["x", "y"]].to_numpy() - [500_000.0, 6_700_000.0],
        tops["z"].to_numpy(),
    )
    rng = np.random.default_rng(11)
    harvested = rng.choice(len(tops), size=int(0.15 * len(tops)), replace=False)
    kept = np.setdiff1d(np.arange(len(tops)), harvested)
    angle = rng.uniform(0, 2 * np.pi, len(kept))
    xy = before[["x", "y"]].to_numpy()
    moved = xy[kept] + 0.5 * np.column_stack([np.cos(angle), np.sin(angle)])
    tree = cKDTree(xy)
    gaps: list[np.ndarray] = []
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    while len(gaps) < 15:
        p = rng.uniform(lo, hi)
        if tree.query(p)[0] > 2.6 and all(np.hypot(*(p - q)) > 2.6 for q in gaps):
            gaps.append(p)
    after = _trees(
        np.arange(5000, 5000 + len(kept) + len(gaps)),
        np.vstack([moved, gaps]) - [500_000.0, 6_700_000.0],
        np.concatenate(
            [before["height_m"].to_numpy()[kept] + 0.4 * 5.0, rng.uniform(1.5, 3.0, len(gaps))]
        ),
    )
    result = match_trees(before, after, date_from="2019-07-01", date_to="2024-07-01")
    assert result.years == pytest.approx(1827 / 365.25)
    assert result.counts() == {"grown": len(kept), "new": len(gaps), "removed": len(harvested)}
    pairs = dict(
        zip(
            result.grown["tree_id_from"].astype(int),
            result.grown["tree_id_to"].astype(int),
            strict=True,
        )
    )
    assert pairs == {int(before["tree_id"].iloc[k]): 5000 + i for i, k in enumerate(kept)}
    assert result.grown["height_m_per_year"].to_numpy() == pytest.approx(
        2.0 / result.years, abs=1e-5
    )


def test_sparse_solver_of_large_components_equals_dense(monkeypatch):
    """A regeneration-dense stand (6000 stems/ha): candidates chain into big components."""
    import standgrid.enrichment.identity as trees_module

    rng = np.random.default_rng(5)
    n = 600
    xy = rng.uniform(0, 31.6, (n, 2))  # 0.1 ha
    height = rng.uniform(2.0, 8.0, n)
    before = _trees(np.arange(n), xy, height)
    keep = rng.random(n) > 0.2
    after = _trees(
        np.arange(1000, 1000 + keep.sum()),
        xy[keep] + rng.normal(0, 0.3, (keep.sum(), 2)),
        height[keep] * rng.uniform(0.8, 1.4, keep.sum()),
    )
    dense = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    monkeypatch.setattr(trees_module, "DENSE_LIMIT", 0)
    sparse = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert _result_cost(sparse) == pytest.approx(_result_cost(dense), abs=1e-6)
    assert sparse.counts() == dense.counts()
    assert sparse.counts()["grown"] > 0.9 * keep.sum()
