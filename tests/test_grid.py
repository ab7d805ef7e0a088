"""StandGrid and CellId: half-open cells, canonical ids, keys, levels, serialisation."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import shapely
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from standgrid.crs import CRS
from standgrid.errors import CellIdError, CRSError, GridError
from standgrid.partition import CellId, StandGrid, index_to_key, key_to_index

GRID = StandGrid("EPSG:32632")

coords = st.one_of(
    st.floats(-1e7, 1e7, allow_nan=False, allow_infinity=False),
    st.floats(5.69e6, 5.71e6),  # UTM northings
    st.integers(-500_000, 500_000).map(lambda i: i * 20.0),  # exactly on 20 m edges
    st.integers(-100_000, 100_000).map(lambda i: i * 0.1),  # on edges after rounding
)
indices = st.integers(-(2**31), 2**31 - 1)
grids = st.builds(
    StandGrid,
    crs=st.just("EPSG:32633"),
    cell_size=st.sampled_from([1.0, 2.5, 10.0, 20.0, 0.1, 33.3]),
    origin=st.tuples(st.floats(-1e6, 1e6, allow_nan=False), st.floats(-1e6, 1e6, allow_nan=False)),
)


def contains_half_open(bounds: tuple[float, float, float, float], x: float, y: float) -> bool:
    xmin, ymin, xmax, ymax = bounds
    return xmin <= x < xmax and ymin <= y < ymax


# --- points and cells ---------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(grid=grids, x=coords, y=coords)
def test_every_point_lies_in_exactly_its_cell_half_open(grid: StandGrid, x: float, y: float):
    cell = grid.cell(x, y)
    assert contains_half_open(grid.bounds(cell), x, y)
    for other in cell.neighbours():
        assert not contains_half_open(grid.bounds(other), x, y)


@settings(max_examples=200, deadline=None)
@given(x=coords, y=coords)
def test_default_grid_every_point_in_exactly_one_cell_at_every_level(x: float, y: float):
    for level in range(len(GRID.levels)):
        cell = GRID.cell(x, y, level)
        assert contains_half_open(GRID.bounds(cell), x, y)
        assert sum(contains_half_open(GRID.bounds(n), x, y) for n in cell.neighbours()) == 0
    fine, coarse = GRID.cell(x, y, 0), GRID.cell(x, y, 1)
    assert fine.parent(GRID) == coarse
    assert fine in coarse.children(GRID)


def test_points_on_edges_belong_to_the_upper_cell():
    ix, iy = GRID.cell_index([0.0, 20.0, -20.0, 19.999999999, -1e-12], [0.0, 40.0, -0.0, 0.0, 0.0])
    assert ix.tolist() == [0, 1, -1, 0, -1]
    assert iy.tolist() == [0, 2, 0, 0, 0]
    assert ix.dtype == np.int64 and iy.dtype == np.int64


@pytest.mark.parametrize(("size", "x0"), [(0.1, 0.0), (33.3, 0.0), (0.1, 0.37), (2.5, 123.456)])
def test_floor_is_fixed_up_where_division_rounds_across_an_edge(size: float, x0: float):
    # points on computed edges and one ulp either side: plain floor((x - x0) / s) misplaces
    # ~15 % of these for s = 0.1; the recomputed bounds must hold each point half-open
    grid = StandGrid("EPSG:32633", cell_size=size, origin=(x0, x0), levels=(size,))
    rng = np.random.default_rng(7)
    edges = x0 + rng.integers(-(10**6), 10**6, 20_000).astype(np.float64) * size
    x = np.concatenate([edges, np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf)])
    naive = np.floor((x - x0) / size)
    assert ((x < x0 + naive * size) | (x >= x0 + (naive + 1) * size)).any()  # the hazard exists
    ix, iy = grid.cell_index(x, x)
    assert np.array_equal(ix, iy)
    xmin = x0 + ix.astype(np.float64) * size
    xmax = x0 + (ix + 1).astype(np.float64) * size
    assert ((xmin <= x) & (x < xmax)).all()
    for k in rng.choice(len(x), 300, replace=False).tolist():  # bounds() agrees, scalar path
        assert contains_half_open(grid.bounds(grid.cell(x[k], x[k])), x[k], x[k])


def test_huge_and_negative_coordinates_are_never_clamped():
    ix, iy = GRID.cell_index([1e7, -1e7, 5.7e6 + 0.5], [1e7, -3.0, 5.7e6])
    assert ix.tolist() == [500_000, -500_000, 285_000]
    assert iy.tolist() == [500_000, -1, 285_000]


def test_nan_coordinates_are_rejected():
    with pytest.raises(GridError):
        GRID.cell_index([0.0, np.nan], [0.0, 0.0])


def test_cell_keys_vectorised_match_scalar_cells():
    rng = np.random.default_rng(1)
    x = rng.uniform(-1e4, 1e4, 2000)
    y = rng.uniform(5.7e6, 5.71e6, 2000)
    keys = GRID.cell_keys(x, y)
    assert keys.dtype == np.int64
    expected = [GRID.cell(a, b).key for a, b in zip(x.tolist(), y.tolist(), strict=True)]
    assert keys.tolist() == expected
    ix, iy = key_to_index(keys)
    assert np.array_equal(index_to_key(ix, iy), keys)


@settings(deadline=None)
@given(ix=indices, iy=indices)
def test_key_round_trip_and_order(ix: int, iy: int):
    cell = CellId(20.0, ix, iy)
    assert CellId.from_key(cell.key, 20.0) == cell
    kx, ky = key_to_index(np.array([cell.key]))
    assert (int(kx[0]), int(ky[0])) == (ix, iy)
    assert -(2**63) <= cell.key < 2**63


@settings(deadline=None)
@given(a=st.tuples(indices, indices), b=st.tuples(indices, indices))
def test_key_order_is_cell_order(a: tuple[int, int], b: tuple[int, int]):
    ca, cb = CellId(20.0, *a), CellId(20.0, *b)
    assert (ca < cb) == (ca.key < cb.key)
    assert (ca == cb) == (ca.key == cb.key)


def test_out_of_range_index_is_an_error():
    with pytest.raises(GridError):
        CellId(20.0, 2**31, 0)
    with pytest.raises(GridError):
        GRID.cell_index([20.0 * 2**31], [0.0])


# --- canonical ids ------------------------------------------------------------------------


@settings(deadline=None)
@given(size=st.sampled_from([20.0, 100.0, 2.5, 0.1, 1.0, 33.3]), ix=indices, iy=indices)
def test_format_parse_round_trip(size: float, ix: int, iy: int):
    cell = CellId(size, ix, iy)
    text = str(cell)
    assert CellId.parse(text) == cell
    assert str(CellId.parse(text)) == text
    assert all(c.isalnum() or c in "_-" for c in text)


def test_canonical_text_examples():
    assert str(CellId(20.0, 1234, -567)) == "20m_E1234_N-567"
    assert str(CellId(2.5, 0, 0)) == "2p5m_E0_N0"
    assert GRID.cell(24680.0, -11330.0) == CellId.parse("20m_E1234_N-567")


@pytest.mark.parametrize(
    "text",
    [
        "",
        "20m_E1_N",
        "20m_E01_N2",
        "20m_E-0_N2",
        "20m_E+1_N2",
        "20.0m_E1_N2",
        "20p0m_E1_N2",
        "020m_E1_N2",
        "0m_E1_N2",
        "20m_E1_N2.laz",
        " 20m_E1_N2",
        "20M_E1_N2",
        "20m_e1_n2",
        "20m_E99999999999_N2",
        "1e3m_E1_N2",
        "garbage",
    ],
)
def test_non_canonical_ids_are_rejected_naming_the_text(text: str):
    with pytest.raises(CellIdError) as info:
        CellId.parse(text)
    assert repr(text) in str(info.value)


@settings(deadline=None)
@given(text=st.text(max_size=30))
def test_parse_accepts_only_canonical_text(text: str):
    try:
        cell = CellId.parse(text)
    except CellIdError:
        return
    assert str(cell) == text


# --- levels ---------------------------------------------------------------------------------


@settings(deadline=None)
@given(ix=st.integers(-(10**6), 10**6), iy=st.integers(-(10**6), 10**6))
def test_parent_children_consistency(ix: int, iy: int):
    cell = CellId(20.0, ix, iy)
    parent = cell.parent(GRID)
    assert parent.size == 100.0
    children = parent.children(GRID)
    assert len(children) == 25 and cell in children
    assert all(c.parent(GRID) == parent for c in children)
    pxmin, pymin, pxmax, pymax = GRID.bounds(parent)
    xmin, ymin, xmax, ymax = GRID.bounds(cell)
    assert pxmin <= xmin < xmax <= pxmax and pymin <= ymin < ymax <= pymax
    union = shapely.union_all([GRID.polygon(c) for c in children])
    assert union.equals(GRID.polygon(parent))


def test_parent_by_size_and_errors():
    cell = CellId(20.0, -1, 7)
    assert cell.parent(100.0) == CellId(100.0, -1, 1)
    assert cell.parent(100.0).children(20.0)[0] == CellId(20.0, -5, 5)
    with pytest.raises(GridError):
        cell.parent(30.0)
    with pytest.raises(GridError):
        cell.parent(100.0).parent(GRID)  # coarsest level
    with pytest.raises(GridError):
        cell.children(GRID)  # finest level


def test_neighbours_rings():
    cell = CellId(20.0, 0, 0)
    assert len(cell.neighbours()) == 8
    assert len(cell.neighbours(2)) == 24
    assert cell not in cell.neighbours(2)
    assert CellId(20.0, -1, -1) in cell.neighbours()


def test_cells_in_bounds_cover_a_box():
    cells = GRID.cells_in_bounds(-5.0, 10.0, 40.0, 30.0)
    assert cells == sorted(cells)
    assert {(c.ix, c.iy) for c in cells} == {(i, j) for i in (-1, 0, 1, 2) for j in (0, 1)}
    rng = np.random.default_rng(0)
    for x, y in rng.uniform([-5, 10], [40, 30], (200, 2)):
        assert GRID.cell(x, y) in cells
    assert len(GRID.cells_in_bounds(0.0, 0.0, 99.0, 99.0, level=1)) == 1


def test_polygon_and_bounds():
    cell = CellId.parse("20m_E-3_N285000")
    assert GRID.bounds(cell) == (-60.0, 5_700_000.0, -40.0, 5_700_020.0)
    assert GRID.polygon(cell).area == pytest.approx(400.0)
    with pytest.raises(GridError):
        GRID.bounds(CellId(50.0, 0, 0))


# --- the grid value -------------------------------------------------------------------------


def test_equal_parameters_equal_grids_and_fingerprints():
    a = StandGrid("EPSG:32632", 20.0, (0.0, 0.0), (20.0, 100.0))
    b = StandGrid("epsg:32632", 20, (0, 0))
    assert a == b and hash(a) == hash(b) and a.fingerprint == b.fingerprint
    assert len({a, b}) == 1
    assert a != StandGrid("EPSG:32632", origin=(10.0, 0.0))
    assert a.fingerprint != StandGrid("EPSG:32632", origin=(10.0, 0.0)).fingerprint
    assert a.fingerprint != StandGrid("EPSG:32633").fingerprint
    with pytest.raises(AttributeError):
        a.cell_size = 10.0  # type: ignore[misc]


def test_fingerprint_is_stable_across_processes():
    grid = StandGrid("EPSG:25832", 10.0, (500.5, -0.25), (10.0, 50.0, 200.0))
    code = (
        "from standgrid.partition import StandGrid;"
        "print(StandGrid('EPSG:25832', 10.0, (500.5, -0.25), (10.0, 50.0, 200.0)).fingerprint)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == grid.fingerprint
    assert len(grid.fingerprint) == 64


@settings(deadline=None)
@given(grid=grids)
def test_dict_and_json_round_trip_exactly(grid: StandGrid):
    assert StandGrid.from_dict(grid.to_dict()) == grid
    again = StandGrid.from_json(grid.to_json())
    assert again == grid and again.fingerprint == grid.fingerprint
    assert again.origin == grid.origin  # exact floats, not approximately
    assert json.loads(grid.to_json())["crs"] == "EPSG:32633"


def test_crs_normalisation_and_rejection():
    import pyproj

    wkt = pyproj.CRS.from_epsg(32632).to_wkt(version="WKT2_2019")
    assert StandGrid(wkt).crs == CRS.of("EPSG:32632") and StandGrid(wkt).crs.text == "EPSG:32632"
    assert StandGrid(pyproj.CRS.from_epsg(3067)).crs.text == "EPSG:3067"  # type: ignore[arg-type]
    assert StandGrid(CRS.of(32632)) == StandGrid("EPSG:32632")
    assert StandGrid(wkt).to_dict()["crs"] == "EPSG:32632"  # text only in the definition
    custom = pyproj.CRS.from_proj4(
        "+proj=tmerc +lat_0=0 +lon_0=9.1 +k=1 +x_0=0 +y_0=0 +ellps=GRS80"
    )
    custom_wkt = custom.to_wkt(version="WKT2_2019")
    grid = StandGrid(custom_wkt)
    assert grid.crs.text.startswith("PROJCRS")
    assert grid.crs.pyproj_crs == custom
    assert StandGrid.from_json(grid.to_json()) == grid
    for bad in ["+proj=utm +zone=32 +datum=WGS84", "EPSG:4326", "EPSG:4978", "not a crs"]:
        with pytest.raises(CRSError):
            StandGrid(bad)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"cell_size": 0.0},
        {"cell_size": -20.0},
        {"cell_size": float("nan")},
        {"cell_size": float("inf")},
        {"origin": (float("nan"), 0.0)},
        {"origin": (0.0,)},
        {"levels": (20.0, 90.0)},
        {"levels": (20.0, 20.0)},
        {"levels": (100.0, 20.0)},
        {"levels": (10.0, 100.0)},
        {"levels": (20.0, float("nan"))},
        {"cell_size": 1e-7},
    ],
)
def test_invalid_definitions_raise_grid_error(kwargs):
    with pytest.raises(GridError):
        StandGrid("EPSG:32632", **kwargs)


def test_from_dict_rejects_unknown_or_missing_keys():
    data = GRID.to_dict()
    with pytest.raises(GridError):
        StandGrid.from_dict({**data, "extra": 1})
    with pytest.raises(GridError):
        StandGrid.from_dict({k: v for k, v in data.items() if k != "levels"})
    with pytest.raises(GridError):
        StandGrid.from_json("{not json")


# --- same ground, same ids ------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_two_missions_over_shared_ground_get_identical_ids(seed: int):
    rng = np.random.default_rng(seed)
    # mission A covers [0, 300) x [5.7e6, +300); mission B is shifted and overlaps it
    shift = rng.uniform(50, 250, 2)
    a = rng.uniform([0, 5.7e6], [300, 5.7e6 + 300], (5000, 2))
    b = rng.uniform([0, 5.7e6], [300, 5.7e6 + 300], (5000, 2)) + shift
    grid_a = StandGrid("EPSG:32632")  # built independently per mission
    grid_b = StandGrid.from_json(StandGrid("EPSG:32632").to_json())
    shared = (b[:, 0] < 300) & (b[:, 1] < 5.7e6 + 300)
    assume(shared.sum() > 10)
    pts = b[shared]
    ids_a = [str(c) for c in grid_a.iter_cells(grid_a.cell_keys(pts[:, 0], pts[:, 1]))]
    ids_b = [str(c) for c in grid_b.iter_cells(grid_b.cell_keys(pts[:, 0], pts[:, 1]))]
    assert ids_a == ids_b
    # a cell text from mission B names, in mission A's grid, ground that holds the point
    for x, y in pts[:200].tolist():
        cell = CellId.parse(str(grid_b.cell(x, y)))
        assert contains_half_open(grid_a.bounds(cell), x, y)
    # and mission A's own points in those cells got the very same texts
    keys_a = grid_a.cell_keys(a[:, 0], a[:, 1])
    keys_b = grid_b.cell_keys(pts[:, 0], pts[:, 1])
    common = np.intersect1d(keys_a, keys_b)
    assert len(common) > 0
    for key in common[:20].tolist():
        in_a = a[keys_a == key]
        text = str(grid_a.key_to_cell(key))
        assert {str(grid_b.cell(x, y)) for x, y in in_a.tolist()} == {text}
