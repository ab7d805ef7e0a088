"""The catalog's static STAC catalog (``stac/``): written by every commit, valid against the
core STAC schemas and the pointcloud, projection and raster extension schemas (offline,
:mod:`tests.stac_schemas`), true to the tiles and rasters it describes, the same bytes when
built again, and walked over HTTP by pystac-client against a real uvicorn server."""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import laspy
import pystac
import pytest
import rasterio
from pystac.validation import JsonSchemaSTACValidator, validate_dict

from standgrid.catalog import Catalog
from standgrid.catalog.stac import STAC_ROOT, stac_documents, stac_files
from standgrid.catalog.transaction import Transaction
from standgrid.crs import CRS
from tests.pipeline_fixtures import copy_catalog, enriched_pair, tiled_grid25


@pytest.fixture(scope="module")
def catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return enriched_pair(tmp_path_factory).path


@pytest.fixture
def offline(monkeypatch: pytest.MonkeyPatch) -> None:
    """pystac fetches schemas with urllib: any attempt fails the test."""

    def refuse(url: Any, *args: Any, **kwargs: Any) -> Any:
        raise AssertionError(f"validation went to the network: {getattr(url, 'full_url', url)}")

    monkeypatch.setattr(urllib.request, "urlopen", refuse)


def _documents(root: Path) -> dict[str, dict[str, Any]]:
    return {rel: json.loads((root / rel).read_text("utf-8")) for rel in sorted(stac_files(root))}


def _items(root: Path, collection: str) -> list[dict[str, Any]]:
    docs = _documents(root)
    prefix = f"stac/{collection}/"
    return [d for rel, d in docs.items() if rel.startswith(prefix) and d["type"] == "Feature"]


def _target(root: Path, rel: str, href: str) -> Path:
    """Where a relative href in the document ``rel`` points, as a catalog path."""
    return (root / rel).parent.joinpath(href).resolve()


# --- validation ------------------------------------------------------------------------------


def test_stac_core_validates_offline(catalog: Path, offline: None) -> None:
    validator = JsonSchemaSTACValidator()  # pystac's bundled core schemas only
    docs = _documents(catalog)
    kinds = {d["type"] for d in docs.values()}
    assert kinds == {"Catalog", "Collection", "Feature"}
    for rel, doc in docs.items():
        validate_dict(doc, extensions=[], validator=validator, href=rel)
    broken = dict(docs[STAC_ROOT])
    del broken["description"]
    with pytest.raises(pystac.errors.STACValidationError):
        validate_dict(broken, extensions=[], validator=validator)


def test_stac_extensions_validate_offline(catalog: Path, offline: None) -> None:
    from tests.stac_schemas import extension_schemas, required_uris

    try:
        schemas = extension_schemas()
    except RuntimeError as exc:  # no PyPI and no cache: say so, do not pretend
        pytest.skip(f"extension schemas unavailable offline: {exc}")
    validator = JsonSchemaSTACValidator()
    validator.schema_cache.update(schemas)
    used: set[str] = set()
    for rel, doc in _documents(catalog).items():
        used.update(doc.get("stac_extensions", []))
        validate_dict(doc, validator=validator, href=rel)  # core and every extension listed
    assert used == required_uris()
    tile = next(d for d in _items(catalog, "epoch-2024") if "pc:count" in d["properties"])
    tile["properties"]["pc:count"] = -1
    with pytest.raises(pystac.errors.STACValidationError, match="pointcloud"):
        validate_dict(tile, validator=validator)
    raster = next(d for d in _items(catalog, "epoch-2024") if d["id"] == "2024-dtm")
    raster["assets"]["data"]["raster:bands"][0]["data_type"] = "float99"
    with pytest.raises(pystac.errors.STACValidationError, match="raster"):
        validate_dict(raster, validator=validator)


# --- content ---------------------------------------------------------------------------------


