"""``grid_map_msgs/GridMap`` (ANYbotics grid_map, ROS 1 and ROS 2) as elevation maps.

rosbags does not ship grid_map_msgs: its ROS 2 definitions are registered here from their
``.msg`` text (ROS 1 bags carry their own definitions). A message's layer (``elevation``)
becomes an :class:`~standgrid.mission.derived_maps.ElevationMap` in the message's frame:
grid_map stores a layer as a column-major matrix whose row index runs along -x and column
index along -y from the map's ``+x +y`` corner, as a circular buffer starting at
``(outer_start_index, inner_start_index)``; only the position x/y of ``info.pose`` is used
(as grid_map itself does).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import BagFormatError

GRIDMAP_TYPE = "grid_map_msgs/msg/GridMap"
#: The ROS 2 (humble and later) definitions of grid_map_msgs.
GRIDMAP_MSGS_ROS2 = {
    "grid_map_msgs/msg/GridMapInfo": (
        "float64 resolution\nfloat64 length_x\nfloat64 length_y\ngeometry_msgs/Pose pose\n"
    ),
    GRIDMAP_TYPE: (
        "std_msgs/Header header\ngrid_map_msgs/GridMapInfo info\nstring[] layers\n"
        "string[] basic_layers\nstd_msgs/Float32MultiArray[] data\n"
        "uint16 outer_start_index\nuint16 inner_start_index\n"
    ),
}
#: The ROS 1 definitions (the header in the info), for writing ROS 1 bags.
GRIDMAP_MSGS_ROS1 = {
    "grid_map_msgs/msg/GridMapInfo": (
        "std_msgs/Header header\nfloat64 resolution\nfloat64 length_x\nfloat64 length_y\n"
        "geometry_msgs/Pose pose\n"
    ),
    GRIDMAP_TYPE: (
        "grid_map_msgs/GridMapInfo info\nstring[] layers\nstring[] basic_layers\n"
        "std_msgs/Float32MultiArray[] data\nuint16 outer_start_index\nuint16 inner_start_index\n"
    ),
}


def register_gridmap_types(typestore: Any, definitions: dict[str, str] | None = None) -> None:
    """Register grid_map_msgs in a rosbags typestore (the ROS 2 definitions by default),
    unless it has them."""
    from rosbags.typesys import get_types_from_msg

    if GRIDMAP_TYPE in typestore.types:
        return
    types: dict[str, Any] = {}
    for name, text in (definitions or GRIDMAP_MSGS_ROS2).items():
        types.update(get_types_from_msg(text, name))
    typestore.register(types)


def gridmap_header(msg: Any) -> Any:
    """The message's header (ROS 2: ``header``; ROS 1: ``info.header``)."""
    header = getattr(msg, "header", None)
    return header if header is not None else msg.info.header


def gridmap_layer(
    msg: Any, layer: str, where: str
) -> tuple[NDArray[np.float32], float, tuple[float, float], tuple[float, float]]:
    """``layer`` of a GridMap: heights (row 0 at the lowest y, column 0 at the lowest x),
    resolution, the grid's lower-left corner in the message frame, and the map position
    (x, y) the corner is relative to. :class:`BagFormatError` (``where`` says which message)
    when the layer is missing or its array does not fit the map."""
    layers = list(msg.layers)
    if layer not in layers:
        raise BagFormatError(f"{where}: no GridMap layer {layer!r} (layers: {layers})")
    array = msg.data[layers.index(layer)]
    dims = {d.label: int(d.size) for d in array.layout.dim}
    if set(dims) != {"column_index", "row_index"}:
        raise BagFormatError(f"{where}: layer {layer!r} is not a grid_map matrix (dims {dims})")
    rows, cols = dims["row_index"], dims["column_index"]
    values = np.asarray(array.data, dtype=np.float32)
    if values.size != rows * cols or rows == 0 or cols == 0:
        raise BagFormatError(f"{where}: layer {layer!r} holds {values.size} of {rows}x{cols}")
    first = array.layout.dim[0].label
    matrix = values.reshape(cols, rows).T if first == "column_index" else values.reshape(rows, cols)
    matrix = np.roll(matrix, (-int(msg.outer_start_index), -int(msg.inner_start_index)), (0, 1))
    res = float(msg.info.resolution)
    if not (np.isfinite(res) and res > 0):
        raise BagFormatError(f"{where}: GridMap resolution {res}")
    heights = matrix[::-1, ::-1].T  # row index along -x, column index along -y
    p = msg.info.pose.position
    corner = (-rows * res / 2, -cols * res / 2)
    return np.ascontiguousarray(heights), res, corner, (float(p.x), float(p.y))
