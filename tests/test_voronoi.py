"""VoronoiPartition: nearest-site assignment, deterministic ids and ties, clipped polygons."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from standgrid.errors import GridError
from standgrid.partition import (
    VoronoiPartition,
    coverage_from_points,
    coverage_from_trajectory,
    site_id,
)
from standgrid.stamps import Stamp

MISSION = "2024-05-01-wytham-anymal"


def make_partition(seed: int = 0, n: int = 40) -> tuple[VoronoiPartition, np.ndarray]:
    rng = np.random.default_rng(seed)
    xy = rng.uniform([500_000, 5_700_000], [500_400, 5_700_300], (n, 2))
    stamps = [Stamp(1_700_000_000 + 7 * i, (i * 123_456_789) % 10**9) for i in range(n)]
    part = VoronoiPartition.from_payloads(MISSION, stamps, xy, coverage_from_points(xy, 25.0))
    return part, xy


def test_site_ids_come_from_the_payload():
    assert site_id(MISSION, Stamp(1583840261, 39995392)) == f"V_{MISSION}_1583840261_039995392"


def test_point_in_coverage_belongs_to_exactly_the_polygon_of_its_nearest_site():
    part, _ = make_partition()
    polygons = part.polygons()
    assert set(polygons) == set(part.ids)
    rng = np.random.default_rng(1)
    q = rng.uniform([499_970, 5_699_970], [500_430, 5_700_330], (4000, 2))
    inside = shapely.contains_xy(part.coverage, q[:, 0], q[:, 1])
    q = q[inside]
    assigned = part.assign(q[:, 0], q[:, 1])
    brute = np.argmin(((q[:, None, :] - part.xy[None, :, :]) ** 2).sum(axis=2), axis=1)
    assert np.array_equal(assigned, brute)
    polys = [polygons[i] for i in part.ids]
    boundaries = shapely.union_all([p.boundary for p in polys])
    away = shapely.distance(boundaries, shapely.points(q)) > 1e-6
    member = np.column_stack([shapely.contains_xy(p, q[:, 0], q[:, 1]) for p in polys])
    assert (member[away].sum(axis=1) == 1).all()
    assert np.array_equal(np.argmax(member[away], axis=1), assigned[away])
    # the polygons tile the coverage
    assert shapely.union_all(polys).symmetric_difference(part.coverage).area < 1e-6
    assert sum(p.area for p in polys) == pytest.approx(part.coverage.area, rel=1e-9)


def test_each_polygon_contains_its_own_site():
    part, _ = make_partition(3)
    for site, poly in part.polygons().items():
        x, y = part.xy[part.key_of(site)]
        assert shapely.contains_xy(poly, x, y)


def test_indices_follow_site_ids_not_input_order():
    part, xy = make_partition(5, n=25)
    rng = np.random.default_rng(9)
    perm = rng.permutation(len(xy))
    ids = [
        site_id(MISSION, Stamp(1_700_000_000 + 7 * i, (i * 123_456_789) % 10**9)) for i in range(25)
    ]
    again = VoronoiPartition(xy[perm], [ids[i] for i in perm], part.coverage)
    assert again.ids == part.ids == tuple(sorted(ids))
    assert np.array_equal(again.xy, part.xy)
    q = rng.uniform([500_000, 5_700_000], [500_400, 5_700_300], (500, 2))
    assert np.array_equal(again.assign(q[:, 0], q[:, 1]), part.assign(q[:, 0], q[:, 1]))
    assert {k: v.wkb for k, v in again.polygons().items()} == {
        k: v.wkb for k, v in part.polygons().items()
    }
    assert part.keys.tolist() == list(range(25))


def test_ties_go_to_the_lower_site_id():
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    ids = ["V_m_4_000000000", "V_m_3_000000000", "V_m_2_000000000", "V_m_1_000000000"]
    part = VoronoiPartition(xy, ids, shapely.box(-5, -5, 15, 15))
    # the centre is equidistant from all four; the edge midpoints from two
    got = part.assign([5.0, 5.0, 0.0, 10.0], [5.0, 0.0, 5.0, 5.0])
    names = [part.ids[i] for i in got]
    assert names == ["V_m_1_000000000", "V_m_3_000000000", "V_m_2_000000000", "V_m_1_000000000"]


def test_duplicate_positions_give_the_cell_to_the_lower_id():
    xy = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0]])
    part = VoronoiPartition(xy, ["V_b", "V_a", "V_c"], shapely.box(-5, -5, 15, 5))
    polys = part.polygons()
    assert polys["V_b"].is_empty
    assert polys["V_a"].area == pytest.approx(10 * 10)
    assert part.ids[int(part.assign([1.0], [0.0])[0])] == "V_a"


def test_single_site_gets_the_whole_coverage():
    cov = coverage_from_trajectory(np.array([[0.0, 0.0]]), 5.0)
    part = VoronoiPartition(np.array([[0.0, 0.0]]), ["V_only"], cov)
    assert part.polygons()["V_only"].equals(cov)
    assert part.assign([100.0, -3.0], [0.0, 1.0]).tolist() == [0, 0]


def test_collinear_sites_along_a_trajectory():
    xy = np.column_stack([np.arange(0.0, 200.0, 20.0), np.zeros(10)])
    cov = coverage_from_trajectory(xy, 15.0)
    assert cov.area == pytest.approx(180 * 30 + np.pi * 15**2, rel=1e-2)
    part = VoronoiPartition(xy, [f"V_m_{i:03d}_000000000" for i in range(10)], cov)
    polys = part.polygons()
    assert polys["V_m_000_000000000"].bounds[2] == pytest.approx(10.0)
    assert polys["V_m_005_000000000"].bounds[0::2] == pytest.approx((90.0, 110.0))
    assert sum(p.area for p in polys.values()) == pytest.approx(cov.area)


def test_invalid_inputs():
    cov = shapely.box(0, 0, 1, 1)
    with pytest.raises(GridError):
        VoronoiPartition(np.array([[0.0, 0.0], [1.0, 1.0]]), ["V_a", "V_a"], cov)
    with pytest.raises(GridError):
        VoronoiPartition(np.zeros((2, 3)), ["V_a", "V_b"], cov)
    with pytest.raises(GridError):
        VoronoiPartition(np.array([[0.0, np.nan]]), ["V_a"], cov)
    with pytest.raises(GridError):
        VoronoiPartition(np.zeros((1, 2)), ["V_a"], shapely.Polygon())
    with pytest.raises(GridError):
        coverage_from_points(np.zeros((1, 2)), 0.0)
    part = VoronoiPartition(np.zeros((1, 2)), ["V_a"], cov)
    with pytest.raises(GridError):
        part.key_of("V_missing")
