"""COPC 1.0 tile writer (copclib): a tile every LAS 1.4 reader reads, streamable by bounds.

:func:`write_copc_tile` takes the arguments of :func:`~standgrid.export.las.write_tile` and
writes the same points, fields and VLRs as a Cloud Optimized Point Cloud: LAZ 1.4 whose
points are grouped into the nodes of an octree (one LAZ chunk per node) indexed by the COPC
hierarchy, so a reader (laspy's ``CopcReader``, QGIS, PDAL) fetches only the nodes a bounds
or resolution query touches, locally or over HTTP range requests.

How it is built:

1. :func:`write_tile` writes an uncompressed scratch tile beside the target: its point
   records, typed extra-bytes VLR, WKT VLR and standgrid field manifest are the ones a
   plain tile has, by construction.
2. The octree: a cube around the points; the root takes one point per cell of a
   ``resolution``-cubed grid over it (the first point of each cell, in tile order), and
   each child node takes one point per cell of the same grid over its own (half-size) cube
   from the points left, until a node has at most ``leaf_points`` points left (it takes
   them all) or cells are finer than the 1 mm lattice. Every point is in exactly one node;
   within a node points are in Morton order of the finest cells; nodes are written coarse
   to fine.
3. copclib's ``FileWriter`` compresses the nodes and writes the hierarchy.
4. copclib's Python API can declare extra bytes only as untyped bytes and no VLRs of its
   own, so the VLR block is rebuilt: COPC info first, then the scratch tile's VLRs (WKT,
   typed extra bytes, field manifest), then copclib's LAZ VLR; the data after the block
   moves by the size difference, and every absolute offset behind it (header, COPC info,
   LAZ chunk table pointer, hierarchy entries) moves with it. Left out: copclib's extents
   VLR (``copc``/10000, an extension outside COPC 1.0, all zeros when nodes are given as
   raw records: a wrong number) and its WKT EVLR (the WKT is the scratch tile's VLR).

Written atomically (temporary sibling, fsync, rename). Point order differs from the plain
tile's (grouped by node); :func:`~standgrid.export.las.read_tile` reads a COPC tile back to
the same points and fields.
"""

from __future__ import annotations

import os
import struct
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output, temporary_sibling
from standgrid.errors import OutOfSpaceError, PointCloudFormatError, short_of_room_error
from standgrid.export.las import SCALE, TileInfo, rewrite_tile, write_tile
from standgrid.pointcloud import PointCloud

#: Cells per axis of the sampling grid of every node (PDAL/untwine use 128).
RESOLUTION = 128
#: A node with at most this many points left takes them all (a leaf).
LEAF_POINTS = 16_384
#: COPC's VLR/EVLR ids.
COPC_USER_ID = b"copc"
COPC_INFO_RECORD = 1
COPC_HIERARCHY_RECORD = 1000
LAZ_USER_ID = b"laszip encoded"
_HEADER_SIZE = 375
_VLR_HEADER = 54
_EVLR_HEADER = 60
_ENTRY = struct.Struct("<4iQii")  # hierarchy entry: key (d, x, y, z), offset, bytes, points


def is_copc(path: str | os.PathLike[str]) -> bool:
    """True when a tile path names a COPC file (``*.copc.laz``)."""
    return Path(path).name.lower().endswith(".copc.laz")


_MORTON_BITS = 21  # per axis: three fit in a uint64


