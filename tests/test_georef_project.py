"""MapProjector: exact vs. an independent pyproj chain, fast vs. exact, inverses, real CRSs."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from standgrid.errors import GeoreferenceError
from standgrid.geometry import pose_matrix
from standgrid.georeference import MapProjector, enu_to_lla, fit_from_pose_graph, projected_pose_xy
from standgrid.georeference.fit import GeoreferenceFit
from standgrid.mission.posegraph import PoseGraph
from tests.conftest import real_file

WYTHAM = (51.7735, -1.337, 120.0)


def anchored_fit(
    ref: tuple[float, float, float] = WYTHAM, yaw: float = 0.8, rp: float = 0.01
) -> GeoreferenceFit:
    T_map_enu = pose_matrix(
        [35.0, -120.0, 4.0], Rotation.from_euler("xyz", [rp, -rp, yaw]).as_quat()
    )
    fit = fit_from_pose_graph(PoseGraph(vertices={}, gnss_lla_ref=ref, gnss_lla_to_map=T_map_enu))
    assert fit is not None
    return fit


def independent_utm(fit: GeoreferenceFit, xyz_map: np.ndarray, crs: str) -> np.ndarray:
    """map -> ENU by numpy, ENU -> geodetic, then pyproj's EPSG:4979 -> CRS operation."""
    enu = xyz_map @ fit.T_enu_map[:3, :3].T + fit.T_enu_map[:3, 3]
    lat, lon, h = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], fit.lla_ref)
    tr = pyproj.Transformer.from_crs("EPSG:4979", crs, always_xy=True)
    x, y, z = tr.transform(lon, lat, h, errcheck=True)
    return np.stack([x, y, z], -1)


@pytest.fixture(scope="module")
def projector() -> MapProjector:
    return MapProjector(anchored_fit(), "auto")


def test_auto_crs_and_exact_matches_independent_chain(projector: MapProjector) -> None:
    assert projector.crs.text == "EPSG:32630"
    pts = np.random.default_rng(0).uniform(-3000, 3000, (2000, 3)) * [1, 1, 0.02]
    out = projector.exact(pts)
    assert out.dtype == np.float64 and out.shape == (2000, 3)
    np.testing.assert_allclose(
        out, independent_utm(projector.fit, pts, "EPSG:32630"), rtol=0, atol=1e-6
    )


def test_reference_point_lands_on_its_utm_coordinates(projector: MapProjector) -> None:
    # The map point at the ENU origin is the reference point itself: compare with a plain 2-D
    # WGS 84 -> UTM 30N transform of the reference coordinates (height is ellipsoidal).
    at_ref = projector.fit.T_map_enu[:3, 3][None, :]
    x, y = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32630", always_xy=True).transform(
        WYTHAM[1], WYTHAM[0]
    )
    np.testing.assert_allclose(projector.exact(at_ref)[0], [x, y, WYTHAM[2]], rtol=0, atol=1e-6)
    assert 614_000 < x < 616_000 and 5_736_000 < y < 5_738_000


