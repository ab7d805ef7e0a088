"""Payload layers (issue 24): a payload retrieved with its enrichment from the catalog, in the
API, the CLI and the service, equals the tiles' values point for point (the tiles read with
laspy, the second reader); re-tiled or re-enriched epochs are never served stale."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
from click.testing import CliRunner
from fastapi.testclient import TestClient

import standgrid
from standgrid.catalog import Catalog
from standgrid.cli import cli
from standgrid.clouds import read_cloud, write_cloud
from standgrid.enrichment.options import EnrichOptions
from standgrid.enrichment.payload_layers import (
    LAYERS,
    PAYLOAD_TREE_COLUMNS,
    PayloadLayers,
    layers_of,
)
from standgrid.errors import OptionError, PayloadNotTiledError, StaleLayersError
from standgrid.georeference.fit import GeoreferenceFit
from standgrid.georeference.project import MapProjector
from standgrid.mission.opening import open_mission
from standgrid.pipeline.enrich import enrich_catalog
from standgrid.pipeline.tile import tile_missions
from standgrid.pointcloud import PointCloud
from standgrid.serve import create_app
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import MISSIONS, EnrichedPair, copy_catalog, enriched_pair

FIELDS = ("classification", "height_above_ground", "tree_id")


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    return enriched_pair(tmp_path_factory)


def tile_points(root: Path, epoch: str) -> dict[int, dict[str, np.ndarray]]:
    """Per payload_id, the core points of the epoch's tiles (laspy): mm keys and layers; and
    how many buffer copies (withheld) of its points the tiles hold."""
    parts: dict[int, list[dict[str, np.ndarray]]] = {}
    for tile in sorted((root / "tiles" / epoch).glob("*.laz")):
        las = laspy.read(tile)
        ids = np.asarray(las["payload_id"])
        withheld = np.asarray(las.withheld, dtype=bool)
        keys = np.rint(np.column_stack([las.x, las.y, las.z]) * 1000).astype(np.int64)
        for ident in np.unique(ids):
            mine, core = ids == ident, (ids == ident) & ~withheld
            part = {"keys": keys[core], "withheld": np.array([int((mine & withheld).sum())])}
            part |= {name: np.asarray(las[name])[core] for name in FIELDS}
            parts.setdefault(int(ident), []).append(part)
    return {
        ident: {k: np.concatenate([p[k] for p in ps]) for k in ps[0]} for ident, ps in parts.items()
    }


def by_point(keys: np.ndarray, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Points sorted by position then by their values (a multiset, compared row by row)."""
    hag = np.nan_to_num(np.asarray(values["height_above_ground"], np.float64), nan=-1e9)
    order = np.lexsort(
        (hag, values["tree_id"], values["classification"], keys[:, 2], keys[:, 1], keys[:, 0])
    )
    return {"keys": keys[order], **{name: np.asarray(values[name])[order] for name in FIELDS}}


def assert_same_points(got: dict[str, np.ndarray], tiles: dict[str, np.ndarray]) -> None:
    a, b = by_point(got["keys"], got), by_point(tiles["keys"], tiles)
    np.testing.assert_array_equal(a["keys"], b["keys"])
    for name in FIELDS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def layered_points(layered: PayloadLayers) -> dict[str, np.ndarray]:
    keys = np.rint(layered.xyz_crs[layered.tiled] * 1000).astype(np.int64)
    return {"keys": keys, **{n: layered.fields[n][layered.tiled] for n in FIELDS}}


def las_points(data: bytes | Path) -> dict[str, np.ndarray]:
    las = laspy.read(io.BytesIO(data) if isinstance(data, bytes) else data)
    keys = np.rint(np.column_stack([las.x, las.y, las.z]) * 1000).astype(np.int64)
    return {"keys": keys, **{name: np.asarray(las[name]) for name in FIELDS}}


