"""Alignment inside a tiling run: the missions given, and the catalog's missions they
overlap (held where the catalog placed them: the reference), through
:func:`standgrid.alignment.align_missions`. Landmarks are kept in the catalog
(``align/<mission>.npz``, keyed by the mission's files) so a mission is read for them once.
"""

from __future__ import annotations

import datetime as dt
import threading
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import numpy as np

from standgrid.engine import Progress
from standgrid.storage.objects import local_copy

if TYPE_CHECKING:
    from standgrid.alignment.landmarks import Landmarks
    from standgrid.catalog import Catalog, Transaction
    from standgrid.georeference.placement import Placement
    from standgrid.mission.model import Mission
    from standgrid.tiling.epoch import Ingest

#: A catalog mission is a reference when its trajectory comes this close (m) to a new one's.
REFERENCE_REACH_M = 30.0
#: Landmarks of the missions this process saw last (by the digest of their files): a
#: service or a script tiling the same missions into several catalogs reads them once.
_MEMO: OrderedDict[str, Landmarks] = OrderedDict()
_MEMO_MISSIONS = 8
_MEMO_LOCK = threading.Lock()


def _recorded_sigma(record: Any, mission: Mission, crs: str) -> float | None:
    """A catalog mission's absolute DRMS 1-sigma: as aligned, else from its GNSS fit."""
    from standgrid.alignment.graph import placement_sigma
    from standgrid.errors import GeoreferenceError
    from standgrid.georeference.fit import GeoreferenceFit

    geo = record.georeference or {}
    aligned = (geo.get("alignment") or {}).get("sigma_h_m")
    if aligned is not None:
        return float(aligned)
    if geo.get("method") in ("projected", "anchor", "pose_graph", None):
        return None
    try:
        fit = GeoreferenceFit.from_dict(geo)
    except GeoreferenceError:
        return None
    found = placement_sigma(fit, mission.trajectory()[1])
    return None if found is None else found[0]


def _recorded(record: Any) -> Placement | None:
    """The placement a catalog recorded (its transform only; no fixes re-read)."""
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.placement import Placement

    geo = record.georeference or {}
    try:
        if geo.get("method") == "projected":
            return Placement(None, geo.get("source_crs"))
        T = np.array(geo["T_enu_map"], dtype=np.float64).reshape(4, 4)
        lat, lon, alt = (float(v) for v in geo["lla_ref"])
    except (KeyError, TypeError, ValueError):
        return None
    return Placement(GeoreferenceFit.without_fixes((lat, lon, alt), T, str(geo["method"])))


def _record_date(record: Any) -> dt.date:
    try:
        return dt.date.fromisoformat(str(record.date))
    except (AttributeError, ValueError):
        return dt.date(2000, 1, 1)


def _nodes_crs(mission: Mission, placement: Placement, crs: str) -> np.ndarray:
    nodes = mission.trajectory()[1]
    if placement.fit is None:
        return placement.to_catalog(crs, mission.name).projected_points(nodes)
    return placement.to_catalog(crs, mission.name).projector.exact(nodes)


def _references(
    catalog: Catalog, ingests: list[Ingest], crs: str
) -> list[tuple[Mission, Placement, float | None]]:
    """The catalog's missions (not given again) that overlap the new ones, as recorded."""
    from scipy.spatial import cKDTree

    from standgrid.errors import StandgridError
    from standgrid.mission.opening import open_mission
    from standgrid.mission.scan import ScanOptions, is_scan, open_scan

    given = {i.mission.name for i in ingests}
    new_nodes = np.concatenate([_nodes_crs(i.mission, i.placement, crs)[:, :2] for i in ingests])
    if not len(new_nodes):
        return []
    tree = cKDTree(new_nodes)
    from standgrid.alignment.register import GLOBAL_REACH_M
    from standgrid.alignment.stage import is_provisional

    # a mission placed only by its metadata may be that far off: look as far as its search
    reach = REFERENCE_REACH_M
    if any(is_provisional(i.placement) for i in ingests):
        reach += GLOBAL_REACH_M
    out = []
    for name, record in sorted(catalog.mission_records.items()):
        if name in given or not record.path:
            continue
        try:  # a mission tiled from object storage is read from its local copy
            where = local_copy(record.path)
        except StandgridError:
            continue  # a reference that cannot be read is no reference
        if not where.exists():
            continue
        placement = _recorded(record)
        if placement is None:
            continue
        try:
            if is_scan(where):  # a plain scan: its landmarks need neither date nor path
                mission = open_scan(where, ScanOptions(crs=crs, date=_record_date(record)))
            else:
                mission = open_mission(where, cache_points=0)
            nodes = _nodes_crs(mission, placement, crs)
        except StandgridError:
            continue  # a reference that cannot be read is no reference
        if len(nodes):
            d, _ = tree.query(nodes[:, :2], distance_upper_bound=reach)
            if np.isfinite(d).any():
                out.append((mission, placement, _recorded_sigma(record, mission, crs)))
    return out


def _landmarks(mission: Mission, txn: Transaction, progress: Progress) -> Landmarks:
    from standgrid.alignment.landmarks import (
        landmarks_key,
        load_landmarks,
        mission_landmarks,
        save_landmarks,
    )

    key = landmarks_key(mission)
    rel = f"align/{mission.name}.npz"
    current = txn.current(rel)
    marks = load_landmarks(current, key) if current is not None else None
    if marks is None:
        with _MEMO_LOCK:
            marks = _MEMO.get(key)
        if marks is None:
            progress.status(f"aligning: landmarks of {mission.name}")
            marks = mission_landmarks(mission)
        save_landmarks(marks, key, txn.stage(rel))
    with _MEMO_LOCK:
        _MEMO[key] = marks
        _MEMO.move_to_end(key)
        while len(_MEMO) > _MEMO_MISSIONS:
            _MEMO.popitem(last=False)
    return marks


def align_ingests(
    catalog: Catalog, txn: Transaction, ingests: list[Ingest], progress: Progress
) -> dict[str, Any] | None:
    """Align the missions given (their placements replaced) with each other and with the
    catalog's missions they overlap; None when there is nothing to align."""
    from standgrid.alignment import AlignOptions, align_missions

    fitted = [i for i in ingests if i.placement.fit is not None]
    if not fitted:
        return None
    references = _references(catalog, ingests, catalog.crs)
    if len(ingests) + len(references) < 2:
        return None
    items = [*((m, p) for m, p, _ in references), *((i.mission, i.placement) for i in ingests)]
    found = {m.name: _landmarks(m, txn, progress) for m, _ in items}
    options = AlignOptions(
        hold=tuple(m.name for m, _, _ in references),
        held_sigma=tuple((m.name, s) for m, _, s in references if s is not None),
    )
    result = align_missions(items, catalog.crs, options, progress=progress, landmarks=found)
    for ingest in ingests:
        ingest.placement = result.placements[ingest.mission.name]
    for warning in result.warnings:
        progress.status(f"warning: {warning}")
    report = result.to_dict()
    report["references"] = [m.name for m, _, _ in references]
    return report
