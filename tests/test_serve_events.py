"""The live event stream (``GET /events``, Server-Sent Events) against a real uvicorn: a
mission streamed through the ingest API is announced payload by payload, once each, in
order, once stored, with the coordinates the catalog holds after tiling; a reconnect with
``Last-Event-ID`` gets what it missed; a client that stops reading holds up neither the
robot nor the other clients; Ctrl-C ends the streams at once."""

from __future__ import annotations

import json
import queue
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import CRS, MISSIONS

TOKEN = "events-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
NAME = MISSIONS["2024"]
SOURCE = BUNDLED_MISSIONS / NAME


@dataclass
class Received:
    """One event as a client parsed it, when it arrived, and whether its payload's file was
    in the mission folder then."""

    id: str | None
    type: str
    data: dict[str, Any]
    at: float
    stored: bool | None = None


@dataclass
class Listener:
    """An SSE client in a thread (httpx stream): its events in a queue, comments counted."""

    base: str
    missions: Path | None = None
    last_event_id: str | None = None
    events: queue.Queue[Received] = field(default_factory=queue.Queue)
    comments: list[str] = field(default_factory=list)
    ended: threading.Event = field(default_factory=threading.Event)

    def start(self) -> Listener:
        threading.Thread(target=self._run, daemon=True).start()
        hello = self.next(10)
        assert hello.type == "hello" and hello.id is None, hello
        return self

    def _run(self) -> None:
        headers = {"Last-Event-ID": self.last_event_id} if self.last_event_id else {}
        try:
            with httpx.stream(
                "GET", f"{self.base}/events", headers=headers, timeout=httpx.Timeout(5, read=None)
            ) as answer:
                assert answer.headers["content-type"].startswith("text/event-stream")
                fields: dict[str, str] = {}
                for line in answer.iter_lines():
                    if line.startswith(":"):
                        self.comments.append(line)
                    elif line:
                        name, _, value = line.partition(":")
                        fields[name] = value.removeprefix(" ")
                    elif "event" in fields:
                        self.events.put(self._event(fields))
                        fields = {}
        except httpx.HTTPError:
            pass
        finally:
            self.ended.set()

    def _event(self, fields: dict[str, str]) -> Received:
        data = json.loads(fields["data"])
        got = Received(fields.get("id"), fields["event"], data, time.monotonic())
        if got.type == "payload" and self.missions is not None:
            files = self.missions / data["mission"] / "payload_clouds"
            got.stored = any(files.glob(f"cloud_{data['payload']}.*"))
        return got

    def next(self, timeout: float = 30) -> Received:
        return self.events.get(timeout=timeout)

    def next_of(self, kind: str, timeout: float = 30) -> Received:
        """The next event of type ``kind``, skipping trajectories (any other is an error)."""
        while True:
            got = self.next(timeout)
            if got.type == kind:
                return got
            assert got.type == "trajectory", (kind, got)

    def drain(self, wait: float = 0.3) -> list[Received]:
        time.sleep(wait)
        out = []
        while not self.events.empty():
            out.append(self.events.get_nowait())
        return out


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, Path, Any]]:
    """A real server on an empty catalog (writes with the token), heartbeats every 0.2 s."""
    from standgrid.catalog import Catalog
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    folder = tmp_path_factory.mktemp("events")
    catalog, missions = folder / "catalog", folder / "inbox"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    app = create_app(catalog, token=TOKEN, missions=missions)
    app.state.event_heartbeat = 0.2
    with running(app) as server:
        assert server.base_url is not None
        yield server.base_url, catalog, missions, app


def _metadata(name: str = NAME) -> dict[str, Any]:
    meta = yaml.safe_load((SOURCE / "metadata.yaml").read_text())
    return {"name": name, "date": str(meta["date"]), "robot": meta["robot"], "gnss": meta["gnss"]}


