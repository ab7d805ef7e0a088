"""LAS 1.4 / LAZ tile writer and reader (laspy + lazrs).

A tile holds the *core* points of one cell followed by its *buffer* points (neighbours'
points within the buffer distance) with the LAS ``withheld`` flag set, so a reader drops
them exactly. Point data record format 6, or 7 when the cloud has ``red``/``green``/``blue``.

Field mapping (``PointCloud.fields`` -> LAS):

- ``gps_time`` (adjusted standard GPS time; the global-encoding GPS-time-type bit is set),
  ``point_source_id`` (uint16, the mission number; a payload's own is kept as the extra
  dimension ``source_point_source_id``), ``classification``, ``return_number``,
  ``number_of_returns`` (both default to 1), ``user_data``, ``scan_angle`` (LAS 1.4 units of
  0.006 degrees, stored as given; a source's ``scan_angle_rank`` arrives converted),
  ``scan_direction_flag``, ``edge_of_flight_line``, ``synthetic``, ``key_point``,
  ``overlap``, ``scanner_channel``, ``red``/``green``/``blue`` -> the LAS dimension of the
  same name, only when every value is exactly storable (:mod:`standgrid.las_fields`: integral
  and in range, floats such as ``1.0, 2.0`` included; nothing rounded, wrapped or clipped),
  otherwise ``PointCloudFormatError``.
- ``intensity``: unsigned integers of at most 16 bits are stored as they are. Any other
  dtype (float reflectivity, signed or wide integers) is stored as
  ``clip(round(value * intensity_scale), 0, 65535)`` in the LAS intensity, *and* the exact
  values are kept in the extra dimension ``intensity_raw`` so nothing is lost;
  :func:`read_tile` gives the exact values back as ``intensity``.
- ``payload_id`` and every other field -> an extra-bytes dimension of the same dtype
  (bool is stored as uint8 and restored as bool; (N, k<=3) arrays as k-vectors).
- ``withheld`` is not taken from the fields: core points are never withheld, buffer points
  always are.

A private VLR (user id ``standgrid``) records the written field names and dtypes, so
:func:`read_tile` returns exactly the fields that were written. The bytes are those of the
one LAS encoder, :mod:`standgrid.clouds.las_write`, with its ``TILE`` convention.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.clouds.las_write import (
    COLOUR_FIELDS,
    LAS_DIMENSION_NAMES,
    STANDARD_FIELDS,
    TILE,
    VLR_RECORD_ID,
    VLR_USER_ID,
    EncodedLas,
    encode_las,
    extra_type,
    write_las,
)
from standgrid.errors import PointCloudFormatError
from standgrid.las_fields import check_finite_gps_time, las_dimension_values
from standgrid.partition.lattice import SCALE, snap_to_storage
from standgrid.pointcloud import PointCloud

__all__ = ["SCALE", "TileInfo", "read_tile", "snap_to_storage", "write_tile"]


@dataclass(frozen=True)
class TileInfo:
    """What :func:`write_tile` wrote: counts, core bounds and z statistics."""

    path: Path
    core_count: int
    buffer_count: int
    #: (xmin, ymin, zmin, xmax, ymax, zmax) of the core points (NaN when there are none).
    bounds: tuple[float, ...]
    #: The same over every point in the file, buffer included (what the LAS header says).
    file_bounds: tuple[float, ...]
    z_min: float
    z_max: float
    z_mean: float
    z_p95: float
    point_format: int
    compressed: bool
    crs: str
    #: The cell polygon passed in (shapely geometry) or None.
    core_bounds: Any = None
    #: Core point count per ``point_source_id`` (mission number).
    points_per_source: dict[int, int] = field(default_factory=dict)

    @property
    def point_count(self) -> int:
        return self.core_count + self.buffer_count

    def vpc_entry(
        self, datetime: str | None = None
    ) -> tuple[Path, tuple[float, ...], str, int, str | None]:
        """``(path, file_bounds, crs, point_count, datetime)``: one tile for ``write_vpc``."""
        return (self.path, self.file_bounds, self.crs, self.point_count, datetime)


def write_tile(
    path: str | os.PathLike[str],
    core: PointCloud,
    *,
    crs: str,
    buffer: PointCloud | None = None,
    laz: bool | None = None,
    core_bounds: Any = None,
    intensity_scale: float = 1.0,
    overwrite: bool = True,
    lattice_origin: tuple[float, float] = (0.0, 0.0),
    durable: bool = True,
) -> TileInfo:
    """Write ``core`` (+ ``buffer`` points flagged withheld) as one LAS 1.4 tile.

    ``laz`` defaults to the suffix (``.laz`` compressed). Coordinates are stored at 1 mm with
    a per-tile offset (the tile minimum floored to the metre). ``core`` and ``buffer`` must
    carry the same field names. A single cloud with a bool ``withheld`` field (and no
    ``buffer``) is split by it. Written atomically, and fsynced unless ``durable=False`` (a
    tile staged in a catalog transaction: the commit fsyncs it); returns a :class:`TileInfo`.

    Standard LAS fields (``return_number``, ``classification``, colours, flags, ...; see
    :mod:`standgrid.las_fields`) are stored only when exact: integer and bool values must be
    in the dimension's range; float values (``1.0, 2.0``) are accepted when every one is
    integral and in range, and stored as those integers (read back with the float dtype);
    ``gps_time`` must be finite. A fraction, NaN, infinity, out-of-range value, non-numeric
    dtype or a field of more than one value per point raises
    :class:`~standgrid.errors.PointCloudFormatError` naming the tile, the field and the first
    offending value, before any file is created.
    """
    out = Path(path)
    if laz is None:
        laz = out.suffix.lower() == ".laz"
    encoded, core, n_buffer = encode_tile(
        out,
        core,
        crs=crs,
        buffer=buffer,
        lattice_origin=lattice_origin,
        intensity_scale=intensity_scale,
    )
    write_las(
        encoded.las,
        out,
        laz=bool(laz),
        overwrite=overwrite,
        durable=durable,
        extent=encoded.extent,
    )
    return tile_info(out, core, n_buffer, encoded, bool(laz), crs, core_bounds)


def encode_tile(
    out: Path,
    core: PointCloud,
    *,
    crs: str,
    buffer: PointCloud | None,
    lattice_origin: tuple[float, float],
    intensity_scale: float,
) -> tuple[EncodedLas, PointCloud, int]:
    """A tile's record as :func:`write_tile` writes it (nothing written): the encoding, the
    core points and the number of buffer points (for :func:`tile_info`)."""
    core, buffer = _tile_parts(out, core, buffer)
    encoded = encode_las(
        PointCloud(core.xyz, _without_withheld(core)),
        path=out,
        convention=TILE,
        scale=SCALE,
        crs=crs,
        buffer=PointCloud(buffer.xyz, _without_withheld(buffer)) if len(buffer) else None,
        lattice_origin=lattice_origin,
        intensity_scale=intensity_scale,
    )
    return encoded, core, len(buffer)


def _tile_parts(
    out: Path, core: PointCloud, buffer: PointCloud | None
) -> tuple[PointCloud, PointCloud]:
    """The core and buffer points (a combined cloud split by its ``withheld`` flags; no
    buffer: an empty one); withheld core points refused."""
    if buffer is None and "withheld" in core.fields:  # a combined cloud (CellPoints.combined())
        flags = np.asarray(las_dimension_values("withheld", core.fields["withheld"], out), bool)
        if flags.any():
            core, buffer = core.select(~flags), core.select(flags)
    buffer = (
        buffer
        if buffer is not None
        else PointCloud.empty({k: v.dtype for k, v in core.fields.items()})
    )
    if "withheld" in core.fields and np.any(core.fields["withheld"]):
        raise PointCloudFormatError("core points must not be withheld", path=out)
    return core, buffer


def _without_withheld(cloud: PointCloud) -> dict[str, NDArray[Any]]:
    """``cloud``'s fields but ``withheld`` (the part says it)."""
    return {k: v for k, v in cloud.fields.items() if k != "withheld"}


