"""standgrid serve at its edges: a hostile payload blocks no other robot's write (a watchdog
kills a worker call over its limit), workers end with the server, a re-sent mission is
200, numbers are checked at the edge (400/404, never 500), both OpenAPI documents are
valid, announcements are bounded, answers hold no server path, a busy port is one clear
line. A real uvicorn server on 127.0.0.1 throughout."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT
from tests.pipeline_fixtures import CRS, MISSIONS

TOKEN = "edges-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
COYOTE = MISSIONS["2024"]
#: The body of the `POST /missions` example of docs/SERVICE.md (Robot integration).
README_BODY = {
    "name": "2024-05-14-wytham-anymal-coyote",
    "date": "2024-05-14",
    "place": "wytham",
    "robot": "anymal",
    "sensors": ["velodyne-vlp16", "gnss"],
}
#: The write time limit of the write server: a payload that still hangs is refused by then.
WRITE_LIMIT_S = 8.0


def _empty_catalog(folder: Path) -> Path:
    from standgrid.catalog import Catalog
    from standgrid.partition import StandGrid

    catalog = folder / "catalog"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    return catalog


@pytest.fixture(scope="module")
def writes(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, Path]]:
    """A server with writes on an empty catalog: base URL, catalog, missions folder."""
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    folder = tmp_path_factory.mktemp("edges")
    catalog, missions = _empty_catalog(folder), folder / "inbox"
    app = create_app(catalog, token=TOKEN, missions=missions, write_time_limit=WRITE_LIMIT_S)
    with running(app) as server:
        assert server.base_url is not None
        yield server.base_url, catalog, missions


@pytest.fixture(scope="module")
def reads(enriched_catalog: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A server with writes on the shared enriched catalog (writes go to a temporary
    missions folder; none reaches the catalog)."""
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    missions = tmp_path_factory.mktemp("edges-inbox")
    with running(create_app(enriched_catalog, token=TOKEN, missions=missions)) as server:
        assert server.base_url is not None
        yield server.base_url


def hostile_las() -> bytes:
    """A valid 10-point LAS 1.4 whose ``number_of_vlrs`` (uint32 at byte 100) says
    0xFFFFFFFF: laspy walks VLRs for hours."""
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    las = laspy.LasData(header)
    las.x, las.y, las.z = (np.arange(10, dtype=np.float64) + k for k in range(3))
    buffer = io.BytesIO()
    las.write(buffer)
    data = bytearray(buffer.getvalue())
    data[100:104] = (0xFFFFFFFF).to_bytes(4, "little")
    return bytes(data)


# --- 1. a hostile payload, the watchdog, workers ending with the server --------------------


def test_a_hostile_payload_blocks_no_other_write(writes: tuple[str, Path, Path]) -> None:
    base, _, missions = writes
    mission_a = {**README_BODY, "name": "2024-05-14-hostile-anymal-a1"}
    assert httpx.post(f"{base}/missions", json=mission_a, headers=AUTH).status_code == 201
    answers: dict[str, httpx.Response] = {}

    def send_hostile() -> None:
        answers["a"] = httpx.post(
            f"{base}/missions/{mission_a['name']}/payloads",
            params={"stamp": "1715679272_145665588", "format": "las"},
            content=hostile_las(),
            headers=AUTH,
            timeout=WRITE_LIMIT_S + 20,
        )

    sender = threading.Thread(target=send_hostile)
    sender.start()
    time.sleep(0.2)  # the hostile payload is in a writer now (or already refused)
    start = time.monotonic()
    mission_b = {**README_BODY, "name": "2024-05-14-other-anymal-b2"}
    created = httpx.post(f"{base}/missions", json=mission_b, headers=AUTH, timeout=10)
    took = time.monotonic() - start
    sender.join(WRITE_LIMIT_S + 30)
    assert created.status_code == 201, created.text
    assert took < 1.0, f"mission B waited {took:.2f} s behind the hostile payload"
    refused = answers["a"]
    assert refused.status_code == 400, refused.text
    assert refused.headers["content-type"] == "application/problem+json"
    assert not list((missions / mission_a["name"] / "payload_clouds").iterdir())


