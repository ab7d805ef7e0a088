"""The placement tolerance: a GNSS-fit mission streamed batch by batch (pose graph, payloads
and fixes growing, as a robot sends them) keeps the placement its catalog used while a
refit moves it less than the tolerance, re-tiling in place; beyond it the epoch re-tiles
whole; an exact settle at the end gives the catalog `standgrid tile` of the folder gives."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from standgrid.catalog import Catalog
from standgrid.export.las import read_tile
from standgrid.mission.live import LiveMission
from standgrid.mission.metadata import read_metadata
from standgrid.mission.opening import open_mission
from standgrid.pipeline.tile import tile_missions
from standgrid.simulate.stream import fixes_until, graph_until
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import (
    CRS,
    MISSIONS,
    assert_same_tiles_and_cells,
    tile_files,
    tile_points,
)

NAME = MISSIONS["2024"]
SOURCE = BUNDLED_MISSIONS / NAME
TOLERANCE = 0.05
#: payloads per batch the robot sends before asking for a tile
BATCH = 2


def batches() -> list[tuple[bytes, list[tuple], bytes]]:
    """The robot's batches: (pose graph so far, payloads (stamp, bytes, pose), fixes so far);
    the last batch carries the whole graph and log."""
    source = open_mission(SOURCE, strict=False)
    payloads = source.payloads
    out = []
    for start in range(0, len(payloads), BATCH):
        chunk = payloads[start : start + BATCH]
        last = start + BATCH >= len(payloads)
        until = None if last else payloads[start + BATCH].stamp.ns - 1
        graph = graph_until(SOURCE, until if until is not None else 1 << 62)
        sent = [(p.stamp, p.path.read_bytes(), source.pose_of(p)) for p in chunk]
        out.append((graph, sent, fixes_until(SOURCE, until)))
    return out


def _payload_means(root: Path) -> dict[int, np.ndarray]:
    """Mean x, y, z of each payload's points over the catalog's tiles."""
    catalog = Catalog.open(root)
    clouds = [read_tile(catalog.path(rel)) for rel in catalog.tiles("2024")]
    xyz = np.concatenate([c.xyz for c in clouds])
    ids = np.concatenate([c.fields["payload_id"].astype(np.int64) for c in clouds])
    return {int(k): xyz[ids == k].mean(axis=0) for k in np.unique(ids)}


@pytest.fixture(scope="module")
def stream(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The mission streamed batch by batch under the tolerance, tiled after every batch, then
    settled exactly; and `standgrid tile` of the final folder."""
    import pyogrio

    folder = tmp_path_factory.mktemp("tolerance")
    (folder / "missions").mkdir()
    live = LiveMission(folder / "missions" / NAME)
    live.create(read_metadata(SOURCE / "metadata.yaml"))
    catalog = folder / "catalog"
    options = TileOptions(cell_size=20.0, crs=CRS, placement_tolerance=TOLERANCE)
    steps: list[dict] = []
    for graph, payloads, fixes in batches():
        live.set_graph(graph)
        for stamp, data, pose in payloads:
            live.add_payload(stamp, data, "pcd", pose)
        live.add_gnss(fixes)
        before = tile_files(catalog) if catalog.exists() else {}
        report = tile_missions([live.path], catalog, options).to_dict()
        steps.append(
            {
                "report": report,
                "before": before,
                "after": tile_files(catalog),
                "tiled_before": BATCH * len(steps),
            }
        )
    streamed = {
        "record": json.loads((catalog / "catalog.json").read_text())["missions"][NAME],
        "missions_layer": pyogrio.read_dataframe(catalog / "index.gpkg", layer="missions"),
        "means": _payload_means(catalog),
    }
    settle = tile_missions([live.path], catalog, TileOptions(cell_size=20.0, crs=CRS))
    batch = folder / "batch"
    tile_missions([live.path], batch, TileOptions(cell_size=20.0, crs=CRS))
    return {
        "steps": steps,
        "streamed": streamed,
        "settle": settle.to_dict(),
        "catalog": catalog,
        "batch": batch,
        "folder": live.path,
    }


def _placement(step: dict) -> dict:
    return step["report"]["missions"][NAME]["placement"]


def test_a_refit_within_the_tolerance_re_tiles_in_place(stream: dict) -> None:
    kept = [s for s in stream["steps"] if _placement(s)["used"] == "kept"]
    assert len(kept) >= 3  # the fit settles once RTK fixes arrive (data/README.md)
    for step in kept:
        placement, epoch = _placement(step), step["report"]["epochs"]["2024"]
        assert 0 < placement["offset_m"] < TOLERANCE
        assert placement["fresh_fit"]["fixes_used"] > 0
        assert epoch["payloads_unchanged"] == step["tiled_before"] > 0
        assert 0 < epoch["cells_rewritten"] < epoch["cells"]
        old = step["before"]
        untouched = [rel for rel in old if step["after"].get(rel) == old[rel]]  # same file
        assert len(untouched) == epoch["cells"] - epoch["cells_rewritten"] > 0


