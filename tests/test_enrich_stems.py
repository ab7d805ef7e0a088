"""Stems first: leaning stems, small trees under big crowns, snags, stemless crowns, and what
a stand table says when its trees come from canopy tops. Synthetic trees with known truth."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from standgrid.enrichment.stands import NO_TOP_IN_STAND, CoverageRule, StandSample, stand_row
from standgrid.enrichment.trees import segment_trees
from standgrid.features.stems import find_stems

X0, Y0 = 600_000.0, 5_700_000.0


def stem_points(
    rng: np.random.Generator,
    base: tuple[float, float],
    dbh: float,
    height: float,
    *,
    lean_deg: float = 0.0,
    azimuth_deg: float = 0.0,
    top: float | None = None,
    per_m: int = 600,
    noise: float = 0.004,
    seen_deg: float = 360.0,
) -> np.ndarray:
    """Points on a tapered stem (DBH across the axis at 1.3 m, radius 0 at ``height``)
    leaning ``lean_deg`` towards ``azimuth_deg``, seen over ``seen_deg`` of its round, from
    0.2 m up to ``top`` (default: 60 % of the height)."""
    top = 0.6 * height if top is None else top
    n = int(per_m * (top - 0.2))
    s = rng.uniform(0.2, top, n)  # along the axis ~ height for small leans
    radius = dbh / 2 * (height - s) / (height - 1.3) + rng.normal(0, noise, n)
    phi = rng.uniform(0, math.radians(seen_deg), n)
    lean, az = math.radians(lean_deg), math.radians(azimuth_deg)
    axis = np.array([math.sin(lean) * math.cos(az), math.sin(lean) * math.sin(az), math.cos(lean)])
    u = np.cross(axis, [0.0, 0.0, 1.0]) if lean > 0 else np.array([1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    pts = s[:, None] * axis + radius[:, None] * (
        np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v
    )
    return pts + np.array([base[0], base[1], 0.0])


def crown_points(
    rng: np.random.Generator,
    centre: tuple[float, float],
    base: float,
    top: float,
    radius: float,
    n: int,
) -> np.ndarray:
    """A porous ellipsoid crown: points throughout its volume, denser near the surface,
    with its apex."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    r = rng.uniform(0.5, 1.0, n) ** 0.5
    half = (top - base) / 2
    pts = np.column_stack(
        [
            centre[0] + radius * r * u[:, 0],
            centre[1] + radius * r * u[:, 1],
            base + half + half * r * u[:, 2],
        ]
    )
    return np.vstack([pts, [centre[0], centre[1], top]])


def ground_points(rng: np.random.Generator, span: float, n: int = 20_000) -> np.ndarray:
    return np.column_stack(
        [X0 + rng.uniform(-span, span, n), Y0 + rng.uniform(-span, span, n), rng.normal(0, 0.02, n)]
    )


@pytest.mark.parametrize("lean_deg", [0.0, 6.0, 14.0])
def test_a_leaning_stem_gives_its_axis_lean_and_dbh_across_it(lean_deg: float) -> None:
    rng = np.random.default_rng(int(lean_deg))
    dbh, azimuth = 0.32, 40.0
    pts = stem_points(rng, (X0, Y0), dbh, 24.0, lean_deg=lean_deg, azimuth_deg=azimuth, top=6.0)
    found = find_stems(pts, pts[:, 2]).table
    assert len(found) == 1
    stem = found.iloc[0]
    # the axis at 1.3 m height: the base moved along the lean
    along = 1.3 / math.cos(math.radians(lean_deg))
    shift = along * math.sin(math.radians(lean_deg))
    want = (
        X0 + shift * math.cos(math.radians(azimuth)),
        Y0 + shift * math.sin(math.radians(azimuth)),
    )
    assert math.hypot(stem["stem_x"] - want[0], stem["stem_y"] - want[1]) < 0.02
    assert stem["lean_deg"] == pytest.approx(lean_deg, abs=1.0)
    if lean_deg > 3:
        assert stem["lean_azimuth_deg"] == pytest.approx(azimuth, abs=6.0)
    # across the axis at 1.3 m along it (the taper moves it by < 1 mm here)
    assert stem["dbh_m"] == pytest.approx(dbh, abs=0.006)
    assert stem["stem_circles"] >= 8 and stem["stem_high_m"] >= 3.4
    assert 0 < stem["dbh_se_m"] < 0.01