def tile_info(
    out: Path,
    core: PointCloud,
    n_buffer: int,
    encoded: EncodedLas,
    compressed: bool,
    crs: str,
    core_bounds: Any,
) -> TileInfo:
    """What was written: counts, the core's bounds and z statistics, points per source."""
    n_core = len(core)
    core_lo, core_hi = encoded.core_bounds
    z = core.xyz[:, 2]
    if n_core:
        bounds = (*map(float, core_lo), *map(float, core_hi))
        z_stats = (
            float(core_lo[2]),
            float(core_hi[2]),
            float(z.mean()),
            # the same values in the same order as z: percentile copies them either way
            float(np.percentile(encoded.core_columns[2], 95)),
        )
    else:
        bounds = (float("nan"),) * 6
        z_stats = (float("nan"),) * 4
    extent = encoded.extent
    if extent is not None:
        file_bounds = (*map(float, extent.mins), *map(float, extent.maxs))
    else:
        file_bounds = (float("nan"),) * 6
    per_source: dict[int, int] = {}
    if "point_source_id" in core.fields and n_core:
        counts = np.bincount(core.fields["point_source_id"].astype(np.int64), minlength=1)
        per_source = {int(i): int(counts[i]) for i in np.flatnonzero(counts)}
    return TileInfo(
        path=out,
        core_count=n_core,
        buffer_count=n_buffer,
        bounds=bounds,
        file_bounds=file_bounds,
        z_min=z_stats[0],
        z_max=z_stats[1],
        z_mean=z_stats[2],
        z_p95=z_stats[3],
        point_format=encoded.point_format,
        compressed=compressed,
        crs=crs,
        core_bounds=core_bounds,
        points_per_source=per_source,
    )