def test_a_refit_beyond_the_tolerance_re_tiles_the_whole_epoch(stream: dict) -> None:
    moved = [s for s in stream["steps"][1:] if _placement(s)["used"] == "fresh"]
    assert moved  # the first batches' fits move by metres, then decimetres
    for step in moved:
        placement, epoch = _placement(step), step["report"]["epochs"]["2024"]
        assert placement["moved_m"] >= TOLERANCE and placement["offset_m"] == 0.0
        assert epoch["payloads_unchanged"] == 0
        assert epoch["cells_rewritten"] == epoch["cells"]


def test_the_kept_placement_is_within_its_offset_of_the_fresh_fit_for_every_point(
    stream: dict,
) -> None:
    """The last streamed tile kept the placement: every point of every payload, through the
    real transforms, is within the reported offset (and the tolerance) of the fresh fit,
    the bound is tight, and the tiles written agree."""
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.placement import place_mission
    from standgrid.georeference.project import MapProjector
    from standgrid.simulate import load_truth
    from tests.pipeline_fixtures import TRUTH_ROOT

    last = stream["steps"][-1]
    placement = _placement(last)
    assert placement["used"] == "kept"
    record = stream["streamed"]["record"]
    assert record["placement"] == placement  # stored in the catalog, as reported
    mission = open_mission(stream["folder"], strict=False)
    fresh = MapProjector(place_mission(mission).fit, CRS)
    kept = MapProjector(GeoreferenceFit.from_dict(record["georeference"]), CRS)
    truth = load_truth(TRUTH_ROOT / NAME)  # the simulator's true map -> ENU
    true = MapProjector(
        GeoreferenceFit.without_fixes(truth.lla_ref, np.linalg.inv(truth.T_map_enu), "truth"), CRS
    )
    largest, kept_error, fresh_error = 0.0, 0.0, 0.0
    for payload in mission.payloads:
        xyz = mission.load_base(payload).xyz
        pose = mission.pose_of(payload)
        local = xyz @ pose[:3, :3].T + pose[:3, 3]
        at = {"fresh": fresh.exact(local), "kept": kept.exact(local), "true": true.exact(local)}
        largest = max(largest, float(np.linalg.norm(at["fresh"] - at["kept"], axis=1).max()))
        kept_error = max(kept_error, float(np.linalg.norm(at["kept"] - at["true"], axis=1).max()))
        fresh_error = max(
            fresh_error, float(np.linalg.norm(at["fresh"] - at["true"], axis=1).max())
        )
    assert largest <= placement["offset_m"] < TOLERANCE
    # what the tolerance costs against the truth: at most the offset on top of the fit's own
    # error (the georeference alone; the SLAM drift is the same under both)
    assert kept_error <= fresh_error + TOLERANCE and kept_error < 0.1  # fresh: ~3 cm here
    assert placement["offset_m"] - largest < 0.005  # corners of cell boxes, not the points
    # the kept catalog's payloads sit within the offset (+ the 1 mm lattice and affine) of
    # where the exact settle put them
    means, settled = stream["streamed"]["means"], _payload_means(stream["catalog"])
    assert sorted(means) == sorted(settled)
    shift = max(float(np.linalg.norm(means[k] - settled[k])) for k in means)
    assert shift <= placement["offset_m"] + 0.002
    layer = stream["streamed"]["missions_layer"]
    assert layer["placement_offset_m"].tolist() == [placement["offset_m"]]


def test_the_exact_settle_equals_tiling_the_folder(stream: dict) -> None:
    import pyogrio

    catalog, batch = Path(stream["catalog"]), Path(stream["batch"])
    settle = stream["settle"]["missions"][NAME]["placement"]
    assert settle["used"] == "fresh" and settle["offset_m"] == 0.0
    assert_same_tiles_and_cells(catalog, batch)
    state = json.loads((catalog / "catalog.json").read_text())["missions"][NAME]
    want = json.loads((batch / "catalog.json").read_text())["missions"][NAME]
    assert state["georeference"]["T_enu_map"] == want["georeference"]["T_enu_map"]
    missions = pyogrio.read_dataframe(catalog / "index.gpkg", layer="missions")
    assert missions["placement_offset_m"].tolist() == [0.0]


