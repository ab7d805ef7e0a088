"""The viewer's server side against a real uvicorn server: the page at ``/`` for browsers,
its start-up configuration, and a cell's points checked against the tile read with laspy."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import laspy
import numpy as np
import pyogrio
import pytest
import rasterio

from tests.pipeline_fixtures import CRS


def _decode(body: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The points answer read independently of the viewer's JS decoder."""
    length = int(np.frombuffer(body[:4], "<u4")[0])
    header = json.loads(body[4 : 4 + length])
    n, offset, arrays = header["count"], 4 + length, {}
    for name, dtype in header["arrays"]:
        width = 3 if name == "xyz" else 1
        size = n * width * np.dtype(dtype).itemsize
        arrays[name] = np.frombuffer(body[offset : offset + size], dtype).reshape(n, width)
        offset += size
    assert offset == len(body)
    return header, arrays


def test_root_is_the_viewer_for_browsers_and_json_for_clients(enriched_base: str) -> None:
    page = httpx.get(f"{enriched_base}/", headers={"Accept": "text/html,application/xhtml+xml"})
    assert page.status_code == 200
    assert page.headers["content-type"].startswith("text/html")
    script = next(
        s for s in page.text.split('"') if s.startswith("/viewer/assets/") and s.endswith(".js")
    )
    asset = httpx.get(f"{enriched_base}{script}")
    assert asset.status_code == 200
    assert "javascript" in asset.headers["content-type"]
    # laz-perf's WebAssembly (COPC tiles are decoded in the browser) is in the bundle
    from standgrid.serve.viewer import STATIC

    (wasm,) = (STATIC / "assets").glob("laz-perf-*.wasm")
    served = httpx.get(f"{enriched_base}/viewer/assets/{wasm.name}")
    assert served.status_code == 200 and served.content == wasm.read_bytes()
    assert served.headers["content-type"] == "application/wasm"
    service = httpx.get(f"{enriched_base}/").json()
    assert {link["rel"] for link in service["links"]} >= {"ogc", "files", "viewer"}


def test_config_names_the_crs_epochs_and_chm_ranges(
    enriched_base: str, enriched_catalog: Path
) -> None:
    config = httpx.get(f"{enriched_base}/viewer/config.json").json()
    assert config["crs"]["code"] == CRS
    assert config["crs"]["uri"] == "http://www.opengis.net/def/crs/EPSG/0/32630"
    stored = json.loads((enriched_catalog / "catalog.json").read_text())["epochs"]
    assert [e["label"] for e in config["epochs"]] == list(stored)
    for epoch in config["epochs"]:
        assert epoch["date"] == stored[epoch["label"]]["date"]
        assert epoch["chm"] == f"files/rasters/{epoch['label']}/chm.tif"
        assert httpx.head(f"{enriched_base}/{epoch['chm']}").status_code == 200
        with rasterio.open(enriched_catalog / epoch["chm"].removeprefix("files/")) as src:
            valid = src.read(1, masked=True).compressed()
        assert epoch["chm_max"] == pytest.approx(np.percentile(valid, 98.0), abs=1e-4)
    assert {"cells", "stand_metrics", "trees"} <= set(config["layers"])
    # LAZ tiles: the page asks the server for a cell's points (COPC: tests/test_tile_copc.py)
    assert config["tiles"] == "laz" and {e["tiles"] for e in config["epochs"]} == {"laz"}
    assert config["max_view_points"] > 0


