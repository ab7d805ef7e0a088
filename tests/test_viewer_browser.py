"""The web viewer in a real browser: headless Chromium (Debian's ``chromium``) driven by
Playwright against a real ``standgrid serve`` on the bundled enriched pair. Skipped when
chromium or the python ``playwright`` package is missing. Screenshots go to
``$STANDGRID_SCREENSHOTS`` when it is set and that folder exists."""

from __future__ import annotations

import io
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyogrio
import pytest
import rasterio
from PIL import Image

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    # WebGL (the CHM layer, the 3-D view) on the CPU: SwiftShader, as --disable-gpu asks
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
_SHOTS = os.environ.get("STANDGRID_SCREENSHOTS")
SHOTS = Path(_SHOTS) if _SHOTS else None


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    playwright_api = pytest.importorskip("playwright.sync_api")
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no chromium at {CHROMIUM}")
    with playwright_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        yield browser
        browser.close()


class Page:
    """A page of the viewer with every console error and failed request recorded."""

    def __init__(self, browser: Any, base: str) -> None:
        self.page = browser.new_page(viewport={"width": 1500, "height": 900})
        self.errors: list[str] = []
        self.failed: list[str] = []
        self.page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.on("requestfailed", lambda r: self.failed.append(f"{r.url} {r.failure}"))
        self.page.on(
            "response", lambda r: r.status >= 400 and self.failed.append(f"{r.url} HTTP {r.status}")
        )
        self.base = base

    def open(self) -> float:
        t0 = time.perf_counter()
        self.page.goto(f"{self.base}/")
        self.page.wait_for_selector("body[data-ready=true]", timeout=30_000)
        return time.perf_counter() - t0

    def js(self, expression: str, arg: Any = None) -> Any:
        return self.page.evaluate(expression, arg)

    def idle(self) -> None:
        self.js("() => window.standgrid.idle()")

    def map_png(self) -> bytes:
        png: bytes = self.page.locator("#map").screenshot()
        return png

    def shot(self, name: str) -> None:
        if SHOTS is not None and SHOTS.is_dir():
            self.page.screenshot(path=str(SHOTS / f"web-{name}.png"))


def _cells(catalog: Path) -> Any:
    return pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")