def _payload_requests() -> list[tuple[dict[str, str], bytes]]:
    """The bundled mission's payloads as the robot sends them: stamp, format, node pose."""
    from standgrid.geometry import translation_quat
    from standgrid.mission.opening import open_mission

    mission = open_mission(SOURCE, strict=False)
    sent = []
    for payload in mission.payloads:
        pose = mission.pose_of(payload)
        _, q = translation_quat(pose)
        params = {
            "stamp": f"{payload.stamp.sec}_{payload.stamp.nsec:09d}",
            "format": "pcd",
            "pose": ",".join(repr(float(v)) for v in (*pose[:3, 3], *q)),
        }
        sent.append((params, payload.path.read_bytes()))
    return sent


def _start_mission(base: str, name: str = NAME) -> None:
    url = f"{base}/missions"
    assert httpx.post(url, json=_metadata(name), headers=AUTH).status_code == 201
    graph = (SOURCE / "slam_pose_graph.g2o").read_bytes()
    assert httpx.put(f"{url}/{name}/graph", content=graph, headers=AUTH).status_code == 200
    fixes = (SOURCE / "gnss/fixes.txt").read_bytes()
    r = httpx.post(f"{url}/{name}/gnss", content=fixes, headers=AUTH, timeout=60)
    assert r.status_code == 200, r.text


def test_a_streamed_mission_is_announced_payload_by_payload(
    served: tuple[str, Path, Path, Any],
) -> None:
    import pyogrio
    import shapely

    from standgrid.crs import CRS as CRSValue

    base, catalog, missions, _ = served
    listener = Listener(base, missions).start()
    _start_mission(base)
    mission = listener.next_of("mission")
    assert mission.data["mission"] == NAME and mission.data["date"] == "2024-05-14"
    # the graph and the fixes place the mission: its trajectory, in the catalog CRS
    trajectory = None
    for got in listener.drain():
        assert got.type == "trajectory", got
        trajectory = got.data
    assert trajectory is not None and trajectory["placed"] and trajectory["nodes"] > 10
    assert trajectory["line"]["crs"]["type"] == "LineString"

    announced = []
    for params, body in _payload_requests():
        sent = time.monotonic()
        r = httpx.post(
            f"{base}/missions/{NAME}/payloads",
            params=params,
            content=body,
            headers=AUTH,
            timeout=60,
        )
        assert r.status_code == 201, r.text
        got = listener.next_of("payload", timeout=10)
        # this payload, stored before it was announced, announced while its POST was open
        assert got.data["payload"] == params["stamp"] and got.data["mission"] == NAME
        assert got.stored is True and got.at > sent
        assert got.data["placed"] is True and got.data["reason"] is None
        announced.append(got)
    # sent again: stored once, announced once; ids in the order of publication
    params, body = _payload_requests()[0]
    again = httpx.post(
        f"{base}/missions/{NAME}/payloads", params=params, content=body, headers=AUTH
    )
    assert again.json()["outcome"] == "unchanged"
    assert [g.type for g in listener.drain()] == []
    numbers = [int(g.id.rpartition("-")[2]) for g in announced if g.id]
    assert numbers == sorted(numbers) and len(set(numbers)) == len(announced)
    assert [g.data["index"] for g in announced] == list(range(len(announced)))

    tiled = httpx.post(f"{base}/missions/{NAME}/tile", headers=AUTH, timeout=300)
    assert tiled.status_code == 200, tiled.text
    event = listener.next_of("tiled")
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    assert event.data["epoch"] == "2024"
    assert sorted(event.data["epochs"]["2024"]["new"]) == sorted(cells["cell_id"])
    assert event.data["epochs"]["2024"]["changed"] == []
    assert listener.comments.count(": heartbeat") >= 1

    # the coordinates announced are those the catalog's payloads layer holds
    rows = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    rows["stamp"] = [
        f"{s}_{n:09d}" for s, n in zip(rows["stamp_sec"], rows["stamp_nsec"], strict=True)
    ]
    by_stamp = rows.set_index("stamp")
    to_lonlat = CRSValue.of(CRS).transformer_to("EPSG:4326")
    for got in announced:
        row = by_stamp.loc[got.data["payload"]]
        x, y = got.data["position"]["crs"]["coordinates"]
        assert (x, y, got.data["position"]["z"]) == pytest.approx(
            (row["x"], row["y"], row["z"]), abs=1e-3
        )
        lon, lat = got.data["position"]["wgs84"]["coordinates"]
        assert (lon, lat) == pytest.approx(to_lonlat.transform(row["x"], row["y"]), abs=1e-7)
        footprint = shapely.geometry.shape(got.data["footprint"]["crs"])
        assert footprint.geom_type == "Polygon" and footprint.area > 10
        # the tiler hulls points snapped to the 1 mm lattice: the same polygon within mm
        assert shapely.hausdorff_distance(footprint, row["geometry"]) < 0.005
        assert got.data["points"] == row["point_count"]


