"""One field schema per epoch: every chunk fed to the partition engine is brought to it."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import CatalogError, PointCloudFormatError
from standgrid.las_fields import LAS_INTEGER_DIMENSIONS
from standgrid.pointcloud import PointCloud

#: Fields the tiler sets on every point.
TILER_FIELDS: dict[str, np.dtype] = {
    "gps_time": np.dtype(np.float64),
    "point_source_id": np.dtype(np.uint16),
    "payload_id": np.dtype(np.uint32),
}
#: What a payload without a field stored in a standard LAS dimension gets, whatever the
#: field's dtype: the value of a tile's point record when no payload carries the field
#: (return 1 of 1, else 0). Other fields get NaN (floats) or 0.
FILL_VALUES: dict[str, int] = {
    **dict.fromkeys(LAS_INTEGER_DIMENSIONS, 0),
    "return_number": 1,
    "number_of_returns": 1,
}
#: The buffer flag: set by the partition engine, never part of a schema.
WITHHELD = "withheld"
#: Where a payload's own ``point_source_id`` (a LAS flight line) is kept when it is not 0
#: everywhere: the tiles' ``point_source_id`` is the mission number.
SOURCE_POINT_SOURCE_ID = "source_point_source_id"

Schema = dict[str, np.dtype]


def epoch_schema(samples: Iterable[PointCloud], where: Path) -> Schema:
    """The field set and dtypes of an epoch's chunks: the union over ``samples`` (promoted),
    plus :data:`TILER_FIELDS`. ``(N, k)`` fields keep their ``k`` (a sub-array dtype)."""
    schema: Schema = {}
    for cloud in samples:
        for name, values in cloud.fields.items():
            if name == WITHHELD:
                continue
            dtype = np.dtype((values.dtype, values.shape[1:])) if values.ndim > 1 else values.dtype
            if name in schema and schema[name].shape != dtype.shape:
                raise CatalogError(
                    f"field {name!r} has shape {dtype.shape} here and {schema[name].shape} "
                    "in another payload of the epoch",
                    path=where,
                )
            if name in schema:
                base = np.result_type(schema[name].base, dtype.base)
                dtype = np.dtype((base, dtype.shape)) if dtype.shape else base
            schema[name] = dtype
    for name, dtype in TILER_FIELDS.items():
        schema[name] = dtype
    return schema


def conform(cloud: PointCloud, schema: Schema, source: Path) -> PointCloud:
    """Bring a chunk to the epoch's schema: cast (a value an integer dtype cannot hold
    exactly is refused: ``PointCloudFormatError`` naming ``source``), fill absent fields
    (:data:`FILL_VALUES`, else NaN or 0)."""
    unknown = sorted(set(cloud.fields) - set(schema) - {WITHHELD})
    if unknown:
        raise CatalogError(
            f"fields {unknown} appear here but not in the epoch's first payload; "
            "every payload of a mission must carry the same fields",
            path=source,
        )
    n = len(cloud)
    fields = {}
    for name, dtype in schema.items():
        values = cloud.fields.get(name)
        base, shape = dtype.base, dtype.shape
        if values is None:
            fill = FILL_VALUES.get(name, np.nan if np.issubdtype(base, np.floating) else 0)
            fields[name] = np.full((n, *shape), fill, dtype=base)
        elif values.shape[1:] != shape:
            raise CatalogError(
                f"field {name!r} has shape {values.shape[1:]}, the epoch's is {shape}",
                path=source,
            )
        else:
            fields[name] = _exact_cast(name, values, base, source)
    return PointCloud(cloud.xyz, fields)


def _exact_cast(name: str, values: NDArray[Any], base: np.dtype, source: Path) -> NDArray[Any]:
    """``values`` as ``base``; a cast that would change a value (wrap, truncate or round it:
    checked only when the cast is not safe for every value) is refused. NaN stays NaN."""
    if np.can_cast(values.dtype, base, "safe"):
        return values.astype(base, copy=False)
    with np.errstate(invalid="ignore", over="ignore"):  # NaN and huge floats: refused below
        cast = values.astype(base)
    if base.kind in "biu":
        changed = cast != values
        if values.dtype.kind == "f":
            changed |= ~np.isfinite(values)
    else:  # a float or complex target: the cast back must give the same value (or NaN)
        back = cast.astype(values.dtype)
        changed = (back != values) & ~(np.isnan(values) if values.dtype.kind in "fc" else False)
    if changed.any():
        k = int(np.argmax(changed.reshape(len(values), -1).any(axis=1)))
        raise PointCloudFormatError(
            f"field {name!r} value {values[k]} (point {k}) cannot be stored exactly as "
            f"{base}, the epoch's dtype for it (from the mission's first payload)",
            path=source,
        )
    return cast