def test_viewer_map_epochs_metrics_and_cell_view(
    browser: Any, enriched_base: str, enriched_catalog: Path
) -> None:
    base, catalog = enriched_base, enriched_catalog
    metrics = pyogrio.read_dataframe(catalog / "index.gpkg", layer="stand_metrics")
    cells = _cells(catalog)
    view = Page(browser, base)
    wall = view.open()
    first_map_ms = view.js("() => window.standgrid.firstMapMs")
    trees_ms = view.js("() => window.standgrid.treesMs")
    print(
        f"\nfirst map: {first_map_ms:.0f} ms from navigation, trees drawn at {trees_ms:.0f} ms "
        f"({wall:.2f} s wall, from goto)"
    )

    # The map shows the catalog's 20 m cells of the first epoch: every one loaded and drawn.
    epochs = sorted(metrics["epoch"].unique())
    level0 = metrics[metrics["level"] == 0]
    per_epoch = level0.groupby("epoch").size()
    for epoch in epochs:
        assert view.js("e => window.standgrid.loadedCells(e)", epoch) == per_epoch[epoch]
    assert view.js("() => window.standgrid.state.epoch") == epochs[0]
    assert view.js("() => window.standgrid.drawnCells()") == per_epoch[epochs[0]]
    view.shot("map-2024")

    # The CHM is drawn where the COG says: the map's value at pixel centres = rasterio's.
    with rasterio.open(catalog / "rasters" / epochs[0] / "chm.tif") as src:
        chm = src.read(1, masked=True)
        rows, cols = np.nonzero(~np.ma.getmaskarray(chm))
        picks = np.linspace(0, len(rows) - 1, 12).astype(int)
        for r, c in zip(rows[picks], cols[picks], strict=True):
            x, y = src.xy(r, c)
            # the map holds a value once its COG tile is loaded (slower on a loaded machine)
            view.page.wait_for_function(
                "([x, y]) => window.standgrid.chmAt(x, y) !== null", arg=[x, y], timeout=30_000
            )
            shown = view.js("([x, y]) => window.standgrid.chmAt(x, y)", [x, y])
            assert shown == pytest.approx(float(chm[r, c]), abs=1e-4), (x, y)

    # The choropleth: equal intervals over both epochs, so the highest value of a metric is
    # in the top class (yellow) and the lowest in the bottom one (purple).
    def fills(epoch: str) -> dict[str, str]:
        ids = level0.loc[level0["epoch"] == epoch, "cell_id"].tolist()
        return dict(
            zip(ids, view.js("ids => ids.map(window.standgrid.cellFill)", ids), strict=True)
        )

    def check_extremes(metric: str) -> None:
        values = level0.dropna(subset=[metric])
        top, low = values.loc[values[metric].idxmax()], values.loc[values[metric].idxmin()]
        for row, colour in ((top, "#fde725"), (low, "#440154")):
            if row["epoch"] != view.js("() => window.standgrid.state.epoch"):
                view.page.select_option("#epoch", row["epoch"])
                view.idle()
            assert view.js("c => window.standgrid.cellFill(c)", row["cell_id"]) == colour

    before, fills_q95 = view.map_png(), fills(epochs[0])
    check_extremes("zq95")
    view.page.select_option("#epoch", epochs[0])
    view.idle()

    # Another metric: other class colours, another legend, another picture.
    view.page.select_option("#metric", "stems_ha")
    view.idle()
    assert view.js("() => window.standgrid.state.metric") == "stems_ha"
    assert "stems per ha" in view.page.inner_text("#legend")
    assert fills(epochs[0]) != fills_q95
    assert view.map_png() != before
    view.shot("map-stems")
    check_extremes("stems_ha")

    # Another epoch: the other epoch's cells drawn, with other colours where values differ.
    view.page.select_option("#metric", "zq95")
    view.page.select_option("#epoch", epochs[0])
    view.idle()
    assert fills(epochs[0]) == fills_q95
    view.page.select_option("#epoch", epochs[1])
    view.idle()
    assert view.js("() => window.standgrid.drawnCells()") == per_epoch[epochs[1]]
    assert fills(epochs[1]) != fills_q95
    assert view.map_png() != before
    view.shot(f"map-{epochs[1]}")
    view.page.select_option("#epoch", epochs[0])
    view.idle()

    # A comparison: the change of the metric per cell on a red-blue ramp symmetric about 0,
    # the CHM difference under it.
    changes = pyogrio.read_dataframe(catalog / "index.gpkg", layer="stand_changes")
    pair = (changes["epoch_from"] == epochs[0]) & (changes["epoch_to"] == epochs[1])
    changes = changes[(changes["level"] == 0) & pair]
    view.page.select_option("#epoch", f"change:{epochs[0]}__{epochs[1]}")
    view.idle()
    assert view.js("() => window.standgrid.drawnCells()") == len(changes)
    changes = changes.dropna(subset=["zq95_delta"])
    assert f"change in height, 95th percentile (m), {epochs[0]} → {epochs[1]}" in (
        view.page.inner_text("#legend")
    )
    biggest = changes.loc[changes["zq95_delta"].abs().idxmax()]
    end = "#2166ac" if biggest["zq95_delta"] > 0 else "#b2182b"  # gain blue, loss red
    assert view.js("c => window.standgrid.cellFill(c)", biggest["cell_id"]) == end
    diff_tif = catalog / "compare" / f"{epochs[0]}__{epochs[1]}" / "chm_diff.tif"
    with rasterio.open(diff_tif) as src:
        diff = src.read(1, masked=True)
        rows, cols = np.nonzero(~np.ma.getmaskarray(diff))
        for r, c in zip(rows[::997][:8], cols[::997][:8], strict=True):
            shown = view.js("([x, y]) => window.standgrid.chmAt(x, y)", list(src.xy(r, c)))
            assert shown == pytest.approx(float(diff[r, c]), abs=1e-4)
    view.shot("map-change")
    view.page.select_option("#epoch", epochs[0])
    view.idle()

    # A click on a cell opens its 3-D view with that cell's point count.
    cell_row = cells[(cells["epoch"] == epochs[0])].sort_values("point_count").iloc[-1]
    x, y = view.js("c => window.standgrid.pixelOf(c)", cell_row["cell_id"])
    box = view.page.locator("#map").bounding_box()
    t0 = time.perf_counter()
    view.page.mouse.click(box["x"] + x, box["y"] + y)
    view.page.wait_for_function(
        "c => window.standgrid.state.cellView && window.standgrid.state.cellView.cellId === c",
        arg=cell_row["cell_id"],
        timeout=20_000,
    )
    wall_3d = time.perf_counter() - t0
    assert view.page.get_attribute("#panel-count", "data-tree-count") is None  # a cell
    shown = int(view.page.get_attribute("#panel-count", "data-count") or -1)
    las = laspy.read(catalog / cell_row["tile_path"])
    core = int((~np.asarray(las.withheld, dtype=bool)).sum())
    assert shown == core == int(cell_row["point_count"])
    assert f"{core:,} points in the cell" in view.page.inner_text("#panel-count")
    assert cell_row["cell_id"] in view.page.inner_text("#panel-title")
    assert view.page.get_attribute("#panel-source", "data-source") == "server"  # LAZ tiles
    ms_3d = view.js("() => window.standgrid.state.cellView.ms")
    print(
        f"3-D view of {cell_row['cell_id']} ({core} points): {ms_3d:.0f} ms in the page "
        f"({wall_3d:.2f} s wall, click to drawn)"
    )
    # The 3-D canvas is drawn: many colours of the height ramp, not its background alone.
    png = Image.open(io.BytesIO(view.page.locator("#view3d canvas").screenshot()))
    colours = np.unique(np.asarray(png.convert("RGB")).reshape(-1, 3), axis=0)
    assert len(colours) > 50
    view.shot("cell-3d")
    view.page.select_option("#colour-by", "tree")
    view.shot("cell-3d-trees")

    # Both epochs of the cell overlaid, each with its own tile's point count.
    view.page.select_option("#view-layout", "overlay")
    other = cells[(cells["epoch"] == epochs[1]) & (cells["cell_id"] == cell_row["cell_id"])]
    expected = f"{epochs[1]}: {int(other['point_count'].iloc[0]):,} points"
    view.page.wait_for_function(
        "t => document.querySelector('#colour-legend').innerText.includes(t)",
        arg=expected,
        timeout=20_000,
    )
    assert f"{epochs[0]}: {core:,} points" in view.page.inner_text("#colour-legend")
    view.shot("cell-3d-epochs")
    view.page.select_option("#view-layout", "single")

    # A click on a tree's marker (stem or top): the tree's attributes, its cell's points with
    # the tree's marked, as many as the tile holds with its tree_id.
    trees = pyogrio.read_dataframe(catalog / "index.gpkg", layer="trees", fid_as_index=True)
    tree = trees[trees["epoch"] == epochs[0]].sort_values("n_points").iloc[-1]
    x, y = view.js("f => window.standgrid.treePixel(f)", int(tree.name))
    box = view.page.locator("#map").bounding_box()
    view.page.mouse.click(box["x"] + x, box["y"] + y)
    view.page.wait_for_function(
        "() => document.querySelector('#panel-count').dataset.treeCount !== undefined",
        timeout=20_000,
    )
    assert view.js("() => window.standgrid.state.cellView.treeFid") == int(tree.name)
    tile = laspy.read(catalog / "tiles" / epochs[0] / f"{tree['cell_id']}.laz")
    core = ~np.asarray(tile.withheld, dtype=bool)
    of_tree = int((np.asarray(tile["tree_id"])[core] == int(tree["tree_id"])).sum())
    assert of_tree > 0
    assert int(view.page.get_attribute("#panel-count", "data-tree-count") or -1) == of_tree
    assert view.page.get_attribute("#panel-count", "data-count") == str(int(core.sum()))
    assert f"tree in {tree['cell_id']}" in view.page.inner_text("#panel-title")
    assert f"{tree['height_m']:.1f}" in view.page.inner_text("#panel-attributes")
    assert str(int(tree["tree_id"])) in view.page.inner_text("#panel-attributes")  # exact
    view.shot("tree-3d")

    # The printable page of the tree's 1 ha stand: every tree of the stand in that epoch.
    href = view.page.get_attribute("#stand-link", "href") or ""
    stand_id = tree["stand_id"]
    assert f"stand={stand_id}" in href
    stand = Page(browser, base)
    stand.page.goto(f"{base}{href}")
    stand.page.wait_for_selector("body[data-ready=true]", state="attached", timeout=30_000)
    expected_trees = trees[(trees["stand_id"] == stand_id) & (trees["epoch"] == epochs[0])]
    assert stand.page.locator("#tree-list tr").count() == len(expected_trees) + 1  # + header
    assert f"Trees ({len(expected_trees)}, {epochs[0]})" in stand.page.inner_text("#stand")
    row = metrics[(metrics["cell_id"] == stand_id) & (metrics["epoch"] == epochs[0])].iloc[0]
    metrics_text = stand.page.inner_text("table.metrics")
    assert f"{row['basal_area_m2_ha']:.1f}" in metrics_text
    assert stand.page.locator("section.plots svg").count() == 2
    if SHOTS is not None and SHOTS.is_dir():
        stand.page.screenshot(path=str(SHOTS / "web-stand.png"), full_page=True)
    assert stand.errors == [] and stand.failed == []

    assert view.errors == []
    assert view.failed == []


