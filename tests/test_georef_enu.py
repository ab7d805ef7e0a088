"""Exact ENU conversions against closed-form ellipsoid formulas and PROJ's topocentric pipeline."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest
from pyproj.exceptions import ProjError

from standgrid.errors import GeoreferenceError
from standgrid.georeference import ecef_to_lla, enu_rotation, enu_to_lla, lla_to_ecef, lla_to_enu

WYTHAM = (51.7735, -1.337, 120.0)
A = 6378137.0
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)


def closed_form_ecef(lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    phi, lam = np.radians(lat), np.radians(lon)
    n = A / np.sqrt(1.0 - E2 * np.sin(phi) ** 2)
    return np.stack(
        [
            (n + h) * np.cos(phi) * np.cos(lam),
            (n + h) * np.cos(phi) * np.sin(lam),
            (n * (1.0 - E2) + h) * np.sin(phi),
        ],
        axis=-1,
    )


def topocentric(ref: tuple[float, float, float]) -> pyproj.Transformer:
    """PROJ's own geodetic -> ENU operation (an independent implementation), input lat, lon, h."""
    lat0, lon0, h0 = ref
    return pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +proj=axisswap +order=2,1 +step +proj=unitconvert +xy_in=deg "
        "+xy_out=rad +step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={h0!r}"
    )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(42)


def test_lla_to_ecef_matches_closed_form(rng: np.random.Generator) -> None:
    lat = rng.uniform(-89.9, 89.9, 500)
    lon = rng.uniform(-180, 180, 500)
    h = rng.uniform(-100, 5000, 500)
    x, y, z = lla_to_ecef(lat, lon, h)
    assert x.dtype == np.float64
    np.testing.assert_allclose(
        np.stack([x, y, z], -1), closed_form_ecef(lat, lon, h), rtol=0, atol=1e-6
    )
    lat2, lon2, h2 = ecef_to_lla(x, y, z)
    np.testing.assert_allclose(lat2, lat, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lon2, lon, rtol=0, atol=1e-10)
    np.testing.assert_allclose(h2, h, rtol=0, atol=1e-6)


def test_enu_rotation_axes() -> None:
    r = enu_rotation(0.0, 0.0)
    np.testing.assert_allclose(r, [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-15)
    r = enu_rotation(90.0, 0.0)  # north pole: up is +z
    np.testing.assert_allclose(r[2], [0, 0, 1], atol=1e-15)
    r = enu_rotation(*WYTHAM[:2])
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-15)
    # Up is the ellipsoid normal: moving along it changes height only.
    ref_ecef = closed_form_ecef(np.array(WYTHAM[0]), np.array(WYTHAM[1]), np.array(WYTHAM[2]))
    lat, lon, h = ecef_to_lla(*(ref_ecef + 250.0 * r[2]))
    assert float(lat) == pytest.approx(WYTHAM[0], abs=1e-11)
    assert float(lon) == pytest.approx(WYTHAM[1], abs=1e-11)
    assert float(h) == pytest.approx(WYTHAM[2] + 250.0, abs=1e-7)


@pytest.mark.parametrize(
    "ref", [WYTHAM, (-33.9, 151.2, 40.0), (78.2, 15.6, 0.0), (0.0, 179.99, -20.0)]
)
def test_lla_to_enu_matches_proj_topocentric(
    ref: tuple[float, float, float], rng: np.random.Generator
) -> None:
    lat = ref[0] + rng.uniform(-0.05, 0.05, 300)
    lon = ref[1] + rng.uniform(-0.05, 0.05, 300)
    h = ref[2] + rng.uniform(-50, 300, 300)
    e, n, u = lla_to_enu(lat, lon, h, ref)
    te, tn, tu = topocentric(ref).transform(lat, lon, h)
    np.testing.assert_allclose(e, te, rtol=0, atol=1e-6)
    np.testing.assert_allclose(n, tn, rtol=0, atol=1e-6)
    np.testing.assert_allclose(u, tu, rtol=0, atol=1e-6)


def test_round_trip_over_ten_kilometres(rng: np.random.Generator) -> None:
    enu = rng.uniform(-10_000, 10_000, (1000, 3))
    enu[:, 2] *= 0.05
    lat, lon, h = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], WYTHAM)
    e, n, u = lla_to_enu(lat, lon, h, WYTHAM)
    np.testing.assert_allclose(np.stack([e, n, u], -1), enu, rtol=0, atol=1e-6)


def test_reference_is_origin_and_shapes_are_kept() -> None:
    e, n, u = lla_to_enu(*WYTHAM, WYTHAM)
    assert e.shape == () and abs(float(e)) < 1e-8 and abs(float(n)) < 1e-8 and abs(float(u)) < 1e-8
    lat, _, _ = enu_to_lla(np.zeros((2, 3)), 0.0, 0.0, WYTHAM)
    assert lat.shape == (2, 3)
    np.testing.assert_allclose(lat, WYTHAM[0], atol=1e-12)
    # 111.2 km of northing is about one degree of latitude at 51.8 N.
    lat1, _, _ = enu_to_lla(0.0, 111_257.0, 0.0, WYTHAM)
    assert float(lat1) - WYTHAM[0] == pytest.approx(1.0, abs=2e-3)


def test_invalid_latitude_is_a_typed_chained_error() -> None:
    with pytest.raises(GeoreferenceError) as info:
        lla_to_ecef(np.array([95.0]), np.array([0.0]), np.array([0.0]))
    assert isinstance(info.value.__cause__, ProjError)