def test_stac_items_match_the_tiles_and_rasters(catalog: Path) -> None:
    opened = Catalog.open(catalog)
    to_wgs84 = CRS.of(opened.crs).transformer_to("EPSG:4326")
    for epoch in sorted(opened.epochs):
        items = {d["id"]: d for d in _items(catalog, f"epoch-{epoch}")}
        tiles = {d["id"]: d for d in items.values() if "pc:count" in d["properties"]}
        rel_of = {
            _target(catalog, f"stac/epoch-{epoch}/x.json", d["assets"]["data"]["href"]): d
            for d in tiles.values()
        }
        assert set(rel_of) == {(catalog / t).resolve() for t in opened.tiles(epoch)}
        for path, item in rel_of.items():
            props = item["properties"]
            with laspy.open(path) as reader:
                header = reader.header
                names = list(header.point_format.dimension_names)
            assert props["pc:count"] == header.point_count > 0
            assert props["pc:type"] == "lidar" and props["pc:encoding"] == "LAZ"
            assert [s["name"] for s in props["pc:schemas"]] == names
            assert props["proj:code"] == opened.crs
            lo, hi = header.mins, header.maxs
            assert props["proj:bbox"] == pytest.approx([*lo, *hi], abs=1e-6)
            lon0, lat0, _, lon1, lat1, _ = item["bbox"]
            for x, y in ((lo[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1]), (hi[0], lo[1])):
                lon, lat = to_wgs84.transform(x, y)
                assert lon0 - 1e-9 <= lon <= lon1 + 1e-9 and lat0 - 1e-9 <= lat <= lat1 + 1e-9
            assert props["datetime"].startswith(str(opened.epochs[epoch]["date"]))
        rasters = {d["id"]: d for d in items.values() if "pc:count" not in d["properties"]}
        assert {"dtm", "chm", "density", "observed"} <= {r.split("-", 1)[1] for r in rasters}
        for item in rasters.values():
            asset = item["assets"]["data"]
            band = asset["raster:bands"][0]
            with rasterio.open(_target(catalog, f"stac/epoch-{epoch}/x.json", asset["href"])) as ds:
                assert band["nodata"] == ds.nodata
                assert band["data_type"] == ds.dtypes[0]
                assert band["spatial_resolution"] == pytest.approx(ds.res[0])
                assert item["properties"]["proj:shape"] == [ds.height, ds.width]
                assert item["properties"]["proj:bbox"] == pytest.approx(list(ds.bounds))
        assert rasters[f"{epoch}-dtm"]["assets"]["data"]["raster:bands"][0]["unit"] == "m"


def test_stac_links_the_vpc_index_tables_and_comparison(catalog: Path) -> None:
    docs = _documents(catalog)
    for rel, doc in docs.items():
        for link in doc["links"]:
            assert not link["href"].startswith(("/", "http")), (rel, link)
            assert _target(catalog, rel, link["href"]).is_file(), (rel, link)
        for asset in doc.get("assets", {}).values():
            assert _target(catalog, rel, asset["href"]).is_file(), (rel, asset)
    epoch = docs["stac/epoch-2024/collection.json"]["assets"]
    assert epoch["vpc"]["href"] == "../../tiles_2024.vpc"
    assert epoch["index"]["href"] == "../../index.gpkg"
    assert epoch["tree_list_parquet"]["href"] == "../../tables/tree_list_2024.parquet"
    change = docs["stac/compare-2024__2028/collection.json"]
    assert {"stand_csv", "tree_parquet", "index"} <= change["assets"].keys()
    assert docs["stac/compare-2024__2028/2024__2028-chm_diff.json"]["assets"]["data"]["href"] == (
        "../../compare/2024__2028/chm_diff.tif"
    )
    children = [link["href"] for link in docs[STAC_ROOT]["links"] if link["rel"] == "child"]
    assert children == [
        "./compare-2024__2028/collection.json",
        "./epoch-2024/collection.json",
        "./epoch-2028/collection.json",
    ]


def test_stac_is_the_same_bytes_when_built_again(catalog: Path) -> None:
    again = stac_documents(Transaction(Catalog.open(catalog)))
    assert again is not None
    assert set(again) == stac_files(catalog)
    for rel, data in again.items():
        assert (catalog / rel).read_bytes() == data, rel


