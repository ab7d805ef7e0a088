"""standgrid serve: catalog files with range requests (httpx, GDAL /vsicurl/, laspy),
the retrieval API against the library, writes refused without the token, the body limit,
and the command itself. A real uvicorn server on 127.0.0.1 throughout."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import laspy
import numpy as np
import pytest

from tests.conftest import REPO_ROOT
from tests.pipeline_fixtures import MISSIONS, enriched_pair

TOKEN = "s3cret-token-for-tests-0123456789"
MAX_BODY = 4096
COYOTE = MISSIONS["2024"]


@pytest.fixture(scope="module")
def catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return enriched_pair(tmp_path_factory).path


@pytest.fixture(scope="module")
def base(catalog: Path) -> Iterator[str]:
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    with running(create_app(catalog, token=TOKEN, max_body=MAX_BODY)) as server:
        assert server.base_url is not None
        yield server.base_url


def _tile(catalog: Path) -> str:
    from standgrid.catalog import Catalog

    return Catalog.open(catalog).tiles("2024")[0]


# --- files and ranges ----------------------------------------------------------------------


def test_range_requests_return_exactly_the_bytes_asked(base: str, catalog: Path) -> None:
    rel = _tile(catalog)
    data = (catalog / rel).read_bytes()
    size = len(data)
    url = f"{base}/files/{rel}"
    whole = httpx.get(url)
    assert whole.status_code == 200 and whole.content == data
    assert whole.headers["accept-ranges"] == "bytes"
    for spec, (lo, hi) in {
        "bytes=0-99": (0, 100),
        "bytes=100-": (100, size),
        "bytes=-50": (size - 50, size),
        f"bytes=10-{size + 500}": (10, size),
    }.items():
        r = httpx.get(url, headers={"Range": spec})
        assert r.status_code == 206, spec
        assert r.content == data[lo:hi], spec
        assert r.headers["content-range"] == f"bytes {lo}-{hi - 1}/{size}", spec
    two = httpx.get(url, headers={"Range": "bytes=0-9,20-29"})
    assert two.status_code == 206
    assert two.headers["content-type"].startswith("multipart/byteranges")
    assert data[0:10] in two.content and data[20:30] in two.content
    head = httpx.head(url)
    assert head.status_code == 200 and int(head.headers["content-length"]) == size
    bad = httpx.get(url, headers={"Range": f"bytes={size}-"})
    assert bad.status_code == 416
    assert bad.headers["content-range"] == f"bytes */{size}"
    assert bad.headers["content-type"] == "application/problem+json"
    assert httpx.get(url, headers={"Range": "bytes=9-3"}).status_code == 400
    assert httpx.get(url, headers={"Range": "lines=1-2"}).status_code == 400
    many = ",".join(f"{i}-{i}" for i in range(17))
    assert httpx.get(url, headers={"Range": f"bytes={many}"}).status_code == 400


@pytest.mark.parametrize(
    "path",
    [
        "catalog.json",
        "tiles/2024/nope.laz",
        "%2e%2e/%2e%2e/etc/passwd",
        "..%2fcatalog.json",
        "tiles/2024/../../catalog.json",
        "/etc/passwd",
    ],
)
def test_only_published_files_are_served(base: str, path: str) -> None:
    r = httpx.get(f"{base}/files/{path}")
    assert r.status_code == 404
    assert r.headers["content-type"] == "application/problem+json"


def test_gdal_vsicurl_reads_a_served_cog(base: str, catalog: Path) -> None:
    import rasterio

    with rasterio.open(catalog / "rasters/2024/chm.tif") as local:
        expected, profile = local.read(1), local.profile
    options = {"GDAL_DISABLE_READDIR_ON_OPEN": "EMPTY_DIR", "GDAL_HTTP_MULTIRANGE": "NO"}
    url = f"/vsicurl/{base}/files/rasters/2024/chm.tif"
    with rasterio.Env(**options), rasterio.open(url) as ds:
        assert ds.crs == profile["crs"] and ds.transform == profile["transform"]
        np.testing.assert_array_equal(ds.read(1), expected)
        window = ds.read(1, window=((10, 20), (30, 50)))
    np.testing.assert_array_equal(window, expected[10:20, 30:50])


def test_vpc_links_resolve_to_served_tiles(base: str, catalog: Path) -> None:
    vpc = httpx.get(f"{base}/files/tiles_2024.vpc")
    assert vpc.status_code == 200
    items = vpc.json()["features"]
    href = items[0]["assets"]["data"]["href"]
    tile = httpx.get(httpx.URL(f"{base}/files/tiles_2024.vpc").join(href))
    assert tile.status_code == 200
    las = laspy.read(io.BytesIO(tile.content))
    local = laspy.read(catalog / href.removeprefix("./"))
    np.testing.assert_array_equal(las.points.array, local.points.array)
    listed = {f["path"] for f in httpx.get(f"{base}/files").json()["files"]}
    assert {"index.gpkg", "tiles_2024.vpc", "rasters/2028/dtm.tif"} <= listed
    assert "catalog.json" not in listed


# --- retrieval ------------------------------------------------------------------------------


def test_mission_search_and_summary(base: str) -> None:
    def names(**params: str | list[str]) -> list[str]:
        r = httpx.get(f"{base}/missions", params=params)
        assert r.status_code == 200, r.text
        return [m["name"] for m in r.json()["missions"]]

    both = sorted(MISSIONS.values())
    assert names() == both
    assert names(site="Wytham") == both
    assert names(robot="anymal") == [COYOTE]
    assert names(**{"from": "2025-01-01"}) == [MISSIONS["2028"]]
    assert names(**{"from": "2024-05-14", "to": "2024-05-14"}) == [COYOTE]
    assert names(sensor=["lidar", "gnss"]) == both
    assert names(sensor="velodyne") == [COYOTE]
    assert names(site="elsewhere") == []
    assert httpx.get(f"{base}/missions", params={"from": "May"}).status_code == 400
    summary = httpx.get(f"{base}/missions/{COYOTE}").json()
    assert summary["epoch"] == "2024" and summary["robot"] == "anymal"
    assert summary["payload_count"] == 16 and summary["point_count"] > 0
    assert httpx.get(summary["tiles"][0]).status_code == 200


def test_payload_retrieval_matches_the_library(base: str) -> None:
    from standgrid.georeference.retrieval import retrieve_payload_by_gnss
    from standgrid.mission.opening import open_mission
    from standgrid.mission.retrieval import retrieve_payload_by_pose, retrieve_payload_by_type

    mission = open_mission(REPO_ROOT / "data/missions" / COYOTE, strict=False)
    url = f"{base}/missions/{COYOTE}/payloads"
    for kind in ("point_cloud", "gnss", "imu", "image"):
        got = httpx.get(url, params={"type": kind}).json()["payloads"]
        want = retrieve_payload_by_type(mission, kind)
        assert [p["stamp_ns"] for p in got] == [p.stamp.ns for p in want], kind
        assert all("path" not in p for p in got)  # no server paths leak
    assert httpx.get(url, params={"type": "radar"}).status_code == 400  # not a data type
    x, y, z = mission.pose_of(mission.payloads[5])[:3, 3]
    got = httpx.get(f"{url}/by-pose", params={"x": x, "y": y, "k": 3}).json()["payloads"]
    want = retrieve_payload_by_pose(mission, (x, y), k=3)
    assert [p["stamp_ns"] for p in got] == [p.stamp.ns for p in want]
    assert got[0]["distance_m"] == pytest.approx(0.0, abs=1e-9)
    near = httpx.get(f"{url}/by-pose", params={"x": x, "y": y, "z": z + 40, "radius": 45})
    want = retrieve_payload_by_pose(mission, (x, y, z + 40), radius=45)
    assert [p["stamp_ns"] for p in near.json()["payloads"]] == [p.stamp.ns for p in want]
    assert 0 < len(want) < len(mission.payloads)
    lat, lon = 51.77320, -1.33739
    got = httpx.get(f"{url}/by-gnss", params={"lat": lat, "lon": lon, "k": 2}).json()["payloads"]
    want = retrieve_payload_by_gnss(mission, (lat, lon), k=2)
    assert [p["stamp_ns"] for p in got] == [p.stamp.ns for p in want]
    from standgrid.georeference.retrieval import locate_by_gnss

    distances = locate_by_gnss(mission, (lat, lon), k=2).distances_m
    assert [p["distance_m"] for p in got] == pytest.approx(distances, abs=1e-9)
    swapped = httpx.get(f"{url}/by-gnss", params={"lat": lon, "lon": lat})
    assert swapped.status_code == 404 and "km away" in swapped.text and "swapped" in swapped.text
    assert httpx.get(f"{url}/by-gnss", params={"lat": 91, "lon": 0}).status_code == 400


def test_payload_cloud_as_laz(base: str, catalog: Path) -> None:
    from standgrid.catalog import Catalog
    from standgrid.export.las import read_tile
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.project import MapProjector
    from standgrid.mission.opening import open_mission

    mission = open_mission(REPO_ROOT / "data/missions" / COYOTE, strict=False)
    payload = mission.payloads[3]
    listed = httpx.get(f"{base}/missions/{COYOTE}/payloads").json()["payloads"][3]
    opened = Catalog.open(catalog)
    fit = GeoreferenceFit.from_dict(opened.mission_records[COYOTE].georeference or {})
    map_xyz = mission.load_payload(payload, frame="map").xyz
    expected = {
        "map": map_xyz,
        "base": mission.load_payload(payload, frame="base").xyz,
        "crs": MapProjector(fit, opened.crs).exact(map_xyz),
    }
    for frame, xyz in expected.items():
        r = httpx.get(listed["cloud"], params={"frame": frame})
        assert r.status_code == 200 and r.headers["content-type"] == "application/vnd.laszip"
        las = laspy.read(io.BytesIO(r.content))
        got = np.column_stack([las.x, las.y, las.z])
        assert len(got) == len(xyz)
        np.testing.assert_allclose(got, xyz, atol=0.0005 + 1e-9)  # 1 mm LAS quantum
        has_crs = las.header.parse_crs() is not None
        assert has_crs == (frame == "crs"), frame
    # the georeferenced cloud lands where the catalog's tiles put this payload's points
    from scipy.spatial import cKDTree

    las = laspy.read(io.BytesIO(httpx.get(listed["cloud"]).content))
    assert las.header.parse_crs().to_epsg() == 32630
    number = opened.mission_records[COYOTE].number
    tiled = []
    for rel in opened.tiles("2024"):
        tile = read_tile(catalog / rel)
        tiled.append(tile.xyz[tile.fields["payload_id"] == (number << 16 | 3)])
    tiled_xyz = np.concatenate(tiled)
    served = np.column_stack([las.x, las.y, las.z])
    assert len(tiled_xyz) == len(served)
    distance, _ = cKDTree(tiled_xyz).query(served)
    assert distance.max() < 0.0015  # both on a 1 mm lattice
    assert httpx.get(f"{base}/missions/{COYOTE}/payloads/1_000000001/cloud.laz").status_code == 404
    assert httpx.get(f"{base}/missions/{COYOTE}/payloads/x/cloud.laz").status_code == 400


# --- writes, limits --------------------------------------------------------------------------


def _state(catalog: Path) -> dict[str, int]:
    return {str(p.relative_to(catalog)): p.stat().st_mtime_ns for p in catalog.rglob("*")}


def test_writes_need_the_token_and_change_nothing(base: str, catalog: Path) -> None:
    before = _state(catalog)
    for headers in (
        {},
        {"Authorization": "Bearer wrong"},
        {"Authorization": f"Basic {TOKEN}"},
        {"Authorization": f"Bearer {TOKEN}x"},
    ):
        for method in ("POST", "PUT", "DELETE", "PATCH"):
            r = httpx.request(method, f"{base}/missions", headers=headers, content=b"{}")
            assert r.status_code == 401, (method, headers)
            assert r.headers["www-authenticate"] == "Bearer"
            assert r.headers["content-type"] == "application/problem+json"
    ok = httpx.post(f"{base}/missions", headers={"Authorization": f"Bearer {TOKEN}"})
    assert ok.status_code == 400  # past the guard, refused by the route: no mission given
    assert _state(catalog) == before
    assert not catalog.with_name(f"{catalog.name}-missions").exists()


def test_bodies_over_the_limit_are_refused(base: str) -> None:
    auth = {"Authorization": f"Bearer {TOKEN}"}
    r = httpx.post(f"{base}/missions", headers=auth, content=b"x" * (MAX_BODY + 1))
    assert r.status_code == 413 and r.json()["status"] == 413
    assert r.headers["content-type"] == "application/problem+json"

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted as the route reads it
        for _ in range(8):
            yield b"y" * 1024

    streamed = httpx.post(
        f"{base}/missions/{COYOTE}/payloads",
        params={"stamp": "1_000000001"},
        headers=auth,
        content=chunks(),
    )
    assert streamed.status_code == 413


def test_token_sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from standgrid.errors import FormatError, StandgridError
    from standgrid.serve.auth import TOKEN_ENV, bearer_matches, load_token

    monkeypatch.delenv(TOKEN_ENV, raising=False)
    assert load_token() is None
    monkeypatch.setenv(TOKEN_ENV, TOKEN)
    assert load_token() == TOKEN
    file = tmp_path / "token"
    file.write_text(f"  {TOKEN}-file\n")
    assert load_token(file) == f"{TOKEN}-file"
    file.write_text("short")
    with pytest.raises(FormatError, match="16 characters"):
        load_token(file)
    with pytest.raises(StandgridError, match="cannot read"):
        load_token(tmp_path / "missing")
    assert bearer_matches(f"bearer {TOKEN}", TOKEN) and not bearer_matches(None, TOKEN)


def test_serve_command_prints_urls_and_stops_on_ctrl_c(catalog: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "STANDGRID_TOKEN"}
    command = [
        sys.executable,
        "-c",
        "from standgrid.cli import main; main()",
        "serve",
        str(catalog),
        "--port",
        "0",
        "--json",
    ]
    proc = subprocess.Popen(
        command, cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        urls = json.loads(proc.stdout.readline())
        assert urls["writes"] is False
        assert httpx.get(urls["ogc"]).json()["links"]
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert "stopped" in err


def test_a_reused_catalog_is_given_again_only_until_a_commit(tmp_path: Path) -> None:
    from standgrid.catalog import Catalog
    from tests.pipeline_fixtures import build_small_catalog

    root = build_small_catalog(tmp_path / "small")
    with Catalog.reading(root) as first:
        pass
    with Catalog.reading(root, reuse=first) as again:
        assert again is first
    with Catalog.writing(root) as catalog, catalog.transaction() as txn:
        txn.record_mission(
            "2030-01-01-test-robot-r9",
            epoch="2030",
            date="2030-01-01",
            tiles=[],
            point_count=0,
            payload_count=0,
        )
    with Catalog.reading(root, reuse=first) as after:
        assert after is not first
        assert "2030-01-01-test-robot-r9" in after.mission_records
        assert "2030-01-01-test-robot-r9" not in first.mission_records