def _core_counts(tile: Path) -> tuple[int, Any]:
    """A tile's core point count and the payload_id of each core point (laspy)."""
    las = laspy.read(tile)
    core = ~np.asarray(las.withheld, dtype=bool)
    return int(core.sum()), np.asarray(las["payload_id"])[core]


def _keep_shot(view: Page, tmp_path: Path, name: str) -> Path:
    """A screenshot in the test's tmp folder, copied to ``SHOTS`` when that folder exists."""
    path = tmp_path / f"web-{name}.png"
    view.page.screenshot(path=str(path))
    if SHOTS is not None and SHOTS.is_dir():
        shutil.copy(path, SHOTS / path.name)
    return path


def _canvas_colours(locator: Any) -> int:
    png = Image.open(io.BytesIO(locator.screenshot()))
    return len(np.unique(np.asarray(png.convert("RGB")).reshape(-1, 3), axis=0))


def test_viewer_payload_view_and_epochs_side_by_side(
    browser: Any, enriched_base: str, enriched_catalog: Path, tmp_path: Path
) -> None:
    base, catalog = enriched_base, enriched_catalog
    payloads = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    view = Page(browser, base)
    view.open()
    epoch = view.js("() => window.standgrid.state.epoch")

    # Footprints on, tree markers off (a click near a tree's dot opens the tree): a click at
    # a payload's pose opens that payload.
    view.page.check("input[data-layer=payloads]")
    view.page.uncheck("input[data-layer=trees]")
    view.idle()
    row = payloads[payloads["epoch"] == epoch].sort_values("point_count").iloc[-1]
    ident = int(row["payload_id"])
    x, y = view.js("i => window.standgrid.payloadPixel(i)", ident)
    box = view.page.locator("#map").bounding_box()
    t0 = time.perf_counter()
    view.page.mouse.click(box["x"] + x, box["y"] + y)
    view.page.wait_for_function(
        "i => window.standgrid.state.cellView && window.standgrid.state.cellView.payloadId === i",
        arg=ident,
        timeout=20_000,
    )
    wall = time.perf_counter() - t0
    shown = int(view.page.get_attribute("#panel-count", "data-count") or -1)
    # The payload's points as the tiles hold them, counted with laspy over every tile of the
    # epoch: the same number as the payloads layer records, and all of them drawn (under the cap).
    counted = 0
    for tile in sorted((catalog / "tiles" / epoch).glob("*.la[sz]")):
        counted += int((_core_counts(tile)[1] == ident).sum())
    assert shown == counted == int(row["point_count"]) > 0
    assert view.page.get_attribute("#panel-count", "data-shown") == str(shown)
    assert view.page.get_attribute("#panel-count", "data-payload") == str(ident)
    assert f"{shown:,} points of the payload" in view.page.inner_text("#panel-count")
    title = view.page.inner_text("#panel-title")
    assert str(ident) in title and row["mission"] in title
    attributes = view.page.inner_text("#panel-attributes")
    assert row["time"] in attributes
    assert f"pose graph node · node_id\t{row['node_id']}" in attributes
    assert view.page.locator("#view-layout").is_disabled()  # a payload is of one epoch
    assert _canvas_colours(view.page.locator("#view3d canvas")) > 50  # the height ramp
    ms = view.js("() => window.standgrid.state.cellView.ms")
    print(
        f"\n3-D view of payload {ident} ({shown} points): {ms:.0f} ms in the page "
        f"({wall:.2f} s wall, click to drawn)"
    )
    _keep_shot(view, tmp_path, "payload-3d")
    view.page.select_option("#colour-by", "classification")
    view.page.uncheck("input[data-layer=payloads]")
    view.idle()

    # A cell with a tile in both epochs, its epochs side by side: two canvases, one per
    # epoch, each labelled with its tile's core point count (laspy).
    cells = _cells(catalog)
    both = cells.groupby("cell_id")["epoch"].nunique()
    mine = cells[(cells["epoch"] == epoch) & cells["cell_id"].isin(both[both == 2].index)]
    cell = mine.sort_values("point_count").iloc[-1]
    x, y = view.js("c => window.standgrid.pixelOf(c)", cell["cell_id"])
    view.page.mouse.click(box["x"] + x, box["y"] + y)
    view.page.wait_for_function(
        "c => window.standgrid.state.cellView && window.standgrid.state.cellView.cellId === c",
        arg=cell["cell_id"],
        timeout=20_000,
    )
    view.page.select_option("#colour-by", "height")
    view.page.select_option("#view-layout", "side")
    view.page.wait_for_function(
        "() => document.querySelectorAll('#view3d .viewport-label').length === 2", timeout=20_000
    )
    assert view.page.locator("#view3d canvas").count() == 2
    labels = view.page.locator("#view3d .viewport-label")
    expected = {}
    for _, tile_row in cells[cells["cell_id"] == cell["cell_id"]].iterrows():
        expected[tile_row["epoch"]] = _core_counts(catalog / tile_row["tile_path"])[0]
        assert expected[tile_row["epoch"]] == int(tile_row["point_count"])
    got = {
        labels.nth(k).get_attribute("data-epoch"): int(labels.nth(k).get_attribute("data-count"))
        for k in range(2)
    }
    assert got == expected
    assert labels.nth(0).get_attribute("data-epoch") == epoch  # the clicked epoch first
    for k in range(2):
        text = labels.nth(k).inner_text()
        assert f"{got[labels.nth(k).get_attribute('data-epoch')]:,} points" in text
    canvases = view.page.locator("#view3d canvas")
    for k in range(2):
        assert _canvas_colours(canvases.nth(k)) > 50
    _keep_shot(view, tmp_path, "side-by-side")

    # One camera: dragging in the left view turns the right one too.
    right_before = canvases.nth(1).screenshot()
    left = canvases.nth(0).bounding_box()
    cx, cy = left["x"] + left["width"] / 2, left["y"] + left["height"] / 2
    view.page.mouse.move(cx, cy)
    view.page.mouse.down()
    view.page.mouse.move(cx + 80, cy + 10, steps=6)
    view.page.mouse.up()
    assert canvases.nth(1).screenshot() != right_before

    # Back to one view: one canvas.
    view.page.select_option("#view-layout", "single")
    view.page.wait_for_function(
        "() => document.querySelectorAll('#view3d canvas').length === 1", timeout=20_000
    )
    assert view.errors == []
    assert view.failed == []


