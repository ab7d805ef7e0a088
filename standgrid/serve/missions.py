"""The retrieval API over HTTP: the catalog's missions, searched by site, date range, robot
and sensors; a mission's summary; its payloads by type, by SLAM pose and by GNSS position;
a payload's cloud as LAZ; a payload with its layers from the catalog (per-point ground
class, height above ground and tree id, its trees and terrain:
:mod:`standgrid.enrichment.payload_layers`), as LAZ or JSON.

The logic is the library's (:func:`~standgrid.mission.collection.metadata_matches`,
:func:`~standgrid.mission.retrieval.retrieve_payload_by_type` / ``_by_pose``,
:func:`~standgrid.georeference.retrieval.retrieve_payload_by_gnss`); this module parses
requests and shapes answers. A mission is found by its name in catalog.json, never by a path
from the request; its folder is the source path the catalog recorded.
"""

from __future__ import annotations

import datetime as dt
import re
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response

from standgrid.catalog import MissionRecord
from standgrid.serve.problems import Problem
from standgrid.serve.snapshot import snapshot

router = APIRouter(prefix="/missions", tags=["Retrieval"])
_STAMP = re.compile(r"^(\d{1,12})_(\d{9})$")
#: Missions kept open (their clouds cached) between requests.
_OPEN_MISSIONS = 4
_missions: OrderedDict[tuple[str, int], Any] = OrderedDict()
_missions_lock = threading.Lock()
#: A finite number (inf and nan are a 400).
Finite = Annotated[float, Query(allow_inf_nan=False)]


def _record(request: Request, name: str) -> MissionRecord:
    with snapshot(request.app.state.catalog_root, with_index=False) as snap:
        record = snap.catalog.mission_records.get(name)
        names = sorted(snap.catalog.mission_records)
    if record is None:
        raise Problem(404, f"no mission {name!r} in the catalog; missions: {names}")
    return record


def _opened(record: MissionRecord) -> Any:
    """The mission's folder, opened once and kept (keyed by path and folder mtime)."""
    from standgrid.mission.opening import open_mission

    if not record.path or not Path(record.path).is_dir():
        raise Problem(404, f"mission {record.name!r}: its folder is not available to this server")
    folder = Path(record.path)
    key = (str(folder), folder.stat().st_mtime_ns)
    with _missions_lock:
        mission = _missions.get(key)
        if mission is not None:
            _missions.move_to_end(key)
            return mission
    mission = open_mission(folder, strict=False)
    with _missions_lock:
        _missions[key] = mission
        while len(_missions) > _OPEN_MISSIONS:
            _missions.popitem(last=False)
    return mission


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _summary(request: Request, record: MissionRecord) -> dict[str, Any]:
    base = _base(request)
    fit = record.georeference or {}
    fit_summary = {k: fit[k] for k in ("method", "rmse_m", "n_used", "n_rejected") if k in fit}
    return {
        "name": record.name,
        "number": record.number,
        "epoch": record.epoch,
        "date": record.date,
        "site": record.place or None,
        "robot": record.robot or None,
        "unit": record.unit or None,
        "sensors": list(record.sensors),
        "payload_count": record.payload_count,
        "point_count": record.point_count,
        "ingested": record.ingested,
        "georeference": fit_summary or None,
        "placement": record.extra.get("placement"),
        "tiles": [f"{base}/files/{t}" for t in record.tiles],
        "links": [
            {"rel": "self", "href": f"{base}/missions/{record.name}"},
            {"rel": "payloads", "href": f"{base}/missions/{record.name}/payloads"},
        ],
    }


def _payloads(request: Request, record: MissionRecord, rows: list[dict[str, Any]]) -> JSONResponse:
    """Payload records for the outside: server paths replaced by URLs."""
    base = f"{_base(request)}/missions/{record.name}/payloads"
    out = []
    for row in rows:
        row = {k: v for k, v in row.items() if k not in ("path", "layers")}
        sec, nsec = divmod(int(row["stamp_ns"]), 1_000_000_000)
        if row["kind"] == "point_cloud":
            row["cloud"] = f"{base}/{sec}_{nsec:09d}/cloud.laz"
        out.append(row)
    return JSONResponse({"mission": record.name, "payloads": out, "count": len(out)})


def _date(text: str | None, name: str) -> dt.date | None:
    if text is None:
        return None
    try:
        return dt.date.fromisoformat(text[:10])
    except ValueError as exc:
        raise Problem(400, f"{name}: {text!r} is not a date (YYYY-MM-DD)") from exc


