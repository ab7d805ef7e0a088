"""A georeference from a known start: the map frame's origin and heading given by hand.

``--anchor LAT LON ALT YAW`` puts the map-frame origin at WGS 84 latitude/longitude
(degrees) and ellipsoidal height ALT (metres), with the map x axis pointing YAW degrees
counter-clockwise from East (ENU convention, the same angle ``standgrid georef`` reports as
yaw: 0 = map x East, 90 = map x North; from a compass heading H of the map x axis, clockwise
from North, YAW = 90 - H). The map z axis is the local up (no roll or pitch). So
``p_enu = Rz(YAW) p_map`` in the ENU frame at the anchor: ``T_enu_map`` is a pure rotation.

SLAM maps usually start at the first pose, so the anchor is the robot's start position and
heading. A wrong anchor moves every point: an error of d degrees in YAW shifts a point r
metres from the origin sideways by r * d * pi / 180.
"""

from __future__ import annotations

import math

import numpy as np

from standgrid.errors import GeoreferenceError

from .fit import GeoreferenceFit


def fit_from_anchor(lat: float, lon: float, alt: float, yaw_deg: float) -> GeoreferenceFit:
    """The georeference of a map whose origin is at ``(lat, lon, alt)`` and whose x axis points
    ``yaw_deg`` counter-clockwise from East (module docstring). Method ``anchor``."""
    values = (lat, lon, alt, yaw_deg)
    if not all(math.isfinite(float(v)) for v in values):
        raise GeoreferenceError(f"anchor values must be finite: {values}")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise GeoreferenceError(f"anchor latitude/longitude out of range: {lat}, {lon}")
    yaw = math.radians(float(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    return GeoreferenceFit.without_fixes((float(lat), float(lon), float(alt)), T, "anchor")