@pytest.fixture(scope="module")
def copc_catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled pair tiled as COPC (2 m buffer), enriched and compared (shared)."""
    from tests.pipeline_fixtures import copc_pair

    return copc_pair(tmp_path_factory)


@pytest.fixture(scope="module")
def copc_base(copc_catalog: Path) -> Iterator[str]:
    from standgrid.serve import create_app
    from standgrid.serve.server import running

    with running(create_app(copc_catalog)) as server:
        assert server.base_url is not None
        yield server.base_url


#: What the page computes from the points it draws (the 3-D view's arrays), for laspy to check.
POINTS_SUMMARY = """() => {
  const p = window.standgrid.state.cellView.points;
  const n = p.header.count;
  let ground = 0, top = -Infinity;
  const max = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < n; i += 1) {
    if (p.classification[i] === 2) ground += 1;
    if (p.height_above_ground[i] > top) top = p.height_above_ground[i];
    for (let d = 0; d < 3; d += 1) max[d] = Math.max(max[d], p.xyz[3 * i + d]);
  }
  return { n, ground, top, origin: p.header.origin, max,
           trees: new Set(Array.from(p.tree_key).filter((k) => k !== 0)).size };
}"""


def test_viewer_streams_a_copc_cell_from_its_tile(
    browser: Any, copc_base: str, copc_catalog: Path, tmp_path: Path
) -> None:
    base, catalog = copc_base, copc_catalog
    cells = _cells(catalog)
    view = Page(browser, base)
    requests: list[dict[str, Any]] = []

    def record(response: Any) -> None:
        requests.append(
            {
                "url": response.url,
                "status": response.status,
                "range": response.request.headers.get("range"),
                "length": int(response.headers.get("content-length") or -1),
            }
        )

    view.page.on("response", record)
    view.open()
    assert view.js("() => window.standgrid.state.config.tiles") == "copc"
    assert view.js("() => window.standgrid.state.streamCopc") is True
    epoch = view.js("() => window.standgrid.state.epoch")

    # A click on the densest cell with a tile in both epochs.
    both = cells.groupby("cell_id")["epoch"].nunique()
    mine = cells[(cells["epoch"] == epoch) & cells["cell_id"].isin(both[both == 2].index)]
    cell = mine.sort_values("point_count").iloc[-1]
    tile = catalog / cell["tile_path"]
    assert cell["tile_path"].endswith(".copc.laz")
    before = len(requests)
    x, y = view.js("c => window.standgrid.pixelOf(c)", cell["cell_id"])
    box = view.page.locator("#map").bounding_box()
    t0 = time.perf_counter()
    view.page.mouse.click(box["x"] + x, box["y"] + y)
    view.page.wait_for_function(
        "c => window.standgrid.state.cellView && window.standgrid.state.cellView.cellId === c",
        arg=cell["cell_id"],
        timeout=20_000,
    )
    wall = time.perf_counter() - t0

    # Exactly the cell's core points: the cells layer's count and laspy's non-withheld points.
    las = laspy.read(tile)
    core = ~np.asarray(las.withheld, dtype=bool)
    shown = int(view.page.get_attribute("#panel-count", "data-count") or -1)
    assert shown == int(core.sum()) == int(cell["point_count"])
    assert f"{shown:,} points in the cell" in view.page.inner_text("#panel-count")
    # ... decoded right: extremes, ground returns, heights and trees as laspy reads them.
    got = view.js(POINTS_SUMMARY)
    assert got["n"] == shown
    xyz = np.column_stack([las.x, las.y, las.z])[core]
    np.testing.assert_allclose(got["origin"], xyz.min(axis=0), rtol=0, atol=1e-9)
    # float32 offsets from the origin: within a float32 step of a few tens of metres
    np.testing.assert_allclose(np.add(got["origin"], got["max"]), xyz.max(axis=0), atol=1e-5)
    assert got["ground"] == int((np.asarray(las.classification)[core] == 2).sum()) > 0
    assert got["top"] == pytest.approx(float(np.max(las["height_above_ground"][core])), abs=0)
    tree_ids = np.asarray(las["tree_id"])[core]
    assert got["trees"] == len(np.unique(tree_ids[tree_ids != 0])) > 0

    # Streamed by the page: range requests answered 206 for that tile, all the bytes it says
    # it fetched, and no /viewer/points call.
    clicked = requests[before:]
    assert not [r for r in clicked if "/viewer/points" in r["url"]]
    ranged = [r for r in clicked if r["url"].endswith(f"/files/{cell['tile_path']}")]
    assert ranged and all(r["status"] == 206 and r["range"] for r in ranged)
    source = view.page.locator("#panel-source")
    assert source.get_attribute("data-source") == "copc"
    assert int(source.get_attribute("data-bytes") or -1) == sum(r["length"] for r in ranged)
    assert int(source.get_attribute("data-requests") or -1) == len(ranged)
    assert int(source.get_attribute("data-file-size") or -1) == tile.stat().st_size
    # no byte twice: the head and tail read ahead (64 + 8 kB) are not fetched again
    assert tile.stat().st_size > (64 + 8) * 1024
    assert sum(r["length"] for r in ranged) <= tile.stat().st_size
    assert "streamed from the COPC tile" in source.inner_text()
    assert _canvas_colours(view.page.locator("#view3d canvas")) > 50  # the height ramp
    ms = view.js("() => window.standgrid.state.cellView.ms")
    print(
        f"\nCOPC 3-D view of {cell['cell_id']} ({shown} points, first click): {ms:.0f} ms "
        f"in the page ({wall:.2f} s wall, click to drawn); {source.inner_text()}"
    )
    path = _keep_shot(view, tmp_path, "copc-3d")
    assert path.stat().st_size > 0

    # The other epoch overlaid: streamed from its own COPC tile, its own core count.
    other = cells[(cells["cell_id"] == cell["cell_id"]) & (cells["epoch"] != epoch)].iloc[0]
    before = len(requests)
    view.page.select_option("#view-layout", "overlay")
    expected = f"{other['epoch']}: {int(other['point_count']):,} points"
    view.page.wait_for_function(
        "t => document.querySelector('#colour-legend').innerText.includes(t)",
        arg=expected,
        timeout=20_000,
    )
    other_las = laspy.read(catalog / other["tile_path"])
    assert int((~np.asarray(other_las.withheld, dtype=bool)).sum()) == int(other["point_count"])
    overlaid = requests[before:]
    assert [r for r in overlaid if r["url"].endswith(f"/files/{other['tile_path']}")]
    assert all(r["status"] == 206 for r in overlaid if "/files/tiles/" in r["url"])
    assert not [r for r in overlaid if "/viewer/points" in r["url"]]
    view.page.select_option("#view-layout", "single")

    # A click on a tree's marker: its cell streamed too, the tree's points told by its exact
    # 64-bit id (read from the feature's JSON text), as many as laspy finds in the tile.
    trees = pyogrio.read_dataframe(catalog / "index.gpkg", layer="trees", fid_as_index=True)
    tree = trees[trees["epoch"] == epoch].sort_values("n_points").iloc[-1]
    before = len(requests)
    x, y = view.js("f => window.standgrid.treePixel(f)", int(tree.name))
    box = view.page.locator("#map").bounding_box()
    view.page.mouse.click(box["x"] + x, box["y"] + y)
    view.page.wait_for_function(
        "() => document.querySelector('#panel-count').dataset.treeCount !== undefined",
        timeout=20_000,
    )
    assert view.js("() => window.standgrid.state.cellView.treeFid") == int(tree.name)
    tree_las = laspy.read(catalog / "tiles" / epoch / f"{tree['cell_id']}.copc.laz")
    tree_core = ~np.asarray(tree_las.withheld, dtype=bool)
    of_tree = int((np.asarray(tree_las["tree_id"])[tree_core] == int(tree["tree_id"])).sum())
    assert of_tree > 0
    assert int(view.page.get_attribute("#panel-count", "data-tree-count") or -1) == of_tree
    assert view.page.get_attribute("#panel-count", "data-count") == str(int(tree_core.sum()))
    assert str(int(tree["tree_id"])) in view.page.inner_text("#panel-attributes")  # exact
    assert view.page.get_attribute("#panel-source", "data-source") == "copc"
    assert not [r for r in requests[before:] if "/viewer/points" in r["url"]]
    view.shot("copc-tree-3d")

    # The same cell read by the server (the LAS/LAZ path): the same count; then the time to
    # the 3-D view both ways, alternated on the same page (warm: laz-perf started).
    def open_cell(stream: bool) -> tuple[float, str, int]:
        view.js("s => { window.standgrid.state.streamCopc = s; }", stream)
        done = view.js(
            "c => window.standgrid.openCell(c).then(v => [v.ms, v.source, v.count])",
            cell["cell_id"],
        )
        return float(done[0]), str(done[1]), int(done[2])

    times: dict[str, list[float]] = {"copc": [], "server": []}
    for _ in range(3):
        for stream in (True, False):
            ms_taken, how, count = open_cell(stream)
            assert count == shown
            times[how].append(ms_taken)
    assert view.page.get_attribute("#panel-source", "data-source") == "server"
    print(
        "time to the 3-D view of the cell, median of 3 (warm): "
        f"COPC streamed {np.median(times['copc']):.0f} ms, /viewer/points "
        f"{np.median(times['server']):.0f} ms"
    )
    assert view.errors == []
    assert view.failed == []


@pytest.fixture(scope="module")
def deep_copc(copc_catalog: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A copy of the COPC catalog whose densest 2024 tile is indexed again into a deep octree
    (4 sampling cells per node axis, leaves of at most 256 points: nodes a few metres wide,
    some wholly in the buffer ring), served: (base URL, catalog, that tile's cells row)."""
    from standgrid.export.copc import write_copc_tile
    from standgrid.export.las import read_tile
    from standgrid.pointcloud import PointCloud
    from standgrid.serve import create_app
    from standgrid.serve.server import running
    from tests.pipeline_fixtures import CRS, copy_catalog

    catalog = copy_catalog(copc_catalog, tmp_path_factory.mktemp("deep") / "catalog")
    cells = _cells(catalog)
    row = cells[cells["epoch"] == "2024"].sort_values("point_count").iloc[-1]
    tile = catalog / row["tile_path"]
    cloud = read_tile(tile, include_withheld=True)
    withheld = np.asarray(cloud.fields["withheld"], dtype=bool)
    points = PointCloud(cloud.xyz, {k: v for k, v in cloud.fields.items() if k != "withheld"})
    write_copc_tile(
        tile,
        points.select(~withheld),
        buffer=points.select(withheld),
        crs=CRS,
        resolution=4,
        leaf_points=256,
    )
    with running(create_app(catalog)) as server:
        yield server.base_url, catalog, row


