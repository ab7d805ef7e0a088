"""Online ingest: robots create a mission, then send payloads, pose-graph updates and GNSS
fixes as they produce them, and ask for the mission to be tiled into the catalog.

Every route here is a write: the write guard (:mod:`standgrid.serve.auth`) has already
checked the bearer token. Files go into a canonical mission folder under the server's
missions folder through :class:`~standgrid.mission.live.LiveMission` (atomic, locked,
idempotent); tiling is :func:`~standgrid.pipeline.tile.tile_missions`, one catalog
transaction under the catalog's writer lock. Both run in worker processes
(:mod:`standgrid.serve.workers`), not in the server's threads. A mission name from the
request becomes a folder name only after :func:`check_name`.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from standgrid.serve.events import EventHub
from standgrid.serve.live import tile_with_cells
from standgrid.serve.problems import Problem
from standgrid.serve.snapshot import snapshot
from standgrid.serve.workers import WorkerProcess, live_mission

router = APIRouter(prefix="/missions", tags=["Ingest (bearer token)"])
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_STAMP = re.compile(r"^(\d{1,12})_(\d{9})$")
_BINARY = {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}
_TEXT = {"text/plain": {"schema": {"type": "string"}}}
#: Bounds of a mission's announcement: list items, characters of a name or tag, of notes.
MAX_ITEMS = 64
MAX_LABEL = 128
MAX_NOTES = 16_384
Label = Annotated[str, Field(max_length=MAX_LABEL)]


def _body(content: dict[str, Any], description: str) -> dict[str, Any]:
    return {
        "requestBody": {"required": True, "description": description, "content": content},
        "security": [{"bearer": []}],
    }


class GnssOrigin(BaseModel):
    latitude: float = Field(ge=-90, le=90)
    longitude: float = Field(ge=-180, le=180)
    altitude: float = Field(0.0, ge=-12_000, le=100_000)


class NewMission(BaseModel):
    """A mission as a robot announces it (the fields of ``metadata.yaml``); lists of at most
    ``MAX_ITEMS`` texts of at most ``MAX_LABEL`` characters."""

    name: str = Field(
        max_length=MAX_LABEL, description="folder name, e.g. 2024-05-14-wytham-anymal-coyote"
    )
    date: dt.date
    time: dt.time | None = None
    place: Label | None = None
    robot: Label | None = None
    unit: Label | None = None
    sensors: list[Label] = Field(default_factory=list, max_length=MAX_ITEMS)
    tags: list[Label] = Field(default_factory=list, max_length=MAX_ITEMS)
    notes: str = Field("", max_length=MAX_NOTES)
    gnss: GnssOrigin | None = None


def check_name(name: str) -> str:
    """A mission name that is safe as one folder name (letters, digits, ``.``, ``_``, ``-``;
    no leading dot), else a 400 problem."""
    if not _NAME.match(name) or ".." in name:
        raise Problem(
            400,
            f"mission name {name!r}: use letters, digits, '.', '_', '-' "
            "(at most 128, not starting with '.' or '-')",
        )
    return name


def _live(request: Request, name: str) -> Any:
    from standgrid.mission.live import LiveMission

    root: Path = request.app.state.missions_root
    return LiveMission(root / check_name(name))


@contextlib.asynccontextmanager
async def _turn(request: Request, live: Any) -> AsyncIterator[None]:
    """The mission's turn in this server: its writes and its tiling, one at a time. A write
    waits here, not in the writer process, while its mission tiles (the tiling holds the
    folder), so the writes of other missions pass. A turn nobody holds or waits for is
    dropped (names from the outside do not pile up)."""
    turns: dict[str, list[Any]] = request.app.state.mission_turns
    name = live.path.name
    turn = turns.setdefault(name, [asyncio.Lock(), 0])
    turn[1] += 1
    try:
        async with turn[0]:
            yield
    finally:
        turn[1] -= 1
        if turn[1] == 0:
            del turns[name]


async def _write(
    request: Request, live: Any, method: str, *args: Any, announce: tuple[int, int] | bool = False
) -> Any:
    """``live.<method>(*args)`` in the mission folders' worker process, in the mission's turn.
    Once it stored something (outcome ``created`` or ``stored``), ``announce`` publishes the
    mission's trajectory (True) and the payload of that stamp (a stamp), still in the turn:
    a mission's events come in the order its writes were stored."""
    writer: WorkerProcess = request.app.state.mission_writer
    async with _turn(request, live):
        result = await writer.call(live_mission, str(live.path.absolute()), method, *args)
        outcome = result[0] if isinstance(result, tuple) else result
        if announce is not False and outcome in ("created", "stored"):
            await _announce(request, live, None if announce is True else announce)
        return result