@router.get("", summary="Missions of the catalog, searched by site, date range, robot, sensors")
def search(
    request: Request,
    site: str | None = None,
    date_from: Annotated[str | None, Query(alias="from")] = None,
    date_to: Annotated[str | None, Query(alias="to")] = None,
    robot: str | None = None,
    sensor: Annotated[list[str] | None, Query(description="repeat for several")] = None,
) -> JSONResponse:
    from standgrid.mission.collection import metadata_matches

    start, end = _date(date_from, "from"), _date(date_to, "to")
    with snapshot(request.app.state.catalog_root, with_index=False) as snap:
        records = list(snap.catalog.mission_records.values())
    found = [
        _summary(request, r)
        for r in sorted(records, key=lambda r: (r.date, r.name))
        if metadata_matches(
            r.place,
            r.robot,
            r.date or None,
            r.sensors,
            site=site,
            date_from=start,
            date_to=end,
            robot=robot,
            sensors=sensor,
        )
    ]
    return JSONResponse({"missions": found, "count": len(found)})


@router.get("/{name}", summary="A mission's summary")
def summary(request: Request, name: str) -> JSONResponse:
    return JSONResponse(_summary(request, _record(request, name)))


@router.get("/{name}/payloads", summary="A mission's payloads of one type")
def by_type(
    request: Request,
    name: str,
    type: Annotated[str, Query(description="point_cloud, scan, gnss, imu, image")] = "point_cloud",
) -> JSONResponse:
    from standgrid.mission.retrieval import DATA_TYPES, payload_records, retrieve_payload_by_type

    if type.lower().replace("-", "_") not in DATA_TYPES:
        raise Problem(
            400, f"type: unknown data type {type[:64]!r}; known: {', '.join(sorted(DATA_TYPES))}"
        )
    record = _record(request, name)
    found = retrieve_payload_by_type(_opened(record), type)
    return _payloads(request, record, payload_records(found))


@router.get("/{name}/payloads/by-pose", summary="Payloads nearest a map-frame point")
def by_pose(
    request: Request,
    name: str,
    x: Finite,
    y: Finite,
    z: Annotated[float | None, Query(allow_inf_nan=False)] = None,
    k: Annotated[int, Query(ge=1, le=10_000)] = 1,
    radius: Annotated[float | None, Query(gt=0, allow_inf_nan=False)] = None,
    covering: bool = False,
) -> JSONResponse:
    from standgrid.mission.retrieval import payload_records, retrieve_payload_by_pose

    record = _record(request, name)
    mission = _opened(record)
    query = (x, y) if z is None else (x, y, z)
    found = retrieve_payload_by_pose(mission, query, k=k, radius=radius, covering=covering)
    return _payloads(request, record, payload_records(found, query, mission))


@router.get("/{name}/payloads/by-gnss", summary="Payloads nearest a WGS 84 coordinate")
def by_gnss(
    request: Request,
    name: str,
    lat: Annotated[float, Query(ge=-90, le=90, allow_inf_nan=False)],
    lon: Annotated[float, Query(ge=-180, le=180, allow_inf_nan=False)],
    alt: Annotated[float | None, Query(ge=-12_000, le=100_000, allow_inf_nan=False)] = None,
    k: Annotated[int, Query(ge=1, le=10_000)] = 1,
    max_distance: Annotated[
        float,
        Query(
            gt=0,
            allow_inf_nan=False,
            description="metres: a 404 when the nearest payload is farther",
        ),
    ] = 1000.0,
) -> JSONResponse:
    from standgrid.georeference.retrieval import locate_by_gnss
    from standgrid.mission.retrieval import payload_records

    record = _record(request, name)
    coord = (lat, lon) if alt is None else (lat, lon, alt)
    mission = _opened(record)
    found = locate_by_gnss(mission, coord, k=k, max_distance=max_distance)
    return _payloads(request, record, payload_records(found.payloads, found.query_map, mission))


@router.get(
    "/{name}/payloads/{stamp}/cloud.laz",
    summary="A payload's cloud as LAZ: in the catalog CRS (default), the map frame or its "
    "node's base frame",
    response_class=Response,
    responses={200: {"content": {"application/vnd.laszip": {}}}},
)
def cloud(
    request: Request, name: str, stamp: str, frame: Literal["crs", "map", "base"] = "crs"
) -> Response:
    """``crs``: georeferenced (the mission's fit, exact pyproj chain) as a tile is, with the
    CRS in the header; ``map`` / ``base``: SLAM frames, no CRS. A non-LAS intensity (float
    reflectivity) is kept exactly, in the ``intensity_raw`` extra dimension."""
    match = _STAMP.match(stamp)
    if match is None:
        raise Problem(400, f"stamp {stamp!r} is not <sec>_<nsec, 9 digits>")
    record = _record(request, name)
    mission = _opened(record)
    wanted = int(match[1]) * 1_000_000_000 + int(match[2])
    payload = next((p for p in mission.payloads if p.stamp.ns == wanted), None)
    if payload is None:
        raise Problem(404, f"mission {name!r} has no payload cloud stamped {stamp}")
    points = mission.load_payload(payload, frame="base" if frame == "base" else "map")
    with tempfile.TemporaryDirectory(prefix="standgrid-serve-") as folder:
        path = Path(folder) / f"cloud_{stamp}.laz"
        if frame == "crs":
            _write_georeferenced(request, record, points, path)
        else:
            _write_local(points, path)
        data = path.read_bytes()
    return Response(
        data,
        media_type="application/vnd.laszip",
        headers={"Content-Disposition": f'inline; filename="{record.name}_{stamp}.laz"'},
    )