def test_viewer_streams_only_the_octree_nodes_a_cell_needs(browser: Any, deep_copc: Any) -> None:
    import copclib

    base, catalog, row = deep_copc
    tile = catalog / row["tile_path"]
    reader = copclib.FileReader(str(tile))
    try:
        nodes = len([n for n in reader.GetAllNodes() if n.point_count > 0])
    finally:
        reader.Close()
    view = Page(browser, base)
    ranged: list[Any] = []
    view.page.on("response", lambda r: r.url.endswith(row["tile_path"]) and ranged.append(r))
    view.open()
    got = view.js(
        "c => window.standgrid.openCell(c).then(v => ({count: v.count, source: "
        "v.source, copc: v.points.header.meta.copc}))",
        row["cell_id"],
    )
    las = laspy.read(tile)
    core = int((~np.asarray(las.withheld, dtype=bool)).sum())
    assert got["source"] == "copc"
    assert got["count"] == core == int(row["point_count"])
    streamed = got["copc"]
    assert streamed["nodes"] == nodes > 50
    # the nodes wholly in the buffer ring are left out, and their bytes are not fetched
    assert streamed["nodes_read"] < nodes
    assert streamed["bytes"] < tile.stat().st_size == streamed["file_size"]
    assert ranged and all(r.status == 206 for r in ranged)
    assert streamed["requests"] == len(ranged) < streamed["nodes_read"]  # runs coalesced
    print(
        f"\ndeep octree: {streamed['nodes_read']} of {nodes} nodes, {streamed['bytes']} of "
        f"{tile.stat().st_size} bytes in {streamed['requests']} range requests"
    )
    assert view.errors == []
    assert view.failed == []