def read_tile_record(path: str | os.PathLike[str], **options: Any) -> Any:
    """A tile's ``laspy.LasData`` as stored (its size checked first); ``options`` go to
    ``laspy.read`` (e.g. ``decompression_selection``)."""
    import laspy

    from standgrid.clouds.las import check_las_size

    src = Path(path)
    check_las_size(src)
    try:
        return laspy.read(src, **options)
    except (laspy.errors.LaspyException, OSError, ValueError, RuntimeError) as exc:
        # lazrs.LazrsError is a RuntimeError
        raise PointCloudFormatError(f"cannot read LAS/LAZ: {exc}", path=src) from exc


def rewrite_tile(
    record: Any,
    path: str | os.PathLike[str],
    fields: dict[str, NDArray[Any]],
    *,
    source: str | os.PathLike[str],
    laz: bool | None = None,
    durable: bool = True,
) -> None:
    """Write a tile read with :func:`read_tile_record` (from ``source``) to ``path`` with
    ``fields`` (one value per stored point, withheld included) set, added when missing; every
    other dimension, the header's offsets and the points' order are kept as stored, so
    :func:`read_tile` of the result equals :func:`write_tile` of the same cloud and fields
    (standard LAS fields checked by the same rule: exact or ``PointCloudFormatError`` naming
    ``source``, before the record is changed). ``laz`` defaults to the suffix of ``path``."""
    out = Path(path)
    set_tile_fields(record, fields, source=source)
    if laz is None:
        laz = out.suffix.lower() == ".laz"
    write_las(record, out, laz=laz, overwrite=True, durable=durable)


def set_tile_fields(
    record: Any, fields: dict[str, NDArray[Any]], *, source: str | os.PathLike[str]
) -> None:
    """:func:`rewrite_tile`'s change of ``record`` (read from ``source``), nothing written:
    every field checked first (a refusal leaves the record as read), then set or added."""
    src = Path(source)
    manifest = _manifest(record, src)
    if manifest is None:
        raise PointCloudFormatError("not a standgrid tile (no field manifest)", path=src)
    stored_values, extra_types = _rewritten_values(record, fields, src)
    _add_extra_dims(record, fields, extra_types, manifest)
    _set_fields(record, fields, stored_values, manifest)


def _rewritten_values(
    record: Any, fields: dict[str, NDArray[Any]], src: Path
) -> tuple[dict[str, NDArray[Any]], dict[str, str]]:
    """Each field's values as stored (checked: one per point; a standard field exact, an
    extra one storable; no other LAS dimension), and the extra-bytes type of each extra."""
    extra_types: dict[str, str] = {}
    stored_values: dict[str, NDArray[Any]] = {}
    for name, values in fields.items():
        if len(values) != len(record.points) or values.ndim != 1:
            raise PointCloudFormatError(
                f"field {name!r} has {values.shape} values for {len(record.points)} points",
                path=src,
            )
        if name in STANDARD_FIELDS:
            stored_values[name] = las_dimension_values(name, values, src)
            if name == "gps_time" and len(values):
                times = stored_values[name]
                check_finite_gps_time(times.min(), times.max(), [times], src)
        elif name in LAS_DIMENSION_NAMES or name == "intensity_raw":
            raise PointCloudFormatError(f"field {name!r} cannot be rewritten", path=src)
        else:
            extra_types[name] = extra_type(name, values, src)
            stored_values[name] = values.astype(np.uint8) if values.dtype == np.bool_ else values
    return stored_values, extra_types


