"""Sensor kinds and the models that tell them: ``velodyne-vlp16`` is a lidar.

Metadata lists sensors by kind (``lidar``), by model (``hesai-xt32``) or by the name of a
folder (``cam_front``). :func:`sensor_kinds` gives the kinds a name stands for, from
:data:`SENSOR_MODELS` (model name patterns, matched on the lower-cased name with ``_`` and
spaces as ``-``, first match wins, so ``zed-f9p`` (a u-blox GNSS receiver) is tried before
``zed`` (a Stereolabs camera)). Extend the table with :func:`register_sensor_model`.

======== =======================================================================================
kind     model patterns (prefixes)
======== =======================================================================================
lidar    velodyne, vlp, hdl, vls, alpha-prime; hesai, pandar, xt16/32, qt64, at128; ouster, os0,
         os1, os2, os-dome; livox, mid-40/70/360, avia, horizon, hap; robosense, rs-lidar,
         rs-bpearl, rs-helios; riegl, vux, vz-; sick, lms, mrs; geoslam, zeb; leica-blk,
         blk2go; faro; emesent, hovermap; innoviz, luminar, cepton, quanergy; lidar, laser
======== =======================================================================================
gnss     zed-f9p, ublox, u-blox, neo-m8; septentrio, mosaic, asterx; novatel, oem7, pwrpak;
         trimble; emlid, reach; swiftnav, piksi, duro; gnss, gps, rtk
imu      xsens, mti; microstrain, 3dm-gx; vectornav, vn-100/200/300; epson-g; bosch-bmi, bmi0;
         adis; imu
camera   zed (Stereolabs), realsense, d435/d455/l515; alphasense, sevensense; flir, blackfly,
         basler, allied, ximea; gopro, insta360; cam, camera, image, rgb, thermal
======== =======================================================================================
"""

from __future__ import annotations

import re
from collections.abc import Iterable

#: Kind names and what else users call them.
KIND_ALIASES: dict[str, str] = {
    "lidar": "lidar",
    "laser": "lidar",
    "laser-scanner": "lidar",
    "tls": "lidar",
    "gnss": "gnss",
    "gps": "gnss",
    "rtk": "gnss",
    "imu": "imu",
    "ins": "imu",
    "camera": "camera",
    "cameras": "camera",
    "cam": "camera",
    "image": "camera",
    "images": "camera",
}

#: ``(pattern, kind)``: a name whose normalised form matches ``pattern`` (re.match) is a kind.
SENSOR_MODELS: list[tuple[str, str]] = [
    # GNSS receivers first: u-blox's ZED-F9P shares its prefix with the ZED camera
    (
        r"(zed-?f9|u-?blox|neo-?m8|septentrio|mosaic|asterx|novatel|oem7|pwrpak|trimble"
        r"|emlid|reach|swift|piksi|duro|gnss|gps|rtk)",
        "gnss",
    ),
    (
        r"(velodyne|vlp|hdl|vls|alpha-?prime|hesai|pandar|xt-?16|xt-?32|qt-?64|at-?128|ouster"
        r"|os-?[012](\b|-|$)|os-?dome|livox|mid-?(40|70|360)|avia|horizon|hap(\b|-|$)|robosense"
        r"|rs-?(lidar|bpearl|helios|ruby|m1)|riegl|vux|vz-|sick|lms|mrs|geoslam|zeb|leica-?blk"
        r"|blk2go|faro|emesent|hovermap|innoviz|luminar|cepton|quanergy|lidar|laser)",
        "lidar",
    ),
    (
        r"(xsens|mti|microstrain|3dm-?gx|vectornav|vn-?[123]00|epson-?g|bosch-?bmi|bmi0|adis|imu"
        r"|ins(\b|-|$))",
        "imu",
    ),
    (
        r"(zed|realsense|d4[0-9]{2}|l515|alphasense|sevensense|flir|blackfly|basler|allied"
        r"|ximea|gopro|insta360|cam|image|rgb|thermal)",
        "camera",
    ),
]


def normalise(name: str) -> str:
    """Lower case, ``_`` and spaces as ``-``."""
    return re.sub(r"[\s_]+", "-", str(name).strip().lower())


def register_sensor_model(pattern: str, kind: str) -> None:
    """Add a model pattern (a regular expression matched at the start of the normalised
    name) for ``kind``; it is tried before the built-in patterns."""
    SENSOR_MODELS.insert(0, (pattern, KIND_ALIASES.get(normalise(kind), normalise(kind))))


def sensor_kinds(name: str) -> set[str]:
    """The kinds ``name`` stands for: its own kind name, or the kind of its model (or none)."""
    norm = normalise(name)
    if norm in KIND_ALIASES:
        return {KIND_ALIASES[norm]}
    for pattern, kind in SENSOR_MODELS:
        if re.match(pattern, norm):
            return {kind}
    return set()


def sensor_matches(wanted: str, names: Iterable[str]) -> bool:
    """True when one of ``names`` is ``wanted``: the same name, a model of the wanted kind
    (``lidar`` finds ``velodyne-vlp16``), or a model of the wanted make (``velodyne`` finds
    ``velodyne-vlp16``)."""
    want = normalise(wanted)
    kind = KIND_ALIASES.get(want)
    for name in names:
        norm = normalise(name)
        if norm == want or norm.startswith(want + "-"):
            return True
        if kind is not None and kind in sensor_kinds(norm):
            return True
    return False