# --- the basemap field: an XYZ template or a WMTS capabilities URL -------------------------

#: Web Mercator: half the world's width (m), and the scale denominator of zoom 0 (256 px tiles).
MERCATOR_HALF = 20037508.342789244
ZOOM0_SCALE = 559082264.0287178
WMTS_COLOUR, XYZ_COLOUR = (196, 48, 112), (40, 150, 210)


def _capabilities(base: str, zooms: int = 23) -> str:
    """A WMTS 1.0.0 capabilities document: one layer ``ortho`` in the GoogleMapsCompatible
    EPSG:3857 tile matrix set, tiles by a RESTful ResourceURL template."""
    matrices = "".join(
        f"<TileMatrix><ows:Identifier>{z}</ows:Identifier>"
        f"<ScaleDenominator>{ZOOM0_SCALE / 2**z!r}</ScaleDenominator>"
        f"<TopLeftCorner>{-MERCATOR_HALF!r} {MERCATOR_HALF!r}</TopLeftCorner>"
        "<TileWidth>256</TileWidth><TileHeight>256</TileHeight>"
        f"<MatrixWidth>{2**z}</MatrixWidth><MatrixHeight>{2**z}</MatrixHeight></TileMatrix>"
        for z in range(zooms)
    )
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<Capabilities xmlns="http://www.opengis.net/wmts/1.0" xmlns:ows="http://www.opengis.net/ows/1.1"
    xmlns:xlink="http://www.w3.org/1999/xlink" version="1.0.0">
  <ows:ServiceIdentification>
    <ows:Title>test tiles</ows:Title>
    <ows:ServiceType>OGC WMTS</ows:ServiceType>
    <ows:ServiceTypeVersion>1.0.0</ows:ServiceTypeVersion>
  </ows:ServiceIdentification>
  <ows:OperationsMetadata>
    <ows:Operation name="GetTile"><ows:DCP><ows:HTTP>
      <ows:Get xlink:href="{base}/wmts/"><ows:Constraint name="GetEncoding">
        <ows:AllowedValues><ows:Value>RESTful</ows:Value></ows:AllowedValues>
      </ows:Constraint></ows:Get>
    </ows:HTTP></ows:DCP></ows:Operation>
  </ows:OperationsMetadata>
  <Contents>
    <Layer>
      <ows:Title>ortho</ows:Title>
      <ows:WGS84BoundingBox>
        <ows:LowerCorner>-180 -85.0511287798</ows:LowerCorner>
        <ows:UpperCorner>180 85.0511287798</ows:UpperCorner>
      </ows:WGS84BoundingBox>
      <ows:Identifier>ortho</ows:Identifier>
      <Style isDefault="true"><ows:Identifier>default</ows:Identifier></Style>
      <Format>image/png</Format>
      <TileMatrixSetLink><TileMatrixSet>GoogleMapsCompatible</TileMatrixSet></TileMatrixSetLink>
      <ResourceURL format="image/png" resourceType="tile"
        template="{base}/wmts/ortho/{{Style}}/{{TileMatrixSet}}/{{TileMatrix}}/{{TileRow}}/{{TileCol}}.png"/>
    </Layer>
    <TileMatrixSet>
      <ows:Identifier>GoogleMapsCompatible</ows:Identifier>
      <ows:SupportedCRS>urn:ogc:def:crs:EPSG::3857</ows:SupportedCRS>
      <WellKnownScaleSet>urn:ogc:def:wkss:OGC:1.0:GoogleMapsCompatible</WellKnownScaleSet>
      {matrices}
    </TileMatrixSet>
  </Contents>
