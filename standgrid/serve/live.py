"""What the live view is told about a streamed mission (:mod:`standgrid.serve.events`),
worked out in a writer worker process once a write is stored: a payload's position and
footprint, the mission's trajectory, and the cells a tiling wrote.

A mission is placed as the catalog holds it (the georeference the catalog recorded at its
last tiling), else as ``tile`` would place it now (a fit of its GNSS fixes, quality
checked): positions and footprints then come in the catalog CRS and in WGS 84 (GeoJSON,
longitude and latitude). A mission that cannot be placed yet (too few fixes, no graph
node for the payload) is described in its map frame and flagged ``placed: false`` with the
reason. A footprint is the convex hull of the payload's points, as the ``payloads`` layer
draws it once tiled.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import StandgridError

if TYPE_CHECKING:
    from standgrid.catalog import Catalog
    from standgrid.georeference.placement import ToCatalog
    from standgrid.mission.model import Mission

#: Decimals of coordinates sent: 1 mm in a projected CRS, ~1 cm in degrees (7).
PROJECTED_DECIMALS = 3
DEGREE_DECIMALS = 8


def describe(
    folder: str, catalog_root: str, stamp: tuple[int, int] | None = None
) -> dict[str, Any]:
    """In the worker: the ``trajectory`` event of the mission in ``folder`` and, given a
    ``stamp``, the ``payload`` event of its payload of that stamp (``payload``: None)."""
    from standgrid.catalog import Catalog
    from standgrid.mission.opening import open_mission

    mission = open_mission(folder, strict=False, cache_points=0)
    catalog = Catalog.open(catalog_root)
    to_catalog, reason = _placement(mission, catalog)
    out: dict[str, Any] = {"trajectory": _trajectory(mission, to_catalog, reason, catalog)}
    out["payload"] = (
        None if stamp is None else _payload(mission, stamp, to_catalog, reason, catalog)
    )
    return out


def _placement(mission: Mission, catalog: Catalog) -> tuple[ToCatalog | None, str | None]:
    """The mission's recipe into the catalog CRS and None, or None and why there is none."""
    from standgrid.georeference.placement import held_placement, place_mission

    try:
        record = catalog.mission_records.get(mission.name)
        held = dict(record.georeference or {}) if record is not None else {}
        if "T_enu_map" in held and "lla_ref" in held:
            placement = held_placement(mission, held)
        else:
            placement = place_mission(mission, crs=catalog.crs)
        if placement.fit is None:
            return None, "the clouds are in a projected CRS, not a mission frame"
        return placement.to_catalog(catalog.crs, mission.name), None
    except StandgridError as exc:
        return None, exc.message


def _round(values: NDArray[np.float64], decimals: int) -> list[Any]:
    rounded: list[Any] = np.round(np.asarray(values, dtype=np.float64), decimals).tolist()
    return rounded


def _geojson(geometry: Any, decimals: int) -> dict[str, Any]:
    import shapely

    mapping: dict[str, Any] = shapely.geometry.mapping(
        shapely.set_precision(geometry, 10.0**-decimals)
    )
    return {"type": mapping["type"], "coordinates": _listed(mapping["coordinates"])}


def _listed(value: Any) -> Any:
    return [_listed(v) for v in value] if isinstance(value, (list, tuple)) else value


def _wgs84(geometry: Any, catalog: Catalog) -> dict[str, Any]:
    import shapely

    from standgrid.crs import CRS

    to_lonlat = CRS.of(catalog.crs).transformer_to("EPSG:4326")
    moved = shapely.transform(
        geometry, lambda xy: np.column_stack(to_lonlat.transform(xy[:, 0], xy[:, 1], errcheck=True))
    )
    return _geojson(moved, DEGREE_DECIMALS)


def _placed(geometry: Any, catalog: Catalog) -> dict[str, Any]:
    """A geometry in the catalog CRS, as the event's ``crs`` and ``wgs84`` GeoJSON."""
    return {"crs": _geojson(geometry, PROJECTED_DECIMALS), "wgs84": _wgs84(geometry, catalog)}


def _trajectory(
    mission: Mission, to_catalog: ToCatalog | None, reason: str | None, catalog: Catalog
) -> dict[str, Any]:
    import shapely

    from standgrid.crs import CRS

    positions = np.zeros((0, 3))
    if mission.graph is not None:  # without one, no node (payload poses are not a track)
        positions = mission.trajectory()[1]
    out: dict[str, Any] = {
        "mission": mission.name,
        "nodes": len(positions),
        "placed": to_catalog is not None,
        "reason": reason,
        "crs": CRS.of(catalog.crs).text,
        "map": _round(positions, PROJECTED_DECIMALS),
        "line": None,
    }
    if to_catalog is not None and len(positions) > 1:
        xyz = to_catalog.projector.exact(positions)
        out["line"] = _placed(shapely.LineString(xyz[:, :2]), catalog)
    return out


