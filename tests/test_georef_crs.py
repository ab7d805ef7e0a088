"""resolve_crs / crs_to_text: EPSG, WKT2, 'auto' UTM zones, refusals, real ALS header CRSs."""

from __future__ import annotations

import pyproj
import pytest
from pyproj.exceptions import CRSError as PyprojCRSError

from standgrid.errors import CRSError
from standgrid.georeference import crs_to_text, resolve_crs
from standgrid.georeference.crs import standard_utm_zone
from tests.conftest import real_file


@pytest.mark.parametrize(
    ("lon", "lat", "code"),
    [
        (-1.337, 51.7735, 32630),  # Wytham Woods
        (-81.0, 30.0, 32617),
        (-81.0, -30.0, 32717),  # southern hemisphere
        (151.2, -33.9, 32756),  # Sydney
        (8.6, 47.7, 32632),  # Stein am Rhein
        (5.5, 60.5, 32632),  # Norway exception (standard zone would be 31)
        (15.0, 78.0, 32633),  # Svalbard exception
        (179.9, 10.0, 32660),
    ],
)
def test_auto_picks_the_utm_zone(lon: float, lat: float, code: int) -> None:
    crs = resolve_crs("auto", lon=lon, lat=lat)
    assert crs.to_epsg() == code
    assert crs_to_text(crs) == f"EPSG:{code}"
    aou = crs.area_of_use
    exception_zone = (lon, lat) in {(5.5, 60.5), (15.0, 78.0)}
    assert aou is not None
    assert exception_zone or aou.west - 1e-9 <= lon <= aou.east + 1e-9


def test_standard_zone_formula() -> None:
    assert standard_utm_zone(-180.0, 0.0) == 1
    assert standard_utm_zone(-1.337, 51.7) == 30
    assert standard_utm_zone(179.99, 0.0) == 60
    assert standard_utm_zone(5.5, 50.0) == 31


@pytest.mark.parametrize("spec", [32630, "EPSG:32630", "epsg:32630", " EPSG:32630 "])
def test_codes_resolve(spec: int | str) -> None:
    assert resolve_crs(spec) == pyproj.CRS.from_epsg(32630)


def test_wkt_and_crs_objects_resolve() -> None:
    utm = pyproj.CRS.from_epsg(25832)
    assert resolve_crs(utm.to_wkt("WKT2_2019")) == utm
    assert resolve_crs(utm.to_wkt("WKT1_GDAL")).to_epsg() == 25832
    assert resolve_crs(utm) is utm


@pytest.mark.parametrize(
    "spec", [4326, "EPSG:4326", "EPSG:4979", "EPSG:4978", pyproj.CRS.from_epsg(4258)]
)
def test_non_projected_refused(spec: int | str | pyproj.CRS) -> None:
    with pytest.raises(CRSError, match="refused"):
        resolve_crs(spec)


def test_compound_refused() -> None:
    with pytest.raises(CRSError, match="compound"):
        resolve_crs("EPSG:32630+5773")


@pytest.mark.parametrize("spec", [999999, "EPSG:999999", "not a crs at all"])
def test_unknown_refused_and_chained(spec: int | str) -> None:
    with pytest.raises(CRSError) as info:
        resolve_crs(spec)
    assert isinstance(info.value.__cause__, PyprojCRSError)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    "spec", ["+proj=utm +zone=30 +datum=WGS84", "proj=utm zone=30", "+init=epsg:32630"]
)
def test_proj_strings_refused(spec: str) -> None:
    with pytest.raises(CRSError, match=r"EPSG code .* WKT2"):
        resolve_crs(spec)


@pytest.mark.parametrize("bad", [True, 3.5, None, ""])
def test_nonsense_refused(bad: object) -> None:
    with pytest.raises(CRSError):
        resolve_crs(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("lon", "lat"), [(None, 51.0), (-1.0, None), (float("nan"), 51.0), (10.0, 86.0)]
)
def test_auto_needs_a_position_inside_utm(lon: float | None, lat: float | None) -> None:
    with pytest.raises(CRSError, match="auto"):
        resolve_crs("auto", lon=lon, lat=lat)


def test_crs_to_text_falls_back_to_wkt2_and_round_trips() -> None:
    # A custom transverse Mercator (no EPSG code) built from parameters, not a PROJ string.
    conversion = pyproj.crs.coordinate_operation.TransverseMercatorConversion(
        latitude_natural_origin=0.0,
        longitude_natural_origin=-1.3,
        false_easting=100000.0,
        false_northing=-5000000.0,
        scale_factor_natural_origin=1.0,
    )
    custom = pyproj.crs.ProjectedCRS(conversion=conversion, geodetic_crs=pyproj.CRS.from_epsg(4326))
    text = crs_to_text(custom)
    assert text.startswith("PROJCRS[")
    assert resolve_crs(text) == custom
    assert crs_to_text(resolve_crs(text)) == text


@pytest.mark.parametrize(
    ("relative", "code"),
    [
        ("als/lasR_bcts/bcts_1.laz", 3005),
        ("als/lidR/MixedConifer.laz", 26912),
        ("als/las_chablais3.laz", 2154),
        ("als/pyfor/test.laz", 32617),
    ],
)
def test_real_als_header_crs(relative: str, code: int) -> None:
    laspy = pytest.importorskip("laspy")
    with laspy.open(real_file(relative)) as reader:
        header_crs = reader.header.parse_crs()
    assert header_crs is not None
    crs = resolve_crs(header_crs)
    assert crs.to_epsg() == code
    assert crs_to_text(crs) == f"EPSG:{code}"
