"""Online ingest: a mission streamed piece by piece over HTTP to a real server ends in the
same catalog as `standgrid tile` of the mission folder; re-sent pieces are stored once;
writes without the token change nothing."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import laspy
import numpy as np
import pytest
import yaml

from standgrid.mission.live import LiveMission
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import CRS, MISSIONS

TOKEN = "ingest-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
NAME = MISSIONS["2024"]
SOURCE = BUNDLED_MISSIONS / NAME


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, Path]]:
    from standgrid.catalog import Catalog
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    folder = tmp_path_factory.mktemp("ingest")
    catalog = folder / "catalog"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    missions = folder / "inbox"
    with running(create_app(catalog, token=TOKEN, missions=missions)) as server:
        assert server.base_url is not None
        yield server.base_url, catalog, missions


def _metadata() -> dict:
    meta = yaml.safe_load((SOURCE / "metadata.yaml").read_text())
    return {
        "name": NAME,
        "date": str(meta["date"]),
        "time": meta["time"],
        "place": meta["place"],
        "robot": meta["robot"],
        "unit": meta["unit"],
        "sensors": meta["sensors"],
        "tags": meta["tags"],
        "gnss": meta["gnss"],
    }


def _tiles(catalog: Path) -> dict[str, laspy.LasData]:
    from standgrid.catalog import Catalog

    opened = Catalog.open(catalog)
    return {rel: laspy.read(opened.path(rel)) for rel in opened.tiles_of(NAME)}


def test_streamed_mission_tiles_like_the_folder(
    served: tuple[str, Path, Path], tmp_path: Path
) -> None:
    from standgrid.mission.opening import open_mission
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    base, catalog, missions = served
    url = f"{base}/missions"
    # unauthenticated writes are refused and leave nothing behind
    assert httpx.post(url, json=_metadata()).status_code == 401
    assert not missions.exists()

    created = httpx.post(url, json=_metadata(), headers=AUTH)
    assert created.status_code == 201, created.text
    assert httpx.post(url, json=_metadata(), headers=AUTH).status_code == 200  # idempotent
    other = {**_metadata(), "robot": "spot"}
    assert httpx.post(url, json=other, headers=AUTH).status_code == 409

    graph = (SOURCE / "slam_pose_graph.g2o").read_bytes()
    r = httpx.put(f"{url}/{NAME}/graph", content=graph, headers=AUTH)
    assert r.status_code == 200 and r.json()["outcome"] == "stored"
    assert (
        httpx.put(f"{url}/{NAME}/graph", content=graph, headers=AUTH).json()["outcome"]
        == "unchanged"
    )

    mission = open_mission(SOURCE, strict=False)
    for payload in mission.payloads:
        x, y, z = mission.pose_of(payload)[:3, 3]
        from standgrid.geometry import translation_quat

        _, q = translation_quat(mission.pose_of(payload))
        params = {
            "stamp": f"{payload.stamp.sec}_{payload.stamp.nsec:09d}",
            "format": "pcd",
            "pose": ",".join(repr(float(v)) for v in (x, y, z, *q)),
        }
        r = httpx.post(
            f"{url}/{NAME}/payloads", params=params, content=payload.path.read_bytes(), headers=AUTH
        )
        assert r.status_code == 201, r.text
    # a payload re-sent after a dropped connection is stored once; another cloud is refused
    first = mission.payloads[0]
    params = {"stamp": f"{first.stamp.sec}_{first.stamp.nsec:09d}"}
    again = httpx.post(
        f"{url}/{NAME}/payloads", params=params, content=first.path.read_bytes(), headers=AUTH
    )
    assert again.status_code == 200 and again.json()["outcome"] == "unchanged"
    changed = httpx.post(
        f"{url}/{NAME}/payloads",
        params=params,
        content=mission.payloads[1].path.read_bytes(),
        headers=AUTH,
    )
    assert changed.status_code == 409
    garbage = httpx.post(
        f"{url}/{NAME}/payloads",
        params={"stamp": "1_000000001"},
        content=b"not a cloud",
        headers=AUTH,
    )
    assert garbage.status_code == 400 and garbage.json()["detail"]
    stored = sorted(p.name for p in (missions / NAME / "payload_clouds").iterdir())
    assert stored == sorted(p.path.name for p in mission.payloads)

    # GNSS in two overlapping chunks: every fix kept once
    lines = (SOURCE / "gnss/fixes.txt").read_text().splitlines()
    header, rows = lines[0], lines[1:]
    half = len(rows) // 2
    for chunk in (rows[: half + 50], rows[half - 50 :]):
        r = httpx.post(
            f"{url}/{NAME}/gnss", content="\n".join([header, *chunk]) + "\n", headers=AUTH
        )
        assert r.status_code == 200, r.text
    from standgrid.mission.sensors import read_gnss

    assert len(read_gnss(missions / NAME / "gnss/fixes.txt")) == len(rows)

    tiled = httpx.post(f"{url}/{NAME}/tile", headers=AUTH, timeout=300)
    assert tiled.status_code == 200, tiled.text

    reference = tmp_path / "reference"
    tile_missions([SOURCE], reference, TileOptions(cell_size=20.0, crs=CRS))
    got, want = _tiles(catalog), _tiles(reference)
    assert sorted(got) == sorted(want) and got
    for rel, las in want.items():
        assert got[rel].header.point_count == las.header.point_count, rel
        np.testing.assert_array_equal(got[rel].points.array, las.points.array)
    # the served catalog answers for the new mission at once
    summary = httpx.get(f"{url}/{NAME}").json()
    assert summary["payload_count"] == len(mission.payloads)

    # a pose-graph update moving one payload's node 2 m re-aligns that payload at the next tile
    moved = mission.payloads[5]
    lines = []
    for line in graph.decode().splitlines():
        parts = line.split()
        if (
            parts
            and parts[0] == "VERTEX_SE3:QUAT_TIME"
            and (int(parts[-2]), int(parts[-1])) == (moved.stamp.sec, moved.stamp.nsec)
        ):
            parts[2] = repr(float(parts[2]) + 2.0)
            line = " ".join(parts)
        lines.append(line)
    before = _payload_centres(got, len(mission.payloads))
    r = httpx.put(f"{url}/{NAME}/graph", content="\n".join(lines) + "\n", headers=AUTH)
    assert r.json()["outcome"] == "stored"
    assert httpx.post(f"{url}/{NAME}/tile", headers=AUTH, timeout=300).status_code == 200
    after = _payload_centres(_tiles(catalog), len(mission.payloads))
    shift = np.hypot(*(after - before)[:, :2].T)
    assert shift[5] == pytest.approx(2.0, abs=0.05)
    assert np.delete(shift, 5).max() < 0.05


def _payload_centres(tiles: dict[str, laspy.LasData], count: int) -> np.ndarray:
    """Mean x, y of each payload's points over the tiles (payload index = payload_id & 0xFFFF)."""
    xyz = np.concatenate([np.column_stack([t.x, t.y]) for t in tiles.values()])
    index = np.concatenate([np.asarray(t["payload_id"]) & 0xFFFF for t in tiles.values()])
    return np.array([xyz[index == k].mean(axis=0) for k in range(count)])


