"""The web viewer at ``/``: the built bundle (``serve/static``, made from ``web/`` by vite),
its start-up description of the catalog (``/viewer/config.json``) and the points of a cell
(``/viewer/points/{epoch}/{cell_id}``) or of a payload (``/viewer/points?payload=<id>``) for
the 3-D view.

A browser asking for ``/`` (``Accept: text/html``) gets the viewer; any other client gets
the service's JSON description (``app.py``). Every script and style comes from the package.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, JSONResponse, Response

from standgrid.catalog import Catalog, paths
from standgrid.serve.files import published_files
from standgrid.serve.problems import Problem
from standgrid.serve.snapshot import snapshot

#: The built viewer (vite's output; see web/ and tests/test_viewer_bundle.py).
STATIC = Path(__file__).with_name("static")
#: The build's record of its sources and outputs (hashes), checked by the tests.
BUILD_MANIFEST = "build-manifest.json"
#: Media type of a cell's points (layout in :func:`cell_points`).
POINTS_MEDIA_TYPE = "application/vnd.standgrid.points"
#: Per-point arrays of the points answer, in order: name, numpy dtype.
POINT_ARRAYS = (
    ("xyz", "<f4"),
    ("height_above_ground", "<f4"),
    ("tree_key", "<u4"),
    ("classification", "u1"),
)
#: At most this many points in one points answer: beyond it every k-th point is sent
#: (evenly strided; ``meta.capped``), so a dense cell or payload stays drawable.
MAX_VIEW_POINTS = 500_000
#: Height range of the CHM colour ramp: a raster's percentile (as its QGIS style).
CHM_PERCENTILE = 98.0

router = APIRouter(tags=["Viewer"])


def viewer_page() -> FileResponse:
    """The viewer's HTML page (a 404 problem when the package was built without it)."""
    page = STATIC / "index.html"
    if not page.is_file():
        raise Problem(404, f"the web viewer is not built into this package ({page} missing)")
    return FileResponse(page, media_type="text/html")