def _add_extra_dims(
    record: Any,
    fields: dict[str, NDArray[Any]],
    extra_types: dict[str, str],
    manifest: dict[str, str],
) -> None:
    """The extra dimensions missing from ``record`` (or stored with another type) added:
    one new record, the stored bytes copied field by field of the raw array."""
    import laspy

    added = []
    for name in extra_types:
        values = fields[name]
        if name in manifest and manifest[name] != values.dtype.str:
            record.remove_extra_dim(name)  # stored with another type: stored anew
        if name not in record.point_format.extra_dimension_names:
            added.append(
                laspy.ExtraBytesParams(
                    name=name,
                    type=extra_types[name],
                    description="bool" if values.dtype == np.bool_ else "",
                )
            )
    if not added:
        return
    stored_points = record.points.array
    record.header.add_extra_dims(added)
    points = laspy.ScaleAwarePointRecord.zeros(len(stored_points), header=record.header)
    for name in stored_points.dtype.names:
        points.array[name] = stored_points[name]
    record.points = points


def _set_fields(
    record: Any,
    fields: dict[str, NDArray[Any]],
    stored_values: dict[str, NDArray[Any]],
    manifest: dict[str, str],
) -> None:
    """The fields' stored values into ``record``, and its field manifest VLR updated."""
    raw = record.points.array
    for name, values in fields.items():
        stored = stored_values[name]
        if name in raw.dtype.names and raw.dtype[name].shape == ():  # a whole field: no packing
            raw[name] = stored
        else:
            record[name] = stored
        manifest[name] = values.dtype.str
    for vlr in record.header.vlrs:
        if getattr(vlr, "user_id", None) == VLR_USER_ID and vlr.record_id == VLR_RECORD_ID:
            data = json.loads(bytes(vlr.record_data).decode())
            data["fields"] = manifest
            vlr.record_data = json.dumps(data).encode()


def _manifest(las: Any, path: Path) -> dict[str, str] | None:
    for vlr in las.header.vlrs:
        if getattr(vlr, "user_id", None) == VLR_USER_ID and vlr.record_id == VLR_RECORD_ID:
            try:
                data = json.loads(bytes(vlr.record_data).decode())
                return dict(data["fields"])
            except (ValueError, KeyError, TypeError) as exc:
                raise PointCloudFormatError(
                    f"corrupt standgrid field manifest: {exc}", path=path
                ) from exc
    return None


def read_tile(path: str | os.PathLike[str], *, include_withheld: bool = False) -> PointCloud:
    """Read a tile (or any LAS/LAZ) into a :class:`PointCloud`.

    Withheld points are dropped unless ``include_withheld`` (then a bool ``withheld`` field
    tells them apart). Tiles from :func:`write_tile` give back exactly the fields written,
    with their dtypes; other files give the common LAS dimensions plus extra bytes.
    """
    src = Path(path)
    las = read_tile_record(src)
    withheld = np.asarray(las.withheld, dtype=bool)
    keep = slice(None) if include_withheld else ~withheld
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])[keep]
    dims = set(las.point_format.dimension_names)
    extra_names = list(las.point_format.extra_dimension_names)
    manifest = _manifest(las, src)
    fields: dict[str, NDArray[Any]] = {}
    if manifest is None:
        names = [
            n
            for n in (
                "intensity",
                "gps_time",
                "point_source_id",
                "classification",
                "return_number",
                "number_of_returns",
                *COLOUR_FIELDS,
            )
            if n in dims
        ] + extra_names
        for name in names:
            fields[name] = np.asarray(las[name])[keep]
    else:
        for name, dtype_text in manifest.items():
            if name == "intensity" and "intensity_raw" in extra_names:
                source = "intensity_raw"
            else:
                source = name
            values = np.asarray(las[source])[keep]
            dtype = np.dtype(dtype_text.lstrip("0123456789"))
            fields[name] = values.astype(dtype, copy=False)
    if include_withheld:
        fields["withheld"] = withheld
    return PointCloud(xyz, fields)