async def _announce(request: Request, live: Any, stamp: tuple[int, int] | None) -> None:
    """Publish the ``payload`` event of ``stamp`` (when given) and the ``trajectory`` event
    of the mission, described in a writer worker (:func:`~standgrid.serve.live.describe`).
    Described it cannot be (its worker failed): the payload is announced unplaced, without
    geometry, and the trajectory not at all. Call it in the mission's turn, once stored."""
    from standgrid.serve.live import describe

    hub: EventHub = request.app.state.events
    writer: WorkerProcess = request.app.state.mission_writer
    root = str(request.app.state.catalog_root)
    try:
        told = await writer.call(describe, str(live.path.absolute()), root, stamp)
    except Problem as exc:
        if stamp is not None:
            hub.publish(
                "payload",
                {
                    "mission": live.path.name,
                    "payload": f"{stamp[0]}_{stamp[1]:09d}",
                    "placed": False,
                    "reason": f"not described: {exc.detail}",
                },
            )
        return
    if told["payload"] is not None:
        hub.publish("payload", told["payload"])
    hub.publish_changed("trajectory", live.path.name, told["trajectory"])


def _answer(outcome: str, status_created: int = 201, **extra: Any) -> JSONResponse:
    return JSONResponse(
        {"outcome": outcome, **extra}, status_code=200 if outcome == "unchanged" else status_created
    )


@router.post(
    "",
    summary="Create a mission (idempotent: the same metadata again is 200, other metadata 409)",
    status_code=201,
    openapi_extra={"security": [{"bearer": []}]},
)
async def create(request: Request, mission: NewMission) -> JSONResponse:
    from standgrid.mission.metadata import MissionMetadata

    live = _live(request, mission.name)
    _check_catalog_folder(request, live)
    metadata = MissionMetadata(
        name=mission.name,
        date=mission.date,
        place=mission.place,
        robot=mission.robot,
        unit=mission.unit,
        time=mission.time,
        sensors=list(mission.sensors),
        tags=list(mission.tags),
        notes=mission.notes,
        gnss=None
        if mission.gnss is None
        else (mission.gnss.latitude, mission.gnss.longitude, mission.gnss.altitude),
    )
    live.path.parent.mkdir(parents=True, exist_ok=True)
    outcome = await _write(request, live, "create", metadata)
    if outcome == "created":
        hub: EventHub = request.app.state.events
        hub.publish(
            "mission",
            {
                "mission": mission.name,
                "date": mission.date.isoformat(),
                "robot": mission.robot,
                "place": mission.place,
                "gnss": None if mission.gnss is None else mission.gnss.model_dump(),
            },
        )
    return _answer(outcome, name=mission.name)


def _pose(text: str | None) -> Any:
    if text is None:
        return None
    from standgrid.geometry import pose_matrix

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError as exc:
        raise Problem(400, f"pose: {text!r} is not 7 numbers x,y,z,qx,qy,qz,qw") from exc
    if len(values) != 7 or not all(abs(v) < float("inf") for v in values):
        raise Problem(400, f"pose: {text!r} is not 7 finite numbers x,y,z,qx,qy,qz,qw")
    if abs(sum(v * v for v in values[3:]) - 1.0) > 1e-6:
        raise Problem(400, "pose: the quaternion qx,qy,qz,qw is not of unit length")
    return pose_matrix(values[:3], values[3:])


@router.post(
    "/{name}/payloads",
    summary="Send one payload cloud in its node's base frame, with its stamp and node pose",
    status_code=201,
    openapi_extra=_body(_BINARY, "the cloud file: PCD, PLY, LAS or LAZ (see format)"),
)
async def payload(
    request: Request,
    name: str,
    stamp: Annotated[str, Query(description="<sec>_<nsec, 9 digits>")],
    format: Annotated[str, Query(description="pcd, ply, las or laz")] = "pcd",
    pose: Annotated[
        str | None,
        Query(
            description="node pose T_map_base: x,y,z,qx,qy,qz,qw "
            "(adds the node when the graph lacks it)"
        ),
    ] = None,
) -> JSONResponse:
    from standgrid.stamps import Stamp

    match = _STAMP.match(stamp)
    if match is None:
        raise Problem(400, f"stamp {stamp!r} is not <sec>_<nsec, 9 digits>")
    live = _live(request, name)
    data = await request.body()
    if not data:
        raise Problem(400, "empty body: send the cloud file")
    at = Stamp(int(match[1]), int(match[2]))
    outcome = await _write(
        request, live, "add_payload", at, data, format, _pose(pose), announce=(at.sec, at.nsec)
    )
    return _answer(outcome, stamp=stamp, bytes=len(data))


