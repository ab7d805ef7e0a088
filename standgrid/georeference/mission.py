"""Georeference one mission: its pose graph's GNSS anchor, or a fit of its GNSS fixes."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from standgrid.errors import InsufficientGnssError, NotGeoreferencedError
from standgrid.mission.posegraph import PoseGraph
from standgrid.mission.sensors import GnssFixes

from .fit import (
    DEFAULT_MAX_TIME_GAP_S,
    GeoreferenceFit,
    evaluate_georeference,
    fit_from_pose_graph,
    fit_georeference,
)


class MissionLike(Protocol):
    """What :func:`georeference_mission` reads of a ``standgrid.mission.model.Mission``."""

    @property
    def path(self) -> Any: ...
    @property
    def graph(self) -> PoseGraph | None: ...
    @property
    def gnss(self) -> GnssFixes | None: ...


def georeference_mission(
    mission: MissionLike,
    *,
    method: str = "yaw2d",
    min_fixes: int = 10,
    use_graph_anchor: bool = True,
    max_time_gap_s: float = DEFAULT_MAX_TIME_GAP_S,
) -> GeoreferenceFit:
    """The map -> ENU georeference of ``mission``.

    With ``use_graph_anchor`` and a graph carrying ``GNSS_LLA_REF`` + ``GNSS_LLA_TO_MAP`` the
    graph's transform is used as is (method ``pose_graph``), with residuals of the mission's
    GNSS fixes when it has any. Otherwise the fixes are fitted to the graph's node positions
    (:func:`fit_georeference`). Raises :class:`NotGeoreferencedError` without a graph or
    without any GNSS, :class:`InsufficientGnssError` with too few good fixes.
    """
    path = Path(mission.path) if mission.path is not None else None
    graph = mission.graph
    gnss = mission.gnss
    if graph is None or len(graph) == 0:
        raise NotGeoreferencedError("mission has no pose graph to georeference", path=path)
    anchor = fit_from_pose_graph(graph) if use_graph_anchor else None
    has_fixes = gnss is not None and len(gnss) > 0
    if anchor is not None:
        if not has_fixes:
            return anchor
        assert gnss is not None
        return evaluate_georeference(
            anchor.T_enu_map,
            anchor.lla_ref,
            anchor.method,
            gnss,
            graph.stamps_ns,
            graph.positions,
            max_time_gap_s=max_time_gap_s,
            source=path,
        )
    if gnss is None:
        raise NotGeoreferencedError(
            "mission has no GNSS log (gnss/fixes.txt) and its pose graph has no "
            "GNSS_LLA_REF/GNSS_LLA_TO_MAP anchor",
            path=path,
        )
    gnss_log = getattr(getattr(mission, "layout", None), "gnss_log", None)
    if not has_fixes:
        raise InsufficientGnssError(
            "the mission's GNSS log has no fixes", path=gnss_log if gnss_log else path
        )
    return fit_georeference(
        gnss,
        graph.stamps_ns,
        graph.positions,
        method=method,
        min_fixes=min_fixes,
        max_time_gap_s=max_time_gap_s,
        source=Path(gnss_log) if gnss_log is not None else path,
    )