def test_api_layers_equal_the_tiles_point_for_point(pair: EnrichedPair) -> None:
    """Every payload of both missions: its per-point layers are the tiles' core points of its
    payload_id (buffer copies excluded), one to one; each layered point lies where the
    payload's own point projects (exact chain, independent of the tiler's fast path)."""
    catalog = Catalog.open(pair.path)
    copies = 0
    for epoch, name in MISSIONS.items():
        tiles = tile_points(pair.path, epoch)
        mission = open_mission(BUNDLED_MISSIONS / name, strict=False)
        found = standgrid.retrieve_payload_by_type(mission, "point_cloud", catalog=pair.path)
        assert len(found) == len(mission.payloads) and set(tiles) == {f.payload_id for f in found}
        record = catalog.mission_records[name]
        projector = MapProjector(GeoreferenceFit.from_dict(record.georeference), catalog.crs)
        for layered in found:
            assert layered.tiled.all() and layered.layers == LAYERS
            assert layered.enrichment_id == catalog.epochs[epoch]["enrichment_id"]
            mine = tiles[layered.payload_id]
            assert len(mine["keys"]) == layered.point_count
            assert_same_points(layered_points(layered), mine)
            copies += int(mine["withheld"].sum())
            pose = mission.pose_of(layered.payload)
            exact = projector.exact(layered.cloud.xyz @ pose[:3, :3].T + pose[:3, 3])
            assert np.abs(layered.xyz_crs - exact).max() <= 1.5e-3
    assert copies > 1000  # the tiles' buffer copies of these points were there, and left out


def test_trees_and_terrain_of_a_payload(pair: EnrichedPair) -> None:
    import pandas as pd
    import rasterio

    mission = open_mission(BUNDLED_MISSIONS / MISSIONS["2024"], strict=False)
    (layered,) = standgrid.retrieve_payload_by_pose(mission, (10.0, 0.0), catalog=pair.path)
    trees, ids = layered.trees, layered.fields["tree_id"]
    assert trees is not None and len(trees) > 10
    assert tuple(trees.columns) == PAYLOAD_TREE_COLUMNS
    table = pd.read_parquet(pair.path / "tables/tree_list_2024.parquet").set_index("tree_id")
    seen = set(np.unique(ids[ids != 0]).tolist())
    assert seen <= set(trees["tree_id"])  # every tree the payload's points belong to
    for row in trees.itertuples():
        assert row.payload_points == int((ids == row.tree_id).sum())
        assert row.payload_points > 0 or row.in_footprint
        listed = table.loc[row.tree_id]
        assert (row.x, row.y, row.height_m) == (listed["x"], listed["y"], listed["height_m"])
    # positions in the payload frame: back through the pose and projection to the CRS
    record = Catalog.open(pair.path).mission_records[MISSIONS["2024"]]
    projector = MapProjector(GeoreferenceFit.from_dict(record.georeference), "EPSG:32630")
    pose = mission.pose_of(layered.payload)
    local = trees[["x_payload", "y_payload", "z_payload"]].to_numpy()
    back = projector.exact(local @ pose[:3, :3].T + pose[:3, 3])
    assert np.abs(back - trees[["x", "y", "z"]].to_numpy()).max() < 1e-6
    terrain = layered.terrain
    assert terrain is not None
    with rasterio.open(pair.path / "rasters/2024/dtm.tif") as ds:
        row, col = ds.index(terrain.grid.x0 + 0.5, terrain.grid.y0 + 0.5)  # lower-left pixel
        dtm = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    bottom_left = dtm[row - terrain.grid.nrows + 1 : row + 1, col : col + terrain.grid.ncols]
    np.testing.assert_array_equal(terrain.heights, bottom_left)
    xy = layered.xyz_crs[:, :2]
    assert terrain.grid.x0 <= xy[:, 0].min() and xy[:, 0].max() < terrain.grid.bounds[2]
    seen_px = np.isfinite(terrain.heights.ravel())
    assert seen_px.sum() > 100 and np.isfinite(terrain.payload_xyz[seen_px]).all()