</Capabilities>
"""


def _png(colour: tuple[int, int, int]) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.full((256, 256, 3), colour, dtype=np.uint8)).save(out, format="PNG")
    return out.getvalue()


@pytest.fixture(scope="module")
def tile_server() -> Iterator[tuple[str, list[str]]]:
    """A real HTTP server on 127.0.0.1 (another origin than the viewer's, CORS allowed):
    ``/WMTSCapabilities.xml``, WMTS tiles of one colour and ``/xyz/{z}/{x}/{y}.png`` tiles of
    another. Yields its base URL and the paths it was asked for."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    asked: list[str] = []
    tiles = {"wmts": _png(WMTS_COLOUR), "xyz": _png(XYZ_COLOUR)}

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            asked.append(self.path)
            route = self.path.strip("/").split("/")[0]
            if self.path == "/WMTSCapabilities.xml":
                body, kind = _capabilities(base).encode(), "application/xml"
            elif route in tiles and self.path.endswith(".png"):
                body, kind = tiles[route], "image/png"
            else:
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Access-Control-Allow-Origin", "*")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    base = f"http://127.0.0.1:{server.server_address[1]}"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield base, asked
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


def _set_basemap(view: Page, text: str) -> str:
    """Type into the basemap field (committed by leaving it); the note shown next to it."""
    view.page.fill("#basemap", text)
    view.page.press("#basemap", "Tab")
    view.idle()
    return view.page.inner_text("#basemap-status")


def _corner_colour(view: Page) -> np.ndarray:
    """The median colour of a 5x5 patch in the map's top-left padding: outside the cells
    (the view is fitted to them with 20 px of padding), where only a basemap draws."""
    png = np.asarray(Image.open(io.BytesIO(view.map_png())).convert("RGB"))
    return np.median(png[6:11, 6:11].reshape(-1, 3), axis=0)


def _tiles_asked(asked: list[str], prefix: str) -> list[tuple[int, int, int]]:
    """(z, x, y) of the tiles asked for under a route (the WMTS path ends .../z/row/col.png)."""
    found = []
    for path in asked:
        parts = path.removesuffix(".png").split("/")
        if path.startswith(prefix):
            z, a, b = (int(p) for p in parts[-3:])
            found.append((z, b, a) if prefix.startswith("/wmts") else (z, a, b))
    return found


def _covers(tiles: list[tuple[int, int, int]], x: float, y: float) -> bool:
    """Whether a Web Mercator point is in one of the tiles of the deepest zoom asked for."""
    z = max(t[0] for t in tiles)
    size = 2 * MERCATOR_HALF / 2**z
    col, row = int((x + MERCATOR_HALF) // size), int((MERCATOR_HALF - y) // size)
    return (z, col, row) in set(tiles)


def test_viewer_basemap_from_wmts_capabilities_and_xyz(
    browser: Any,
    enriched_base: str,
    enriched_catalog: Path,
    tile_server: tuple[str, list[str]],
    tmp_path: Path,
) -> None:
    from pyproj import Transformer

    tiles_base, asked = tile_server
    cells = _cells(enriched_catalog)
    x0, y0, x1, y1 = cells.total_bounds
    to_mercator = Transformer.from_crs(cells.crs, "EPSG:3857", always_xy=True)
    centre = to_mercator.transform((x0 + x1) / 2, (y0 + y1) / 2)
    view = Page(browser, enriched_base)
    view.open()
    background = _corner_colour(view)
    assert np.abs(background - WMTS_COLOUR).max() > 40

    # WMTS: the capabilities read, the first layer's EPSG:3857 tiles asked for where the
    # catalog is (reprojected to the catalog's CRS), their colour on the map.
    note = _set_basemap(view, f"{tiles_base}/WMTSCapabilities.xml")
    assert note == "WMTS layer ortho, tile matrix set GoogleMapsCompatible"
    assert "/WMTSCapabilities.xml" in asked
    wmts = _tiles_asked(asked, "/wmts/ortho/default/GoogleMapsCompatible/")
    assert wmts and _covers(wmts, *centre), wmts
    assert np.abs(_corner_colour(view) - WMTS_COLOUR).max() <= 2
    _keep_shot(view, tmp_path, "wmts")

    # The layer named after '#', and one that is not there: said next to the field.
    asked.clear()
    assert _set_basemap(view, f"{tiles_base}/WMTSCapabilities.xml#layer=ortho").startswith(
        "WMTS layer ortho"
    )
    note = _set_basemap(view, f"{tiles_base}/WMTSCapabilities.xml#layer=roads")
    assert note == f"basemap: {tiles_base}/WMTSCapabilities.xml: no layer roads (layers: ortho)"
    assert np.abs(_corner_colour(view) - background).max() <= 2

    # XYZ: the same server's {z}/{x}/{y} route, the other colour.
    asked.clear()
    assert _set_basemap(view, f"{tiles_base}/xyz/{{z}}/{{x}}/{{y}}.png") == "XYZ tiles"
    xyz = _tiles_asked(asked, "/xyz/")
    assert xyz and _covers(xyz, *centre), xyz
    assert np.abs(_corner_colour(view) - XYZ_COLOUR).max() <= 2
    _keep_shot(view, tmp_path, "xyz")

    # Cleared: no basemap.
    assert _set_basemap(view, "") == ""
    assert np.abs(_corner_colour(view) - background).max() <= 2
    assert view.errors == []
    assert view.failed == []

    # Neither a template nor capabilities, and an unreachable server: said next to the field,
    # nothing uncaught (the browser's own log of the refused connection aside).
    assert "not an XYZ template" in _set_basemap(view, "https://example.invalid/tiles.png")
    unreachable = "http://127.0.0.1:9/WMTSCapabilities.xml"
    note = _set_basemap(view, unreachable)
    assert note.startswith(f"basemap: {unreachable}: unreachable"), note
    assert view.js("() => document.getElementById('basemap-status').classList.contains('warning')")
    _keep_shot(view, tmp_path, "basemap-error")
    assert [e for e in view.errors if "Failed to load resource" not in e] == []


# --- a catalog without a comparison: the stand page and the cell panel ----------------------

#: The cells' texts of each table row a selector picks.
ROW_TEXTS = "s => [...document.querySelectorAll(s)].map(r => [...r.children].map(c => c.innerText))"
#: The stand page's epoch colours (web/src/stand.js), first epoch first.
EPOCH_COLOURS = [(0x4E, 0x79, 0xA7), (0xF2, 0x8E, 0x2B)]


def _without_comparisons(catalog: Path) -> None:
    """Make a copied catalog one that was never compared: no change layers in its index, no
    compare/ folder, no comparisons in catalog.json (as after ``enrich`` alone)."""
    import json
    import sqlite3

    with sqlite3.connect(catalog / "index.gpkg") as db:
        for layer in ("stand_changes", "tree_changes"):
            (geom,) = db.execute(
                "SELECT column_name FROM gpkg_geometry_columns WHERE table_name = ?", (layer,)
            ).fetchone()
            db.execute(f'DROP TABLE IF EXISTS "rtree_{layer}_{geom}"')
            db.execute(f'DROP TABLE "{layer}"')
            for table, column in (
                ("gpkg_contents", "table_name"),
                ("gpkg_geometry_columns", "table_name"),
                ("gpkg_extensions", "table_name"),
                ("layer_styles", "f_table_name"),
            ):
                db.execute(f"DELETE FROM {table} WHERE {column} = ?", (layer,))
    shutil.rmtree(catalog / "compare")
    state = json.loads((catalog / "catalog.json").read_text())
    state["comparisons"] = {}
    (catalog / "catalog.json").write_text(json.dumps(state, indent=1))


@pytest.fixture(scope="module")
def uncompared(enriched_catalog: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A copy of the enriched pair without its comparison, served: (base URL, catalog)."""
    from standgrid.serve import create_app
    from standgrid.serve.server import running
    from tests.pipeline_fixtures import copy_catalog

    catalog = copy_catalog(enriched_catalog, tmp_path_factory.mktemp("uncompared") / "catalog")
    _without_comparisons(catalog)
    with running(create_app(catalog)) as server:
        assert server.base_url is not None
        yield server.base_url, catalog


def _get_json(url: str) -> Any:
    import json
    import urllib.request

    with urllib.request.urlopen(url, timeout=30) as answer:
        return json.load(answer)


def _has_colour(png: bytes, rgb: tuple[int, int, int], tolerance: int = 12) -> bool:
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    return bool((np.abs(pixels - np.array(rgb)).max(axis=-1) <= tolerance).any())


def test_stand_page_of_an_uncompared_catalog(browser: Any, uncompared: Any) -> None:
    """The printable stand page on a catalog never compared: it asks only for collections the
    catalog has (no 404 for stand_changes in the console), its plots' legend squares are in
    the epochs' bar colours (not black), and counts read as whole numbers."""
    base, catalog = uncompared
    collections = {c["id"] for c in _get_json(f"{base}/ogc/collections")["collections"]}
    assert "stand_changes" not in collections and "stand_metrics" in collections
    metrics = pyogrio.read_dataframe(catalog / "index.gpkg", layer="stand_metrics")
    stands = metrics[(metrics["level"] == 1) & (metrics["n_trees"] > 0)]
    row = stands.sort_values("n_trees").iloc[-1]
    stand = Page(browser, base)
    stand.page.goto(f"{base}/?stand={row['cell_id']}&epoch={row['epoch']}")
    stand.page.wait_for_selector("body[data-ready=true]", state="attached", timeout=30_000)
    requested = stand.js("() => window.standgrid.standPage.requested")
    assert requested == ["stand_metrics", "trees"]
    assert stand.page.locator("#tree-list tr").count() == int(row["n_trees"]) + 1

    # the legend squares of both plots: each epoch's colour, as its bars
    legends = stand.page.locator("#stand .fig-legend")
    assert legends.count() == 2
    for k in range(2):
        png = legends.nth(k).screenshot()
        for rgb in EPOCH_COLOURS:
            assert _has_colour(png, rgb), (k, rgb)
    if SHOTS is not None and SHOTS.is_dir():
        stand.page.screenshot(path=str(SHOTS / "web-stand-uncompared.png"), full_page=True)

    # counts as integers: the "trees" and "returns" rows hold no decimals
    table = {r[0]: r[1:] for r in stand.js(ROW_TEXTS, "table.metrics tr")}
    by_epoch = metrics[metrics["cell_id"] == row["cell_id"]].sort_values("epoch")
    assert table["trees"] == [str(int(n)) for n in by_epoch["n_trees"]]
    assert table["returns"] == [f"{int(n):,}" for n in by_epoch["n_points"]]
    # the tree list: one decimal throughout a column (a 7 m² crown reads "7.0", not "7")
    trees = stand.js(ROW_TEXTS, "#tree-list tr")[1:]
    assert trees and all(re.fullmatch(r"\d+\.\d", t[4]) for t in trees), trees[:5]
    assert stand.errors == [] and stand.failed == []  # no 404, no console error


def test_cell_panel_shows_counts_as_integers(browser: Any, uncompared: Any) -> None:
    """The clicked cell's attributes: trees "3", not "3.00"; returns with thousands
    separators; other numbers with a few decimals. The map of a catalog without a
    comparison loads with no failed request either."""
    base, catalog = uncompared
    metrics = pyogrio.read_dataframe(catalog / "index.gpkg", layer="stand_metrics")
    view = Page(browser, base)
    view.open()
    epoch = view.js("() => window.standgrid.state.epoch")
    level0 = metrics[(metrics["level"] == 0) & (metrics["epoch"] == epoch)]
    cell = level0[(level0["n_trees"] > 0) & (level0["n_trees"] < 10)].iloc[0]
    view.js("c => window.standgrid.openCell(c).then(() => true)", cell["cell_id"])
    rows = dict(view.js(ROW_TEXTS, "#panel-attributes tr"))
    assert rows["trees · n_trees"] == str(int(cell["n_trees"]))
    assert rows["returns · n_points"] == f"{int(cell['n_points']):,}"
    for label, text in rows.items():
        column = label.rsplit(" · ", 1)[-1]
        if column.startswith("n_") or column.endswith("count"):
            assert text.replace(",", "").isdigit(), (label, text)
    assert rows["max height (m) · zmax"] == f"{cell['zmax']:.1f}"
    view.shot("cell-panel-counts")
    assert view.errors == [] and view.failed == []