def _write_georeferenced(request: Request, record: MissionRecord, points: Any, path: Path) -> None:
    from standgrid.export.las import write_tile
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.project import MapProjector

    if not record.georeference:
        raise Problem(
            409,
            f"mission {record.name!r} has no georeference fit in the catalog "
            "(its clouds were tiled as they came): ask for frame=map or base",
        )
    with snapshot(request.app.state.catalog_root, with_index=False) as snap:
        crs = snap.catalog.crs
    projector = MapProjector(GeoreferenceFit.from_dict(record.georeference), crs)
    fields = {k: v for k, v in points.fields.items() if k != "withheld"}
    write_tile(path, type(points)(projector.exact(points.xyz), fields), crs=crs, laz=True)


def _write_local(points: Any, path: Path) -> None:
    import numpy as np

    from standgrid.clouds import write_cloud

    fields = dict(points.fields)
    intensity = fields.get("intensity")
    if intensity is not None and not (
        np.issubdtype(intensity.dtype, np.unsignedinteger) and intensity.dtype.itemsize <= 2
    ):
        fields["intensity_raw"] = fields.pop("intensity")
    write_cloud(type(points)(points.xyz, fields), path)


@router.get(
    "/{name}/payloads/{payload}",
    summary="A payload cloud's record, or with ?layers= the payload with its layers from the "
    "catalog (LAZ with the per-point layers, or JSON with its trees and terrain)",
    response_class=Response,
    responses={200: {"content": {"application/vnd.laszip": {}, "application/json": {}}}},
)
def payload(
    request: Request,
    name: str,
    payload: str,
    layers: Annotated[
        str | None,
        Query(description="comma separated: ground, height, trees, terrain (or all)"),
    ] = None,
    format: Literal["laz", "json"] = "laz",
    frame: Literal["crs", "payload"] = "crs",
    points: Annotated[bool, Query(description="JSON: every point's xyz and layers too")] = False,
) -> Response:
    """``payload``: its stamp ``<sec>_<nsec>`` or its ``payload_id`` in the catalog. Without
    ``layers``: the payload's record. With ``layers``: the layers exactly as the catalog's
    tiles hold them for its points (read at each request: a re-tiled or re-enriched epoch is
    never served stale): LAZ (``frame`` crs: coordinates as the tiles store them; payload:
    the payload frame) with ``classification``, ``height_above_ground``, ``tree_id``; or
    JSON (``format=json``): counts, the tree list and the terrain window. An unknown layer
    is a 400, an epoch not enriched or re-tiled since a 409."""
    from standgrid.enrichment.payload_layers import layers_of, parse_layers, write_layered_cloud
    from standgrid.mission.retrieval import payload_records

    wanted = None if layers is None else parse_layers(layers)  # 400 before any work
    record = _record(request, name)
    mission = _opened(record)
    found = _payload(mission, record, payload)
    if wanted is None:
        return _payloads(request, record, payload_records([found]))
    (layered,) = layers_of(request.app.state.catalog_root, mission, [found], wanted)
    headers = {"Cache-Control": "no-cache", "X-Standgrid-Enrichment": str(layered.enrichment_id)}
    if format == "json":
        return JSONResponse(layered.to_dict(points=points), headers=headers)
    stamp = f"{found.stamp.sec}_{found.stamp.nsec:09d}"
    with tempfile.TemporaryDirectory(prefix="standgrid-serve-") as folder:
        path = write_layered_cloud(layered, Path(folder) / "layers.laz", frame=frame)
        data = path.read_bytes()
    headers["Content-Disposition"] = f'inline; filename="{record.name}_{stamp}_layers.laz"'
    return Response(data, media_type="application/vnd.laszip", headers=headers)


def _payload(mission: Any, record: MissionRecord, ident: str) -> Any:
    """The mission's payload cloud of a stamp ``<sec>_<nsec>`` or a catalog ``payload_id``."""
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.tiling.mission_rows import PAYLOAD_INDEX_BITS

    clouds = cloud_payloads(mission)
    match = _STAMP.match(ident)
    if match is not None:
        wanted = int(match[1]) * 1_000_000_000 + int(match[2])
        found = next((p for p in clouds if p.stamp.ns == wanted), None)
    elif ident.isdigit() and len(ident) <= 12:
        number, index = divmod(int(ident), 1 << PAYLOAD_INDEX_BITS)
        found = clouds[index] if number == record.number and index < len(clouds) else None
    else:
        raise Problem(400, f"payload {ident[:40]!r} is not <sec>_<nsec, 9 digits> or a payload_id")
    if found is None:
        raise Problem(404, f"mission {record.name!r} has no payload cloud {ident}")
    return found