def test_by_gnss_gives_the_same_layers_and_asks_only_for_named_ones(pair: EnrichedPair) -> None:
    name = MISSIONS["2028"]
    mission = open_mission(BUNDLED_MISSIONS / name, strict=False)
    (hit,) = standgrid.retrieve_payload_by_gnss(mission, (51.77650, -1.33860), max_distance=None)
    (layered,) = standgrid.retrieve_payload_by_gnss(
        mission, (51.77650, -1.33860), max_distance=None, catalog=pair.path, layers="ground"
    )
    from standgrid.georeference.retrieval import retrieve_payload_by_gnss

    assert [hit] == retrieve_payload_by_gnss(mission, (51.77650, -1.33860), max_distance=None)
    assert layered.payload == hit and layered.layers == ("ground",)
    assert set(layered.fields) == {"classification"} and layered.trees is None
    tiles = tile_points(pair.path, "2028")[layered.payload_id]
    mine = np.rint(layered.xyz_crs * 1000).astype(np.int64)
    a = np.lexsort((layered.fields["classification"], *mine.T[::-1]))
    b = np.lexsort((tiles["classification"], *tiles["keys"].T[::-1]))
    np.testing.assert_array_equal(mine[a], tiles["keys"][b])
    np.testing.assert_array_equal(layered.fields["classification"][a], tiles["classification"][b])
    with pytest.raises(OptionError, match="unknown layer 'crowns'"):
        standgrid.retrieve_payload_by_type(
            mission, "point_cloud", catalog=pair.path, layers="ground,crowns"
        )