def test_a_reconnect_gets_what_it_missed(served: tuple[str, Path, Path, Any]) -> None:
    base = served[0]
    first = Listener(base).start()
    name = "reconnect-mission"
    assert httpx.post(f"{base}/missions", json=_metadata(name), headers=AUTH).status_code == 201
    created = first.next_of("mission")
    assert created.id is not None
    # sent while no one is listening from ``created`` on: a reconnect gets them, in order
    graph = (SOURCE / "slam_pose_graph.g2o").read_bytes()
    httpx.put(f"{base}/missions/{name}/graph", content=graph, headers=AUTH)
    params, body = _payload_requests()[3]
    r = httpx.post(f"{base}/missions/{name}/payloads", params=params, content=body, headers=AUTH)
    assert r.status_code == 201
    missed = [g for g in first.drain() if g.data.get("mission") == name]
    assert [g.type for g in missed] == ["trajectory", "payload"]

    again = Listener(base, last_event_id=created.id).start()
    replayed = again.drain()
    assert [(g.id, g.type, g.data) for g in replayed] == [(g.id, g.type, g.data) for g in missed]
    # an id this server never gave (another run, or one it no longer keeps): resync
    for stale in ("0badc0de-1", "nonsense", f"{created.id.rpartition('-')[0]}-999999"):
        resync = Listener(base, last_event_id=stale).start().next(10)
        assert resync.type == "resync" and resync.data["reason"] == "gap", stale


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_a_client_that_stops_reading_holds_up_nothing(tmp_path: Path) -> None:
    """A client connects and never reads: the robot's writes answer as fast as ever, the
    other client gets every event, and the silent one, read at last, finds a ``resync``
    where its queue overflowed. (The server listens with a small send buffer, as over a slow
    link: on loopback the kernel would otherwise take a megabyte for the silent client.)"""
    from standgrid.catalog import Catalog
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app
    from standgrid.serve.server import Server, config

    Catalog.create(tmp_path / "catalog", StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    app = create_app(tmp_path / "catalog", token=TOKEN, missions=tmp_path / "inbox")
    hub = app.state.events
    hub.queue_size = 8
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)  # accepted sockets inherit it
    sock.bind(("127.0.0.1", 0))
    server = Server(config(app, "127.0.0.1", 0))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    silent = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    silent.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        deadline = time.monotonic() + 20
        while server.base_url is None:
            assert time.monotonic() < deadline and thread.is_alive()
            time.sleep(0.02)
        base = server.base_url
        silent.connect(sock.getsockname())
        silent.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        fast = Listener(base).start()
        while len(hub.subscribers) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        name = "slow-client-mission"
        _start_mission(base, name)
        took = []
        sent = _payload_requests()[:4]
        for params, body in sent:
            t0 = time.monotonic()
            r = httpx.post(
                f"{base}/missions/{name}/payloads",
                params=params,
                content=body,
                headers=AUTH,
                timeout=30,
            )
            took.append(time.monotonic() - t0)
            assert r.status_code == 201, r.text
        # pose-graph updates (a loop closure moving the last node): a trajectory event each,
        # until what the silent client left unread overflows its queue
        lines = (SOURCE / "slam_pose_graph.g2o").read_text().splitlines()
        last = max(k for k, line in enumerate(lines) if line.startswith("VERTEX_SE3"))
        updates = 0
        while sum(s.dropped for s in hub.subscribers) == 0:
            updates += 1
            assert updates <= 60, "the silent client's queue never overflowed"
            parts = lines[last].split()
            parts[2] = repr(float(parts[2]) + 0.01 * updates)
            graph = "\n".join([*lines[:last], " ".join(parts), *lines[last + 1 :]]) + "\n"
            t0 = time.monotonic()
            r = httpx.put(f"{base}/missions/{name}/graph", content=graph, headers=AUTH)
            took.append(time.monotonic() - t0)
            assert r.json()["outcome"] == "stored"
        print(
            f"\nsilent client: overflowed after {updates} graph updates; writes took "
            f"{max(took):.2f} s at most"
        )
        got = fast.drain(1.0)
        assert [g.data["payload"] for g in got if g.type == "payload"] == [
            p["stamp"] for p, _ in sent
        ]
        assert sum(g.type == "trajectory" for g in got) >= updates
        assert max(took) < 5, took
        assert max(s.queue.qsize() for s in hub.subscribers) <= hub.queue_size
        silent.settimeout(5)
        text = b""
        while b"event: resync" not in text:
            chunk = silent.recv(65536)
            assert chunk, "the stream ended without a resync"
            text += chunk
        assert b'"reason":"overflow"' in text.split(b"event: resync", 1)[1][:300]
    finally:
        silent.close()
        server.should_exit = True
        thread.join(20)


