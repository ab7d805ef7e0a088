"""Concurrent readers against a real ``standgrid serve`` (uvicorn in its own process).

N reader threads (default 8), each with its own HTTP connection, run for a fixed time one
workload at a time:

- ``items``: an OGC API items page of 100 features (``/ogc/collections/<layer>/items``,
  random layer among cells, gnss_fixes, payloads, trees, stand_metrics, random offset);
- ``bbox``: an items page answered from the R-tree (random 30 m box over the stand, in the
  catalog CRS, ``limit=100``);
- ``range``: a range read of a random tile (``/files/tiles/...``, random 4 KiB window);
- ``ping``: ``/ogc/conformance`` (a constant document: the HTTP + framework floor).

For each it prints requests/s, p50 / p95 / max latency, errors (any non-2xx, or a page
whose numberReturned disagrees with its features) and the server process's CPU time per
request (all its threads; with ``--stream`` it includes the robot's requests, and not the
tiling, which runs in the server's worker process). On a shared machine latencies swing with
the load of others; the server's CPU per request is the steadier figure. Baselines measured
in the same run: the same items page read in this process straight from the GeoPackage
(``GeoPackageProvider.items``), and ``ping`` for the HTTP floor; ratios are printed against both.

``--stream``: while the readers run, one robot streams the bundled 2024 mission (under a new
name) over HTTP: create, pose graph, every payload, GNSS fixes in chunks, then ``tile``
(a catalog commit under the writer lock). The served catalog is a copy. It prints the
robot's time and checks nothing was lost (the catalog then holds every payload sent).

Example:
    python benchmarks/bench_serve.py                        # builds a demo catalog first
    python benchmarks/bench_serve.py --catalog standgrid-demo --readers 16 --seconds 10
    python benchmarks/bench_serve.py --stream
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("cells", "gnss_fixes", "payloads", "trees", "stand_metrics")
TOKEN = "bench-serve-token-0123456789"
SOURCE = REPO / "data" / "missions" / "2024-05-14-wytham-anymal-coyote"
STREAMED = "2024-05-15-wytham-anymal-bench"


def build_catalog(folder: Path) -> Path:
    from standgrid.pipeline.run import run_pipeline
    from standgrid.tiling.options import TileOptions

    catalog = folder / "catalog"
    print(f"building a demo catalog from data/missions in {catalog} ...", file=sys.stderr)
    run_pipeline([REPO / "data" / "missions"], catalog, TileOptions(buffer=2.0))
    return catalog


def start_server(catalog: Path, token_file: Path) -> tuple[subprocess.Popen[str], str]:
    command = [
        sys.executable,
        "-c",
        "from standgrid.cli import main; main()",
        "serve",
        str(catalog),
        "--port",
        "0",
        "--json",
        "--token-file",
        str(token_file),
    ]
    proc = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        proc.wait()
        raise SystemExit("the server did not start")
    return proc, json.loads(line)["service"].rstrip("/")


def run(
    readers: int, seconds: float, request: Callable[[httpx.Client, random.Random], bool], base: str
) -> tuple[list[float], int]:
    """``readers`` threads sending ``request`` for ``seconds``. The clients are made before
    the clock starts: making one (its SSL context) holds this process's GIL for tens of ms,
    which the first requests of the other threads would count as the server's latency."""
    latencies: list[list[float]] = [[] for _ in range(readers)]
    errors = [0] * readers
    clients = [httpx.Client(base_url=base, timeout=30) for _ in range(readers)]
    start = threading.Barrier(readers + 1)
    stop = [0.0]

    def reader(i: int) -> None:
        rng = random.Random(i)
        start.wait()
        with clients[i] as client:
            while time.perf_counter() < stop[0]:
                t0 = time.perf_counter()
                try:
                    ok = request(client, rng)
                except httpx.HTTPError:
                    ok = False
                latencies[i].append(time.perf_counter() - t0)
                errors[i] += 0 if ok else 1

    threads = [threading.Thread(target=reader, args=(i,)) for i in range(readers)]
    for t in threads:
        t.start()
    stop[0] = time.perf_counter() + seconds
    start.wait()
    for t in threads:
        t.join()
    return [x for per in latencies for x in per], sum(errors)


