"""Per-stand change: metric deltas, annualisation, one-epoch stands, nulls, tree change."""

from __future__ import annotations

import datetime as dt

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import shapely

from standgrid.comparison.stands import assign_stands, check_same_grid, compare_stands
from standgrid.comparison.trees import match_trees
from standgrid.errors import FormatError, GridMismatchError, StandgridError

DATE_FROM = dt.date(2021, 5, 10)
DATE_TO = dt.date(2023, 5, 10)  # 730 days
YEARS = 730 / 365.25
X0, Y0, SIZE = 600_000.0, 5_000_000.0, 50.0


def _cells(names=("A", "B", "C", "D")) -> gpd.GeoDataFrame:
    boxes = [
        shapely.box(X0 + i * SIZE, Y0, X0 + (i + 1) * SIZE, Y0 + SIZE) for i in range(len(names))
    ]
    return gpd.GeoDataFrame({"cell_id": list(names)}, geometry=boxes, crs="EPSG:32633")


def _metrics_pair():
    before = pd.DataFrame(
        {
            "cell_id": ["A", "B", "C"],
            "height_p95_m": [20.0, 18.0, np.nan],
            "canopy_cover": [0.8, 0.6, np.nan],
            "stems_per_ha": [400, 360, np.nan],
            "null_reason": ["", "", "too few points (12 < 100)"],
        }
    )
    after = pd.DataFrame(
        {
            "cell_id": ["A", "B", "C", "D"],
            "height_p95_m": [21.0, 12.0, 15.0, 9.0],
            "canopy_cover": [0.85, np.nan, 0.5, 0.3],
            "stems_per_ha": [400, 200, 300, 100],
            "null_reason": ["", "cover: occluded", "", ""],
        }
    )
    return before, after


def test_check_same_grid_refuses_different_fingerprints():
    check_same_grid("sg1-abc123", "sg1-abc123")
    with pytest.raises(GridMismatchError, match=r"sg1-abc123.*sg1-def456") as info:
        check_same_grid("sg1-abc123", "sg1-def456", label_a="2021", label_b="2023")
    assert isinstance(info.value, StandgridError)
    assert "2021" in str(info.value) and "2023" in str(info.value)


def test_check_same_grid_accepts_grid_objects():
    from standgrid.partition.grid import StandGrid

    grid = StandGrid("EPSG:32633", cell_size=20.0, origin=(0.0, 0.0))
    check_same_grid(grid, StandGrid("EPSG:32633", cell_size=20.0, origin=(0.0, 0.0)))
    check_same_grid(grid, grid.fingerprint)
    shifted = StandGrid("EPSG:32633", cell_size=20.0, origin=(10.0, 0.0))
    with pytest.raises(GridMismatchError) as info:
        check_same_grid(grid, shifted)
    assert grid.fingerprint in str(info.value) and shifted.fingerprint in str(info.value)


def test_metric_deltas_and_annualisation_exact():
    before, after = _metrics_pair()
    out = compare_stands(
        before, after, date_from=DATE_FROM, date_to=DATE_TO, epoch_from="2021", epoch_to="2023"
    )
    assert list(out["cell_id"]) == ["A", "B", "C", "D"]
    a = out.set_index("cell_id").loc["A"]
    assert a["presence"] == "both"
    assert a["years"] == pytest.approx(YEARS)
    assert a["height_p95_m_from"] == 20.0 and a["height_p95_m_to"] == 21.0
    assert a["height_p95_m_delta"] == pytest.approx(1.0)
    assert a["height_p95_m_per_year"] == pytest.approx(1.0 / YEARS)
    assert a["canopy_cover_delta"] == pytest.approx(0.05)
    assert a["stems_per_ha_delta"] == 0.0
    assert a["null_reason"] == ""
    assert (a["epoch_from"], a["epoch_to"]) == ("2021", "2023")
    assert (a["date_from"], a["date_to"]) == ("2021-05-10", "2023-05-10")
    b = out.set_index("cell_id").loc["B"]
    assert b["height_p95_m_delta"] == pytest.approx(-6.0)
    assert b["stems_per_ha_per_year"] == pytest.approx(-160 / YEARS)


def test_null_metrics_stay_null_with_reason_carried_over():
    before, after = _metrics_pair()
    out = compare_stands(before, after, date_from=DATE_FROM, date_to=DATE_TO).set_index("cell_id")
    b = out.loc["B"]
    assert np.isnan(b["canopy_cover_to"]) and np.isnan(b["canopy_cover_delta"])
    assert np.isnan(b["canopy_cover_per_year"])
    assert "to: cover: occluded" in b["null_reason"]
    assert b["null_reason_to"] == "cover: occluded"
    c = out.loc["C"]
    assert c["presence"] == "both"
    for metric in ("height_p95_m", "canopy_cover", "stems_per_ha"):
        assert np.isnan(c[f"{metric}_delta"])  # never a silent zero
        assert c[f"{metric}_to"] > 0
    assert c["null_reason"] == "from: too few points (12 < 100)"