def _raster_max(path: Path) -> float | None:
    """A raster's colour ramp top: its ``CHM_PERCENTILE`` of |value| over valid pixels (read
    decimated to at most 1024 x 1024), or None without valid pixels (CHM: heights; CHM
    difference: the half-width of its ramp centred on 0, as its QGIS style)."""
    import rasterio

    with rasterio.open(path) as src:
        scale = max(1, int(np.ceil(max(src.width, src.height) / 1024)))
        shape = (max(1, src.height // scale), max(1, src.width // scale))
        band = src.read(1, out_shape=shape, masked=True)
    valid = band.compressed()
    valid = valid[np.isfinite(valid)]
    return float(np.percentile(np.abs(valid), CHM_PERCENTILE)) if valid.size else None


def tile_format(tiles: Iterable[str]) -> str:
    """``copc``, ``laz`` or ``las`` when every tile is of that format, ``mixed`` for several,
    ``none`` without tiles."""
    kinds = {"copc" if t.endswith(".copc.laz") else Path(t).suffix.lstrip(".") for t in tiles}
    return kinds.pop() if len(kinds) == 1 else "mixed" if kinds else "none"


def viewer_config(catalog: Catalog, layers: set[str]) -> dict[str, Any]:
    """What the viewer needs to start: the CRS (EPSG code and WKT2, which proj4js reads to
    draw in it), the epochs (each with its tiles' format), the comparisons, the served CHMs
    (and CHM differences) with their colour ramp tops, which layers exist, the tiles' format
    (``tiles``: with ``copc`` the page streams a cell's points from its tile itself) and the
    most points one 3-D view draws."""
    from standgrid.crs import CRS

    crs = CRS.of(catalog.crs)
    epsg = crs.epsg
    published = published_files(catalog)
    epochs = []
    for label, record in catalog.epoch_records.items():
        chm = paths.raster(label, "chm")
        chm_path = catalog.path(chm)
        has_chm = chm in published and chm_path.is_file()
        epochs.append(
            {
                "label": label,
                "date": record.date,
                "state": record.state,
                "chm": f"files/{chm}" if has_chm else None,
                "chm_max": _raster_max(chm_path) if has_chm else None,
                "tiles": tile_format(catalog.tiles(label)),
            }
        )
    comparisons = []
    for key, entry in catalog.comparisons.items():
        if entry.get("other_catalog"):
            continue  # against another catalog: its layers are not in this index
        diff = str((entry.get("outputs") or {}).get("chm_difference") or "")
        has_diff = bool(diff) and diff in published and catalog.path(diff).is_file()
        comparisons.append(
            {
                "key": key,
                "from": entry["from"],
                "to": entry["to"],
                "chm_diff": f"files/{diff}" if has_diff else None,
                "chm_diff_max": _raster_max(catalog.path(diff)) if has_diff else None,
            }
        )
    return {
        "catalog": catalog.root.name,
        "crs": {
            "code": f"EPSG:{epsg}" if epsg else None,
            "uri": f"http://www.opengis.net/def/crs/EPSG/0/{epsg}" if epsg else None,
            "wkt": crs.wkt2,
        },
        "epochs": epochs,
        "comparisons": comparisons,
        "layers": sorted(layers),
        "tiles": tile_format(t for label in catalog.epochs for t in catalog.tiles(label)),
        "max_view_points": MAX_VIEW_POINTS,
    }


@router.get("/viewer/config.json", summary="What the web viewer needs to start")
def config(request: Request) -> JSONResponse:
    with snapshot(request.app.state.catalog_root) as snap:
        return JSONResponse(viewer_config(snap.catalog, set(snap.layers)))


def tree_key(tree_id: Any) -> Any:
    """A tree id folded to 32 bits for the browser, both halves mixed (the low half alone is
    only the top's y: trees on one 0.1 m row would share it); 0 only for no tree."""
    ids = np.asarray(tree_id, dtype=np.int64).astype(np.uint64)
    hi, lo = ids >> np.uint64(32), ids & np.uint64(0xFFFFFFFF)
    key = ((hi * np.uint64(0x9E3779B1)) ^ lo) & np.uint64(0xFFFFFFFF)
    key = np.where((key == 0) & (ids != 0), np.uint64(1), key)
    return np.where(ids == 0, np.uint64(0), key).astype(np.uint32)


def encode_points(
    xyz: np.ndarray,
    height: np.ndarray,
    tree_id: np.ndarray,
    classification: np.ndarray,
    meta: dict[str, Any],
    limit: int = MAX_VIEW_POINTS,
) -> bytes:
    """Points as one binary answer: a little-endian uint32 byte length, a JSON header
    (``count`` sent, ``origin`` [x, y, z], ``arrays`` [[name, dtype], ...] and ``meta``)
    padded with spaces to a multiple of 4 bytes, then each array of ``POINT_ARRAYS`` in
    turn: xyz float32 relative to ``origin`` (mm-exact within a few tens of metres), height
    above ground float32 (NaN before enrichment), the tree id folded to uint32 (a colour
    key; 0 = no tree) and the LAS classification. Beyond ``limit`` points, every k-th is
    sent (``meta``: ``total`` points, ``capped`` true, ``stride`` k as a float)."""
    total = len(xyz)
    meta = {**meta, "total": total, "capped": total > limit}
    if total > limit:
        # ``limit`` distinct indices spread evenly over the points, in their order
        keep = np.linspace(0, total, limit, endpoint=False).astype(np.int64)
        xyz, height, tree_id, classification = (
            a[keep] for a in (xyz, height, tree_id, classification)
        )
        meta["stride"] = total / limit
    count = len(xyz)
    origin = xyz.min(axis=0) if count else np.zeros(3)
    header = json.dumps(
        {
            "count": count,
            "origin": [float(v) for v in origin],
            "arrays": [list(a) for a in POINT_ARRAYS],
            "meta": meta,
        }
    )
    head = header.encode()
    head += b" " * (-(4 + len(head)) % 4)
    keys = tree_key(tree_id).astype("<u4")
    body = [
        (xyz - origin).astype("<f4"),
        height.astype("<f4"),
        keys,
        classification.astype("u1"),
    ]
    return (
        np.uint32(len(head)).astype("<u4").tobytes()
        + head
        + b"".join(np.ascontiguousarray(a).tobytes() for a in body)
    )


#: A feature id (``fid``) or payload id: SQLite's 64-bit integers, not negative.
FeatureId = Annotated[int, Query(ge=0, le=2**63 - 1)]
#: How many points one answer may hold (a request may ask for fewer).
Limit = Annotated[
    int,
    Query(
        ge=1,
        le=MAX_VIEW_POINTS,
        description="at most this many points are sent (every k-th beyond it)",
    ),
]


def _read_tile(path: Path, relative: str) -> Any:
    import laspy

    try:
        return laspy.read(path)
    except (OSError, laspy.errors.LaspyException) as exc:
        raise Problem(500, f"{relative}: cannot read the tile: {exc}") from exc


def _fields(las: Any, keep: np.ndarray) -> tuple[np.ndarray, ...]:
    """xyz (float64), height above ground (NaN without), tree id (0 without) and
    classification of the points ``keep`` (a mask) of a tile."""
    names = set(las.point_format.dimension_names)
    count = int(keep.sum())

    def field(name: str, fill: float) -> np.ndarray:
        return np.asarray(las[name])[keep] if name in names else np.full(count, fill)

    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])[keep]
    return (
        xyz,
        field("height_above_ground", np.nan).astype(np.float64),
        field("tree_id", 0).astype(np.int64),
        np.asarray(las.classification)[keep],
    )


