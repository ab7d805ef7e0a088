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
:func:`read_tile` returns exactly the fields that were written.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.errors import CRSError, PointCloudFormatError, out_of_space_error
from standgrid.las_fields import check_finite_gps_time, las_dimension_values
from standgrid.partition.lattice import SCALE, snap_to_storage
from standgrid.pointcloud import PointCloud

__all__ = ["SCALE", "TileInfo", "read_tile", "snap_to_storage", "write_tile"]

#: Private VLR holding the field manifest.
VLR_USER_ID = "standgrid"
VLR_RECORD_ID = 1
GENERATING_SOFTWARE = "standgrid"
INT32_MAX = 2**31 - 1

#: Fields copied into the LAS dimension of the same name.
_STANDARD_FIELDS = (
    "gps_time",
    "point_source_id",
    "classification",
    "return_number",
    "number_of_returns",
    "user_data",
    "scan_angle",
    "scan_direction_flag",
    "edge_of_flight_line",
    "synthetic",
    "key_point",
    "overlap",
    "scanner_channel",
)
_COLOUR_FIELDS = ("red", "green", "blue")
_LAS_DIMENSION_NAMES = frozenset(
    {"x", "y", "z", "intensity", "withheld", *_STANDARD_FIELDS, *_COLOUR_FIELDS}
)


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


def _crs_wkt(crs: str) -> tuple[Any, str]:
    import pyproj

    try:
        parsed = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError as exc:
        raise CRSError(f"unusable CRS {crs!r}: {exc}") from exc
    # LAS 1.4 asks for OGC WKT; WKT1 (GDAL flavour) is what most LAS readers parse, WKT2
    # is the fall-back for CRSs that WKT1 cannot express.
    wkt = parsed.to_wkt(pyproj.enums.WktVersion.WKT1_GDAL) or parsed.to_wkt()
    return parsed, wkt