def _payload(
    mission: Mission,
    stamp: tuple[int, int],
    to_catalog: ToCatalog | None,
    reason: str | None,
    catalog: Catalog,
) -> dict[str, Any]:
    import shapely

    from standgrid.crs import CRS
    from standgrid.errors import OrphanPayloadError
    from standgrid.geometry import transform_points
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.partition.chunks import footprint

    payloads = cloud_payloads(mission)
    index = next((k for k, p in enumerate(payloads) if (p.stamp.sec, p.stamp.nsec) == stamp), None)
    if index is None:  # stored, but not a point cloud the mission places (nothing to draw)
        return {
            "mission": mission.name,
            "payload": f"{stamp[0]}_{stamp[1]:09d}",
            "payloads": len(payloads),
            "placed": False,
            "reason": "not a point-cloud payload of the mission",
        }
    payload = payloads[index]
    xyz = mission.load_base(payload).xyz
    out: dict[str, Any] = {
        "mission": mission.name,
        "payload": f"{stamp[0]}_{stamp[1]:09d}",
        "index": index,
        "payloads": len(payloads),
        "points": len(xyz),
        "placed": False,
        "reason": reason,
        "crs": CRS.of(catalog.crs).text,
        "map": None,
        "position": None,
        "footprint": None,
    }
    try:
        pose = mission.pose_of(payload)
    except OrphanPayloadError as exc:
        out["reason"] = exc.message
        return out
    centre = pose[:3, 3]
    hull = footprint(transform_points(pose, xyz), shapely.Point(centre[:2]))
    out["map"] = {
        "position": _round(centre, PROJECTED_DECIMALS),
        "footprint": _geojson(hull, PROJECTED_DECIMALS),
    }
    if to_catalog is not None:
        at = to_catalog.projector.exact(centre[None, :])[0]
        points = to_catalog.base_points(np.array(xyz, dtype=np.float64), pose)
        hull = footprint(points, shapely.Point(at[:2]))
        out["placed"] = True
        out["position"] = {
            **_placed(shapely.Point(at[:2]), catalog),
            "z": round(float(at[2]), PROJECTED_DECIMALS),
        }
        out["footprint"] = _placed(hull, catalog)
    return out


def tile_with_cells(folder: str, catalog_root: str, placement_tolerance: float | None) -> Any:
    """In the worker: :func:`~standgrid.serve.workers.tile_mission`, and the cells whose
    tiles it wrote: ``{epoch: {"new": [cell ids], "changed": [...], "removed": [...]}}``
    (a tile is rewritten as a new file: a cell is changed when its tile's file changed)."""
    from standgrid.serve.workers import tile_mission

    before = _tile_files(Path(catalog_root))
    report = tile_mission(folder, catalog_root, placement_tolerance)
    after = _tile_files(Path(catalog_root))
    cells: dict[str, dict[str, list[str]]] = {}
    for key in sorted(before.keys() | after.keys()):
        old, new = before.get(key), after.get(key)
        kind = (
            "new"
            if old is None
            else "removed"
            if new is None
            else ("changed" if old != new else None)
        )
        if kind is not None:
            epoch, cell_id = key
            cells.setdefault(epoch, {"new": [], "changed": [], "removed": []})[kind].append(cell_id)
    return report, cells


def _tile_files(root: Path) -> dict[tuple[str, str], tuple[str, int, int, int]]:
    """(epoch, cell id) -> its tile's path and file identity (inode, mtime, size), from the
    catalog's ``cells`` layer as committed now."""
    import contextlib

    from standgrid.catalog import Catalog
    from standgrid.catalog.index import CatalogIndex

    found: dict[tuple[str, str], tuple[str, int, int, int]] = {}
    with Catalog.reading(root) as catalog:
        cells = CatalogIndex(catalog).read("cells")
        for row in cells[["epoch", "cell_id", "tile_path"]].itertuples(index=False):
            with contextlib.suppress(OSError):
                stat = catalog.path(str(row.tile_path)).stat()
                found[(str(row.epoch), str(row.cell_id))] = (
                    str(row.tile_path),
                    stat.st_ino,
                    stat.st_mtime_ns,
                    stat.st_size,
                )
    return found