@pytest.mark.slow
def test_stac_written_by_tile_and_updated_by_enrich(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    from standgrid.pipeline.enrich import enrich_catalog

    root = copy_catalog(tiled_grid25(tmp_path_factory), tmp_path / "catalog")
    before = _documents(root)
    tiled = Catalog.open(root)
    assert {f"stac/epoch-{e}/collection.json" for e in tiled.epochs} <= before.keys()
    items = _items(root, "epoch-2024")
    assert len([d for d in items if "pc:count" in d["properties"]]) == len(tiled.tiles("2024"))
    assert not any(d["id"] == "2024-dtm" for d in items)
    assert "tree_list_csv" not in before["stac/epoch-2024/collection.json"]["assets"]
    enrich_catalog(root)
    after = _documents(root)
    items = {d["id"]: d for d in _items(root, "epoch-2024")}
    assert "2024-dtm" in items and "2024-chm" in items
    assets = after["stac/epoch-2024/collection.json"]["assets"]
    assert {"tree_list_csv", "tree_list_parquet", "stand_metrics_csv"} <= assets.keys()
    assert after == {rel: json.loads(d) for rel, d in _stac_now(root).items()}


def _stac_now(root: Path) -> dict[str, bytes]:
    found = stac_documents(Transaction(Catalog.open(root)))
    assert found is not None
    return found


# --- over HTTP -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def base(catalog: Path) -> Iterator[str]:
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    with running(create_app(catalog)) as server:
        assert server.base_url is not None
        yield server.base_url


# a static catalog: no API conformance classes, so pystac-client walks it with pystac
@pytest.mark.filterwarnings("ignore::pystac_client.warnings.PystacClientWarning")
def test_stac_client_walks_the_served_catalog(base: str, catalog: Path) -> None:
    from pystac_client import Client

    client = Client.open(f"{base}/files/stac/catalog.json")
    collections = {c.id: c for c in client.get_collections()}
    assert set(collections) == {"compare-2024__2028", "epoch-2024", "epoch-2028"}
    checked = 0
    with httpx.Client() as http:
        for cid, collection in sorted(collections.items()):
            items = list(collection.get_items())
            assert len(items) == len(_items(catalog, cid)) > 0
            assets = [*collection.assets.values(), *(a for i in items for a in i.assets.values())]
            for asset in assets:
                href = asset.get_absolute_href()
                assert href is not None and href.startswith(f"{base}/files/")
                r = http.head(href)
                assert r.status_code == 200, href
                local = catalog / href.removeprefix(f"{base}/files/")
                assert int(r.headers["content-length"]) == local.stat().st_size
                checked += 1
    expected = [
        a for d in _documents(catalog).values() if d["type"] != "Catalog" for a in d["assets"]
    ]
    assert checked == len(expected) > 50
    # a tile item read over HTTP says what the one on disk says
    tile = next(i for i in collections["epoch-2024"].get_items() if "pc:count" in i.properties)
    local = json.loads((catalog / f"stac/epoch-2024/{tile.id}.json").read_text("utf-8"))
    assert tile.properties["pc:count"] == local["properties"]["pc:count"] > 0


@pytest.mark.parametrize(
    "path",
    [
        "stac/nope.json",
        "stac/epoch-2024",
        "stac/../catalog.json",
        "stac/%2e%2e/catalog.json",
        "stac/epoch-2024/../../catalog.json",
        "stac/epoch-2024/collection.json/x",
    ],
)
def test_stac_serves_only_its_documents(base: str, path: str) -> None:
    r = httpx.get(f"{base}/files/{path}")
    assert r.status_code == 404
    assert r.headers["content-type"] == "application/problem+json"


def test_stac_listed_and_linked_from_the_landing_page(base: str) -> None:
    files = {f["path"] for f in httpx.get(f"{base}/files").json()["files"]}
    assert {STAC_ROOT, "stac/epoch-2024/collection.json"} <= files
    r = httpx.get(f"{base}/files/{STAC_ROOT}")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/json")
    assert r.json()["type"] == "Catalog"
    landing = httpx.get(f"{base}/", headers={"Accept": "application/json"})
    links = {link["rel"]: link["href"] for link in landing.json()["links"]}
    assert links["stac"] == f"/files/{STAC_ROOT}"


def test_stac_follows_a_commit_that_removes_a_raster(catalog: Path, tmp_path: Path) -> None:
    from standgrid.catalog import paths

    root = copy_catalog(catalog, tmp_path / "catalog")
    item = root / "stac/epoch-2024/2024-dtm.json"
    assert item.is_file()
    opened = Catalog.open(root)
    with opened.transaction() as txn:
        txn.delete(paths.raster("2024", "dtm"))
    assert not item.exists()
    links = json.loads((root / "stac/epoch-2024/collection.json").read_text("utf-8"))["links"]
    assert "./2024-dtm.json" not in {link["href"] for link in links}
    assert "./2024-chm.json" in {link["href"] for link in links}
    assert _stac_now(root) == {rel: (root / rel).read_bytes() for rel in stac_files(root)}


def test_stac_of_copc_tiles_a_crs_without_epsg_and_nan_nodata() -> None:
    import pyproj

    from standgrid.catalog import paths
    from standgrid.export.stac import (
        Band,
        StacGroup,
        StacLayout,
        StacRaster,
        StacTile,
        build_stac,
    )

    wkt = pyproj.CRS.from_proj4(
        "+proj=tmerc +lat_0=0 +lon_0=9.5 +k=1 +x_0=500000 +y_0=0 +ellps=WGS84 +units=m"
    ).to_wkt()
    tile = StacTile(
        "c1",
        "tiles/e/c1.copc.laz",
        12,
        (500000.0, 5300000.0, 1.0, 500020.0, 5300020.0, 9.0),
        ({"name": "X", "size": 8, "type": "floating"},),
    )
    band = Band("float32", "nan", 0.5, "m")
    raster = StacRaster(
        "dtm",
        "rasters/e/dtm.tif",
        (500000.0, 5300000.0, 500020.0, 5300020.0),
        (40, 40),
        (0.5, 0.0, 500000.0, 0.0, -0.5, 5300020.0),
        band,
    )
    group = StacGroup("epoch-e", "Epoch e", "e", ("2030-06-01",), (tile,), (raster,), prefix="e")
    layout = StacLayout(paths.STAC_ROOT, paths.stac_collection, paths.stac_item)
    docs = build_stac("t", wkt, [group], layout)
    item = docs[paths.stac_item("epoch-e", "e-c1")]
    props = item["properties"]
    assert props["pc:encoding"] == "COPC" and props["pc:count"] == 12
    assert "proj:code" not in props and pyproj.CRS(props["proj:wkt2"]) == pyproj.CRS(wkt)
    assert props["datetime"] == "2030-06-01T00:00:00Z"
    assert item["assets"]["data"]["type"] == "application/vnd.laszip+copc"
    lon0, lat0, _, lon1, lat1, _ = item["bbox"]
    assert 9.4 < lon0 < lon1 < 9.6 and 47.0 < lat0 < lat1 < 48.5
    nodata = docs[paths.stac_item("epoch-e", "e-dtm")]["assets"]["data"]["raster:bands"][0]
    assert nodata["nodata"] == "nan"
    assert build_stac("t", wkt, [group], layout) == docs  # nothing depends on the time
    validator = JsonSchemaSTACValidator()
    try:
        from tests.stac_schemas import extension_schemas

        validator.schema_cache.update(extension_schemas())
    except RuntimeError:  # no PyPI and no cache: the core only
        for rel, doc in docs.items():
            validate_dict(doc, extensions=[], validator=validator, href=rel)
    else:
        for rel, doc in docs.items():
            validate_dict(doc, validator=validator, href=rel)


def test_an_epoch_without_a_date_says_so_instead_of_a_made_up_day() -> None:
    from standgrid.catalog import paths
    from standgrid.export.stac import StacGroup, StacLayout, StacTile, build_stac

    tile = StacTile(
        "c1",
        "tiles/e/c1.laz",
        5,
        (500000.0, 5300000.0, 1.0, 500020.0, 5300020.0, 9.0),
        ({"name": "X", "size": 8, "type": "floating"},),
    )
    group = StacGroup("epoch-e", "Epoch e", "e", (None,), (tile,), (), prefix="e")
    layout = StacLayout(paths.STAC_ROOT, paths.stac_collection, paths.stac_item)
    docs = build_stac("t", "EPSG:32632", [group], layout)
    props = docs[paths.stac_item("epoch-e", "e-c1")]["properties"]
    assert props["datetime"] is None and props["standgrid:date"] is None
    assert "no date" in props["standgrid:date_note"]
    assert props["start_datetime"] < props["end_datetime"]  # any time: no claim
    extent = docs[paths.stac_collection("epoch-e")]["extent"]["temporal"]["interval"]
    assert extent == [[None, None]]
    validator = JsonSchemaSTACValidator()
    for rel, doc in docs.items():
        validate_dict(doc, extensions=[], validator=validator, href=rel)
