"""The CRS value and resolve_crs: EPSG, WKT2, 'auto' UTM zones, refusals, canonical text,
hashing and pickling, cached transformers, real ALS header CRSs."""

from __future__ import annotations

import pyproj
import pytest
from pyproj.exceptions import CRSError as PyprojCRSError

from standgrid.crs import CRS
from standgrid.errors import CRSError
from standgrid.georeference import resolve_crs
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
    assert crs.epsg == code
    assert crs.text == f"EPSG:{code}"
    aou = crs.pyproj_crs.area_of_use
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
    crs = resolve_crs(spec)
    assert crs == CRS.of(32630) and crs.text == "EPSG:32630"
    assert crs.pyproj_crs == pyproj.CRS.from_epsg(32630)


def test_wkt_and_crs_objects_resolve() -> None:
    utm = pyproj.CRS.from_epsg(25832)
    assert resolve_crs(utm.to_wkt("WKT2_2019")).pyproj_crs == utm
    assert resolve_crs(utm.to_wkt("WKT1_GDAL")).epsg == 25832
    assert resolve_crs(utm).pyproj_crs is utm
    value = CRS.of(utm)
    assert CRS.of(value) is value and value.wkt2 == utm.to_wkt("WKT2_2019")


def test_a_crs_is_a_hashable_immutable_value() -> None:
    import dataclasses
    import pickle

    a, b = CRS.of("EPSG:32630"), CRS.of(32630)
    assert a == b and hash(a) == hash(b) and len({a, b, CRS.of(32631)}) == 2
    assert a != "EPSG:32630" and str(a) == "EPSG:32630"  # text only where it is written
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.text = "EPSG:32631"  # type: ignore[misc]
    back = pickle.loads(pickle.dumps(a))
    assert back == a and back.pyproj_crs == a.pyproj_crs
    assert CRS.of(4326).is_geographic and CRS.of(4326).northing_first
    assert not CRS.of(32630).northing_first and CRS.of(32630).is_projected
    assert CRS.of("OGC:CRS84").equivalent(CRS.of("OGC:CRS84").wkt2)


def test_transformers_are_always_xy_and_cached() -> None:
    utm = CRS.of(32630)
    to_utm = CRS.of(4326).transformer_to(utm)
    assert CRS.of("EPSG:4326").transformer_to("EPSG:32630") is to_utm
    x, y = to_utm.transform(-3.0, 0.0)  # lon, lat: the zone's central meridian, the equator
    assert x == pytest.approx(500_000.0) and y == pytest.approx(0.0, abs=1e-6)


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


def test_text_falls_back_to_wkt2_and_round_trips() -> None:
    # A custom transverse Mercator (no EPSG code) built from parameters, not a PROJ string.
    conversion = pyproj.crs.coordinate_operation.TransverseMercatorConversion(
        latitude_natural_origin=0.0,
        longitude_natural_origin=-1.3,
        false_easting=100000.0,
        false_northing=-5000000.0,
        scale_factor_natural_origin=1.0,
    )
    custom = pyproj.crs.ProjectedCRS(conversion=conversion, geodetic_crs=pyproj.CRS.from_epsg(4326))
    text = CRS.of(custom).text
    assert text.startswith("PROJCRS[")
    assert resolve_crs(text).pyproj_crs == custom
    assert resolve_crs(text).text == text and resolve_crs(text) == CRS.of(custom)


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
    assert crs.epsg == code
    assert crs.text == f"EPSG:{code}"