def test_placement_offset_of_a_known_shift(tmp_path: Path) -> None:
    """Moving a fit by a known ENU translation moves every point by its length (times the
    projection's scale, within 0.1 % here), and a rotation about the map origin by the
    angle times the farthest point's distance."""
    import dataclasses

    from standgrid.georeference.placement import Placement, place_mission, placement_offset

    fit = place_mission(open_mission(SOURCE, strict=False)).fit
    assert fit is not None
    box = np.array(np.meshgrid([-40.0, 60.0], [-30.0, 50.0], [-5.0, 30.0], indexing="ij"))
    points = box.reshape(3, -1).T
    shifted = np.array(fit.T_enu_map, copy=True)
    shifted[:3, 3] += [0.03, -0.04, 0.0]  # 5 cm horizontally
    moved = Placement(dataclasses.replace(fit, T_enu_map=shifted))
    assert placement_offset(Placement(fit), moved, points, CRS) == pytest.approx(0.05, rel=1e-3)
    angle = 1e-3
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    turned = Placement(dataclasses.replace(fit, T_enu_map=np.asarray(fit.T_enu_map) @ turn))
    farthest = float(np.max(np.hypot(points[:, 0], points[:, 1])))
    assert placement_offset(Placement(fit), turned, points, CRS) == pytest.approx(
        angle * farthest, rel=2e-3
    )


def test_a_negative_tolerance_is_refused(tmp_path: Path) -> None:
    from standgrid.errors import OptionError, TilingError

    with pytest.raises(OptionError, match=r"placement_tolerance: -0\.01"):  # the options refuse it
        tile_missions([SOURCE], tmp_path / "c", TileOptions(placement_tolerance=-0.01))
    assert not (tmp_path / "c").exists()
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app

    catalog = tmp_path / "served"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    for bad in (float("nan"), float("inf"), -1.0):  # refused when the server starts
        with pytest.raises(TilingError, match="placement tolerance"):
            create_app(catalog, placement_tolerance=bad)


def test_a_served_stream_keeps_its_placement_then_settles_exactly(tmp_path: Path) -> None:
    """Over HTTP: batches tiled under the server's tolerance report the placement used;
    `tile?exact=true` settles on the fresh fit, and the catalog equals `standgrid tile` of
    the mission folder, tile for tile, point for point."""
    import httpx

    from standgrid.geometry import translation_quat
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    token = "tolerance-token-0123456789abcdef"
    auth = {"Authorization": f"Bearer {token}"}
    catalog = tmp_path / "catalog"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    app = create_app(
        catalog, token=token, missions=tmp_path / "inbox", placement_tolerance=TOLERANCE
    )
    meta = read_metadata(SOURCE / "metadata.yaml")
    reports = []
    with (
        running(app) as server,
        httpx.Client(base_url=str(server.base_url), headers=auth, timeout=300) as client,
    ):
        r = client.post("/missions", json={"name": NAME, "date": meta.date.isoformat()})
        assert r.status_code == 201, r.text
        sent = batches()
        for k, (graph, payloads, fixes) in enumerate(sent):
            assert client.put(f"/missions/{NAME}/graph", content=graph).status_code == 200
            for stamp, data, pose in payloads:
                t, q = translation_quat(pose)
                params = {
                    "stamp": f"{stamp.sec}_{stamp.nsec:09d}",
                    "pose": ",".join(repr(float(v)) for v in (*t, *q)),
                }
                r = client.post(f"/missions/{NAME}/payloads", params=params, content=data)
                assert r.status_code == 201, r.text
            assert client.post(f"/missions/{NAME}/gnss", content=fixes).status_code == 200
            if k in (2, 5, len(sent) - 1):  # the robot asks for a tile now and then
                r = client.post(f"/missions/{NAME}/tile")
                assert r.status_code == 200, r.text
                reports.append(r.json()["missions"][NAME]["placement"])
        summary = client.get(f"/missions/{NAME}").json()
        r = client.post(f"/missions/{NAME}/tile", params={"exact": "true"})
        assert r.status_code == 200, r.text
        settled = r.json()["missions"][NAME]["placement"]
        after = client.get(f"/missions/{NAME}").json()
    assert [p["tolerance_m"] for p in reports] == [TOLERANCE] * 3
    assert reports[-1]["used"] == "kept" and 0 < reports[-1]["offset_m"] < TOLERANCE
    assert summary["placement"] == reports[-1]  # the forester sees it in the summary
    assert settled == {
        "used": "fresh",
        "tolerance_m": None,
        "offset_m": 0.0,
        "moved_m": None,
        "fresh_fit": None,
    }
    assert after["placement"] == settled
    reference = tmp_path / "reference"
    tile_missions([tmp_path / "inbox" / NAME], reference, TileOptions(cell_size=20.0, crs=CRS))
    got, want = tile_files(catalog), tile_files(reference)
    assert sorted(got) == sorted(want) and got
    for rel in want:
        np.testing.assert_array_equal(tile_points(catalog / rel), tile_points(reference / rel), rel)
