"""The live view in a real browser (the harness and skip rules of test_viewer_browser.py):
the viewer open on an empty catalog while a mission streams in through the ingest API, as a
robot sends it (the pose graph so far, then the payload of its newest node), shows each
payload's footprint and the growing trajectory as it is stored, then the new cells once the
mission is tiled, without reloading the page. A screenshot per step goes to the test's tmp
folder (``web-live-*.png``; copied to ``$STANDGRID_SCREENSHOTS``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pyogrio
import pytest
import shapely

from tests.test_serve_events import (
    AUTH,
    NAME,
    SOURCE,
    TOKEN,
    Listener,
    _metadata,
    _payload_requests,
)
from tests.test_viewer_browser import Page, _keep_shot, browser  # noqa: F401 (a fixture)

#: Payloads after which a screenshot is kept (every one is checked).
SHOT_AT = (0, 1, 5, 10, 15)


def _graph_until(stamp: str) -> str:
    """The bundled mission's pose graph as the robot had it at ``stamp`` (<sec>_<nsec>): its
    nodes up to then and the edges between them."""
    sec, nsec = (int(v) for v in stamp.split("_"))
    kept: set[str] = set()
    lines = []
    for line in (SOURCE / "slam_pose_graph.g2o").read_text().splitlines():
        parts = line.split()
        if parts and parts[0].startswith("VERTEX"):
            if (int(parts[-2]), int(parts[-1])) > (sec, nsec):
                continue
            kept.add(parts[1])
        elif parts and parts[0].startswith("EDGE") and not {parts[1], parts[2]} <= kept:
            continue
        lines.append(line)
    return "\n".join(lines) + "\n"


@pytest.fixture
def live_base(tmp_path: Path) -> Any:
    from standgrid.catalog import Catalog
    from standgrid.partition import StandGrid
    from standgrid.serve import create_app
    from standgrid.serve.server import running
    from tests.pipeline_fixtures import CRS

    catalog = tmp_path / "catalog"
    Catalog.create(catalog, StandGrid(CRS, 20.0).to_dict(), CRS, "grid")
    with running(create_app(catalog, token=TOKEN, missions=tmp_path / "inbox")) as server:
        yield server.base_url, catalog


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_live_view_shows_each_payload_then_the_cells(
    browser: Any,  # noqa: F811
    live_base: tuple[str, Path],
    tmp_path: Path,
) -> None:
    base, catalog = live_base
    view = Page(browser, base)
    view.open()
    view.page.wait_for_function("() => window.standgrid.live.connected", timeout=10_000)
    # a mark on this document: gone if the page were reloaded
    view.js("() => { window.liveMark = 'this page'; }")
    assert view.js("() => window.standgrid.cellIds(undefined).length") == 0
    shots = [_keep_shot(view, tmp_path, "live-0-empty")]
    assert "live" in view.page.inner_text("#live")

    events = Listener(base).start()  # what the page is told, to compare what it draws
    url = f"{base}/missions/{NAME}"
    assert httpx.post(f"{base}/missions", json=_metadata(), headers=AUTH).status_code == 201
    assert events.next_of("mission").data["mission"] == NAME
    fixes = (SOURCE / "gnss/fixes.txt").read_bytes()
    assert httpx.post(f"{url}/gnss", content=fixes, headers=AUTH, timeout=60).status_code == 200
    view.page.wait_for_function("() => window.standgrid.live.missions.length === 1")
    shown, announced, nodes = {}, {}, []
    for k, (params, body) in enumerate(_payload_requests()):
        graph = _graph_until(params["stamp"])
        assert httpx.put(f"{url}/graph", content=graph, headers=AUTH).status_code == 200
        r = httpx.post(f"{url}/payloads", params=params, content=body, headers=AUTH, timeout=60)
        assert r.status_code == 201, r.text
        announced[params["stamp"]] = events.next_of("payload", timeout=10).data
        ident = f"{NAME}/{params['stamp']}"
        view.page.wait_for_function(
            "id => window.standgrid.livePayloads().includes(id)", arg=ident, timeout=10_000
        )
        assert view.js("() => window.standgrid.livePayloads().length") == k + 1
        shown[params["stamp"]] = (
            view.js("id => window.standgrid.liveGeometry(id)", ident),
            view.js("id => window.standgrid.liveGeometry(id + '#position')", ident),
        )
        # the trajectory drawn grows with the graph
        nodes.append(
            view.js(
                f"() => window.standgrid.live.source.getFeatureById("
                f"'trajectory:{NAME}')?.get('nodes')"
            )
        )
        assert nodes[-1] == graph.count("\nVERTEX_SE3")
        assert f"{k + 1} payload" in view.page.inner_text("#live")
        if k in SHOT_AT:
            view.idle()
            # the newest payload's pose is on the canvas
            x, y = view.js("id => window.standgrid.livePixel(id)", ident)
            box = view.page.locator("#map").bounding_box()
            assert 0 <= x <= box["width"] and 0 <= y <= box["height"]
            shots.append(_keep_shot(view, tmp_path, f"live-1-payload-{k + 1:02d}"))
    assert nodes == sorted(nodes) and nodes[0] < nodes[-1]
    full = (SOURCE / "slam_pose_graph.g2o").read_bytes()
    assert httpx.put(f"{url}/graph", content=full, headers=AUTH).status_code == 200

    tiled = httpx.post(f"{base}/missions/{NAME}/tile", headers=AUTH, timeout=300)
    assert tiled.status_code == 200, tiled.text
    cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
    view.page.wait_for_function(
        "n => window.standgrid.live.tiled.length === 1 && "
        "window.standgrid.cellIds('2024').length === n",
        arg=len(cells),
        timeout=30_000,
    )
    view.idle()
    assert sorted(view.js("() => window.standgrid.cellIds('2024')")) == sorted(cells["cell_id"])
    assert view.js("() => window.standgrid.state.epoch") == "2024"
    shots.append(_keep_shot(view, tmp_path, "live-2-tiled"))
    assert view.js("() => window.liveMark") == "this page"  # never reloaded
    assert view.js("() => performance.getEntriesByType('navigation').length") == 1

    # the page drew what it was told; the catalog, tiled with the whole mission's fit, holds
    # each payload within the fit's change since: metres at first (a heading fitted over a
    # few metres of track), millimetres at the end
    rows = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    rows = rows.sort_values(["stamp_sec", "stamp_nsec"])
    assert len(rows) == len(shown)
    apart = []
    for row in rows.itertuples():
        stamp = f"{row.stamp_sec}_{row.stamp_nsec:09d}"
        ring, position = shown[stamp]
        told = announced[stamp]
        assert position == told["position"]["crs"]["coordinates"]
        assert ring == told["footprint"]["crs"]["coordinates"]
        drawn = shapely.Polygon(np.asarray(ring[0]))
        apart.append(shapely.hausdorff_distance(drawn, row.geometry))
        assert np.hypot(position[0] - row.x, position[1] - row.y) <= apart[-1] + 1e-3
    print(f"\nlive footprints from the catalog's: {', '.join(f'{d:.3f}' for d in apart)} m")
    assert max(apart) < 5.0 and apart[-1] < 0.01
    assert view.errors == [] and view.failed == []
    print("\nscreenshots: " + ", ".join(p.name for p in shots))
    assert all(p.stat().st_size > 10_000 for p in shots)