def _spread(v: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """Bits ``b`` of 21-bit integers moved to ``3 * b`` (Morton interleaving)."""
    v = v & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _compact(v: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """The inverse of :func:`_spread`."""
    v = v & np.uint64(0x1249249249249249)
    for shift, mask in (
        (2, 0x10C30C30C30C30C3),
        (4, 0x100F00F00F00F00F),
        (8, 0x1F0000FF0000FF),
        (16, 0x1F00000000FFFF),
        (32, 0x1FFFFF),
    ):
        v = (v | (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def octree_nodes(
    ijk: NDArray[np.int64],
    edge: int,
    *,
    resolution: int = RESOLUTION,
    leaf_points: int = LEAF_POINTS,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Assign integer lattice points to octree nodes; ``(keys, node_of_point, grouped)``.

    ``ijk``: (N, 3) integer coordinates counted from the cube's corner, in ``[0, edge]``
    (the cube is closed: a point on its far face is in the last node). ``keys``: (M, 4)
    node keys ``(depth, x, y, z)``, coarse to fine; ``node_of_point``: (N,) index into
    ``keys``; ``grouped``: the input indices node by node (in ``keys`` order; within a
    node in finest-cell order). Exact integer arithmetic: node ``k`` of depth ``d`` holds
    ``k * edge / 2**d <= u < (k + 1) * edge / 2**d`` on each axis; a node takes the first
    point (in input order) of each cell of its ``resolution``-cubed grid, or all its
    points when at most ``leaf_points`` are left. ``resolution`` is a power of two.

    One sort: cells of every depth are prefixes of the finest cells' Morton codes
    (``floor(floor(x) / 2) == floor(x / 2)``), so each depth is a pass over runs.
    """
    if resolution < 1 or resolution & (resolution - 1):
        raise ValueError(f"resolution {resolution} is not a power of two")
    n = len(ijk)
    edge = max(int(edge), 1)
    r_bits = resolution.bit_length() - 1
    finest = 0  # cells of the finest depth: at least the lattice, at most 2**21 per axis
    while (resolution << finest) < edge and (resolution << (finest + 1)) <= 1 << _MORTON_BITS:
        finest += 1
    cells = resolution << finest
    c = np.minimum((np.asarray(ijk, dtype=np.int64) * cells) // edge, cells - 1).astype(np.uint64)
    morton = _spread(c[:, 0]) << np.uint64(2) | _spread(c[:, 1]) << np.uint64(1) | _spread(c[:, 2])
    order = np.argsort(morton, kind="stable")  # ties: input order
    code = morton[order]
    rank = np.empty(n, dtype=np.int64)  # sorted position of each input point
    rank[order] = np.arange(n)
    remaining = np.ones(n, dtype=bool)  # over sorted positions
    node_of_point = np.full(n, -1, dtype=np.int64)
    keys: list[NDArray[np.int64]] = []
    grouped: list[NDArray[np.int64]] = []
    count = 0
    for depth in range(finest + 1):
        pos = np.flatnonzero(remaining)
        if not len(pos):
            break
        cell = code[pos] >> np.uint64(3 * (finest - depth))
        node = cell >> np.uint64(3 * r_bits)
        node_start = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
        if depth == finest:
            take = np.ones(len(pos), dtype=bool)
        else:
            sizes = np.diff(np.r_[node_start, len(pos)])
            take = np.repeat(sizes <= leaf_points, sizes)
            cell_start = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
            # the first point in input order of each cell (a run is in finest-cell order)
            first = np.minimum.reduceat(order[pos], cell_start)
            take[np.searchsorted(pos, rank[first])] = True
        taken = pos[take]
        taken_node = node[take]
        starts = np.r_[True, taken_node[1:] != taken_node[:-1]]
        index = count + np.cumsum(starts) - 1
        node_of_point[order[taken]] = index
        grouped.append(order[taken])
        unique_nodes = taken_node[starts]
        x, y, z = (_compact(unique_nodes >> np.uint64(2 - axis)) for axis in range(3))
        keys.append(np.column_stack([np.full(len(unique_nodes), depth), x, y, z]).astype(np.int64))
        count += len(unique_nodes)
        remaining[taken] = False
    if not keys:
        return np.zeros((0, 4), dtype=np.int64), node_of_point, np.zeros(0, dtype=np.int64)
    return np.concatenate(keys), node_of_point, np.concatenate(grouped)


def write_copc_tile(
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
    resolution: int = RESOLUTION,
    leaf_points: int = LEAF_POINTS,
    durable: bool = True,
) -> TileInfo:
    """Write ``core`` (+ ``buffer`` points flagged withheld) as one COPC 1.0 tile.

    The arguments are :func:`~standgrid.export.las.write_tile`'s (``laz`` must be None or
    True: COPC is compressed), plus the octree's ``resolution`` (sampling cells per node
    axis) and ``leaf_points``. Returns the :class:`TileInfo` a plain tile would have.
    Fsynced unless ``durable=False`` (a tile staged in a transaction: its commit fsyncs).
    """
    out = Path(path)
    if laz is False:
        raise PointCloudFormatError("a COPC tile is always compressed (laz=False given)", path=out)
    if resolution < 1 or resolution & (resolution - 1) or leaf_points < 1:
        raise PointCloudFormatError(
            f"resolution {resolution} must be a power of two, leaf_points {leaf_points} positive",
            path=out,
        )
    if out.exists() and not overwrite:  # before any work; atomic_output checks again
        from standgrid.errors import OVERWRITE_HINT, OutputExistsError

        raise OutputExistsError(f"exists ({OVERWRITE_HINT})", path=out)
    scratch = temporary_sibling(out, "scratch")
    raw = temporary_sibling(out, "copclib")
    try:
        try:
            info = write_tile(
                scratch,
                core,
                crs=crs,
                buffer=buffer,
                laz=False,
                core_bounds=core_bounds,
                intensity_scale=intensity_scale,
                overwrite=True,
                lattice_origin=lattice_origin,
            )
        except (PointCloudFormatError, OutOfSpaceError) as exc:  # named with the tile
            if exc.path != scratch:
                raise
            raise type(exc)(exc.message, path=out) from exc
        with atomic_output(out, overwrite=overwrite, durable=durable) as tmp:
            _scratch_to_copc(scratch, raw, tmp, resolution=resolution, leaf_points=leaf_points)
    finally:
        scratch.unlink(missing_ok=True)
        raw.unlink(missing_ok=True)
    return replace(info, path=out, compressed=True)


def rewrite_copc_tile(
    record: Any,
    path: str | os.PathLike[str],
    fields: dict[str, NDArray[Any]],
    *,
    source: str | os.PathLike[str],
    durable: bool = True,
) -> None:
    """:func:`~standgrid.export.las.rewrite_tile` for a COPC tile: the stored record with
    ``fields`` set, indexed again into an octree (the same nodes: the points have not moved)."""
    out = Path(path)
    header = record.header
    header.vlrs = [v for v in header.vlrs if _user_id(v) != COPC_USER_ID.decode()]
    header.evlrs = [v for v in (header.evlrs or []) if _user_id(v) != COPC_USER_ID.decode()]
    scratch = temporary_sibling(out, "scratch")
    raw = temporary_sibling(out, "copclib")
    try:
        rewrite_tile(record, scratch, fields, source=source, laz=False, durable=False)
        with atomic_output(out, overwrite=True, durable=durable) as tmp:
            _scratch_to_copc(scratch, raw, tmp, resolution=RESOLUTION, leaf_points=LEAF_POINTS)
    finally:
        scratch.unlink(missing_ok=True)
        raw.unlink(missing_ok=True)


def _user_id(vlr: Any) -> str:
    return str(getattr(vlr, "user_id", "")).rstrip("\x00")


def _scratch_to_copc(
    scratch: Path, raw: Path, target: Path, *, resolution: int, leaf_points: int
) -> None:
    import copclib
    import laspy

    las = laspy.read(scratch)
    header = las.header
    records = las.points.array
    n = len(records)
    ijk_stored = np.column_stack(
        [
            records["X"].astype(np.int64),
            records["Y"].astype(np.int64),
            records["Z"].astype(np.int64),
        ]
    )
    # The cube copclib's reader checks nodes against (and the COPC info states): corner at
    # the header minimum, edge the largest extent (in lattice steps).
    corner = ijk_stored.min(axis=0) if n else np.zeros(3, np.int64)
    edge = int((ijk_stored.max(axis=0) - corner).max()) if n else 1
    keys, node_of_point, order = octree_nodes(
        ijk_stored - corner, edge, resolution=resolution, leaf_points=leaf_points
    )
    starts = np.r_[0, np.cumsum(np.bincount(node_of_point, minlength=len(keys)))]

    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    half_m = max(edge, 1) * SCALE / 2
    center = offsets + corner * scales + half_m
    eb_size = header.point_format.num_extra_bytes
    config = copclib.CopcConfigWriter(
        header.point_format.id,
        copclib.Vector3(*map(float, scales)),
        copclib.Vector3(*map(float, offsets)),
        "",
        copclib.EbVlr(eb_size),
    )
    h = config.las_header
    h.min = copclib.Vector3(*map(float, header.mins if n else np.zeros(3)))
    h.max = copclib.Vector3(*map(float, header.maxs if n else np.zeros(3)))
    h.generating_software = header.generating_software
    h.system_identifier = header.system_identifier
    h.global_encoding = int(header.global_encoding.value)
    h.points_by_return = [int(v) for v in header.number_of_points_by_return]
    if header.creation_date is not None:
        h.creation_day = header.creation_date.timetuple().tm_yday
        h.creation_year = header.creation_date.year
    try:
        writer = copclib.FileWriter(str(raw), config)
        try:
            if n:
                data = records[order]
                for k, (d, x, y, z) in enumerate(keys):
                    chunk = data[starts[k] : starts[k + 1]]  # contiguous: no copy
                    writer.AddNode(
                        copclib.VoxelKey(int(d), int(x), int(y), int(z)),
                        copclib.VectorChar(np.frombuffer(chunk, dtype=np.int8)),
                    )
        finally:
            writer.Close()
    except (RuntimeError, ValueError, TypeError) as exc:
        _refuse_when_full(exc, raw, target)
        raise PointCloudFormatError(
            f"copclib could not write the tile: {exc}", path=target
        ) from exc
    if raw.stat().st_size == 0 or (n and raw.stat().st_size < _HEADER_SIZE):
        _refuse_when_full(None, raw, target)
    gps = records["gps_time"] if n else np.zeros(1)
    # COPC info: the cube (the one copclib's reader derives from the header bounds, stated
    # for readers that take it from the info: laspy, PDAL), GPS time range.
    cube = (*map(float, center), half_m, 2 * half_m / resolution)
    own_vlrs = [_vlr_bytes(v) for v in _raw_vlrs(scratch)]
    _relocate(raw, target, own_vlrs, info=(*cube, float(gps.min()), float(gps.max())))


def _refuse_when_full(exc: BaseException | None, raw: Path, target: Path) -> None:
    """Raise :class:`OutOfSpaceError` (naming ``target``) when copclib's write of ``raw``
    failed for want of room (its C++ streams report no errno:
    :func:`~standgrid.errors.short_of_room_error` looks at the room left)."""
    full = short_of_room_error(exc, raw, target)
    if full is not None:
        raise full from exc


def _raw_vlrs(path: Path) -> list[tuple[bytes, int, bytes, bytes]]:
    """``(user_id, record_id, description, data)`` of every VLR of a LAS file, from its bytes."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_SIZE)
        size = os.fstat(f.fileno()).st_size
        header_size, point_offset, count = struct.unpack_from("<HII", head, 94)
        if point_offset > size or count * _VLR_HEADER > point_offset:
            raise PointCloudFormatError(
                f"{count} VLRs do not fit before the point data at byte {point_offset}", path=path
            )
        f.seek(header_size)
        block = f.read(point_offset - header_size)
    vlrs = []
    pos = 0
    for _ in range(count):
        if pos + _VLR_HEADER > len(block):
            raise PointCloudFormatError("VLR headers run past the point data", path=path)
        user_id = block[pos + 2 : pos + 18]
        record_id, length = struct.unpack_from("<HH", block, pos + 18)
        description = block[pos + 22 : pos + 54]
        if pos + _VLR_HEADER + length > len(block):
            raise PointCloudFormatError(f"VLR {user_id!r} runs past the point data", path=path)
        vlrs.append((user_id, record_id, description, block[pos + 54 : pos + 54 + length]))
        pos += _VLR_HEADER + length
    return vlrs


def _vlr_bytes(vlr: tuple[bytes, int, bytes, bytes]) -> bytes:
    user_id, record_id, description, data = vlr
    return struct.pack("<H16sHH32s", 0, user_id, record_id, len(data), description) + data


def _relocate(raw: Path, target: Path, own_vlrs: list[bytes], *, info: tuple[float, ...]) -> None:
    """Copy copclib's file ``raw`` to ``target`` with the VLR block rebuilt (see the module
    docstring) and every absolute offset after it moved accordingly.

    ``info``: the COPC info's cube ``(center_x, center_y, center_z, halfsize, spacing)``
    and GPS time ``(minimum, maximum)``."""
    vlrs = _raw_vlrs(raw)
    copc = [v for v in vlrs if v[0].rstrip(b"\0") == COPC_USER_ID and v[1] == COPC_INFO_RECORD]
    lazvlr = [v for v in vlrs if v[0].rstrip(b"\0") == LAZ_USER_ID]
    if len(copc) != 1 or len(lazvlr) != 1:
        raise PointCloudFormatError("copclib wrote no COPC info or LAZ VLR", path=raw)
    size = raw.stat().st_size
    with open(raw, "rb") as src:
        header = bytearray(src.read(_HEADER_SIZE))
        old_points = struct.unpack_from("<I", header, 96)[0]
        evlr_start, evlr_count = struct.unpack_from("<QI", header, 235)
        if not old_points <= evlr_start <= size:
            raise PointCloudFormatError("EVLRs start outside the file", path=raw)
        src.seek(old_points)
        body = src.read(evlr_start - old_points)
        evlr_bytes = src.read(size - evlr_start)
    # EVLRs: keep only the hierarchy (copclib also writes its WKT as an EVLR).
    hierarchy: bytes | None = None
    pos = 0
    for _ in range(evlr_count):
        if pos + _EVLR_HEADER > len(evlr_bytes):
            raise PointCloudFormatError("EVLR headers run past the end of the file", path=raw)
        user_id = evlr_bytes[pos + 2 : pos + 18].rstrip(b"\0")
        record_id = struct.unpack_from("<H", evlr_bytes, pos + 18)[0]
        length = struct.unpack_from("<Q", evlr_bytes, pos + 20)[0]
        if pos + _EVLR_HEADER + length > len(evlr_bytes):
            raise PointCloudFormatError("an EVLR runs past the end of the file", path=raw)
        if user_id == COPC_USER_ID and record_id == COPC_HIERARCHY_RECORD:
            hierarchy = evlr_bytes[pos : pos + _EVLR_HEADER + length]
        pos += _EVLR_HEADER + length
    if hierarchy is None:
        raise PointCloudFormatError("copclib wrote no COPC hierarchy", path=raw)

    info_vlr = bytearray(_vlr_bytes(copc[0]))
    new_points = _HEADER_SIZE + len(info_vlr) + sum(map(len, own_vlrs)) + len(_vlr_bytes(lazvlr[0]))
    delta = new_points - old_points
    new_evlr = evlr_start + delta
    # The hierarchy's entries point at node chunks in the body: all move by delta.
    entries = bytearray(hierarchy[_EVLR_HEADER:])
    if len(entries) % _ENTRY.size:
        raise PointCloudFormatError("a COPC hierarchy page of a partial entry", path=raw)
    for at in range(0, len(entries), _ENTRY.size):
        d, x, y, z, offset, nbytes, npoints = _ENTRY.unpack_from(entries, at)
        if npoints != 0:
            _ENTRY.pack_into(entries, at, d, x, y, z, offset + delta, nbytes, npoints)
    # COPC info: cube, spacing, root hierarchy page offset and size, GPS time range.
    cx, cy, cz, half, spacing, gps_min, gps_max = info
    struct.pack_into(
        "<5dQQdd",
        info_vlr,
        _VLR_HEADER,
        cx,
        cy,
        cz,
        half,
        spacing,
        new_evlr + _EVLR_HEADER,
        len(entries),
        gps_min,
        gps_max,
    )
    block = b"".join([bytes(info_vlr), *own_vlrs, _vlr_bytes(lazvlr[0])])
    struct.pack_into("<II", header, 96, new_points, 2 + len(own_vlrs))
    struct.pack_into("<QI", header, 235, new_evlr, 1)
    # LAZ: the point data starts with the (absolute) offset of the chunk table.
    body_head = bytearray(body[:8])
    chunk_table = struct.unpack_from("<q", body_head)[0]
    struct.pack_into("<q", body_head, 0, chunk_table + delta)
    with open(target, "wb") as dst:
        dst.write(header)
        dst.write(block)
        dst.write(body_head)
        dst.write(memoryview(body)[8:])
        dst.write(hierarchy[:_EVLR_HEADER])
        dst.write(entries)
