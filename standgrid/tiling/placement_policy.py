"""The placement tolerance: a catalog keeps the placement it used while a refit moves a
mission by less than a tolerance.

A robot streaming a mission sends GNSS fixes with its payloads, and every tiling of the
grown mission fits its georeference again: the fit moves by centimetres, every payload moves
with it, and the whole epoch is re-tiled each time (O(N^2) over a mission). Under a
tolerance, :func:`choose_placement` keeps the placement the catalog recorded for the mission
(its transform, with the residuals of the current fixes under it) when the fresh fit would
move no point of the mission (the boxes of its payloads, its trajectory) by as much as the
tolerance (:func:`~standgrid.georeference.placement.placement_offset`): the payloads already
tiled keep their points and the epoch is re-tiled in place. Beyond the tolerance the fresh
fit is used and the whole epoch re-tiles, as without one. Either way the choice is reported
(:class:`PlacementChoice`: the tile report, the mission record, the ``missions`` layer's
``placement_offset_m``): coordinates are never off the fresh fit silently.

The points bounded: a payload already in the catalog whose source is unchanged (its
``source_digest`` under the kept placement) has its points in the cells holding the mission,
each cell's square between its lowest and highest point (the ``cells`` layer): those boxes'
corners, taken back to the map frame through the kept placement (exactly: pyproj's inverse);
the eight corners of the base-frame box of every other payload (new or changed: read, as it
is read again to be tiled) through its node pose; and the trajectory's nodes. (The stored
footprints are not used: they are hulls of at most 20,000 points of a payload.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pandas as pd
    from numpy.typing import NDArray

    from standgrid.catalog.records import MissionRecord
    from standgrid.georeference.placement import Placement, ToCatalog
    from standgrid.mission.model import Mission
    from standgrid.partition.schema import Schema


@dataclass(frozen=True)
class PlacementChoice:
    """The placement to tile a mission with, and what the catalog says about it."""

    placement: Placement
    #: ``"fresh"`` (the mission's own fit, as without a tolerance) or ``"kept"`` (the
    #: placement the catalog already used, within ``tolerance_m`` of the fresh fit)
    used: str
    tolerance_m: float | None = None
    #: bound on how far any point of the mission is from where the fresh fit puts it (m)
    offset_m: float = 0.0
    #: with ``used == "fresh"`` after a kept placement: how far the fresh fit moved the
    #: mission from the placement the catalog held (why the epoch re-tiled whole)
    moved_m: float | None = None
    #: the fresh fit's headline figures when it was not used
    fresh_fit: dict[str, Any] | None = None

    def note(self) -> dict[str, Any]:
        """The JSON of the tile report and the mission record (``placement``)."""
        return {
            "used": self.used,
            "tolerance_m": self.tolerance_m,
            "offset_m": self.offset_m,
            "moved_m": self.moved_m,
            "fresh_fit": self.fresh_fit,
        }


@dataclass
class _Placed:
    """A mission with its number and recipe into the catalog CRS (``PlacedMission``)."""

    mission: Mission
    number: int
    to_catalog: ToCatalog | None


def choose_placement(
    mission: Mission,
    number: int,
    epoch: str,
    fresh: Placement,
    record: MissionRecord | None,
    stored: pd.DataFrame,
    cells: pd.DataFrame,
    schema: Schema,
    crs: str,
    tolerance: float | None,
) -> PlacementChoice:
    """The placement to tile ``mission`` (number ``number``) into ``epoch`` with: ``fresh``
    (its own fit), or the one its catalog ``record`` holds when that is in the same epoch and
    within ``tolerance`` (m) of ``fresh`` for every point of the mission. ``stored``: the
    epoch's ``payloads`` rows; ``cells``: its ``cells`` rows; ``schema``: the epoch's field
    schema (of the source digests)."""
    from standgrid.georeference.placement import held_placement, placement_offset

    exact = PlacementChoice(fresh, "fresh", tolerance)
    if tolerance is None or fresh.fit is None or record is None or record.epoch != epoch:
        return exact
    held_record = dict(record.georeference or {})
    if "T_enu_map" not in held_record or "lla_ref" not in held_record:
        return exact  # projected clouds, or a catalog without the record
    same = np.array_equal(
        np.asarray(held_record["T_enu_map"], dtype=np.float64), fresh.fit.T_enu_map
    ) and tuple(map(float, held_record["lla_ref"])) == tuple(map(float, fresh.fit.lla_ref))
    if same:
        return exact  # the fit did not move: the payloads are unchanged as they are
    held = held_placement(mission, held_record)
    points = _mission_points(mission, number, epoch, held, stored, cells, schema, crs)
    offset = placement_offset(held, fresh, points, crs)
    if offset < tolerance:
        return PlacementChoice(held, "kept", tolerance, offset, fresh_fit=fresh.summary())
    return PlacementChoice(fresh, "fresh", tolerance, moved_m=offset)


def _mission_points(
    mission: Mission,
    number: int,
    epoch: str,
    held: Placement,
    stored: pd.DataFrame,
    cells: pd.DataFrame,
    schema: Schema,
    crs: str,
) -> NDArray[np.float64]:
    """Map-frame points whose convex hull holds every point of the mission (module doc)."""
    from standgrid.georeference.placement import cloud_payloads
    from standgrid.tiling.increment import placement_digest, source_digest
    from standgrid.tiling.mission_rows import payload_rows

    to_catalog = held.to_catalog(crs, mission.name)
    _, sources = payload_rows([_Placed(mission, number, to_catalog)], epoch)
    mine = stored[stored["mission"].astype(str) == mission.name]
    digests = {}
    if len(mine) and "source_digest" in mine.columns:
        known = mine["source_digest"].notna()
        ids = mine["payload_id"][known].astype(np.int64)
        digests = dict(zip(ids, mine["source_digest"][known].astype(str), strict=True))
    placed = placement_digest(held.record())
    kept_ids, corners = set(), []
    for payload, source in zip(cloud_payloads(mission), sources, strict=True):
        ident = int(source["payload_id"])
        if digests.get(ident) == source_digest(source, placed, schema):
            kept_ids.add(ident)
            continue
        xyz = mission.load_base(payload).xyz
        if not len(xyz):
            continue
        lo = np.array([xyz[:, k].min() for k in range(3)])
        hi = np.array([xyz[:, k].max() for k in range(3)])
        box = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
        pose = mission.pose_of(payload)
        corners.append(box @ pose[:3, :3].T + pose[:3, 3])
    graph = mission.graph
    if graph is not None and len(graph):
        corners.append(np.asarray(graph.positions, dtype=np.float64))
    if kept_ids:  # their points are in the catalog's cells, placed by ``held``
        corners.append(to_catalog.projector.to_map(_stored_boxes(mission.name, cells)))
    return np.concatenate(corners) if corners else np.zeros((0, 3))


def _stored_boxes(name: str, cells: pd.DataFrame) -> NDArray[np.float64]:
    """Catalog-CRS corners of the boxes holding the mission's points in the catalog: each
    cell holding the mission, its square from its lowest to its highest point (a tile's
    points lie in its cell: the partition put them there)."""
    import shapely

    holding = cells[cells["missions"].astype(str).map(lambda text: name in text.split(","))]
    if not len(holding):
        return np.zeros((0, 3))
    low, high = holding["z_min"].to_numpy(np.float64), holding["z_max"].to_numpy(np.float64)
    if not (np.isfinite(low).all() and np.isfinite(high).all()):
        from standgrid.errors import CatalogError

        raise CatalogError(f"cells of mission {name!r} without a finite height range")
    squares = np.asarray(holding["geometry"].values)
    xy, which = shapely.get_coordinates(squares, return_index=True)
    return np.concatenate([np.column_stack([xy, z[which]]) for z in (low, high)])
