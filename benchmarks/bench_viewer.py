"""The web viewer on a large catalog, in headless Chromium: time to the first map and to a
cell's and a payload's 3-D view, against the served data's own floor measured in the same run.

A real ``standgrid serve`` (uvicorn in a thread) on CATALOG; Playwright drives Debian's
``chromium``. Printed: the catalog's size (cells, points), the first map (from navigation:
the page, the OGC layers, the CHM tiles drawn) and the trees, then for ``--cells`` cells
picked across the catalog the 3-D view (points fetched, decoded, drawn) with the point
count, then the same for ``--payloads`` payloads (their points gathered from the tiles);
baselines: the same OGC layers and points fetched by httpx in this process. On a COPC
catalog (``standgrid tile --copc``) each cell is opened both ways, alternately: streamed by
the page from its COPC tile, and read by the server (``/viewer/points``); both printed.

Example (a 1,024-cell, ~20 M point catalog):
    standgrid simulate /tmp/big --epochs 1 --area 640 --points-per-payload 20000
    standgrid run /tmp/big/missions -o /tmp/big/catalog
    python benchmarks/bench_viewer.py /tmp/big/catalog --screenshot /tmp/big/viewer.png
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import httpx
import pyogrio

ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("catalog", type=Path)
    parser.add_argument("--cells", type=int, default=5, help="cells whose 3-D view is timed")
    parser.add_argument("--payloads", type=int, default=5, help="payloads whose 3-D view is timed")
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--screenshot", type=Path, help="PNG of the map and the last 3-D view")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    from standgrid.serve import create_app
    from standgrid.serve.server import running

    cells = pyogrio.read_dataframe(args.catalog / "index.gpkg", layer="cells", read_geometry=False)
    epoch = sorted(cells["epoch"].unique())[0]
    print(f"catalog: {len(cells)} cell tiles, {int(cells['point_count'].sum()):,} points")
    with running(create_app(args.catalog)) as server, sync_playwright() as p:
        base = server.base_url
        t0 = time.perf_counter()
        for layer in ("stand_metrics", "cells", "trajectories", "payloads"):
            url: str | None = f"{base}/ogc/collections/{layer}/items?limit=10000"
            while url:
                page = httpx.get(url, timeout=120).json()
                url = next((x["href"] for x in page["links"] if x["rel"] == "next"), None)
        floor = 1000 * (time.perf_counter() - t0)
        print(f"baseline: the map's OGC layers fetched by httpx: {floor:.0f} ms")

        browser = p.chromium.launch(executable_path=args.chromium, args=ARGS)
        page = browser.new_page(viewport={"width": 1500, "height": 900})
        errors: list[str] = []
        page.on("console", lambda m: m.type == "error" and errors.append(m.text))
        page.goto(f"{base}/")
        page.wait_for_function("document.body.dataset.ready === 'true'", timeout=120_000)
        first = page.evaluate("() => window.standgrid.firstMapMs")
        trees = page.evaluate("() => window.standgrid.treesMs")
        print(
            f"viewer: first map {first:.0f} ms from navigation ({first / floor:.1f}x the "
            f"layers' fetch), trees drawn at {trees:.0f} ms"
        )
        if args.screenshot:
            page.screenshot(path=str(args.screenshot.with_stem(args.screenshot.stem + "-map")))

        picks = cells[cells["epoch"] == epoch].sort_values("point_count")
        picks = picks.iloc[
            [round(k * (len(picks) - 1) / max(1, args.cells - 1)) for k in range(args.cells)]
        ]
        in_page, fetched, streamed = [], [], []
        copc = page.evaluate("() => window.standgrid.state.streamCopc")
        open_cell = (
            "([c, s]) => { window.standgrid.state.streamCopc = s; return window.standgrid"
            ".openCell(c).then(v => [v.count, v.ms, v.points.header.meta.copc || null]); }"
        )
        for _, row in picks.iterrows():
            t0 = time.perf_counter()
            httpx.get(f"{base}/viewer/points/{epoch}/{row['cell_id']}", timeout=60)
            fetched.append(1000 * (time.perf_counter() - t0))
            view = page.evaluate(open_cell, [row["cell_id"], False])
            assert view[0] == row["point_count"], (row["cell_id"], view[0], row["point_count"])
            in_page.append(view[1])
            print(
                f"  3-D view of {row['cell_id']}: {view[0]:,} points in {view[1]:.0f} ms "
                f"(points by httpx: {fetched[-1]:.0f} ms)"
            )
            if copc:
                view = page.evaluate(open_cell, [row["cell_id"], True])
                assert view[0] == row["point_count"], (row["cell_id"], view[0])
                streamed.append(view[1])
                got = view[2]
                print(
                    f"    streamed from its COPC tile: {view[1]:.0f} ms, {got['bytes']:,} of "
                    f"{got['file_size']:,} bytes in {got['requests']} range requests, "
                    f"{got['nodes_read']} of {got['nodes']} nodes"
                )
        ratio = statistics.median(in_page) / statistics.median(fetched)
        print(
            f"3-D view: median {statistics.median(in_page):.0f} ms, max {max(in_page):.0f} ms; "
            f"{ratio:.1f}x the points' fetch alone"
        )
        if streamed:
            ratio = statistics.median(streamed) / statistics.median(in_page)
            print(
                f"3-D view streamed from COPC: median {statistics.median(streamed):.0f} ms, max "
                f"{max(streamed):.0f} ms; {ratio:.2f}x the /viewer/points median (same cells, "
                "alternated)"
            )
        if args.screenshot:
            page.screenshot(path=str(args.screenshot.with_stem(args.screenshot.stem + "-3d")))

        payloads = pyogrio.read_dataframe(
            args.catalog / "index.gpkg", layer="payloads", read_geometry=False
        )
        payloads = payloads[payloads["epoch"] == epoch].sort_values("payload_id")
        picks = payloads.iloc[
            [
                round(k * (len(payloads) - 1) / max(1, args.payloads - 1))
                for k in range(min(args.payloads, len(payloads)))
            ]
        ]
        in_page, fetched = [], []
        for _, row in picks.iterrows():
            ident = int(row["payload_id"])
            t0 = time.perf_counter()
            answer = httpx.get(f"{base}/viewer/points", params={"payload": ident}, timeout=60)
            fetched.append(1000 * (time.perf_counter() - t0))
            length = int.from_bytes(answer.content[:4], "little")
            tiles = json.loads(answer.content[4 : 4 + length])["meta"]["payload"]["tiles"]
            view = page.evaluate(
                "i => window.standgrid.openPayload(i).then(v => [v.count, v.ms])", ident
            )
            assert view[0] == row["point_count"], (ident, view[0], row["point_count"])
            in_page.append(view[1])
            print(
                f"  3-D view of payload {ident}: {view[0]:,} points from {len(tiles)} tiles read "
                f"in {view[1]:.0f} ms (points by httpx: {fetched[-1]:.0f} ms)"
            )
        if in_page:
            ratio = statistics.median(in_page) / statistics.median(fetched)
            print(
                f"payload 3-D view: median {statistics.median(in_page):.0f} ms, max "
                f"{max(in_page):.0f} ms; {ratio:.1f}x the points' fetch alone"
            )
        print(f"console errors: {len(errors)}" + (f": {errors[:3]}" if errors else ""))
        browser.close()


if __name__ == "__main__":
    main()