def test_a_small_tree_under_a_big_crown_keeps_its_own_height() -> None:
    """Stems first, crowns grown from them: the understorey tree under the crown is a tree
    of its own (no canopy top of its own) with its own height; the big tree carries the top."""
    rng = np.random.default_rng(11)
    big = (X0, Y0)
    small = (X0 + 2.5, Y0 + 0.5)
    xyz = np.vstack(
        [
            stem_points(rng, big, 0.45, 27.0, top=14.0),
            crown_points(rng, big, 12.0, 27.0, 5.0, 30_000),
            stem_points(rng, small, 0.08, 7.5, top=3.0),
            crown_points(rng, small, 3.0, 7.5, 1.2, 3_000),
            ground_points(rng, 12.0),
        ]
    )
    table = segment_trees(xyz, xyz[:, 2]).table
    assert len(table) == 2
    at_small = table.iloc[int(np.argmin(np.hypot(table["x"] - small[0], table["y"] - small[1])))]
    at_big = table.iloc[int(np.argmin(np.hypot(table["x"] - big[0], table["y"] - big[1])))]
    assert at_small["detected_by"] == "stem" and at_big["detected_by"] == "both"
    assert at_small["height_m"] == pytest.approx(7.5, abs=0.3)
    assert at_big["height_m"] == pytest.approx(27.0, abs=0.05)
    assert at_small["dbh_m"] == pytest.approx(0.08, abs=0.01)
    assert at_big["dbh_m"] == pytest.approx(0.45, abs=0.01)
    # trees stand where their stems are; the big crown's points are the big tree's
    assert math.hypot(at_small["x"] - small[0], at_small["y"] - small[1]) < 0.03
    labels = segment_trees(xyz, xyz[:, 2]).point_tree_ids()
    big_crown = xyz[:, 2] > 12.5
    assert (labels[big_crown] == at_big["tree_id"]).mean() > 0.97


def test_a_snag_and_a_stemless_crown_are_trees() -> None:
    """A dead stem without a crown is a tree of its own height; a crown whose stem was not
    seen is a tree found from its top, without a DBH (and with the reason)."""
    rng = np.random.default_rng(12)
    snag, hidden = (X0, Y0), (X0 + 9.0, Y0)
    xyz = np.vstack(
        [
            stem_points(rng, snag, 0.30, 40.0, top=9.0),  # broken at 9 m
            crown_points(rng, hidden, 9.0, 21.0, 3.0, 15_000),
            ground_points(rng, 14.0),
        ]
    )
    table = segment_trees(xyz, xyz[:, 2]).table.sort_values("x").reset_index(drop=True)
    assert len(table) == 2
    assert table.loc[0, "height_m"] == pytest.approx(9.0, abs=0.2)
    assert table.loc[0, "dbh_m"] == pytest.approx(0.30, abs=0.01)
    assert table.loc[1, "detected_by"] == "top" and np.isnan(table.loc[1, "dbh_m"])
    assert table.loc[1, "height_m"] == pytest.approx(21.0, abs=0.01)
    assert table.loc[1, "dbh_reason"] == "no stem points at 1.3 m near the tree"


def test_two_stems_at_a_metre_are_two_trees_and_a_shrub_ring_is_none() -> None:
    rng = np.random.default_rng(13)
    xyz = np.vstack(
        [
            stem_points(rng, (X0, Y0), 0.20, 20.0, top=8.0),
            stem_points(rng, (X0 + 1.0, Y0), 0.12, 14.0, top=6.0, lean_deg=8.0, azimuth_deg=0.0),
            crown_points(rng, (X0 + 0.5, Y0), 8.0, 20.0, 3.0, 10_000),
            ground_points(rng, 8.0),
        ]
    )
    found = find_stems(xyz, xyz[:, 2]).table.sort_values("stem_x").reset_index(drop=True)
    assert len(found) == 2
    assert found["dbh_m"].to_numpy() == pytest.approx([0.20, 0.12], abs=0.01)
    assert found.loc[1, "lean_deg"] == pytest.approx(8.0, abs=1.5)


def _sample(stand_id: str, heights: np.ndarray, trees: pd.DataFrame) -> StandSample:
    return StandSample(
        stand_id=stand_id,
        level=0,
        cell_size=20.0,
        area_m2=400.0,
        observed_m2=400.0,
        n_points=len(heights),
        heights=heights.astype(np.float32),
        trees=trees,
    )


def test_a_stand_says_what_canopy_tops_miss_and_is_never_zero_under_a_canopy() -> None:
    rng = np.random.default_rng(3)
    canopy = np.r_[rng.uniform(0, 0.4, 4000), rng.uniform(10, 26, 2000)]  # 33 % above 2 m
    tops = pd.DataFrame(
        {"height_m": [22.0, 25.0], "dbh_m": [np.nan, np.nan], "detected_by": ["top", "top"]}
    )
    stems = tops.assign(detected_by=["both", "stem"], dbh_m=[0.3, 0.4])
    rule = CoverageRule()
    row = stand_row(_sample("a", canopy, tops), rule, tops_only=True)
    assert row["n_trees_by_stem"] == 0 and row["stem_detected_share"] == 0.0
    assert "lower bounds" in row["tree_detection_note"]
    row = stand_row(_sample("b", canopy, stems), rule)
    assert row["stem_detected_share"] == 1.0 and row["tree_detection_note"] is None
    # no tree top in it, a canopy over it: unknown where the trees are seen from above only
    empty = tops.iloc[0:0]
    row = stand_row(_sample("c", canopy, empty), rule, tops_only=True)
    assert math.isnan(row["stems_ha"]) and math.isnan(row["basal_area_m2_ha"])
    assert row["null_reason"] == NO_TOP_IN_STAND.format(cover=100 * 2000 / 6000, brk=2.0)
    # a ground robot sees stems: no stem under a crown is no stem
    row = stand_row(_sample("d", canopy, empty), rule, tops_only=False)
    assert row["stems_ha"] == 0.0 and row["basal_area_m2_ha"] == 0.0
    # and an open stand (no canopy) seen from above has no trees
    row = stand_row(_sample("e", canopy[:4000], empty), rule, tops_only=True)
    assert row["stems_ha"] == 0.0
