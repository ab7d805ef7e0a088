"""Georeferencing: GNSS fixes -> a transform from the SLAM map frame into a projected CRS."""

from .anchor import fit_from_anchor
from .crs import resolve_crs, utm_crs_for
from .enu import ecef_to_lla, enu_rotation, enu_to_lla, lla_to_ecef, lla_to_enu
from .fit import (
    FIX_STATUS,
    GeoreferenceFit,
    evaluate_georeference,
    fit_from_pose_graph,
    fit_georeference,
)
from .mission import georeference_mission
from .project import MapProjector, projected_pose_xy

__all__ = [
    "FIX_STATUS",
    "GeoreferenceFit",
    "MapProjector",
    "ecef_to_lla",
    "enu_rotation",
    "enu_to_lla",
    "evaluate_georeference",
    "fit_from_anchor",
    "fit_from_pose_graph",
    "fit_georeference",
    "georeference_mission",
    "lla_to_ecef",
    "lla_to_enu",
    "projected_pose_xy",
    "resolve_crs",
    "utm_crs_for",
]