def test_stands_in_one_epoch_are_listed_with_reason():
    before, after = _metrics_pair()
    before = pd.concat(
        [
            before,
            pd.DataFrame(
                {
                    "cell_id": ["E"],
                    "height_p95_m": [5.0],
                    "canopy_cover": [0.1],
                    "stems_per_ha": [50],
                    "null_reason": [""],
                }
            ),
        ]
    )
    out = compare_stands(
        before, after, date_from=DATE_FROM, date_to=DATE_TO, epoch_from="2021", epoch_to="2023"
    ).set_index("cell_id")
    assert out.loc["D", "presence"] == "to_only"
    assert "not observed in the 2021 epoch" in out.loc["D", "null_reason"]
    assert out.loc["D", "height_p95_m_to"] == 9.0 and np.isnan(out.loc["D", "height_p95_m_delta"])
    assert out.loc["E", "presence"] == "from_only"
    assert "not observed in the 2023 epoch" in out.loc["E", "null_reason"]
    assert out.loc["E", "height_p95_m_from"] == 5.0
    assert len(out) == 5


def test_metric_computed_in_one_epoch_only_is_kept_with_reason():
    before, after = _metrics_pair()
    after["gap_fraction"] = [0.1, 0.2, 0.3, 0.4]
    out = compare_stands(before, after, date_from=DATE_FROM, date_to=DATE_TO).set_index("cell_id")
    assert out.loc["A", "gap_fraction_to"] == pytest.approx(0.1)
    assert np.isnan(out.loc["A", "gap_fraction_delta"])
    assert "metric gap_fraction not computed" in out.loc["A", "null_reason"]


def test_bad_metric_tables_are_refused():
    before, after = _metrics_pair()
    with pytest.raises(FormatError, match=r"metrics_from.*cell_id"):
        compare_stands(before.drop(columns="cell_id"), after, date_from=DATE_FROM, date_to=DATE_TO)
    with pytest.raises(FormatError, match="'A' appears more than once"):
        compare_stands(
            before, pd.concat([after, after.iloc[:1]]), date_from=DATE_FROM, date_to=DATE_TO
        )
    with pytest.raises(StandgridError, match="must be after"):
        compare_stands(before, after, date_from=DATE_TO, date_to=DATE_FROM)


def _trees(ids, xy, height) -> pd.DataFrame:
    xy = np.asarray(xy, dtype=np.float64)
    return pd.DataFrame({"tree_id": ids, "x": xy[:, 0], "y": xy[:, 1], "height_m": height})


def test_assign_stands_by_polygon():
    cells = _cells()
    x = np.array([X0 + 10, X0 + 60, X0 + 199, X0 + 250, X0 + 50.0])
    y = np.full(len(x), Y0 + 10)
    stands = assign_stands(x, y, cells)
    assert stands.iloc[:4].tolist() == ["A", "B", "D", None]
    assert stands.iloc[4] in ("A", "B")  # a point on a shared edge goes to exactly one