def test_cell_points_are_the_tiles_core_points(enriched_base: str, enriched_catalog: Path) -> None:
    cells = pyogrio.read_dataframe(enriched_catalog / "index.gpkg", layer="cells")
    row = cells.sort_values("point_count").iloc[-1]
    answer = httpx.get(f"{enriched_base}/viewer/points/{row['epoch']}/{row['cell_id']}")
    assert answer.status_code == 200
    header, arrays = _decode(answer.content)
    las = laspy.read(enriched_catalog / row["tile_path"])
    core = ~np.asarray(las.withheld, dtype=bool)
    assert header["count"] == int(core.sum()) == int(row["point_count"])
    assert header["meta"]["tile_points"] == las.header.point_count
    assert header["meta"]["buffer_points"] == int((~core).sum()) > 0
    xyz = np.column_stack([las.x, las.y, las.z])[core]
    back = arrays["xyz"].astype(np.float64) + np.asarray(header["origin"])
    assert np.abs(back - xyz).max() < 1e-5  # float32 offsets within a 20 m cell
    hag = np.asarray(las["height_above_ground"])[core]
    np.testing.assert_allclose(arrays["height_above_ground"][:, 0], hag, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(
        arrays["classification"][:, 0], np.asarray(las.classification)[core]
    )
    tree = np.asarray(las["tree_id"])[core]
    np.testing.assert_array_equal(arrays["tree_key"][:, 0] == 0, tree == 0)
    assert len(np.unique(arrays["tree_key"])) == len(np.unique(tree))


@pytest.mark.parametrize("path", ["/viewer/points/1999/20m_E1_N1", "/viewer/points/2024/20m_E1_N1"])
def test_unknown_cell_or_epoch_is_a_404_problem(enriched_base: str, path: str) -> None:
    answer = httpx.get(f"{enriched_base}{path}")
    assert answer.status_code == 404
    assert answer.headers["content-type"] == "application/problem+json"
    assert "20m_E1_N1" in answer.json()["detail"] or "1999" in answer.json()["detail"]


def test_a_trees_points_are_marked_with_its_exact_id(
    enriched_base: str, enriched_catalog: Path
) -> None:
    trees = pyogrio.read_dataframe(
        enriched_catalog / "index.gpkg", layer="trees", fid_as_index=True
    )
    tree = trees.sort_values("n_points").iloc[-1]
    url = f"{enriched_base}/viewer/points/{tree['epoch']}/{tree['cell_id']}"
    header, arrays = _decode(httpx.get(url, params={"tree": int(tree.name)}).content)
    marked = header["meta"]["tree"]
    assert marked["tree_id"] == str(int(tree["tree_id"]))  # text: exact beyond 2**53
    las = laspy.read(enriched_catalog / "tiles" / tree["epoch"] / f"{tree['cell_id']}.laz")
    ids = np.asarray(las["tree_id"])[~np.asarray(las.withheld, dtype=bool)]
    assert marked["points"] == int((ids == int(tree["tree_id"])).sum()) > 0
    assert int((arrays["tree_key"][:, 0] == marked["key"]).sum()) == marked["points"]
    missing = httpx.get(url, params={"tree": 10**9})
    assert missing.status_code == 404
    assert "no tree" in missing.json()["detail"]


def test_tree_keys_tell_apart_trees_on_one_row() -> None:
    """Tree ids pack x and y at 0.1 m; trees whose tops share a y row must not share a key."""
    from standgrid.enrichment.trees import tree_id_from_xy
    from standgrid.serve.viewer import tree_key

    x = 614_700.0 + np.arange(200) * 0.1
    ids = tree_id_from_xy(x, np.full(200, 5_737_150.0))
    keys = tree_key(ids)
    assert len(np.unique(keys)) == 200 and (keys != 0).all()
    assert tree_key(np.array([0]))[0] == 0


def _payload_points(catalog: Path, epoch: str, ident: int) -> np.ndarray:
    """The core points of every tile of ``epoch`` whose payload_id is ``ident`` (laspy),
    sorted by x, y, z."""
    parts = []
    for tile in sorted((catalog / "tiles" / epoch).glob("*.la[sz]")):
        las = laspy.read(tile)
        mine = ~np.asarray(las.withheld, dtype=bool) & (np.asarray(las["payload_id"]) == ident)
        parts.append(np.column_stack([las.x, las.y, las.z])[mine])
    xyz = np.concatenate(parts)
    return xyz[np.lexsort(xyz.T[::-1])]


def test_payload_points_are_exactly_the_payloads_points_in_the_tiles(
    enriched_base: str, enriched_catalog: Path
) -> None:
    payloads = pyogrio.read_dataframe(enriched_catalog / "index.gpkg", layer="payloads")
    for epoch in sorted(payloads["epoch"].unique()):
        row = payloads[payloads["epoch"] == epoch].sort_values("payload_id").iloc[0]
        ident = int(row["payload_id"])
        answer = httpx.get(f"{enriched_base}/viewer/points", params={"payload": ident})
        assert answer.status_code == 200
        header, arrays = _decode(answer.content)
        expected = _payload_points(enriched_catalog, epoch, ident)
        got = header["meta"]["payload"]
        assert header["count"] == len(expected) == int(row["point_count"]) > 0
        assert got["found"] == got["point_count"] == len(expected) and got["complete"]
        assert got["epoch"] == epoch and got["mission"] == row["mission"]
        assert header["meta"]["capped"] is False and header["meta"]["total"] == len(expected)
        # georeferenced: the same points (float32 offsets from the stated origin)
        back = arrays["xyz"].astype(np.float64) + np.asarray(header["origin"])
        back = back[np.lexsort(back.T[::-1])]
        assert np.abs(back - expected).max() < 1e-4
        # every tile named holds some of them, or was read on the way (under the footprint)
        assert 0 < got["tiles_with_points"] <= len(got["tiles"])


def test_payload_points_are_capped_evenly_and_say_so(
    enriched_base: str, enriched_catalog: Path
) -> None:
    payloads = pyogrio.read_dataframe(enriched_catalog / "index.gpkg", layer="payloads")
    row = payloads.sort_values("point_count").iloc[-1]
    url = f"{enriched_base}/viewer/points"
    full = _decode(httpx.get(url, params={"payload": int(row["payload_id"])}).content)
    capped = _decode(
        httpx.get(url, params={"payload": int(row["payload_id"]), "limit": 1000}).content
    )
    header, arrays = capped
    assert header["count"] == 1000
    assert header["meta"]["total"] == int(row["point_count"]) > 1000
    assert header["meta"]["capped"] is True
    assert header["meta"]["stride"] == pytest.approx(int(row["point_count"]) / 1000)
    # a subset of the full answer's points, spread over all of it
    every = full[1]["xyz"].astype(np.float64) + np.asarray(full[0]["origin"])
    some = arrays["xyz"].astype(np.float64) + np.asarray(header["origin"])
    keep = np.linspace(0, len(every), 1000, endpoint=False).astype(np.int64)
    assert np.abs(some - every[keep]).max() < 1e-4
    too_many = httpx.get(url, params={"payload": int(row["payload_id"]), "limit": 10**9})
    assert too_many.status_code == 400


def test_unknown_payload_is_a_404_problem(enriched_base: str) -> None:
    answer = httpx.get(f"{enriched_base}/viewer/points", params={"payload": 1})
    assert answer.status_code == 404
    assert answer.headers["content-type"] == "application/problem+json"
    assert "no payload 1" in answer.json()["detail"]


def test_cell_points_are_capped_on_request(enriched_base: str, enriched_catalog: Path) -> None:
    cells = pyogrio.read_dataframe(enriched_catalog / "index.gpkg", layer="cells")
    row = cells.sort_values("point_count").iloc[-1]
    url = f"{enriched_base}/viewer/points/{row['epoch']}/{row['cell_id']}"
    header, _ = _decode(httpx.get(url, params={"limit": 500}).content)
    assert header["count"] == 500
    assert header["meta"]["total"] == int(row["point_count"])
    assert header["meta"]["capped"] is True
    uncapped, _ = _decode(httpx.get(url).content)
    assert uncapped["meta"]["capped"] is False
    assert uncapped["count"] == uncapped["meta"]["total"] == int(row["point_count"])
