"""The one LAS 1.4 / LAZ encoder (laspy + lazrs): payload clouds and tiles alike.

:func:`encode_las` turns a cloud (and, for a tile, its withheld buffer points after it) into
a laspy record; :func:`write_las` writes a record atomically. Point data record format 6,
or 7 when the cloud has ``red``/``green``/``blue``; coordinates at ``scale`` with the
offset at the floor of the minimum (a tile: whole metres from its grid's origin).

Field mapping (``PointCloud.fields`` -> LAS), the same for every writer:

- ``gps_time``, ``point_source_id``, ``classification``, ``return_number``,
  ``number_of_returns``, ``user_data``, ``scan_angle`` (LAS 1.4 units of 0.006 degrees),
  ``scan_direction_flag``, ``edge_of_flight_line``, ``synthetic``, ``key_point``,
  ``overlap``, ``scanner_channel``, ``withheld``, ``red``/``green``/``blue`` -> the LAS
  dimension of the same name, only when every value is exactly storable
  (:mod:`standgrid.las_fields`; nothing rounded, wrapped or clipped).
- every other field -> an extra-bytes dimension of the same dtype (bool as uint8; (N, k<=3)
  arrays as k-vectors).

What a writer puts where the cloud says nothing is its :class:`LasConvention`: :data:`TILE`
(``standgrid.export.las``) or :data:`PAYLOAD` (``write_cloud`` to ``.las``/``.laz``). Every
refusal is a :class:`~standgrid.errors.PointCloudFormatError` naming the file, raised before
any file is created.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.errors import CRSError, PointCloudFormatError, out_of_space_error
from standgrid.las_fields import check_finite_gps_time, las_dimension_values
from standgrid.pointcloud import PointCloud

#: Private VLR holding the field manifest.
VLR_USER_ID = "standgrid"
VLR_RECORD_ID = 1
GENERATING_SOFTWARE = "standgrid"
INT32_MAX = 2**31 - 1

#: Fields copied into the LAS dimension of the same name.
STANDARD_FIELDS = (
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
COLOUR_FIELDS = ("red", "green", "blue")
LAS_DIMENSION_NAMES = frozenset(
    {"x", "y", "z", "intensity", "withheld", *STANDARD_FIELDS, *COLOUR_FIELDS}
)


@dataclass(frozen=True)
class LasConvention:
    """What a writer stores where the cloud says nothing (its two users differ only here)."""

    #: Header generating software and system identifier; None: laspy's.
    software: tuple[str, str] | None
    #: The private field-manifest VLR (and bool extra dimensions described ``bool``), so a
    #: reader gives back exactly the fields and dtypes written.
    manifest: bool
    #: The CRS VLR as WKT1 (GDAL flavour, what most LAS readers parse; WKT2 when WKT1
    #: cannot say it), else pyproj's default WKT (laspy's ``add_crs``).
    wkt1: bool
    #: The global encoding says adjusted standard GPS time always, else only with ``gps_time``.
    gps_time_always: bool
    #: Return number and number of returns of points whose cloud carries none (1, or 0).
    default_return: int
    #: ``intensity`` not of an unsigned type of at most 16 bits: scaled into the LAS
    #: intensity (``clip(round(value * intensity_scale), 0, 65535)``) with the exact values
    #: in the extra dimension ``intensity_raw``; else stored exactly or refused.
    keep_raw_intensity: bool


#: Tiles: core points then withheld buffer points, every point return 1 of 1.
TILE = LasConvention(
    software=(GENERATING_SOFTWARE, "standgrid tile"),
    manifest=True,
    wkt1=True,
    gps_time_always=True,
    default_return=1,
    keep_raw_intensity=True,
)
#: Payload clouds (``write_cloud``): laspy's defaults where the cloud says nothing.
PAYLOAD = LasConvention(
    software=None,
    manifest=False,
    wkt1=False,
    gps_time_always=False,
    default_return=0,
    keep_raw_intensity=False,
)


@dataclass(frozen=True)
class LasExtent:
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


@dataclass(frozen=True, eq=False)
class EncodedLas:
    """A cloud as a laspy record, and what the encoding learnt on the way."""

    las: Any  # laspy.LasData
    #: The header's extent (None without points): give it to :func:`write_las`.
    extent: LasExtent | None
    point_format: int
    #: Per-axis (min, max) of the core points (NaN when there are none).
    core_bounds: tuple[NDArray[np.float64], NDArray[np.float64]]
    #: The core coordinates as (3, N) contiguous columns.
    core_columns: NDArray[np.float64]


def crs_wkt(crs: str) -> tuple[Any, str]:
    """``crs`` ("EPSG:XXXX", WKT, ...) as a ``pyproj.CRS`` and its WKT1 (GDAL) text."""
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


def _blank_record(point_format: Any, n_core: int, n_buffer: int, returns: int) -> NDArray[np.void]:
    """A point record of zeros but return number and number of returns ``returns``, and the
    withheld flag on the ``n_buffer`` points after the core ones (bytes set by laspy's own
    packing)."""
    import laspy

    template = laspy.PackedPointRecord.zeros(2, point_format)
    template["return_number"] = np.full(2, returns, np.uint8)
    template["number_of_returns"] = np.full(2, returns, np.uint8)
    template["withheld"] = np.array([0, 1], np.uint8)
    pattern = template.array.view(np.uint8).reshape(2, -1)
    record = np.zeros(n_core + n_buffer, dtype=point_format.dtype())
    as_bytes = record.view(np.uint8).reshape(len(record), record.dtype.itemsize)
    for row, rows in ((0, slice(0, n_core)), (1, slice(n_core, None))):
        for column in np.flatnonzero(pattern[row]):
            as_bytes[rows, column] = pattern[row, column]
    return record


def _storage_ints(values: NDArray[np.float64], offset: float, scale: float) -> NDArray[np.float64]:
    """``round((values - offset) / scale)``: the stored integer coordinates (as floats)."""
    scaled = np.subtract(values, offset)
    scaled /= scale
    return np.round(scaled, out=scaled)


def _scaled_intensity(values: NDArray[Any], intensity_scale: float) -> NDArray[np.uint16]:
    """Non-native intensities as LAS intensities: rounded, scaled, clipped to 16 bits."""
    scaled = values.astype(np.float64)  # a copy, worked on in place
    scaled *= intensity_scale
    np.round(scaled, out=scaled)
    np.nan_to_num(scaled, copy=False)
    np.clip(scaled, 0, 65535, out=scaled)
    return scaled.astype(np.uint16)


def intensity_is_native(values: NDArray[Any]) -> bool:
    """Whether intensities are stored as they are (unsigned or bool, at most 16 bits)."""
    return values.dtype.kind in "ub" and values.dtype.itemsize <= 2


def extra_type(name: str, values: NDArray[Any], path: Path) -> str:
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


#: A part of the points: its first row, its (3, N) contiguous coordinate columns and its
#: fields.
_Part = tuple[int, NDArray[np.float64], dict[str, NDArray[Any]]]
#: A standard dimension's checked values: (first row, values) of each part.
_Checked = list[tuple[int, NDArray[Any]]]


@dataclass(frozen=True)
class _CloudParts:
    """The points as written: the core part, then the buffer part (if any)."""

    n_core: int
    n_buffer: int
    parts: list[_Part]
    #: Each field as a zero-length array of the dtype (and per-point shape) it is written as.
    fields: dict[str, NDArray[Any]]

    @property
    def n(self) -> int:
        """The number of points, buffer included."""
        return self.n_core + self.n_buffer


def _cloud_parts(out: Path, core: PointCloud, buffer: PointCloud | None) -> _CloudParts:
    """The core and buffer parts, their fields checked to agree (names, per-point shapes).
    The parts go straight into the record: no concatenated copies."""
    n_core = len(core)
    n_buffer = len(buffer) if buffer is not None else 0
    core_fields = dict(core.fields)
    buffer_fields = dict(buffer.fields) if buffer is not None else {}
    if n_buffer and set(core_fields) != set(buffer_fields):
        raise PointCloudFormatError(
            f"core fields {sorted(core_fields)} differ from buffer fields {sorted(buffer_fields)}",
            path=out,
        )
    for name, values in core_fields.items():
        if n_buffer and buffer_fields[name].shape[1:] != values.shape[1:]:
            raise PointCloudFormatError(
                f"field {name!r} has shape {values.shape[1:]} per core point and "
                f"{buffer_fields[name].shape[1:]} per buffer point",
                path=out,
            )
    # (x, y, z) as contiguous columns: reduced for the bounds, scaled into the record
    parts: list[_Part] = [(0, np.ascontiguousarray(core.xyz.T), core_fields)]
    if n_buffer:
        assert buffer is not None
        parts.append((n_core, np.ascontiguousarray(buffer.xyz.T), buffer_fields))
    fields = {
        name: _probe(values, buffer_fields[name] if n_buffer else None)
        for name, values in core_fields.items()
    }
    return _CloudParts(n_core, n_buffer, parts, fields)


def _standard_values(
    out: Path, parts: _CloudParts, has_colour: bool, convention: LasConvention
) -> dict[str, _Checked]:
    """The standard dimensions' values of each part, checked (and floats made integers)
    before any work; an intensity of more than one value per point refused."""
    fields = parts.fields
    exact_intensity = () if convention.keep_raw_intensity else ("intensity",)
    standard = {
        name: [
            (start, las_dimension_values(name, f[name], out, first_point=start))
            for start, _, f in parts.parts
        ]
        for name in (
            *STANDARD_FIELDS,
            "withheld",
            *exact_intensity,
            *(COLOUR_FIELDS if has_colour else ()),
        )
        if name in fields
    }
    if "intensity" in fields and fields["intensity"].ndim != 1:
        raise PointCloudFormatError(
            f"field 'intensity' has shape {fields['intensity'].shape[1:]} per point; "
            "LAS intensity holds one value per point",
            path=out,
        )
    return standard


def _las_header(
    out: Path, convention: LasConvention, point_format: int, has_gps_time: bool, crs: str | None
) -> Any:
    """A LAS 1.4 header: the convention's software, the GPS time type, the CRS VLR."""
    import laspy

    header = laspy.LasHeader(point_format=point_format, version="1.4")
    if convention.software is not None:
        header.generating_software, header.system_identifier = convention.software
    if convention.gps_time_always or has_gps_time:
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    if crs is not None:
        _add_crs(out, header, crs, wkt1=convention.wkt1)
    return header