def test_ctrl_c_ends_the_streams_at_once(tmp_path: Path) -> None:
    """``standgrid serve`` with a client listening: SIGINT stops it well within its grace
    period for requests in flight (the stream ends first), and the client sees the end."""
    import os
    import signal
    import subprocess
    import sys

    from standgrid.catalog import Catalog
    from standgrid.partition import StandGrid
    from tests.conftest import REPO_ROOT

    catalog = tmp_path / "catalog"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
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
        command,
        cwd=REPO_ROOT,
        env=dict(os.environ),
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        base = json.loads(proc.stdout.readline())["service"].rstrip("/")
        listeners = [Listener(base).start() for _ in range(2)]
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)
        stopped = time.monotonic() - t0
        assert proc.returncode == 0
        assert stopped < 3, f"the server took {stopped:.1f} s to stop"
        for listener in listeners:
            assert listener.ended.wait(5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_published_events_are_bounded() -> None:
    """The hub keeps at most its ring of events and each client at most its queue."""
    import asyncio

    from standgrid.serve.events import Event, EventHub

    async def run() -> None:
        hub = EventHub(ring=5, queue=3)
        reader = hub.subscribe()
        published = [hub.publish("mission", {"mission": f"m{k}"}) for k in range(8)]
        assert [e.id for e in hub.ring] == [e.id for e in published[-5:]]
        first = reader.queue.get_nowait()
        assert isinstance(first, Event) and first.type == "resync"
        assert reader.dropped >= 1
        late = hub.subscribe(published[4].id)
        assert [late.queue.get_nowait().id for _ in range(3)] == [e.id for e in published[5:]]
        assert hub.subscribe(published[0].id).queue.get_nowait().type == "resync"
        for hostile in (f"{hub.run}-²", f"{hub.run}-", "-1", "x" * 10_000):  # a resync, no error
            assert hub.subscribe(hostile).queue.get_nowait().type == "resync", hostile
        hub.close()
        assert hub.subscribers == set()

    asyncio.run(run())