def test_cli_writes_the_layered_payload(pair: EnrichedPair, tmp_path: Path) -> None:
    folder = BUNDLED_MISSIONS / MISSIONS["2024"]
    out = tmp_path / "payload.laz"
    args = ["retrieve", "by-pose", str(folder), "10", "0", "--layers", str(pair.path)]
    result = CliRunner().invoke(cli, [*args, "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    (row,) = json.loads(result.output)
    enrichment = row["enrichment"]
    assert enrichment["written"] == str(out) and enrichment["points_tiled"] == enrichment["points"]
    tiles = tile_points(pair.path, "2024")[enrichment["payload_id"]]
    got = las_points(out)
    assert len(got["keys"]) == enrichment["points"]
    assert_same_points(got, tiles)
    assert enrichment["ground_points"] == int((tiles["classification"] == 2).sum())
    human = CliRunner().invoke(cli, [*args, "--which", "ground,height"])
    assert human.exit_code == 0 and f"{enrichment['ground_points']} ground" in human.output
    # two payloads into a folder, in the payload frame: the payload file's points, in order
    folder_out = tmp_path / "clouds"
    two = CliRunner().invoke(
        cli, [*args, "-k", "2", "--frame", "payload", "--out", str(folder_out)]
    )
    assert two.exit_code == 0, two.output
    mission = open_mission(folder, strict=False)
    for written in sorted(folder_out.glob("*.laz")):
        (payload,) = [
            p for p in mission.payloads if written.stem == f"{p.stamp.sec}_{p.stamp.nsec:09d}"
        ]
        las = laspy.read(written)
        xyz = np.column_stack([las.x, las.y, las.z])
        assert np.abs(xyz - mission.load_base(payload).xyz).max() <= 0.5e-3
    assert len(list(folder_out.glob("*.laz"))) == 2
    bad = CliRunner().invoke(cli, [*args, "--which", "ground,crowns"])
    assert bad.exit_code == 2 and "--which" in bad.output


def test_service_serves_the_layered_payload(pair: EnrichedPair) -> None:
    name = MISSIONS["2028"]
    tiles = tile_points(pair.path, "2028")
    ident = min(tiles)
    with TestClient(create_app(pair.path)) as client:
        base = f"/missions/{name}/payloads/{ident}"
        laz = client.get(base, params={"layers": "ground,height,trees"})
        assert laz.status_code == 200 and laz.headers["content-type"] == "application/vnd.laszip"
        assert_same_points(las_points(laz.content), tiles[ident])
        as_json = client.get(base, params={"layers": "trees,terrain", "format": "json"}).json()
        assert as_json["payload_id"] == ident and as_json["points"] == len(tiles[ident]["keys"])
        assert len(as_json["tree_list"]) == as_json["trees"] > 0
        assert as_json["terrain"]["nrows"] * as_json["terrain"]["ncols"] > 100
        stamp = as_json["stamp"].replace(".", "_")
        by_stamp = client.get(f"/missions/{name}/payloads/{stamp}", params={"layers": "all"})
        assert_same_points(las_points(by_stamp.content), tiles[ident])
        record = client.get(base).json()
        assert record["payloads"][0]["stamp"] == as_json["stamp"]
        unknown = client.get(base, params={"layers": "ground,crowns"})
        assert unknown.status_code == 400 and "crowns" in unknown.json()["detail"]
        missing = client.get(f"/missions/{name}/payloads/{ident + 500}", params={"layers": "all"})
        assert missing.status_code == 404


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_never_stale_after_retiling_or_re_enriching(pair: EnrichedPair, tmp_path: Path) -> None:
    """One server over a copy: re-tiling 2028 makes its layers a 409 (typed error in the
    API); enriching it again (other options) serves the new tiles' values."""
    root = copy_catalog(pair.path, tmp_path / "catalog")
    name = MISSIONS["2028"]
    mission = open_mission(BUNDLED_MISSIONS / name, strict=False)
    first = mission.payloads[3]
    with TestClient(create_app(root)) as client:
        url = f"/missions/{name}/payloads/{first.stamp.sec}_{first.stamp.nsec:09d}"
        before = client.get(url, params={"layers": "all"})
        assert before.status_code == 200
        tile_missions([BUNDLED_MISSIONS / name], root)
        stale = client.get(url, params={"layers": "all"})
        assert stale.status_code == 409 and "re-tiled" in stale.json()["detail"]
        with pytest.raises(StaleLayersError, match="re-tiled"):
            standgrid.retrieve_payload_by_type(mission, "point_cloud", catalog=root)
        enrich_catalog(
            root, EnrichOptions(epochs=("2028",), cloth_resolution=1.0, tree_min_height=5.0)
        )
        after = client.get(url, params={"layers": "all"})
        assert after.status_code == 200
        assert after.headers["x-standgrid-enrichment"] != before.headers["x-standgrid-enrichment"]
    (layered,) = standgrid.retrieve_payload_by_pose(
        mission, mission.pose_of(first)[:3, 3], catalog=root
    )
    tiles = tile_points(root, "2028")[layered.payload_id]
    assert_same_points(layered_points(layered), tiles)
    old, new = las_points(before.content), las_points(after.content)
    assert_same_points(new, tiles)
    # the payload's points in their order: the new enrichment's values, not the old ones
    assert not all(np.array_equal(old[n], new[n], equal_nan=True) for n in FIELDS)


def test_refusals(pair: EnrichedPair, tmp_path: Path) -> None:
    """Not tiled (another folder, an IMU payload), not enriched, changed since tiled: typed
    errors."""
    name = MISSIONS["2024"]
    mission = open_mission(BUNDLED_MISSIONS / name, strict=False)
    imu = standgrid.retrieve_payload_by_type(mission, "imu")
    with pytest.raises(PayloadNotTiledError, match="not a point-cloud payload"):
        layers_of(pair.path, mission, imu[:1])
    moved = shutil.copytree(BUNDLED_MISSIONS / name, tmp_path / name)
    with pytest.raises(PayloadNotTiledError, match="was tiled from"):
        standgrid.retrieve_payload_by_type(moved, "point_cloud", catalog=pair.path)
    # the catalog's record pointed at the copy, one payload nudged by 2 mm: no longer its tiles
    root = copy_catalog(pair.path, tmp_path / "catalog")
    state = json.loads((root / "catalog.json").read_text())
    state["missions"][name]["path"] = str(moved)
    state["epochs"]["2028"]["enriched"] = False  # as if never enriched
    (root / "catalog.json").write_text(json.dumps(state))
    other = open_mission(BUNDLED_MISSIONS / MISSIONS["2028"], strict=False)
    with pytest.raises(StaleLayersError, match="is not enriched"):
        layers_of(root, other, other.payloads[:1])
    with TestClient(create_app(root)) as client:
        url = f"/missions/{MISSIONS['2028']}/payloads/{2 << 16}"
        assert client.get(url, params={"layers": "ground"}).status_code == 409
    copy = open_mission(moved, strict=False)
    payload = copy.payloads[5]
    cloud = read_cloud(payload.path)
    write_cloud(PointCloud(cloud.xyz + np.array([0.002, 0.0, 0.0]), cloud.fields), payload.path)
    fresh = open_mission(moved, strict=False)
    with pytest.raises(StaleLayersError, match="do not match"):
        standgrid.retrieve_payload_by_pose(fresh, fresh.pose_of(payload)[:3, 3], catalog=root)
    others = standgrid.retrieve_payload_by_pose(
        fresh, fresh.pose_of(fresh.payloads[0])[:3, 3], catalog=root
    )
    assert others[0].tiled.all()  # the other payloads still match