def _sleep(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def _allocate(size: int) -> int:
    return len(bytearray(size))


def test_the_watchdog_kills_a_call_over_its_limit() -> None:
    from standgrid.serve.problems import Problem
    from standgrid.serve.workers import WorkerProcess

    async def scenario() -> None:
        worker = WorkerProcess(
            "test", processes=2, time_limit=0.5, limit_status=400, memory_limit=1 << 30
        )
        try:
            # both processes started, this module imported in each (no limit for that)
            warm = [worker.call(_sleep, 0.2, time_limit=None) for _ in range(2)]
            pids = set(await asyncio.gather(*warm))
            assert len(pids) == 2 and os.getpid() not in pids
            start = time.monotonic()
            # one call hangs; the other process answers meanwhile
            hung = asyncio.ensure_future(worker.call(_sleep, 60.0))
            await asyncio.sleep(0.05)
            assert await worker.call(_sleep, 0.0) in pids
            with pytest.raises(Problem) as over:
                await hung
            assert over.value.status == 400 and "limit of 0.5 s" in over.value.detail
            assert time.monotonic() - start < 5
            killed = pids - set(worker.pids)
            assert len(killed) == 1 and not _alive(killed.pop())
            # the hung process is gone (killed and reaped), another one serves
            assert await worker.call(_sleep, 0.0, time_limit=None) != os.getpid()
            # beyond the memory limit: a problem of the limit's status, the process kept
            with pytest.raises(Problem) as memory:
                await worker.call(_allocate, 2 << 30)
            assert memory.value.status == 400 and "memory limit" in memory.value.detail
            assert await worker.call(_allocate, 64 << 20) == 64 << 20
        finally:
            worker.shutdown()
        assert not worker.pids

    asyncio.run(scenario())


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def _children(pid: int) -> dict[int, str]:
    """The processes whose parent is ``pid``: their state letter (R running, S sleeping)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except (FileNotFoundError, ProcessLookupError):
                continue
            if int(fields[1]) == pid:
                found[int(entry.name)] = fields[0]
    return found


def _ascii_pcd(points: int) -> bytes:
    header = (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\n"
        "DATA ascii\n"
    )
    return header.encode() + b"1.250 -2.500 0.750\n" * points


@pytest.mark.slow  # a whole server started and stopped: ~3.5 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ctrl_c_ends_the_workers_of_standgrid_serve(tmp_path: Path) -> None:
    """SIGINT while a writer parses a large payload: the server stops and leaves no worker."""
    catalog = _empty_catalog(tmp_path)
    env = {**os.environ, "STANDGRID_TOKEN": TOKEN}
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
    sender = None
    try:
        assert proc.stdout is not None
        base = json.loads(proc.stdout.readline())["service"].rstrip("/")
        name = "2024-05-14-sigint-anymal-c3"
        r = httpx.post(f"{base}/missions", json={**README_BODY, "name": name}, headers=AUTH)
        assert r.status_code == 201, r.text
        body = _ascii_pcd(2_500_000)  # ~50 MB: a second or two of parsing

        def send() -> None:
            with contextlib.suppress(httpx.HTTPError):  # answered, or closed unanswered
                httpx.post(
                    f"{base}/missions/{name}/payloads",
                    params={"stamp": "1_000000000"},
                    content=body,
                    headers=AUTH,
                    timeout=30,
                )

        deadline = time.monotonic() + 10
        while set(_children(proc.pid).values()) != {"S"}:  # every worker started and idle
            assert time.monotonic() < deadline, "the workers did not settle"
            time.sleep(0.02)
        sender = threading.Thread(target=send)
        sender.start()
        while "R" not in _children(proc.pid).values():  # a worker busy with the payload
            assert time.monotonic() < deadline, "no worker got busy"
            time.sleep(0.02)
        workers = list(_children(proc.pid))
        assert workers
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        if sender is not None:
            sender.join(30)
    assert proc.returncode == 0, err
    assert not [pid for pid in workers if _alive(pid)], "a worker outlived the server"


# --- 2. a mission announced again -----------------------------------------------------------


def test_the_readme_announcement_sent_again_is_unchanged(writes: tuple[str, Path, Path]) -> None:
    base, _, _ = writes
    created = httpx.post(f"{base}/missions", json=README_BODY, headers=AUTH)
    assert created.status_code == 201, created.text
    again = httpx.post(f"{base}/missions", json=README_BODY, headers=AUTH)
    assert again.status_code == 200 and again.json()["outcome"] == "unchanged", again.text
    # a time of day, a GNSS origin and an explicit unit compare equal once stored too
    full = {
        **README_BODY,
        "name": "2024-05-14-wytham-anymal-d4",
        "time": "10:33:05.250",
        "unit": "d4",
        "tags": ["retry"],
        "notes": "x",
        "gnss": {"latitude": 51.77, "longitude": -1.34, "altitude": 120.5},
    }
    assert httpx.post(f"{base}/missions", json=full, headers=AUTH).status_code == 201
    assert httpx.post(f"{base}/missions", json=full, headers=AUTH).status_code == 200
    other = httpx.post(f"{base}/missions", json={**README_BODY, "robot": "spot"}, headers=AUTH)
    assert other.status_code == 409, other.text


def test_a_name_the_catalog_holds_from_another_folder_is_refused_at_creation(
    reads: str,
) -> None:
    body = {**README_BODY, "name": COYOTE}  # tiled from data/missions, not the inbox
    refused = httpx.post(f"{reads}/missions", json=body, headers=AUTH)
    assert refused.status_code == 409, refused.text
    assert "another folder" in refused.json()["detail"]


# --- 3. numbers at the edge -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "status"),
    [
        ("/ogc/collections/cells/items?offset=100000000000000000000", 400),
        ("/ogc/collections/cells/items?bbox=-1,-100,1,100", 400),
        ("/ogc/collections/cells/items?bbox=-181,0,1,1", 400),
        ("/ogc/collections/cells/items/9999999999999999999999999999999999999999", 404),
        ("/ogc/collections/cells/items/-99999999999999999999", 404),
        ("/ogc/collections/cells/items?point_count=99999999999999999999999", 400),
        ("/ogc/collections/stand_metrics/items?level=nan", 400),
        ("/ogc/collections/gnss_fixes/items?datetime=1111-01-01T00:00:00Z/..", 200),
        ("/ogc/collections/gnss_fixes/items?datetime=0001-01-01T00:00:00%2B05:00/9999-12-31", 200),
        ("/ogc/collections/cells/items?datetime=0001-01-01T00:00:00%2B05:00/9999-12-31", 200),
        (f"/missions/{COYOTE}/payloads/by-pose?x=inf&y=0", 400),
        (f"/missions/{COYOTE}/payloads/by-pose?x=0&y=nan", 400),
        (f"/missions/{COYOTE}/payloads/by-gnss?lat=51&lon=-1&alt=inf", 400),
        ("/viewer/points?payload=999999999999999999999999999999", 400),
        ("/viewer/points?payload=-1", 400),
        ("/viewer/points/2024/x?tree=99999999999999999999", 400),
        (f"/missions/{COYOTE}/payloads?type=bogus", 400),
    ],
)
def test_numbers_are_checked_at_the_edge(reads: str, url: str, status: int) -> None:
    r = httpx.get(reads + url, timeout=30)
    assert r.status_code == status, r.text
    if status >= 400:
        assert r.headers["content-type"] == "application/problem+json"


# --- 4. OpenAPI -----------------------------------------------------------------------------


def test_both_openapi_documents_are_valid(reads: str) -> None:
    from openapi_spec_validator import validate

    service = httpx.get(f"{reads}/openapi.json").json()
    validate(service)
    ids = [
        op["operationId"]
        for item in service["paths"].values()
        for op in item.values()
        if isinstance(op, dict) and "operationId" in op
    ]
    assert len(ids) == len(set(ids))
    assert {"get", "head"} <= set(service["paths"]["/files/{relative}"])
    validate(httpx.get(f"{reads}/ogc/api").json())


# --- 5. bounded announcements, no server paths, a busy port ---------------------------------


@pytest.mark.parametrize(
    "change",
    [
        {"sensors": [f"lidar-{k}" for k in range(100_000)]},
        {"tags": ["t"] * 65},
        {"sensors": ["x" * 129]},
        {"place": "p" * 129},
        {"notes": "n" * 100_000},
        {"name": "m" * 100_000},
        {"gnss": {"latitude": 91, "longitude": 0}},
        {"gnss": {"latitude": 0, "longitude": 0, "altitude": 1e300}},
    ],
)
def test_announcements_are_bounded(writes: tuple[str, Path, Path], change: dict) -> None:
    base, _, missions = writes
    body = {**README_BODY, "name": "2024-05-14-bounded-anymal-e5", **change}
    r = httpx.post(f"{base}/missions", json=body, headers=AUTH)
    assert r.status_code == 400, r.text[:300]
    assert not (missions / "2024-05-14-bounded-anymal-e5").exists()


def test_the_tile_answer_names_no_server_path(
    writes: tuple[str, Path, Path], tmp_path: Path
) -> None:
    base, catalog, missions = writes
    name = MISSIONS["2028"]
    shutil.copytree(BUNDLED_MISSIONS / name, missions / name)
    tiled = httpx.post(f"{base}/missions/{name}/tile", headers=AUTH, timeout=120)
    assert tiled.status_code == 200, tiled.text
    text = tiled.text
    for where in (catalog, missions, tmp_path, REPO_ROOT):
        assert str(where) not in text, where
    report = tiled.json()
    assert report["catalog"] == catalog.name and name in report["missions"]


def test_a_busy_port_is_one_clear_line(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from standgrid.cli import cli

    catalog = _empty_catalog(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = CliRunner().invoke(cli, ["serve", str(catalog), "--port", str(port)])
    assert result.exit_code == 1
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    assert f"127.0.0.1:{port}" in lines[0] and "--port" in lines[0]
    assert "Traceback" not in result.output and "errno" not in result.output.lower()