@router.put(
    "/{name}/graph",
    summary="Replace the mission's pose graph (g2o); payloads follow their nodes",
    openapi_extra=_body(_TEXT, "the pose graph, g2o text (VERTEX_SE3:QUAT_TIME ...)"),
)
async def graph(request: Request, name: str) -> JSONResponse:
    live = _live(request, name)
    outcome = await _write(request, live, "set_graph", await request.body(), announce=True)
    return _answer(outcome, status_created=200)


@router.post(
    "/{name}/gnss",
    summary="Send GNSS fixes (the canonical text log); fixes already stored are kept once",
    openapi_extra=_body(_TEXT, "# sec, nsec, latitude, longitude, altitude, quality, h_std, v_std"),
)
async def gnss(request: Request, name: str) -> JSONResponse:
    live = _live(request, name)
    outcome, new = await _write(request, live, "add_gnss", await request.body(), announce=True)
    return _answer(outcome, status_created=200, new_fixes=new)


@router.post(
    "/{name}/tile",
    summary="Tile the mission into the catalog (one transaction under the writer lock, in "
    "the server's tiling worker process; one mission at a time)",
    description="While the mission grows, its placement in the catalog is kept as long as "
    "a refit of its georeference moves none of its points by the server's placement "
    "tolerance (`--placement-tolerance`): the catalog is re-tiled in place, and the "
    "report's `missions.<name>.placement` says which placement was used and how far "
    "(`offset_m`) it may put a point from the fresh fit. `exact=true` settles on the fresh "
    "fit (send it at the end of a mission): the catalog then equals `standgrid tile` of the "
    "mission folder.",
    openapi_extra={"security": [{"bearer": []}]},
)
async def tile(
    request: Request,
    name: str,
    exact: Annotated[
        bool, Query(description="use the fresh georeference fit, whatever the placement tolerance")
    ] = False,
) -> JSONResponse:
    live = _live(request, name)
    if not (live.path / "metadata.yaml").is_file():
        raise Problem(404, f"no mission {name!r} was created on this server")
    root: Path = request.app.state.catalog_root
    _check_catalog_folder(request, live)
    tiler: WorkerProcess = request.app.state.tiler
    tolerance = None if exact else request.app.state.placement_tolerance
    folder = str(live.path.absolute())
    async with _turn(request, live):
        report, cells = await tiler.call(tile_with_cells, folder, str(root), tolerance)
        hub: EventHub = request.app.state.events
        tiled = report["missions"].get(name, {})
        hub.publish(
            "tiled",
            {
                "mission": name,
                "epoch": tiled.get("epoch"),
                "epochs": cells,
                "placement": tiled.get("placement"),
            },
        )
    return JSONResponse(_public(request, report))


def _check_catalog_folder(request: Request, live: Any) -> None:
    """A 409 problem when the catalog holds a mission of this name tiled from another folder
    than this server's mission folder (its tile would be refused)."""
    name = live.path.name
    with snapshot(request.app.state.catalog_root, with_index=False) as snap:
        record = snap.catalog.mission_records.get(name)
    if record is not None and record.path and Path(record.path) != live.path.absolute():
        raise Problem(
            409,
            f"the catalog holds a mission {name!r} tiled from another folder "
            "than this server's: choose another name",
        )


def _public(request: Request, report: Any) -> Any:
    """The tile report for the outside: the catalog as its name, a path in it as its URL
    under ``/files`` (catalog-relative), a mission folder as the mission's URL; no server
    path."""
    base = str(request.base_url).rstrip("/")
    roots = (
        (str(request.app.state.catalog_root), f"{base}/files"),
        (str(request.app.state.missions_root), f"{base}/missions"),
    )

    def clean(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, list):
            return [clean(v) for v in value]
        if isinstance(value, str):
            for root, url in roots:
                if value == root:
                    return Path(root).name
                if value.startswith(root + "/"):
                    return f"{url}/{value[len(root) + 1 :]}"
        return value

    return clean(report)