def test_tree_based_change_per_stand():
    rng = np.random.default_rng(3)
    cells = _cells()
    # stand A: 20 trees, 5 harvested; stand B: 10 trees, 2 new; C: no trees; D: metrics only to
    xy_a = np.column_stack([X0 + 5 + 10 * (np.arange(20) % 5), Y0 + 5 + 10 * (np.arange(20) // 5)])
    xy_b = np.column_stack(
        [X0 + SIZE + 5 + 10 * (np.arange(10) % 5), Y0 + 5 + 10 * (np.arange(10) // 5)]
    )
    xy = np.vstack([xy_a, xy_b])
    height = rng.uniform(10, 25, len(xy))
    before = _trees(np.arange(len(xy)), xy, height)
    harvested = np.array([0, 3, 7, 12, 19])
    kept = np.setdiff1d(np.arange(len(xy)), harvested)
    growth = np.where(kept < 20, 0.6, 0.3) * YEARS  # stand A grows 0.6 m/yr, B 0.3 m/yr
    ingrowth = np.array([[X0 + SIZE + 5, Y0 + 35.0], [X0 + SIZE + 25, Y0 + 45.0]])
    after = _trees(
        np.arange(100, 100 + len(kept) + 2),
        np.vstack([xy[kept] + rng.normal(0, 0.3, (len(kept), 2)), ingrowth]),
        np.concatenate([height[kept] + growth, [2.0, 3.0]]),
    )
    matches = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert matches.counts() == {"grown": 25, "new": 2, "removed": 5}

    metrics_before, metrics_after = _metrics_pair()
    out = compare_stands(
        metrics_before,
        metrics_after,
        date_from=DATE_FROM,
        date_to=DATE_TO,
        tree_matches=matches,
        cells=cells,
    ).set_index("cell_id")
    a, b, c = out.loc["A"], out.loc["B"], out.loc["C"]
    assert (a["trees_grown"], a["trees_removed"], a["trees_new"]) == (15, 5, 0)
    assert (b["trees_grown"], b["trees_removed"], b["trees_new"]) == (10, 0, 2)
    assert a["trees_removed_per_ha"] == pytest.approx(5 / 0.25)
    assert b["trees_new_per_ha"] == pytest.approx(2 / 0.25)
    assert a["tree_height_growth_m_per_year"] == pytest.approx(0.6)
    assert b["tree_height_growth_m_per_year"] == pytest.approx(0.3)
    assert b["tree_height_growth_m"] == pytest.approx(0.3 * YEARS)
    # C observed in both epochs without trees: a real zero; D (to only): unknown
    assert (c["trees_removed"], c["trees_removed_per_ha"]) == (0, 0.0)
    assert pd.isna(out.loc["D", "trees_removed"])
    assert out.attrs["trees_outside_stands"] == 0
    # the total harvest is conserved over stands
    assert int(out["trees_removed"].sum()) == 5


def test_trees_without_metrics_or_outside_stands_are_not_dropped():
    cells = _cells()
    before = _trees([1, 2], [[X0 + 160.0, Y0 + 10], [X0 - 30.0, Y0 + 10]], [10.0, 10.0])
    after = _trees([3], [[X0 + 160.2, Y0 + 10]], [11.0])
    matches = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    metrics_before, metrics_after = _metrics_pair()
    # cell D has trees but no metrics in the from epoch and we drop it from "to" as well
    out = compare_stands(
        metrics_before,
        metrics_after.iloc[:3],
        date_from=DATE_FROM,
        date_to=DATE_TO,
        tree_matches=matches,
        cells=cells,
    )
    d = out.set_index("cell_id").loc["D"]
    assert d["presence"] == "trees_only"
    assert d["trees_grown"] == 1 and "no metrics" in d["null_reason"]
    assert d["years"] == pytest.approx(YEARS)
    assert out.attrs["trees_outside_stands"] == 1


def test_tree_change_needs_the_stand_of_each_tree():
    before, after = _metrics_pair()
    matches = match_trees(
        _trees([1], [[0.0, 0.0]], [10.0]),
        _trees([2], [[0.0, 0.1]], [11.0]),
        date_from=DATE_FROM,
        date_to=DATE_TO,
    )
    with pytest.raises(StandgridError, match="cell_id"):
        compare_stands(before, after, date_from=DATE_FROM, date_to=DATE_TO, tree_matches=matches)


def test_metrics_indexed_by_cell_with_string_reasons():
    # the shape enrich writes: integer cell keys as the index "cell", reasons as pd.NA/str
    index = pd.Index([10, 11], name="cell")
    before = pd.DataFrame(
        {
            "n_points": [500, 0],
            "zmean": [12.0, np.nan],
            "null_reason": pd.array([pd.NA, "no points"], dtype="string"),
        },
        index=index,
    )
    after = pd.DataFrame(
        {
            "n_points": [650, 40],
            "zmean": [12.5, 3.0],
            "null_reason": pd.array([pd.NA, pd.NA], dtype="string"),
        },
        index=index,
    )
    out = compare_stands(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    assert out["cell_id"].tolist() == [10, 11]
    assert out["zmean_per_year"].iloc[0] == pytest.approx(0.5 / YEARS)
    assert out["n_points_delta"].tolist() == [150.0, 40.0]
    assert out["null_reason"].tolist() == ["", "from: no points"]
    assert np.isnan(out["zmean_delta"].iloc[1])


def test_no_trees_at_all_gives_zero_tree_change_for_observed_stands():
    empty = _trees([], np.empty((0, 2)), [])
    matches = match_trees(empty, empty, date_from=DATE_FROM, date_to=DATE_TO)
    before, after = _metrics_pair()
    out = compare_stands(
        before, after, date_from=DATE_FROM, date_to=DATE_TO, tree_matches=matches, cells=_cells()
    ).set_index("cell_id")
    assert out.loc["A", "trees_removed"] == 0 and out.loc["C", "trees_new_per_ha"] == 0.0
    assert pd.isna(out.loc["D", "trees_removed"])  # D only observed in "to": unknown
    assert np.isnan(out.loc["A", "tree_height_growth_m"])  # no grown tree: no mean growth