def test_write_names_and_bodies_are_checked(served: tuple[str, Path, Path]) -> None:
    base, _, missions = served
    for name in ("..", ".hidden", "a/b", "a b", "x" * 200):
        r = httpx.post(f"{base}/missions", json={**_metadata(), "name": name}, headers=AUTH)
        assert r.status_code in (400, 404), name  # a slash never reaches the route
        assert r.headers["content-type"] == "application/problem+json"
    made = list(missions.iterdir()) if missions.exists() else []
    assert not any(p.name.startswith(".") and p.is_dir() for p in made)
    r = httpx.post(
        f"{base}/missions/nope/payloads",
        params={"stamp": "1_000000001"},
        content=b"x",
        headers=AUTH,
    )
    assert r.status_code == 404
    assert httpx.post(f"{base}/missions/nope/tile", headers=AUTH).status_code == 404
    r = httpx.post(f"{base}/missions", json={"name": "x"}, headers=AUTH)
    assert r.status_code == 400 and "date" in r.json()["detail"]


def test_a_payload_pose_adds_its_node(tmp_path: Path) -> None:
    from standgrid.geometry import pose_matrix
    from standgrid.mission.metadata import read_metadata
    from standgrid.mission.opening import open_mission
    from standgrid.stamps import Stamp

    live = LiveMission(tmp_path / NAME)
    meta = read_metadata(SOURCE / "metadata.yaml")
    assert live.create(meta) == "created"
    assert live.create(meta) == "unchanged"
    source = open_mission(SOURCE, strict=False)
    poses = {}
    for k, payload in enumerate(source.payloads[:3]):
        pose = pose_matrix([10.0 * k, 2.0, 0.5], [0.0, 0.0, np.sin(k / 4), np.cos(k / 4)])
        poses[payload.stamp] = pose
        assert live.add_payload(payload.stamp, payload.path.read_bytes(), "pcd", pose) == "stored"
    mission = open_mission(live.path)
    assert [p.stamp for p in mission.payloads] == list(poses)
    for p in mission.payloads:
        np.testing.assert_allclose(mission.pose_of(p), poses[p.stamp], atol=1e-12)
    from standgrid.errors import StandgridError

    with pytest.raises(StandgridError, match="unknown cloud format"):
        live.add_payload(Stamp(1, 2), b"data", "xyz")
    assert not list(live.path.glob("payload_clouds/cloud_1_*"))