@router.get(
    "/viewer/points/{epoch}/{cell_id}",
    summary="A cell's points for the 3-D view (compact binary; buffer points left out)",
    responses={200: {"content": {POINTS_MEDIA_TYPE: {}}}},
)
def cell_points(
    request: Request,
    epoch: str,
    cell_id: str,
    tree: Annotated[int | None, Query(ge=0, le=2**63 - 1)] = None,
    limit: Limit = MAX_VIEW_POINTS,
) -> Response:
    """``tree``: the fid of a tree (``trees`` layer) whose points the answer marks
    (``meta.tree``: its id as text, its colour key and its point count in the cell)."""
    with snapshot(request.app.state.catalog_root, with_index=tree is not None) as snap:
        chosen = _tree(snap, tree) if tree is not None else None
        if epoch not in snap.catalog.epochs:
            raise Problem(404, f"no epoch {epoch!r}; epochs: {sorted(snap.catalog.epochs)}")
        tiles = set(snap.catalog.tiles(epoch))
        candidates = (
            paths.tile(epoch, cell_id, laz=laz, copc=copc)
            for laz, copc in ((True, True), (True, False), (False, False))
        )
        relative = next((t for t in candidates if t in tiles), None)
        if relative is None:
            raise Problem(404, f"epoch {epoch!r} has no tile of cell {cell_id!r}")
        las = _read_tile(snap.catalog.path(relative), relative)
    core = ~np.asarray(las.withheld, dtype=bool)
    xyz, height, tree_ids, classification = _fields(las, core)
    meta: dict[str, Any] = {
        "tile": f"files/{relative}",
        "tile_points": int(las.header.point_count),
        "buffer_points": int(las.header.point_count) - len(xyz),
    }
    if chosen is not None:
        key = int(tree_key(np.array([chosen]))[0])
        meta["tree"] = {
            "fid": tree,
            "tree_id": str(chosen),
            "key": key,
            "points": int((tree_ids == chosen).sum()),
        }
    body = encode_points(xyz, height, tree_ids, classification, meta, limit)
    return Response(body, media_type=POINTS_MEDIA_TYPE, headers={"Cache-Control": "no-cache"})


