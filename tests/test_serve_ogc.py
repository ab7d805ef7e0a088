"""standgrid serve: OGC API - Features against a real uvicorn server, read with OWSLib and
httpx, checked against the GeoPackage read independently with pyogrio."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import httpx
import numpy as np
import pyogrio
import pyproj
import pytest
import shapely

from tests.pipeline_fixtures import CRS

CRS84 = "http://www.opengis.net/def/crs/OGC/1.3/CRS84"
UTM = "http://www.opengis.net/def/crs/EPSG/0/32630"


@pytest.fixture(scope="module")
def catalog(enriched_catalog: Path) -> Path:
    return enriched_catalog


@pytest.fixture(scope="module")
def base(enriched_base: str) -> str:
    return enriched_base


def _layers(catalog: Path) -> list[str]:
    return sorted(n for n, _ in pyogrio.list_layers(catalog / "index.gpkg") if n != "layer_styles")


def _frame(catalog: Path, layer: str):  # type: ignore[no-untyped-def]
    return pyogrio.read_dataframe(catalog / "index.gpkg", layer=layer, fid_as_index=True)


def _all_pages(url: str, params: dict[str, str]) -> list[dict]:
    features: list[dict] = []
    next_url: str | None = url
    first = True
    while next_url is not None:
        r = httpx.get(next_url, params=params if first else None, timeout=30)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["numberReturned"] == len(body["features"])
        features.extend(body["features"])
        next_url = next((link["href"] for link in body["links"] if link["rel"] == "next"), None)
        first = False
    return features


def test_owslib_reads_every_collection_as_pyogrio_does(base: str, catalog: Path) -> None:
    from owslib.ogcapi.features import Features

    api = Features(f"{base}/ogc")
    layers = _layers(catalog)
    assert {
        "cells",
        "payloads",
        "trajectories",
        "gnss_fixes",
        "missions",
        "stand_metrics",
        "trees",
        "stand_changes",
        "tree_changes",
    } <= set(layers)
    assert sorted(api.feature_collections()) == layers
    conformance = api.conformance()["conformsTo"]
    assert "http://www.opengis.net/spec/ogcapi-features-2/1.0/conf/crs" in conformance
    to84 = pyproj.Transformer.from_crs(CRS, "OGC:CRS84", always_xy=True)
    for layer in layers:
        frame = _frame(catalog, layer)
        described = api.collection(layer)
        assert described["itemType"] == "feature"
        assert described["crs"] == [CRS84, UTM]
        result = api.collection_items(layer, limit=10_000, crs=UTM)
        assert result["numberMatched"] == result["numberReturned"] == len(frame), layer
        ids = [f["id"] for f in result["features"]]
        assert ids == sorted(frame.index.tolist()), layer
        # every property value as pyogrio reads it (NaN -> null)
        first = result["features"][0]
        row = frame.loc[first["id"]]
        for name, value in first["properties"].items():
            expected = row[name]
            if isinstance(expected, float) and np.isnan(expected):
                assert value is None, (layer, name)
            elif isinstance(expected, float):
                assert value == pytest.approx(expected, rel=1e-12), (layer, name)
            else:
                assert value == expected, (layer, name)
        if "geometry" in frame and frame.geometry.notna().any():
            geom = shapely.geometry.shape(first["geometry"])
            assert shapely.equals_exact(geom, row.geometry, tolerance=1e-9), layer
            one = api.collection_item(layer, str(first["id"]))  # default CRS84, lon/lat
            got = shapely.get_coordinates(shapely.geometry.shape(one["geometry"]))
            xy = shapely.get_coordinates(row.geometry)
            lon, lat = to84.transform(xy[:, 0], xy[:, 1])
            np.testing.assert_allclose(got, np.column_stack([lon, lat]), atol=1e-9)
            assert -2 < got[0, 0] < 0 and 51 < got[0, 1] < 52  # Wytham: lon first
        else:
            assert first["geometry"] is None


def test_paging_returns_every_feature_exactly_once(base: str, catalog: Path) -> None:
    expected = sorted(_frame(catalog, "gnss_fixes").index.tolist())
    assert len(expected) > 250
    features = _all_pages(f"{base}/ogc/collections/gnss_fixes/items", {"limit": "100"})
    ids = [f["id"] for f in features]
    assert len(ids) == len(set(ids)) == len(expected)
    assert sorted(ids) == expected
    second = httpx.get(
        f"{base}/ogc/collections/gnss_fixes/items", params={"limit": "100", "offset": "100"}
    ).json()
    rels = {link["rel"]: link["href"] for link in second["links"]}
    assert "offset=0" in rels["prev"] and "offset=200" in rels["next"]
    assert second["numberMatched"] == len(expected)


def test_bbox_is_answered_from_the_rtree_and_exactly(base: str, catalog: Path) -> None:
    from standgrid.serve import provider

    conn = sqlite3.connect(catalog / "index.gpkg")
    layers = provider.read_layers(conn)
    box = shapely.box(614720.0, 5737130.0, 614745.0, 5737160.0)
    for name in ("payloads", "trees", "cells", "gnss_fixes"):
        statements = provider.bbox_sql(layers[name], provider.Query(area=box), {})
        for sql, params in (statements.edges, statements.inside_count, statements.page([1, 2])):
            plan = " | ".join(r[3] for r in conn.execute(f"EXPLAIN QUERY PLAN {sql}", params))
            assert f"SCAN rtree_{name}_geom VIRTUAL TABLE INDEX" in plan, plan
            assert (
                f"SCAN {name} " not in plan + " "
                and f"SEARCH {name} USING INTEGER PRIMARY KEY" in plan
            ), plan
        frame = _frame(catalog, name)
        truth = sorted(frame.index[frame.geometry.intersects(box)].tolist())
        assert 0 < len(truth) < len(frame)
        got = _all_pages(
            f"{base}/ogc/collections/{name}/items",
            {"bbox": "614720,5737130,614745,5737160", "bbox-crs": UTM, "limit": "7"},
        )
        assert sorted(f["id"] for f in got) == truth, name
    # the same box given in CRS84 (lon/lat): the transformed box, densified
    to84 = pyproj.Transformer.from_crs(CRS, "OGC:CRS84", always_xy=True)
    w, s, e, n = to84.transform_bounds(614720.0, 5737130.0, 614745.0, 5737160.0)
    frame = _frame(catalog, "trees")
    area = shapely.segmentize(shapely.box(w, s, e, n), max(e - w, n - s) / 64)
    back = shapely.transform(
        area,
        lambda c: np.column_stack(
            pyproj.Transformer.from_crs("OGC:CRS84", CRS, always_xy=True).transform(
                c[:, 0], c[:, 1]
            )
        ),
    )
    truth = sorted(frame.index[frame.geometry.intersects(back)].tolist())
    got = _all_pages(f"{base}/ogc/collections/trees/items", {"bbox": f"{w},{s},{e},{n}"})
    assert sorted(f["id"] for f in got) == truth and truth


def test_bbox_pages_are_exact_for_random_boxes(base: str, catalog: Path) -> None:
    """Random boxes in the catalog CRS and in CRS84 (their transformed, densified polygons),
    also zero-width ones, paged 7 at a time: every feature whose geometry meets the box
    exactly once, in fid order, numberMatched the truth (shapely on every feature, no
    R-tree); a box holding a whole layer tests no feature exactly."""
    from standgrid.serve import crs as crs_mod
    from standgrid.serve.provider import GeoPackageProvider, Query, bbox_sql

    index = GeoPackageProvider.open(catalog / "index.gpkg")
    conn, layers = index.connection, index.layers
    rng = np.random.default_rng(11)
    for name in ("trees", "cells", "payloads", "gnss_fixes"):
        frame = _frame(catalog, name)
        xmin, ymin, xmax, ymax = frame.total_bounds
        for k in range(12):
            size = float(rng.choice([0.0, 5.0, 25.0, 60.0]))
            x, y = rng.uniform(xmin - 10, xmax), rng.uniform(ymin - 10, ymax)
            if k % 2:
                area = shapely.box(x, y, x + size, y + size)
            else:
                box84 = crs_mod.bounds_to_crs84((x, y, x + size, y + size), CRS)
                area = crs_mod.bbox_polygon(box84, crs_mod.CRS84, CRS)
            truth = sorted(frame.index[frame.geometry.intersects(area)].tolist())
            got: list[int] = []
            for offset in range(0, len(truth) + 7, 7):
                page = index.items(layers[name], Query(area=area, limit=7, offset=offset))
                assert page.number_matched == len(truth), (name, k)
                got += page.fids
            assert got == truth, (name, k)
        whole = shapely.box(xmin - 1, ymin - 1, xmax + 1, ymax + 1)
        statements = bbox_sql(layers[name], Query(area=whole), {})
        assert conn.execute(*statements.edges).fetchall() == []
        page = index.items(layers[name], Query(area=whole, limit=5))
        assert page.number_matched == len(frame) and page.fids == sorted(frame.index)[:5]
    # the same over HTTP, in CRS84: numberMatched and the pages agree with the truth
    to84 = pyproj.Transformer.from_crs(CRS, "OGC:CRS84", always_xy=True)
    w, s, e, n = to84.transform_bounds(614700.0, 5737100.0, 614760.0, 5737170.0)
    area = crs_mod.bbox_polygon([w, s, e, n], crs_mod.CRS84, CRS)
    frame = _frame(catalog, "trees")
    truth = sorted(frame.index[frame.geometry.intersects(area)].tolist())
    first = httpx.get(
        f"{base}/ogc/collections/trees/items", params={"bbox": f"{w},{s},{e},{n}", "limit": "5"}
    ).json()
    assert first["numberMatched"] == len(truth) > 5
    got = _all_pages(
        f"{base}/ogc/collections/trees/items", {"bbox": f"{w},{s},{e},{n}", "limit": "5"}
    )
    assert [f["id"] for f in got] == truth


def test_datetime_epoch_and_property_filters(base: str, catalog: Path) -> None:
    url = f"{base}/ogc/collections"
    payloads = _frame(catalog, "payloads")
    day = httpx.get(
        f"{url}/payloads/items", params={"datetime": "2024-05-14", "limit": "1000"}
    ).json()
    assert {f["properties"]["mission"] for f in day["features"]} == {
        "2024-05-14-wytham-anymal-coyote"
    }
    assert day["numberMatched"] == int((payloads["epoch"] == "2024").sum())
    # an instant interval inside the 2024 mission: the payloads stamped within it
    stamps = payloads["stamp_sec"] + payloads["stamp_nsec"] * 1e-9
    lo, hi = np.sort(stamps[payloads["epoch"] == "2024"].to_numpy())[[2, 5]]
    import datetime as dt

    text = "/".join(dt.datetime.fromtimestamp(t, dt.UTC).isoformat() for t in (lo - 1e-3, hi))
    got = httpx.get(f"{url}/payloads/items", params={"datetime": text}).json()
    assert got["numberMatched"] == 4
    # cells carry an epoch: datetime selects it by the epoch's date, and epoch= by label
    open_end = httpx.get(f"{url}/cells/items", params={"datetime": "2025-01-01T00:00:00Z/.."})
    cells = _frame(catalog, "cells")
    assert open_end.json()["numberMatched"] == int((cells["epoch"] == "2028").sum())
    by_label = httpx.get(f"{url}/cells/items", params={"epoch": "2028", "limit": "1"}).json()
    assert by_label["numberMatched"] == int((cells["epoch"] == "2028").sum())
    # changes span both epochs: a date between them meets every change
    changes = httpx.get(f"{url}/tree_changes/items", params={"datetime": "2026-06-01"}).json()
    assert changes["numberMatched"] == len(_frame(catalog, "tree_changes"))
    trees = _frame(catalog, "trees")
    tree_id = int(trees["tree_id"].iloc[0])
    same = httpx.get(f"{url}/trees/items", params={"tree_id": str(tree_id)}).json()
    assert same["numberMatched"] == int((trees["tree_id"] == tree_id).sum()) >= 1
    inliers = httpx.get(f"{url}/gnss_fixes/items", params={"inlier": "true"}).json()
    assert inliers["numberMatched"] == int(_frame(catalog, "gnss_fixes")["inlier"].sum())


@pytest.mark.parametrize(
    ("path", "params", "status"),
    [
        ("/ogc/collections/nope/items", {}, 404),
        ("/ogc/collections/cells/items", {"colour": "red"}, 400),
        ("/ogc/collections/cells/items", {"level": "one"}, 400),
        ("/ogc/collections/cells/items", {"bbox": "1,2,3"}, 400),
        ("/ogc/collections/cells/items", {"bbox": "3,2,1,4"}, 400),
        ("/ogc/collections/cells/items", {"limit": "0"}, 400),
        (
            "/ogc/collections/cells/items",
            {"crs": "http://www.opengis.net/def/crs/EPSG/0/2180"},
            400,
        ),
        ("/ogc/collections/cells/items", {"datetime": "yesterday"}, 400),
        ("/ogc/collections/cells/items", {"datetime": "2028-01-01/2024-01-01"}, 400),
        ("/ogc/collections/cells/items/999999", {}, 404),
        ("/ogc/collections/cells/items/abc", {}, 404),
        ("/missions/nope", {}, 404),
        ("/missions/2024-05-14-wytham-anymal-coyote/payloads/by-pose", {"y": "1"}, 400),
        ("/no/such/route", {}, 404),
    ],
)
def test_every_error_is_a_problem_document(
    base: str, path: str, params: dict[str, str], status: int
) -> None:
    r = httpx.get(base + path, params=params)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/problem+json"
    body = r.json()
    assert body["status"] == status and body["title"] and body["detail"]


def test_crs_headers_and_openapi(base: str) -> None:
    from owslib.ogcapi.features import Features

    r = httpx.get(f"{base}/ogc/collections/cells/items", params={"limit": "1"})
    assert r.headers["content-crs"] == f"<{CRS84}>"
    assert r.headers["content-type"] == "application/geo+json"
    r = httpx.get(f"{base}/ogc/collections/cells/items", params={"limit": "1", "crs": UTM})
    assert r.headers["content-crs"] == f"<{UTM}>"
    x, y = r.json()["features"][0]["geometry"]["coordinates"][0][0]
    assert 600_000 < x < 700_000 and 5_700_000 < y < 5_800_000  # easting first
    document = Features(f"{base}/ogc").api()
    assert document["openapi"].startswith("3.0")
    assert "/collections/trees/items" in document["paths"]
    names = {p["name"] for p in document["paths"]["/collections/trees/items"]["get"]["parameters"]}
    assert {"bbox", "bbox-crs", "crs", "datetime", "limit", "offset", "tree_id"} <= names