def _start(catalog: Path, missions: Path, token_file: Path, env: dict[str, str]) -> tuple:
    import json
    import os
    import subprocess
    import sys

    from tests.conftest import REPO_ROOT

    command = [
        sys.executable,
        "-c",
        "from standgrid.cli import main; main()",
        "serve",
        str(catalog),
        "--port",
        "0",
        "--json",
        "--missions",
        str(missions),
        "--token-file",
        str(token_file),
    ]
    proc = subprocess.Popen(
        command,
        cwd=REPO_ROOT,
        env={**os.environ, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    return proc, json.loads(proc.stdout.readline())["service"].rstrip("/")


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _wait_gone(pids: list[int], timeout: float = 10.0) -> None:
    import time

    deadline = time.monotonic() + timeout
    while any(Path(f"/proc/{p}").exists() for p in pids):
        assert time.monotonic() < deadline, f"processes {pids} outlived the server"
        time.sleep(0.05)


def test_a_tiler_killed_while_committing_then_the_server_restart_consistent(
    tmp_path: Path,
) -> None:
    """SIGKILL of the tiling worker in the middle of the tile commit's renames (after its
    journal): the server answers a problem document and keeps serving; the server is then
    killed too (before any read finished the commit) and the restarted server rolls the
    commit forward and serves the whole mission, every tile complete."""
    import shutil
    import signal

    from standgrid.catalog import Catalog
    from standgrid.catalog.journal import CRASH_ENV, JOURNAL_FILE
    from standgrid.mission.metadata import read_metadata
    from standgrid.partition import StandGrid

    catalog = tmp_path / "catalog"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    missions = tmp_path / "inbox"
    missions.mkdir()
    live = LiveMission(missions / NAME)
    live.create(read_metadata(SOURCE / "metadata.yaml"))
    live.set_graph((SOURCE / "slam_pose_graph.g2o").read_bytes())
    live.add_gnss((SOURCE / "gnss/fixes.txt").read_bytes())
    for cloud in sorted((SOURCE / "payload_clouds").iterdir()):
        shutil.copy(cloud, live.path / "payload_clouds" / cloud.name)
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)

    proc, base = _start(catalog, missions, token_file, {CRASH_ENV: "rename-1"})
    try:
        r = httpx.post(f"{base}/missions/{NAME}/tile", headers=AUTH, timeout=300)
        assert r.status_code == 500, r.text
        assert r.headers["content-type"] == "application/problem+json"
        assert "tiling worker died" in r.json()["detail"]
        # the server lives on (the constant conformance document reads no catalog state)
        assert httpx.get(f"{base}/ogc/conformance").status_code == 200
        assert proc.poll() is None
        assert list(catalog.rglob(JOURNAL_FILE))  # the dead commit, not finished yet
        # a write starts the mission folders' worker; killed with the server, it leaves none
        other = {"name": "another-mission", "date": "2024-05-15"}
        created = httpx.post(f"{base}/missions", json=other, headers=AUTH, timeout=60)
        assert created.status_code == 201, created.text
        workers = _children(proc.pid)
        assert workers
        proc.kill()
        proc.wait(timeout=60)
        assert proc.returncode == -signal.SIGKILL
        _wait_gone(workers)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    proc, base = _start(catalog, missions, token_file, {})
    try:
        summary = httpx.get(f"{base}/missions/{NAME}")
        assert summary.status_code == 200, summary.text
        opened = Catalog.open(catalog)
        record = opened.mission_records[NAME]
        points = sum(laspy.read(opened.path(t)).header.point_count for t in record.tiles)
        assert record.tiles and points >= record.point_count > 0
        cells = httpx.get(f"{base}/ogc/collections/cells/items", params={"limit": 1000}).json()
        assert sorted(f["properties"]["tile_path"] for f in cells["features"]) == sorted(
            record.tiles
        )
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)