def robot_requests() -> list[tuple[str, str, dict[str, Any]]]:
    """The robot's requests (method, path, httpx arguments) for the bundled 2024 mission,
    renamed: create, pose graph, every payload and a chunk of GNSS fixes after each. Built
    before the clocks start: reading the mission in this process holds its GIL for a second
    or two, which would stall the reader threads and count as the server's latency."""
    import yaml

    from standgrid.geometry import translation_quat
    from standgrid.mission.opening import open_mission

    meta = yaml.safe_load((SOURCE / "metadata.yaml").read_text())
    mission = open_mission(SOURCE, strict=False)
    url = f"/missions/{STREAMED}"
    requests: list[tuple[str, str, dict[str, Any]]] = [
        (
            "POST",
            "/missions",
            {
                "json": {
                    "name": STREAMED,
                    "date": "2024-05-15",
                    "place": meta["place"],
                    "robot": meta["robot"],
                    "sensors": meta["sensors"],
                }
            },
        ),
        ("PUT", f"{url}/graph", {"content": (SOURCE / "slam_pose_graph.g2o").read_bytes()}),
    ]
    lines = (SOURCE / "gnss" / "fixes.txt").read_text().splitlines()
    chunk = max(1, (len(lines) - 1) // len(mission.payloads))
    for k, payload in enumerate(mission.payloads):
        t, q = translation_quat(mission.pose_of(payload))
        requests.append(
            (
                "POST",
                f"{url}/payloads",
                {
                    "content": payload.path.read_bytes(),
                    "params": {
                        "stamp": f"{payload.stamp.sec}_{payload.stamp.nsec:09d}",
                        "pose": ",".join(repr(float(v)) for v in (*t, *q)),
                    },
                },
            )
        )
        rows = lines[1 + k * chunk : 1 + (k + 1) * chunk]
        if k == len(mission.payloads) - 1:
            rows = lines[1 + k * chunk :]
        requests.append(("POST", f"{url}/gnss", {"content": "\n".join([lines[0], *rows]) + "\n"}))
    return requests


def stream_mission(
    base: str, requests: list[tuple[str, str, dict[str, Any]]], result: dict[str, float]
) -> None:
    """One robot: sends ``requests`` (:func:`robot_requests`) in order, then ``tile``."""
    auth = {"Authorization": f"Bearer {TOKEN}"}
    t0 = time.perf_counter()
    with httpx.Client(base_url=base, timeout=600, headers=auth) as client:
        for method, path, arguments in requests:
            client.request(method, path, **arguments).raise_for_status()
        result["sent_s"] = time.perf_counter() - t0
        url = f"/missions/{STREAMED}"
        client.post(f"{url}/tile").raise_for_status()
        result["tiled_s"] = time.perf_counter() - t0
        result["payloads_sent"] = sum(path.endswith("/payloads") for _, path, _ in requests)
        result["payloads_in_catalog"] = client.get(url).json()["payload_count"]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (its threads, not its children); NaN
    where /proc is missing."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def report(
    name: str, latencies: list[float], errors: int, seconds: float, server_cpu: float
) -> float:
    ms = np.asarray(latencies) * 1000.0
    p50, p95 = np.percentile(ms, [50, 95])
    print(
        f"{name:7} {len(ms) / seconds:8.1f} req/s  p50 {p50:7.1f} ms  p95 {p95:7.1f} ms  "
        f"max {ms.max():7.1f} ms  errors {errors}/{len(ms)}  "
        f"server CPU {server_cpu * 1000 / len(ms):5.2f} ms/req"
    )
    return float(p50)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--catalog", type=Path, help="catalog to serve (default: build one)")
    parser.add_argument("--readers", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument(
        "--stream", action="store_true", help="one robot streams a mission meanwhile"
    )
    args = parser.parse_args()

    from standgrid.catalog import Catalog
    from standgrid.serve.provider import GeoPackageProvider, Query

    with tempfile.TemporaryDirectory(prefix="bench-serve-") as tmp:
        catalog = args.catalog or build_catalog(Path(tmp))
        if args.stream and args.catalog:  # the robot writes: serve a copy
            catalog = Path(shutil.copytree(args.catalog, Path(tmp) / "catalog"))
        token_file = Path(tmp) / "token"
        token_file.write_text(TOKEN)
        opened = Catalog.open(catalog)
        tiles = [(t, opened.path(t).stat().st_size) for e in opened.epochs for t in opened.tiles(e)]
        index = GeoPackageProvider.open(opened.path("index.gpkg"))
        layers = index.layers
        counts = {n: index.items(layers[n], Query(limit=1)).number_matched for n in LAYERS}
        xmin, ymin, xmax, ymax = layers["cells"].bounds or (0, 0, 0, 0)
        crs_uri = "http://www.opengis.net/def/crs/EPSG/0/" + str(
            __import__("pyproj").CRS(opened.crs).to_epsg()
        )

        def page_params(rng: random.Random) -> tuple[str, int]:
            layer = rng.choice(LAYERS)
            return layer, rng.randrange(0, max(1, counts[layer] - 100))

        def items(client: httpx.Client, rng: random.Random) -> bool:
            layer, offset = page_params(rng)
            r = client.get(
                f"/ogc/collections/{layer}/items", params={"limit": 100, "offset": offset}
            )
            body = r.json()
            return r.status_code == 200 and body["numberReturned"] == len(body["features"])

        def bbox(client: httpx.Client, rng: random.Random) -> bool:
            x, y = rng.uniform(xmin, xmax - 30), rng.uniform(ymin, ymax - 30)
            r = client.get(
                "/ogc/collections/trees/items",
                params={"bbox": f"{x},{y},{x + 30},{y + 30}", "bbox-crs": crs_uri, "limit": 100},
            )
            body = r.json()
            return r.status_code == 200 and body["numberReturned"] == len(body["features"])

        failures: list[str] = []

        def range_read(client: httpx.Client, rng: random.Random) -> bool:
            rel, size = rng.choice(tiles)
            start = rng.randrange(0, max(1, size - 4096))
            end = min(size, start + 4096) - 1
            r = client.get(f"/files/{rel}", headers={"Range": f"bytes={start}-{end}"})
            if r.status_code == 206:
                first, last, total = map(int, re.split(r"[-/]", r.headers["content-range"][6:]))
                if total != size and args.stream:  # the robot's commit replaced the tile
                    return first == start and len(r.content) == last - first + 1
                return (first, last, len(r.content)) == (start, end, end - start + 1)
            # a tile a commit removed or shrank meanwhile: 404, or 416 naming its new size
            replaced = r.status_code == 404 or (
                r.status_code == 416 and r.headers["content-range"] != f"bytes */{size}"
            )
            if not (args.stream and replaced):
                failures.append(f"{r.status_code} {rel} {start}-{end}: {r.text[:120]}")
            return args.stream and replaced

        def ping(client: httpx.Client, rng: random.Random) -> bool:
            return client.get("/ogc/conformance").status_code == 200

        # baseline 1: the same pages read in this process, no HTTP
        rng = random.Random(0)
        local = []
        for _ in range(200):
            layer, offset = page_params(rng)
            t0 = time.perf_counter()
            index.items(layers[layer], Query(limit=100, offset=offset))
            local.append(time.perf_counter() - t0)
        index.close()
        local_p50 = float(np.percentile(local, 50) * 1000)
        print(
            f"catalog {catalog}: {len(tiles)} tiles, {counts} features; "
            f"{args.readers} readers x {args.seconds:.0f} s per workload"
            f"{'; one robot streaming a mission' if args.stream else ''}"
        )
        print(f"local   page of 100 read straight from the GeoPackage: p50 {local_p50:.2f} ms")

        proc, base = start_server(catalog, token_file)
        robot: dict[str, float] = {}
        sent = robot_requests() if args.stream else []
        writer = threading.Thread(target=stream_mission, args=(base, sent, robot))
        try:
            p50 = {}
            for name, request in (
                ("ping", ping),
                ("items", items),
                ("bbox", bbox),
                ("range", range_read),
            ):
                if args.stream and name == "items":
                    writer.start()
                before = cpu_seconds(proc.pid)
                latencies, errors = run(args.readers, args.seconds, request, base)
                used = cpu_seconds(proc.pid) - before
                p50[name] = report(name, latencies, errors, args.seconds, used)
            if args.stream:
                writer.join()
        finally:
            proc.terminate()
            proc.wait(timeout=60)
        for failure in failures[:5]:
            print(f"  range error: {failure}")
        print(
            f"ratios (p50): items/ping {p50['items'] / p50['ping']:.1f}, "
            f"items/local page {p50['items'] / local_p50:.1f}, "
            f"range/ping {p50['range'] / p50['ping']:.1f}"
        )
        if args.stream:
            lost = robot.get("payloads_sent", -1) - robot.get("payloads_in_catalog", -2)
            print(
                f"robot   {robot.get('payloads_sent', 0):.0f} payloads sent in "
                f"{robot.get('sent_s', float('nan')):.1f} s, tiled after "
                f"{robot.get('tiled_s', float('nan')):.1f} s; payloads lost: {lost:.0f}"
            )


if __name__ == "__main__":
    main()