@router.get(
    "/viewer/points",
    summary="A payload's points for the 3-D view, read from the catalog's tiles",
    responses={200: {"content": {POINTS_MEDIA_TYPE: {}}}},
)
def payload_points(
    request: Request, payload: FeatureId, limit: Limit = MAX_VIEW_POINTS
) -> Response:
    """The core points whose ``payload_id`` is ``payload``, gathered from the tiles of the
    payload's epoch that hold its mission: those under its footprint first, then the
    others by distance, until the ``point_count`` of its ``payloads`` row is found (each
    point is the core point of exactly one tile). ``meta.payload`` names the tiles read and
    whether the count was met (``complete``); the answer never silently falls short."""
    import shapely

    from standgrid.serve.provider import Query

    with snapshot(request.app.state.catalog_root) as snap:
        if snap.provider is None:
            raise Problem(404, "the catalog has no index yet")
        found = snap.provider.items(
            snap.layer("payloads"), Query(equals={"payload_id": str(payload)}, limit=2)
        )
        if not found.fids:
            raise Problem(404, f"no payload {payload} in the payloads collection")
        row, footprint = found.properties[0], found.geometries[0]
        if footprint is None:
            footprint = shapely.Point(row["x"], row["y"])
        epoch, mission, expected = str(row["epoch"]), str(row["mission"]), int(row["point_count"])
        tiles = set(snap.catalog.tiles(epoch)) if epoch in snap.catalog.epochs else set()
        cells = snap.provider.items(
            snap.layer("cells"), Query(equals={"epoch": epoch}, limit=1 << 30)
        )
        held = [
            k
            for k, p in enumerate(cells.properties)
            if p["tile_path"] in tiles and mission in str(p.get("missions") or "").split(",")
        ]
        distance = shapely.distance(cells.geometries[held], footprint) if held else []
        order = sorted(
            zip(distance, (str(cells.properties[k]["tile_path"]) for k in held), strict=True)
        )
        parts: list[tuple[np.ndarray, ...]] = []
        read: list[str] = []
        count = 0
        for _, relative in order:
            if count >= expected:
                break
            las = _read_tile(snap.catalog.path(relative), relative)
            if "payload_id" not in set(las.point_format.dimension_names):
                raise Problem(
                    409,
                    f"{relative}: the tile has no payload_id dimension, so a "
                    "payload's points cannot be told apart",
                )
            mine = ~np.asarray(las.withheld, dtype=bool) & (
                np.asarray(las["payload_id"]) == payload
            )
            read.append(relative)
            if mine.any():
                parts.append(_fields(las, mine))
                count += int(mine.sum())
    meta = {
        "payload": {
            "payload_id": payload,
            "mission": mission,
            "epoch": epoch,
            "point_count": expected,
            "found": count,
            "complete": count == expected,
            "tiles": [f"files/{t}" for t in read],
            "tiles_with_points": len(parts),
        }
    }
    none = (np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.uint8))
    xyz, height, tree_ids, classification = (
        np.concatenate(a) for a in zip(*(parts or [none]), strict=True)
    )
    body = encode_points(xyz, height, tree_ids, classification, meta, limit)
    return Response(body, media_type=POINTS_MEDIA_TYPE, headers={"Cache-Control": "no-cache"})


def _tree(snap: Any, fid: int) -> int:
    """The tree id of the ``trees`` feature ``fid`` (a 404 problem when there is none)."""
    page = snap.provider.get(snap.layer("trees"), fid) if snap.provider else None
    if page is None or not page.fids:
        raise Problem(404, f"no tree {fid} in the trees collection")
    return int(page.properties[0]["tree_id"])


def install(app: Any, description: dict[str, Any]) -> None:
    """The viewer's routes and static assets (``/viewer/...``) on ``app``, and ``/``: the
    viewer for a browser (``Accept: text/html``), else ``description`` (JSON)."""
    import mimetypes

    from starlette.staticfiles import StaticFiles

    # laz-perf's WebAssembly: compiled while it streams only when sent as application/wasm
    mimetypes.add_type("application/wasm", ".wasm")

    @app.get(
        "/",
        tags=["Service"],
        summary="The web viewer (Accept: text/html), else what this service offers",
    )
    def index(request: Request) -> Response:
        if "text/html" in request.headers.get("accept", ""):
            return viewer_page()
        return JSONResponse(description)

    app.include_router(router)
    if (STATIC / "assets").is_dir():
        app.mount("/viewer/assets", StaticFiles(directory=STATIC / "assets"), name="viewer")