def test_concurrent_senders_are_serialised(tmp_path: Path) -> None:
    """Eight threads send the same payload (stored once) and eight send different payloads
    with their node poses (every node lands in the graph: no lost update)."""
    from concurrent.futures import ThreadPoolExecutor

    from standgrid.mission.metadata import read_metadata
    from standgrid.mission.opening import open_mission
    from standgrid.mission.posegraph import read_pose_graph

    live = LiveMission(tmp_path / NAME)
    live.create(read_metadata(SOURCE / "metadata.yaml"))
    source = open_mission(SOURCE, strict=False)
    first = source.payloads[0]
    data = first.path.read_bytes()
    with ThreadPoolExecutor(8) as pool:
        outcomes = list(pool.map(lambda _: live.add_payload(first.stamp, data, "pcd"), range(8)))
    assert sorted(outcomes) == ["stored", *["unchanged"] * 7]
    others = source.payloads[1:9]
    with ThreadPoolExecutor(8) as pool:
        outcomes = list(
            pool.map(
                lambda p: live.add_payload(p.stamp, p.path.read_bytes(), "pcd", source.pose_of(p)),
                others,
            )
        )
    assert outcomes == ["stored"] * len(others)
    graph = read_pose_graph(live.path / "slam_pose_graph.g2o")
    assert sorted(v.stamp for v in graph.vertices.values()) == sorted(p.stamp for p in others)


def test_a_mission_tiling_does_not_hold_up_another_missions_writes(tmp_path: Path) -> None:
    """While mission A tiles (here it waits for the catalog, which another writer holds), A's
    next write waits for its turn in the server, and mission B's writes pass at once (they
    used to queue in the writer process behind A's write, itself waiting for A's folder)."""
    import fcntl
    import time
    from concurrent.futures import ThreadPoolExecutor

    from standgrid.catalog import Catalog
    from standgrid.mission.opening import open_mission
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    catalog, missions = tmp_path / "catalog", tmp_path / "inbox"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    source = open_mission(SOURCE, strict=False)
    first = source.payloads[0]
    stamp = {"stamp": f"{first.stamp.sec}_{first.stamp.nsec:09d}", "format": "pcd"}
    app = create_app(catalog, token=TOKEN, missions=missions)
    with running(app) as server:
        url = f"{server.base_url}/missions"
        assert httpx.post(url, json=_metadata(), headers=AUTH).status_code == 201
        graph = (SOURCE / "slam_pose_graph.g2o").read_bytes()
        assert httpx.put(f"{url}/{NAME}/graph", content=graph, headers=AUTH).status_code == 200
        r = httpx.post(
            f"{url}/{NAME}/payloads", params=stamp, content=first.path.read_bytes(), headers=AUTH
        )
        assert r.status_code == 201, r.text
        early = httpx.post(f"{url}/{NAME}/tile", headers=AUTH, timeout=120)
        assert early.status_code == 409 and "GNSS" in early.json()["detail"]  # not yet
        fixes = (SOURCE / "gnss/fixes.txt").read_bytes()
        assert httpx.post(f"{url}/{NAME}/gnss", content=fixes, headers=AUTH).status_code == 200
        a_folder = LiveMission(missions / NAME)
        with ThreadPoolExecutor(2) as pool, Catalog.writing(catalog):
            tiling = pool.submit(httpx.post, f"{url}/{NAME}/tile", headers=AUTH, timeout=120)
            deadline = time.monotonic() + 60
            with open(a_folder.lock_path, "a+b") as handle:  # wait until the tiler holds A
                while True:
                    try:
                        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    except BlockingIOError:
                        break
                    fcntl.flock(handle, fcntl.LOCK_UN)
                    assert time.monotonic() < deadline, "the tiler never took mission A"
                    time.sleep(0.05)
            resent = pool.submit(
                httpx.post,
                f"{url}/{NAME}/payloads",
                params=stamp,
                content=first.path.read_bytes(),
                headers=AUTH,
                timeout=120,
            )
            time.sleep(0.5)  # A's write is in first
            other = {**_metadata(), "name": "another-robot-mission"}
            created = httpx.post(url, json=other, headers=AUTH, timeout=15)
            assert created.status_code == 201, created.text
            assert not tiling.done() and not resent.done()  # A still waits for the catalog
        assert tiling.result().status_code == 200, tiling.result().text
        assert app.state.mission_turns == {}  # turns nobody holds are dropped
        assert resent.result().status_code == 200 and resent.result().json()["outcome"] == (
            "unchanged"
        )