def test_inverse_and_lla(projector: MapProjector) -> None:
    pts = np.random.default_rng(1).uniform(-5000, 5000, (1000, 3)) * [1, 1, 0.05]
    crs_xyz = projector.exact(pts)
    np.testing.assert_allclose(projector.to_map(crs_xyz), pts, rtol=0, atol=1e-6)
    lla = projector.to_lla(pts)
    enu = projector.fit.map_to_enu(pts)
    lat, lon, h = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], WYTHAM)
    np.testing.assert_allclose(lla[:, :2], np.stack([lat, lon], -1), rtol=0, atol=1e-11)
    np.testing.assert_allclose(lla[:, 2], h, rtol=0, atol=1e-6)
    # The vertical output is the WGS 84 ellipsoidal height.
    np.testing.assert_allclose(crs_xyz[:, 2], h, rtol=0, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    size=st.floats(0.5, 60.0),
    height=st.floats(0.0, 40.0),
    offset_x=st.floats(-4000.0, 4000.0),
    offset_y=st.floats(-4000.0, 4000.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_fast_is_within_a_millimetre_of_exact(
    projector: MapProjector, size: float, height: float, offset_x: float, offset_y: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.5, 0.5, (3000, 3)) * [size, size, height] + [offset_x, offset_y, 10.0]
    assert np.abs(projector.fast(pts) - projector.exact(pts)).max() <= 1e-3


def test_fast_uses_the_affine_for_payload_chunks_and_falls_back_for_large_ones() -> None:
    proj = MapProjector(anchored_fit(), "EPSG:32630")
    rng = np.random.default_rng(2)
    chunk = rng.uniform(-20, 20, (20_000, 3)) + np.array([800.0, -300.0, 0.0])
    fast = proj.fast(chunk)
    assert (proj.fast_chunks, proj.fallback_chunks) == (1, 0)
    assert np.abs(fast - proj.exact(chunk)).max() < 1e-4
    assert proj.linearise(chunk) is not None
    big = rng.uniform(-250, 250, (20_000, 3)) * [1, 1, 0.1]
    assert proj.linearise(big) is None
    np.testing.assert_array_equal(proj.fast(big), proj.exact(big))
    assert proj.fallback_chunks == 1
    tiny = chunk[:10]
    np.testing.assert_array_equal(proj.fast(tiny), proj.exact(tiny))
    flat = chunk.copy()
    flat[:, 2] = 3.0  # degenerate bounding box (zero height): still exact to < 1 mm
    assert np.abs(proj.fast(flat) - proj.exact(flat)).max() < 1e-3


def test_projected_pose_xy_accepts_poses_and_positions(projector: MapProjector) -> None:
    positions = np.random.default_rng(3).uniform(-100, 100, (5, 3))
    poses = pose_matrix(positions, np.tile([0.0, 0.0, 0.0, 1.0], (5, 1)))
    xy = projected_pose_xy(projector, poses)
    assert xy.shape == (5, 2)
    np.testing.assert_array_equal(xy, projected_pose_xy(projector, positions))
    np.testing.assert_array_equal(xy, projector.exact(positions)[:, :2])
    np.testing.assert_array_equal(projected_pose_xy(projector, poses[0]), xy[:1])


def test_bad_inputs(projector: MapProjector) -> None:
    with pytest.raises(GeoreferenceError, match=r"\(N, 3\)"):
        projector.exact(np.zeros((4, 2)))
    assert projector.exact(np.zeros((0, 3))).shape == (0, 3)


def test_real_als_crs_other_datum_round_trip() -> None:
    laspy = pytest.importorskip("laspy")
    with laspy.open(real_file("als/lasR_bcts/bcts_1.laz")) as reader:
        header = reader.header
        crs = header.parse_crs()
        centre = 0.5 * (np.asarray(header.mins) + np.asarray(header.maxs))
    # Put the ENU origin at the tile centre (via the same EPSG:3005 <-> WGS 84 operation).
    to_geo = pyproj.Transformer.from_crs(crs, "EPSG:4979", always_xy=True)
    lon, lat, h = to_geo.transform(centre[0], centre[1], centre[2], errcheck=True)
    fit = anchored_fit((lat, lon, h), rp=0.0)
    proj = MapProjector(fit, crs)
    assert proj.crs.text == "EPSG:3005"
    at_ref = fit.T_map_enu[:3, 3][None, :]
    np.testing.assert_allclose(proj.exact(at_ref)[0], centre, rtol=0, atol=1e-6)
    pts = np.random.default_rng(4).uniform(-500, 500, (500, 3)) * [1, 1, 0.1]
    out = proj.exact(pts)
    np.testing.assert_allclose(out, independent_utm(fit, pts, "EPSG:3005"), rtol=0, atol=1e-6)
    np.testing.assert_allclose(proj.to_map(out), pts, rtol=0, atol=1e-6)
    # The projected tile corners fall inside the real file's extent where the map is there.
    assert np.all(np.abs(out[:, :2] - centre[:2]) < 800)


def test_fast_into_the_points_themselves_gives_the_same_values() -> None:
    """``out=`` (the input itself, block after block of rows) changes nothing in the result,
    with and without a pose, across block boundaries."""
    proj = MapProjector(anchored_fit(), "EPSG:32630")
    rng = np.random.default_rng(3)
    pose = pose_matrix([12.0, -4.0, 1.5], Rotation.from_euler("z", 0.3).as_quat())
    for n in (64, 8191, 8192, 20_001):
        base = rng.uniform(-20, 20, (n, 3)) + np.array([800.0, -300.0, 0.0])
        for given_pose in (None, pose):
            expected = proj.fast(base, pose=given_pose)
            points = base.copy()
            result = proj.fast(points, pose=given_pose, out=points)
            assert result is points
            np.testing.assert_array_equal(result, expected)
            in_map = base if given_pose is None else base @ pose[:3, :3].T + pose[:3, 3]
            assert np.abs(expected - proj.exact(in_map)).max() < 1e-3