def _column_bounds(
    columns: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-axis (min, max) of (3, N) contiguous columns (NaN when N is 0)."""
    if not columns.shape[1]:
        return np.full(3, np.nan), np.full(3, np.nan)
    return columns.min(axis=1), columns.max(axis=1)


def _probe(core: NDArray[Any], buffer: NDArray[Any] | None) -> NDArray[Any]:
    """A zero-length array of the dtype and per-point shape a field is written with (the
    core's, promoted with the buffer's as concatenating them would)."""
    dtype = core.dtype if buffer is None else np.result_type(core, buffer)
    return np.empty((0, *core.shape[1:]), dtype=dtype)


def _blank_record(point_format: Any, n_core: int, n_buffer: int) -> NDArray[np.void]:
    """A point record of zeros but return number and number of returns 1, and the withheld
    flag on the ``n_buffer`` points after the core ones (bytes set by laspy's own packing)."""
    import laspy

    template = laspy.PackedPointRecord.zeros(2, point_format)
    template["return_number"] = np.ones(2, np.uint8)
    template["number_of_returns"] = np.ones(2, np.uint8)
    template["withheld"] = np.array([0, 1], np.uint8)
    pattern = template.array.view(np.uint8).reshape(2, -1)
    record = np.zeros(n_core + n_buffer, dtype=point_format.dtype())
    as_bytes = record.view(np.uint8).reshape(len(record), record.dtype.itemsize)
    for row, rows in ((0, slice(0, n_core)), (1, slice(n_core, None))):
        for column in np.flatnonzero(pattern[row]):
            as_bytes[rows, column] = pattern[row, column]
    return record


def _storage_ints(values: NDArray[np.float64], offset: float) -> NDArray[np.float64]:
    """``round((values - offset) / SCALE)``: the stored integer coordinates (as floats)."""
    scaled = np.subtract(values, offset)
    scaled /= SCALE
    return np.round(scaled, out=scaled)


def _scaled_intensity(values: NDArray[Any], intensity_scale: float) -> NDArray[np.uint16]:
    """Non-native intensities as LAS intensities: rounded, scaled, clipped to 16 bits."""
    scaled = values.astype(np.float64)  # a copy, worked on in place
    scaled *= intensity_scale
    np.round(scaled, out=scaled)
    np.nan_to_num(scaled, copy=False)
    np.clip(scaled, 0, 65535, out=scaled)
    return scaled.astype(np.uint16)


def _intensity_is_native(values: NDArray[Any]) -> bool:
    return values.dtype.kind in "ub" and values.dtype.itemsize <= 2


def _extra_type(name: str, values: NDArray[Any], path: Path) -> str:
    """The laspy extra-bytes type string for a field (``"u4"``, ``"3f8"``)."""
    dtype = np.dtype(bool) if values.dtype == np.bool_ else values.dtype
    base = "u1" if dtype == np.bool_ else dtype.str.lstrip("<>|=")
    if dtype.kind not in "biuf" or dtype.itemsize > 8:
        raise PointCloudFormatError(
            f"field {name!r} of dtype {values.dtype} cannot be stored as LAS extra bytes", path=path
        )
    if values.ndim == 1:
        return base
    if values.ndim == 2 and 1 <= values.shape[1] <= 3:
        return f"{values.shape[1]}{base}"
    raise PointCloudFormatError(
        f"field {name!r} has shape {values.shape[1:]} per point; LAS extra bytes hold at most 3",
        path=path,
    )


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
    parts = _tile_parts(out, core, buffer)
    fields = parts.fields
    has_colour = all(c in fields for c in _COLOUR_FIELDS)
    point_format = 7 if has_colour else 6
    standard = _standard_values(out, parts, has_colour)
    header = _tile_header(crs, point_format)
    coordinates = _Coordinates.of(out, parts, lattice_origin)
    header.offsets = coordinates.offsets
    header.scales = np.full(3, SCALE)
    extra = _field_dimensions(out, header, fields, has_colour, intensity_scale)
    las, packed = _point_record(
        header, parts, standard, extra, coordinates.offsets, intensity_scale
    )
    extent = _file_extent(out, parts, standard, packed, coordinates)
    _write_las(las, out, laz=bool(laz), overwrite=overwrite, durable=durable, extent=extent)
    return _tile_info(out, parts, coordinates, extent, point_format, bool(laz), crs, core_bounds)


#: A part of a tile's points: its first row, its (3, N) contiguous coordinate columns and
#: its fields (``withheld`` left out).
_Part = tuple[int, NDArray[np.float64], dict[str, NDArray[Any]]]


@dataclass(frozen=True)
class _TileParts:
    """A tile's points as written: the core part, then the buffer part (if any)."""

    core: PointCloud
    n_core: int
    n_buffer: int
    parts: list[_Part]
    #: Each field as a zero-length array of the dtype (and per-point shape) it is written as.
    fields: dict[str, NDArray[Any]]

    @property
    def n(self) -> int:
        return self.n_core + self.n_buffer


def _tile_parts(out: Path, core: PointCloud, buffer: PointCloud | None) -> _TileParts:
    """The core and buffer parts (a combined cloud split by its ``withheld`` flags), their
    fields checked to agree. The parts go straight into the record: no concatenated copies."""
    if buffer is None and "withheld" in core.fields:  # a combined cloud (CellPoints.combined())
        flags = np.asarray(las_dimension_values("withheld", core.fields["withheld"], out), bool)
        if flags.any():
            core, buffer = core.select(~flags), core.select(flags)
    buffer = (
        buffer
        if buffer is not None
        else PointCloud.empty({k: v.dtype for k, v in core.fields.items()})
    )
    core_fields = {k: v for k, v in core.fields.items() if k != "withheld"}
    buffer_fields = {k: v for k, v in buffer.fields.items() if k != "withheld"}
    if "withheld" in core.fields and np.any(core.fields["withheld"]):
        raise PointCloudFormatError("core points must not be withheld", path=out)
    if len(buffer) and set(core_fields) != set(buffer_fields):
        raise PointCloudFormatError(
            f"core fields {sorted(core_fields)} differ from buffer fields {sorted(buffer_fields)}",
            path=out,
        )
    for name, values in core_fields.items():
        if len(buffer) and buffer_fields[name].shape[1:] != values.shape[1:]:
            raise PointCloudFormatError(
                f"field {name!r} has shape {values.shape[1:]} per core point and "
                f"{buffer_fields[name].shape[1:]} per buffer point",
                path=out,
            )
    n_core, n_buffer = len(core), len(buffer)
    # (x, y, z) as contiguous columns: reduced for the bounds, scaled into the record
    parts: list[_Part] = [(0, np.ascontiguousarray(core.xyz.T), core_fields)]
    if n_buffer:
        parts.append((n_core, np.ascontiguousarray(buffer.xyz.T), buffer_fields))
    fields = {
        name: _probe(values, buffer_fields[name] if n_buffer else None)
        for name, values in core_fields.items()
    }
    return _TileParts(core, n_core, n_buffer, parts, fields)


def _standard_values(
    out: Path, parts: _TileParts, has_colour: bool
) -> dict[str, list[tuple[int, NDArray[Any]]]]:
    """The standard dimensions' values per part, checked (and floats made integers) before
    any work; a multi-valued intensity refused."""
    fields = parts.fields
    standard = {
        name: [
            (start, las_dimension_values(name, f[name], out, first_point=start))
            for start, _, f in parts.parts
        ]
        for name in (*_STANDARD_FIELDS, *(_COLOUR_FIELDS if has_colour else ()))
        if name in fields
    }
    if "intensity" in fields and fields["intensity"].ndim != 1:
        raise PointCloudFormatError(
            f"field 'intensity' has shape {fields['intensity'].shape[1:]} per point; "
            "LAS intensity holds one value per point",
            path=out,
        )
    return standard


def _tile_header(crs: str, point_format: int) -> Any:
    """A LAS 1.4 header: standard GPS time, the CRS as OGC WKT."""
    import laspy

    parsed_crs, wkt = _crs_wkt(crs)
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.generating_software = GENERATING_SOFTWARE
    header.system_identifier = "standgrid tile"
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    header.add_crs(parsed_crs)
    for vlr in header.vlrs:
        if isinstance(vlr, laspy.vlrs.known.WktCoordinateSystemVlr):
            vlr.string = wkt
    return header


@dataclass(frozen=True)
class _Coordinates:
    """The core's and all points' coordinate extremes, and the tile's offsets."""

    core_lo: NDArray[np.float64]
    core_hi: NDArray[np.float64]
    all_lo: NDArray[np.float64]
    all_hi: NDArray[np.float64]
    offsets: NDArray[np.float64]

    @classmethod
    def of(cls, out: Path, parts: _TileParts, lattice_origin: tuple[float, float]) -> _Coordinates:
        """Refuses non-finite coordinates and a tile too large for 1 mm int32 coordinates."""
        n = parts.n
        core_lo, core_hi = _column_bounds(parts.parts[0][1])
        all_lo, all_hi = core_lo, core_hi
        if parts.n_buffer:
            buffer_lo, buffer_hi = _column_bounds(parts.parts[1][1])
            all_lo, all_hi = buffer_lo, buffer_hi
            if parts.n_core:
                all_lo, all_hi = np.minimum(core_lo, buffer_lo), np.maximum(core_hi, buffer_hi)
        # min and max propagate NaN and reach +-inf: finite extremes mean finite coordinates
        if n and not (np.all(np.isfinite(all_lo)) and np.all(np.isfinite(all_hi))):
            raise PointCloudFormatError("non-finite coordinates", path=out)
        # Offsets are whole metres from the grid's origin: the stored 1 mm lattice is then the
        # one snap_to_storage(origin) snaps to, whatever the origin.
        lattice = np.array([float(lattice_origin[0]), float(lattice_origin[1]), 0.0])
        offsets = lattice + np.floor(all_lo - lattice) if n else np.zeros(3)
        if n:
            span = np.round((all_hi - offsets) / SCALE)
            if np.any(span > INT32_MAX):
                raise PointCloudFormatError(
                    f"tile spans {(all_hi - offsets).max():.0f} m: too large for 1 mm "
                    "coordinates in LAS int32",
                    path=out,
                )
        return cls(core_lo, core_hi, all_lo, all_hi, offsets)


def _field_dimensions(
    out: Path,
    header: Any,
    fields: dict[str, NDArray[Any]],
    has_colour: bool,
    intensity_scale: float,
) -> dict[str, tuple[NDArray[Any], str]]:
    """Where every field goes, decided before the record is allocated: the extra-bytes
    dimensions added to ``header`` (name -> (probe, the field it is filled from)), and the
    field manifest VLR."""
    import laspy

    manifest: dict[str, str] = {}
    extra: dict[str, tuple[NDArray[Any], str]] = {}
    for name, values in fields.items():
        manifest[name] = (
            values.dtype.str if values.ndim == 1 else f"{values.shape[1]}{values.dtype.str}"
        )
        if name == "intensity":
            if not _intensity_is_native(values):
                extra["intensity_raw"] = (values, name)
        elif name in _COLOUR_FIELDS:
            if not has_colour:
                extra[name] = (values, name)
        elif name not in _LAS_DIMENSION_NAMES:
            extra[name] = (values, name)
    for name, (values, _) in extra.items():
        if len(name.encode()) > 32:
            raise PointCloudFormatError(
                f"field name {name!r} is longer than the 32 bytes LAS extra bytes allow", path=out
            )
        header.add_extra_dim(
            laspy.ExtraBytesParams(
                name=name,
                type=_extra_type(name, values, out),
                description="bool" if values.dtype == np.bool_ else "",
            )
        )
    header.vlrs.append(
        laspy.VLR(
            VLR_USER_ID,
            VLR_RECORD_ID,
            "standgrid field manifest",
            json.dumps({"fields": manifest, "intensity_scale": intensity_scale}).encode(),
        )
    )
    return extra


def _point_record(
    header: Any,
    parts: _TileParts,
    standard: dict[str, list[tuple[int, NDArray[Any]]]],
    extra: dict[str, tuple[NDArray[Any], str]],
    offsets: NDArray[np.float64],
    intensity_scale: float,
) -> tuple[Any, dict[str, NDArray[Any]]]:
    """The ``laspy.LasData`` of every part's points, and the bit fields' values as given to
    laspy (which packs them)."""
    import laspy

    fields = parts.fields
    record = _blank_record(header.point_format, parts.n_core, parts.n_buffer)
    points = laspy.PackedPointRecord(record, header.point_format)

    def put(target: str, name: str, convert: Any = None) -> None:
        """Field ``name`` of every part into dimension ``target`` (cast to the field's dtype)."""
        dtype = fields[name].dtype
        for start, _, part_fields in parts.parts:
            values = part_fields[name].astype(dtype, copy=False)
            record[target][start : start + len(values)] = (
                values if convert is None else convert(values)
            )

    for axis, upper in enumerate("XYZ"):
        for start, part_columns, _ in parts.parts:
            part = part_columns[axis]
            record[upper][start : start + len(part)] = _storage_ints(part, offsets[axis])
    packed: dict[str, NDArray[Any]] = {}
    for name, checked in standard.items():
        if name in (record.dtype.names or ()):
            for start, values in checked:
                record[name][start : start + len(values)] = values
        else:  # a bit field: laspy packs it
            packed[name] = np.concatenate([values for _, values in checked])
            points[name] = packed[name]
    if "intensity" in fields:
        if _intensity_is_native(fields["intensity"]):
            put("intensity", "intensity")
        else:
            put("intensity", "intensity", lambda v: _scaled_intensity(v, intensity_scale))
    for name, (values, source) in extra.items():
        to_bytes = (lambda v: v.astype(np.uint8)) if values.dtype == np.bool_ else None
        put(name, source, to_bytes)
    return laspy.LasData(header, points), packed


def _file_extent(
    out: Path,
    parts: _TileParts,
    standard: dict[str, list[tuple[int, NDArray[Any]]]],
    packed: dict[str, NDArray[Any]],
    coordinates: _Coordinates,
) -> _Extent | None:
    """What laspy would compute from the packed points, from the values at hand (None: no
    points); refuses NaN or infinite GPS times."""
    n = parts.n
    if not n:
        return None
    returns = packed.get("return_number")
    if returns is not None:
        by_return = np.bincount(returns.astype(np.int64), minlength=16)
    else:  # every point is return 1 of 1 (the blank record)
        by_return = np.zeros(16, np.int64)
        by_return[1] = n
    gps = (0.0, 0.0)
    if "gps_time" in standard:
        stored = [v for _, v in standard["gps_time"] if len(v)]
        # np.min/np.max, not min/max: a NaN extreme of any part propagates
        gps = (
            float(np.min([v.min() for v in stored])),
            float(np.max([v.max() for v in stored])),
        )
        check_finite_gps_time(*gps, stored, out)  # NaN or inf extremes: not written
    # rounding is monotonic: the stored extremes are the rounded true extremes
    offsets = coordinates.offsets
    file_lo = offsets + np.round((coordinates.all_lo - offsets) / SCALE) * SCALE
    file_hi = offsets + np.round((coordinates.all_hi - offsets) / SCALE) * SCALE
    return _Extent(file_lo, file_hi, gps, by_return)


def _tile_info(
    out: Path,
    parts: _TileParts,
    coordinates: _Coordinates,
    extent: _Extent | None,
    point_format: int,
    compressed: bool,
    crs: str,
    core_bounds: Any,
) -> TileInfo:
    """What was written: counts, the core's bounds and z statistics, points per source."""
    core, n_core = parts.core, parts.n_core
    z = core.xyz[:, 2]
    if n_core:
        core_lo, core_hi = coordinates.core_lo, coordinates.core_hi
        bounds = (*map(float, core_lo), *map(float, core_hi))
        z_stats = (
            float(core_lo[2]),
            float(core_hi[2]),
            float(z.mean()),
            # the same values in the same order as z: percentile copies them either way
            float(np.percentile(parts.parts[0][1][2], 95)),
        )
    else:
        bounds = (float("nan"),) * 6
        z_stats = (float("nan"),) * 4
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
        buffer_count=parts.n_buffer,
        bounds=bounds,
        file_bounds=file_bounds,
        z_min=z_stats[0],
        z_max=z_stats[1],
        z_mean=z_stats[2],
        z_p95=z_stats[3],
        point_format=point_format,
        compressed=compressed,
        crs=crs,
        core_bounds=core_bounds,
        points_per_source=per_source,
    )


@dataclass(frozen=True)
class _Extent:
    """What laspy's writer computes from the packed points for the header (``header.grow``:
    passes over the points, a sort of the return numbers), known beforehand; the extra
    bytes' extremes are still laspy's."""

    #: Scaled storage extremes (offset + stored integer * scale).
    mins: NDArray[np.float64]
    maxs: NDArray[np.float64]
    #: (min, max) of the stored GPS times.
    gps: tuple[float, float]
    #: Point count of each return number 0..15.
    by_return: NDArray[np.int64]


def _write_las(
    las: Any, out: Path, *, laz: bool, overwrite: bool, durable: bool, extent: _Extent | None = None
) -> None:
    """Write ``las`` to ``out`` atomically (LAZ with the parallel lazrs backend).

    With ``extent`` (points present), the header's point count, extremes and counts by
    return are set from it rather than recomputed by laspy from the packed points, and a
    LAS header is written once: the same bytes as ``las.write``, without passes over the
    record (``las``'s header is updated as laspy's writer would update its copy)."""
    import laspy

    backend = laspy.LazBackend.LazrsParallel if laz else None
    # A file object: given a path, laspy picks compression from the (temporary) suffix.
    staged = atomic_output(out, overwrite=overwrite, durable=durable)
    with staged as tmp, open(tmp, "wb") as raw, _errors_kept(raw, out) as stream:
        if extent is None or not len(las.points) or las.evlrs:
            las.write(stream, do_compress=laz, laz_backend=backend)
        elif laz:
            with laspy.LasWriter(
                stream, las.header, do_compress=True, laz_backend=backend, closefd=False
            ) as writer:
                _grow(writer.header, extent, las.points)
                writer.point_writer.write_points(las.points)
        else:  # what laspy's LasWriter writes, the header written once, complete
            header = las.header
            header.partial_reset()
            header.are_points_compressed = False
            _grow(header, extent, las.points)
            header.write_to(stream)
            stream.write(las.points.memoryview())


class _ErrorKeepingStream:
    """A binary file whose last ``OSError`` is kept: lazrs turns the errors of the Python
    writes it makes into ``LazrsError("IoError: Failed to call write")``, losing the errno
    that tells a full disk."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.error: OSError | None = None

    def write(self, data: Any) -> int:
        return int(self._call(self._stream.write, data))

    def flush(self) -> None:
        self._call(self._stream.flush)

    def _call(self, method: Any, *args: Any) -> Any:
        try:
            return method(*args)
        except OSError as exc:
            self.error = exc
            raise

    def __getattr__(self, name: str) -> Any:  # seek, tell, ...
        return getattr(self._stream, name)


@contextlib.contextmanager
def _errors_kept(stream: Any, out: Path) -> Iterator[Any]:
    """``stream`` wrapped in :class:`_ErrorKeepingStream`; an error whose writes failed for
    want of room (ENOSPC, EFBIG, EDQUOT) becomes :class:`OutOfSpaceError` naming ``out``."""
    kept = _ErrorKeepingStream(stream)
    try:
        yield kept
    except Exception as exc:
        full = out_of_space_error(exc, out) or (
            out_of_space_error(kept.error, out) if kept.error is not None else None
        )
        if full is not None and full is not exc:
            raise full from (kept.error or exc)
        raise


def _grow(header: Any, extent: _Extent, points: Any) -> None:
    """Set what laspy's ``header.grow(points)`` sets, from ``extent`` (the extra bytes'
    extremes by laspy itself)."""
    header.mins, header.maxs = extent.mins.copy(), extent.maxs.copy()
    header.min_gps_time, header.max_gps_time = extent.gps
    header.number_of_points_by_return[:] += extent.by_return[1:16].astype(np.uint64)
    header.point_count += len(points)
    extra_bytes = header.vlrs.get("ExtraBytesVlr")
    if extra_bytes:
        extra_bytes[0].grow(points)


def read_tile_record(path: str | os.PathLike[str], **options: Any) -> Any:
    """A tile's ``laspy.LasData`` as stored (its size checked first); ``options`` go to
    ``laspy.read`` (e.g. ``decompression_selection``)."""
    import laspy

    from standgrid.mission.clouds import check_las_size

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
    import laspy

    out, src = Path(path), Path(source)
    manifest = _manifest(record, src)
    if manifest is None:
        raise PointCloudFormatError("not a standgrid tile (no field manifest)", path=src)
    # Every field checked before the record is touched: a refusal leaves it as read.
    extra_types: dict[str, str] = {}
    stored_values: dict[str, NDArray[Any]] = {}
    for name, values in fields.items():
        if len(values) != len(record.points) or values.ndim != 1:
            raise PointCloudFormatError(
                f"field {name!r} has {values.shape} values for {len(record.points)} points",
                path=src,
            )
        if name in _STANDARD_FIELDS:
            stored_values[name] = las_dimension_values(name, values, src)
            if name == "gps_time" and len(values):
                times = stored_values[name]
                check_finite_gps_time(times.min(), times.max(), [times], src)
        elif name in _LAS_DIMENSION_NAMES or name == "intensity_raw":
            raise PointCloudFormatError(f"field {name!r} cannot be rewritten", path=src)
        else:
            extra_types[name] = _extra_type(name, values, src)
            stored_values[name] = values.astype(np.uint8) if values.dtype == np.bool_ else values
    added = []
    for name, values in fields.items():
        if name in extra_types:
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
    if added:  # one new record, the stored bytes copied field by field of the raw array
        stored_points = record.points.array
        record.header.add_extra_dims(added)
        points = laspy.ScaleAwarePointRecord.zeros(len(stored_points), header=record.header)
        for name in stored_points.dtype.names:
            points.array[name] = stored_points[name]
        record.points = points
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
    if laz is None:
        laz = out.suffix.lower() == ".laz"
    _write_las(record, out, laz=laz, overwrite=True, durable=durable)


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
                *_COLOUR_FIELDS,
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
