"""Re-tiling a mission that grew: only the tiles its new payloads touch are rewritten, and the
catalog equals one tiled from the whole mission at once."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from standgrid.catalog import Catalog
from standgrid.mission.live import LiveMission
from standgrid.mission.metadata import read_metadata
from standgrid.mission.opening import open_mission
from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import MISSIONS, assert_same_tiles_and_cells, tile_files

SOURCE = BUNDLED_MISSIONS / MISSIONS["2024"]
#: A hand placement (no GNSS fit): the same for every payload count.
ANCHOR = (51.7733, -1.3372, 147.6, 78.1)


def _grow(live: LiveMission, upto: int) -> None:
    """The live mission holds the source's first ``upto`` payloads, with their node poses."""
    source = open_mission(SOURCE, strict=False)
    for payload in source.payloads[:upto]:
        pose = source.pose_of(payload)
        live.add_payload(payload.stamp, payload.path.read_bytes(), payload.path.suffix, pose)


@pytest.fixture(scope="module")
def grown(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A mission tiled with half its payloads, then tiled again with all of them."""
    folder = tmp_path_factory.mktemp("inplace")
    (folder / "missions").mkdir()
    live = LiveMission(folder / "missions" / SOURCE.name)
    live.create(read_metadata(SOURCE / "metadata.yaml"))
    total = len(open_mission(SOURCE, strict=False).payloads)
    options = TileOptions(anchor=ANCHOR)
    catalog = folder / "catalog"
    _grow(live, total // 2)
    tile_missions([live.path], catalog, options)
    before = tile_files(catalog)
    _grow(live, total)
    report = tile_missions([live.path], catalog, options)
    after = tile_files(catalog)
    again = tile_missions([live.path], catalog, options)  # nothing new
    batch = folder / "batch"
    tile_missions([live.path], batch, options)
    return {
        "catalog": catalog,
        "batch": batch,
        "before": before,
        "after": after,
        "report": report.to_dict(),
        "again": again.to_dict(),
        "total": total,
    }


def test_only_the_tiles_the_new_payloads_touch_are_rewritten(grown: dict) -> None:
    epoch = next(iter(grown["report"]["epochs"].values()))
    total = grown["total"]
    assert epoch["payloads_unchanged"] == total // 2
    assert epoch["points_new"] > 0 and 0 < epoch["cells_rewritten"] < epoch["cells"]
    before, after = grown["before"], grown["after"]
    kept = [rel for rel in before if after.get(rel) == before[rel]]  # same file, same bytes
    assert len(kept) == epoch["cells"] - epoch["cells_rewritten"] > 0
    rewritten = [rel for rel in after if after[rel] != before.get(rel)]
    assert len(rewritten) == epoch["cells_rewritten"]


def test_the_grown_catalog_equals_one_tiled_at_once(grown: dict) -> None:
    catalog, batch = Path(grown["catalog"]), Path(grown["batch"])
    tiles = assert_same_tiles_and_cells(catalog, batch)
    import pyogrio

    state = json.loads((catalog / "catalog.json").read_text())
    mission = state["missions"][SOURCE.name]
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    assert mission["point_count"] == cells["point_count"].sum() > 0
    assert sorted(mission["tiles"]) == sorted(tiles)


def test_a_re_tile_of_an_unchanged_mission_rewrites_nothing(grown: dict) -> None:
    epoch = grown["again"]["epochs"]["2024"]
    assert epoch["payloads_unchanged"] == grown["total"]
    assert epoch["cells_rewritten"] == 0 and epoch["points_new"] == 0
    assert "invalidated" not in epoch
    assert tile_files(Path(grown["catalog"])) == grown["after"]


def test_a_buffered_catalog_is_re_tiled_whole(tmp_path: Path) -> None:
    (tmp_path / "missions").mkdir()
    live = LiveMission(tmp_path / "missions" / SOURCE.name)
    live.create(read_metadata(SOURCE / "metadata.yaml"))
    _grow(live, 4)
    options = TileOptions(anchor=ANCHOR, buffer=2.0)
    tile_missions([live.path], tmp_path / "c", options)
    _grow(live, 6)
    report = tile_missions([live.path], tmp_path / "c", options).to_dict()
    epoch = report["epochs"]["2024"]
    assert epoch["payloads_unchanged"] == 0 and epoch["cells_rewritten"] == epoch["cells"]


def test_a_cloud_rewritten_with_its_old_size_and_mtime_is_still_a_change(tmp_path: Path) -> None:
    import os

    from standgrid.tiling.increment import placement_digest, source_digest

    placement = placement_digest({"method": "anchor"})
    cloud = tmp_path / "cloud.pcd"
    cloud.write_bytes(b"A" * 64)
    source = {
        "path": cloud,
        "frame": "base",
        "file_to_base": None,
        "pose": np.eye(4),
        "gps_time": 1.5,
        "point_source_id": 1,
        "payload_id": 65536,
    }
    before = source_digest(source, placement, {"intensity": np.float32})
    assert source_digest(source, placement, {"intensity": np.float32}) == before
    st = cloud.stat()
    cloud.write_bytes(b"B" * 64)  # same size
    os.utime(cloud, ns=(st.st_atime_ns, st.st_mtime_ns))  # and the old modification time
    assert source_digest(source, placement, {"intensity": np.float32}) != before
    moved = dict(source, pose=np.eye(4))
    moved["pose"][0, 3] = 0.001  # a node moved by 1 mm
    changed = source_digest(moved, placement, {"intensity": np.float32})
    assert changed != source_digest(source, placement, {"intensity": np.float32})


def test_an_enriched_epoch_is_re_tiled_in_place_and_kept_when_nothing_changed(
    tmp_path: Path,
) -> None:
    from standgrid.pipeline.enrich import enrich_catalog

    (tmp_path / "missions").mkdir()
    live = LiveMission(tmp_path / "missions" / SOURCE.name)
    live.create(read_metadata(SOURCE / "metadata.yaml"))
    _grow(live, 6)
    catalog, options = tmp_path / "c", TileOptions(anchor=ANCHOR)
    tile_missions([live.path], catalog, options)
    enrich_catalog(catalog)  # adds classification, heights and tree ids to every tile
    chm = catalog / "rasters" / "2024" / "chm.tif"
    again = tile_missions([live.path], catalog, options).to_dict()["epochs"]["2024"]
    assert again["payloads_unchanged"] == 6 and again["cells_rewritten"] == 0
    assert Catalog.open(catalog).epoch("2024").state == "enriched" and chm.exists()
    _grow(live, 8)
    grown = tile_missions([live.path], catalog, options).to_dict()["epochs"]["2024"]
    assert grown["payloads_unchanged"] == 6 and 0 < grown["cells_rewritten"] < grown["cells"]
    assert Catalog.open(catalog).epoch("2024").state == "stale" and not chm.exists()


def test_the_source_field_rules_version_is_in_the_digest_of_clouds_with_those_fields_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bumping the rules for withheld / scan_angle_rank / point_source_id re-reads the
    payloads carrying them (LAS), not every payload: a PCD payload's digest, hence its
    tiles and its epoch's enrichment, stay as they were."""
    import laspy

    from standgrid.tiling import increment
    from standgrid.tiling.increment import placement_digest, source_digest

    pcd = sorted(next(BUNDLED_MISSIONS.iterdir()).glob("payload_clouds/*.pcd"))[0]
    las_path = tmp_path / "cloud.las"
    las = laspy.create(point_format=1, file_version="1.2")
    las.x, las.y, las.z = np.arange(10.0), np.arange(10.0), np.arange(10.0)
    las.write(las_path)
    placement = placement_digest({"method": "anchor"})

    def digests() -> list[str]:
        return [
            source_digest(
                {
                    "path": path,
                    "frame": "base",
                    "file_to_base": None,
                    "pose": np.eye(4),
                    "gps_time": 1.5,
                    "point_source_id": 1,
                    "payload_id": 65536,
                },
                placement,
                {"intensity": np.float32},
            )
            for path in (pcd, las_path)
        ]

    before = digests()
    monkeypatch.setattr(increment, "SOURCE_FIELD_RULES", increment.SOURCE_FIELD_RULES + 1)
    after = digests()
    assert after[0] == before[0] and after[1] != before[1]