def _add_crs(out: Path, header: Any, crs: str, *, wkt1: bool) -> None:
    """The CRS VLR: as WKT1 (GDAL flavour) with ``wkt1``, else pyproj's default WKT."""
    import laspy
    import pyproj

    if wkt1:
        parsed_crs, wkt = crs_wkt(crs)
        header.add_crs(parsed_crs)
        for vlr in header.vlrs:
            if isinstance(vlr, laspy.vlrs.known.WktCoordinateSystemVlr):
                vlr.string = wkt
        return
    try:
        header.add_crs(pyproj.CRS.from_user_input(crs))
    except pyproj.exceptions.CRSError as exc:
        raise CRSError(f"unusable CRS {crs!r}: {exc}", path=out) from exc


@dataclass(frozen=True)
class _Coordinates:
    """The core's and all points' coordinate extremes, and the offsets."""

    core_lo: NDArray[np.float64]
    core_hi: NDArray[np.float64]
    all_lo: NDArray[np.float64]
    all_hi: NDArray[np.float64]
    offsets: NDArray[np.float64]

    @classmethod
    def of(
        cls,
        out: Path,
        parts: _CloudParts,
        scale: float,
        lattice_origin: tuple[float, float] | None,
    ) -> _Coordinates:
        """Refuses non-finite coordinates and a span too large for int32 at ``scale``."""
        core_lo, core_hi = _column_bounds(parts.parts[0][1])
        all_lo, all_hi = core_lo, core_hi
        if parts.n_buffer:
            buffer_lo, buffer_hi = _column_bounds(parts.parts[1][1])
            all_lo, all_hi = buffer_lo, buffer_hi
            if parts.n_core:
                all_lo, all_hi = np.minimum(core_lo, buffer_lo), np.maximum(core_hi, buffer_hi)
        if not parts.n:
            return cls(core_lo, core_hi, all_lo, all_hi, np.zeros(3))
        # min and max propagate NaN and reach +-inf: finite extremes mean finite coordinates
        if not (np.all(np.isfinite(all_lo)) and np.all(np.isfinite(all_hi))):
            raise PointCloudFormatError("non-finite coordinates", path=out)
        offsets = _offsets(all_lo, lattice_origin)
        span = np.round((all_hi - offsets) / scale)
        if np.any(span > INT32_MAX):
            raise PointCloudFormatError(
                f"the points span {(all_hi - offsets).max():.0f} m: too large for "
                f"{scale:g} m coordinates in LAS int32",
                path=out,
            )
        return cls(core_lo, core_hi, all_lo, all_hi, offsets)

    def stored(self, scale: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The stored extremes: rounding is monotonic, so the rounded true extremes."""
        offsets = self.offsets
        file_lo = offsets + np.round((self.all_lo - offsets) / scale) * scale
        file_hi = offsets + np.round((self.all_hi - offsets) / scale) * scale
        return file_lo, file_hi


def _offsets(
    all_lo: NDArray[np.float64], lattice_origin: tuple[float, float] | None
) -> NDArray[np.float64]:
    """The floor of the minimum, or whole metres from ``lattice_origin`` below it."""
    if lattice_origin is None:
        return np.floor(all_lo)
    # Offsets are whole metres from the grid's origin: the stored lattice is then the
    # one snap_to_storage(origin) snaps to, whatever the origin.
    lattice = np.array([float(lattice_origin[0]), float(lattice_origin[1]), 0.0])
    return lattice + np.floor(all_lo - lattice)


#: An extra-bytes dimension: its probe (dtype, per-point shape) and the field it is filled from.
_Extra = tuple[NDArray[Any], str]


def _field_dimensions(
    out: Path,
    header: Any,
    fields: dict[str, NDArray[Any]],
    has_colour: bool,
    convention: LasConvention,
    intensity_scale: float,
) -> dict[str, _Extra]:
    """Where every field goes, decided before the record is allocated: the extra-bytes
    dimensions added to ``header`` (checked), and the convention's field manifest VLR."""
    import laspy

    extra = _extra_fields(fields, has_colour, convention)
    for name, (values, _) in extra.items():
        if len(name.encode()) > 32:
            raise PointCloudFormatError(
                f"field name {name!r} is longer than the 32 bytes LAS extra bytes allow", path=out
            )
        described = convention.manifest and values.dtype == np.bool_
        header.add_extra_dim(
            laspy.ExtraBytesParams(
                name=name,
                type=extra_type(name, values, out),
                description="bool" if described else "",
            )
        )
    if convention.manifest:
        manifest = {
            name: values.dtype.str if values.ndim == 1 else f"{values.shape[1]}{values.dtype.str}"
            for name, values in fields.items()
        }
        header.vlrs.append(
            laspy.VLR(
                VLR_USER_ID,
                VLR_RECORD_ID,
                "standgrid field manifest",
                json.dumps({"fields": manifest, "intensity_scale": intensity_scale}).encode(),
            )
        )
    return extra


def _extra_fields(
    fields: dict[str, NDArray[Any]], has_colour: bool, convention: LasConvention
) -> dict[str, _Extra]:
    """The fields no standard dimension holds (a non-native intensity's exact values as
    ``intensity_raw``, colours short of all three), in field order."""
    extra: dict[str, _Extra] = {}
    for name, values in fields.items():
        if name == "intensity":
            if convention.keep_raw_intensity and not intensity_is_native(values):
                extra["intensity_raw"] = (values, name)
        elif name in COLOUR_FIELDS:
            if not has_colour:
                extra[name] = (values, name)
        elif name not in LAS_DIMENSION_NAMES:
            extra[name] = (values, name)
    return extra


def _point_record(
    header: Any,
    parts: _CloudParts,
    standard: dict[str, _Checked],
    extra: dict[str, _Extra],
    coordinates: _Coordinates,
    scale: float,
    convention: LasConvention,
    intensity_scale: float,
) -> tuple[Any, dict[str, NDArray[Any]]]:
    """The ``laspy.LasData`` of every part's points, and the bit fields' values as given to
    laspy (which packs them)."""
    import laspy

    fields = parts.fields
    record = _blank_record(
        header.point_format, parts.n_core, parts.n_buffer, convention.default_return
    )
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
            record[upper][start : start + len(part)] = _storage_ints(
                part, coordinates.offsets[axis], scale
            )
    packed: dict[str, NDArray[Any]] = {}
    for name, checked in standard.items():
        if name in (record.dtype.names or ()):
            for start, values in checked:
                record[name][start : start + len(values)] = values
        else:  # a bit field: laspy packs it
            packed[name] = np.concatenate([values for _, values in checked])
            points[name] = packed[name]
    if "intensity" in fields and "intensity" not in standard:
        if intensity_is_native(fields["intensity"]):
            put("intensity", "intensity")
        else:
            put("intensity", "intensity", lambda v: _scaled_intensity(v, intensity_scale))
    for name, (values, source) in extra.items():
        to_bytes = (lambda v: v.astype(np.uint8)) if values.dtype == np.bool_ else None
        put(name, source, to_bytes)
    return laspy.LasData(header, points), packed


def _file_extent(
    out: Path,
    parts: _CloudParts,
    standard: dict[str, _Checked],
    packed: dict[str, NDArray[Any]],
    coordinates: _Coordinates,
    scale: float,
    default_return: int,
) -> LasExtent | None:
    """What laspy would compute from the packed points, from the values at hand (None: no
    points); refuses NaN or infinite GPS times."""
    n = parts.n
    if not n:
        return None
    returns = packed.get("return_number")
    if returns is not None:
        by_return = np.bincount(returns.astype(np.int64), minlength=16)
    else:  # every point has the blank record's return number
        by_return = np.zeros(16, np.int64)
        by_return[default_return] = n
    gps = (0.0, 0.0)
    if "gps_time" in standard:
        gps = _gps_extremes(out, standard["gps_time"])
    file_lo, file_hi = coordinates.stored(scale)
    return LasExtent(file_lo, file_hi, gps, by_return)


def _gps_extremes(out: Path, checked: _Checked) -> tuple[float, float]:
    """(min, max) of the stored GPS times; NaN or infinite extremes refused."""
    stored = [v for _, v in checked if len(v)]
    # np.min/np.max, not min/max: a NaN extreme of any part propagates
    gps = (
        float(np.min([v.min() for v in stored])),
        float(np.max([v.max() for v in stored])),
    )
    check_finite_gps_time(*gps, stored, out)  # NaN or inf extremes: not written
    return gps


def encode_las(
    core: PointCloud,
    *,
    path: Path,
    convention: LasConvention,
    scale: float,
    crs: str | None = None,
    buffer: PointCloud | None = None,
    lattice_origin: tuple[float, float] | None = None,
    intensity_scale: float = 1.0,
) -> EncodedLas:
    """``core`` (+ ``buffer`` points, flagged withheld, after it) as a LAS 1.4 record.

    ``path`` is the file it is for (named by errors). Offsets are the floor of the minimum,
    or with ``lattice_origin`` whole metres from it (the stored lattice is then the one of
    that origin). ``core`` and ``buffer`` must carry the same field names; neither may
    carry ``withheld`` when there is a buffer. Every field is checked before any work.
    """
    out = path
    parts = _cloud_parts(out, core, buffer)
    fields = parts.fields
    has_colour = all(c in fields for c in COLOUR_FIELDS)
    point_format = 7 if has_colour else 6
    standard = _standard_values(out, parts, has_colour, convention)
    header = _las_header(out, convention, point_format, "gps_time" in fields, crs)
    coordinates = _Coordinates.of(out, parts, scale, lattice_origin)
    header.offsets = coordinates.offsets
    header.scales = np.full(3, scale)
    extra = _field_dimensions(out, header, fields, has_colour, convention, intensity_scale)
    las, packed = _point_record(
        header, parts, standard, extra, coordinates, scale, convention, intensity_scale
    )
    extent = _file_extent(
        out, parts, standard, packed, coordinates, scale, convention.default_return
    )
    core_bounds = (coordinates.core_lo, coordinates.core_hi)
    return EncodedLas(las, extent, point_format, core_bounds, parts.parts[0][1])


def write_las_cloud(
    cloud: PointCloud, dst: Path, *, laz: bool, scale: float = 0.001, crs: str | None = None
) -> None:
    """Write a payload cloud as LAS 1.4 (``laz``: compressed), atomically: ``scale`` quantum,
    offset at the floor of the minimum, ``crs`` ("EPSG:XXXX" or WKT) as a WKT VLR; a
    ``gps_time`` field is flagged adjusted standard GPS time (:data:`PAYLOAD`)."""
    encoded = encode_las(cloud, path=dst, convention=PAYLOAD, scale=scale, crs=crs)
    write_las(encoded.las, dst, laz=laz, extent=encoded.extent)


def write_las(
    las: Any,
    out: Path,
    *,
    laz: bool,
    overwrite: bool = True,
    durable: bool = True,
    extent: LasExtent | None = None,
) -> None:
    """Write ``las`` to ``out`` atomically (LAZ with the parallel lazrs backend).

    With ``extent`` (points present), the header's point count, extremes and counts by
    return are set from it rather than recomputed by laspy from the packed points, and a
    LAS header is written once: the same bytes as ``las.write``, without passes over the
    record (``las``'s header is updated as laspy's writer would update its copy). A write
    that fails for want of room is an :class:`~standgrid.errors.OutOfSpaceError`."""
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


def _grow(header: Any, extent: LasExtent, points: Any) -> None:
    """Set what laspy's ``header.grow(points)`` sets, from ``extent`` (the extra bytes'
    extremes by laspy itself)."""
    header.mins, header.maxs = extent.mins.copy(), extent.maxs.copy()
    header.min_gps_time, header.max_gps_time = extent.gps
    header.number_of_points_by_return[:] += extent.by_return[1:16].astype(np.uint64)
    header.point_count += len(points)
    extra_bytes = header.vlrs.get("ExtraBytesVlr")
    if extra_bytes:
        extra_bytes[0].grow(points)
