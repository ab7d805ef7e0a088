"""COPC 1.0 tile writer: a tile every LAS 1.4 reader reads, streamable by bounds.

:func:`write_copc_tile` takes the arguments of :func:`~standgrid.export.las.write_tile` and
writes the same points, fields and VLRs as a Cloud Optimized Point Cloud: LAZ 1.4 whose
points are grouped into the nodes of an octree (one LAZ chunk per node) indexed by the COPC
hierarchy, so a reader (laspy's ``CopcReader``, QGIS, PDAL) fetches only the nodes a bounds
or resolution query touches, locally or over HTTP range requests.

How it is built, in memory (no scratch file):

1. The record is the plain tile's (:func:`~standgrid.export.las.encode_tile`, the one LAS
   encoder): its point records, header, typed extra-bytes VLR, WKT VLR and standgrid field
   manifest are a plain tile's by construction.
2. The octree (:func:`octree_nodes`): a cube around the points; the root takes one point
   per cell of a ``resolution``-cubed grid over it (the first point of each cell, in tile
   order), and each child node takes one point per cell of the same grid over its own
   (half-size) cube from the points left, until a node has at most ``leaf_points`` points
   left (it takes them all) or cells reach the finest depth. Every point is in exactly one
   node; within a node points keep the tile's (scan) order; nodes are written coarse to
   fine.
3. lazrs (laspy's LAZ codec) compresses each node as one variable-size LAZ chunk and
   writes the chunk table. The rest is COPC 1.0's few fixed structs, written here: the
   COPC info VLR first (cube, spacing, root hierarchy page, GPS time range), then the
   plain tile's VLRs, then the LAZ VLR (variable-size chunks); the hierarchy is one EVLR
   page whose entries name each node's chunk (offset, bytes, points, from the chunk
   table). The tests read every tile back with laspy (as LAZ and with ``CopcReader``) and
   with copclib's reader, which validates the hierarchy against the points.

Written atomically (temporary sibling, fsync, rename). Point order differs from the plain
tile's (grouped by node); :func:`~standgrid.export.las.read_tile` reads a COPC tile back to
the same points and fields.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid._atomic import atomic_output
from standgrid.clouds.las_write import LasExtent, _errors_kept, _grow
from standgrid.errors import PointCloudFormatError
from standgrid.export.las import TileInfo, encode_tile, set_tile_fields, tile_info
from standgrid.pointcloud import PointCloud

#: Cells per axis of the sampling grid of every node (PDAL/untwine use 128).
RESOLUTION = 128
#: A node with at most this many points left takes them all (a leaf). Each node is a LAZ
#: chunk, and every chunk starts its compression models afresh: small nodes cost CPU (a
#: 250k-point tile of 16k-point leaves is ~50 chunks, ~30 % slower to compress than ~17).
LEAF_POINTS = 65_536
#: Tiles of at least this many points are compressed on the lazrs thread pool (a chunk per
#: task); smaller ones on the calling thread (tiling already writes two tiles at once, and
#: the pool costs ~20 % more CPU on a small tile).
PARALLEL_POINTS = 1_000_000
#: COPC's VLR/EVLR ids.
COPC_USER_ID = b"copc"
COPC_INFO_RECORD = 1
COPC_HIERARCHY_RECORD = 1000
LAZ_USER_ID = b"laszip encoded"
LAZ_RECORD = 22204
_HEADER_SIZE = 375
_VLR_HEADER = 54
_EVLR_HEADER = 60


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


_SPREAD_16: NDArray[np.uint64] | None = None  # _spread of every 16-bit value (512 KiB)


def _morton(c: NDArray[np.int64], cells: int) -> NDArray[np.uint64]:
    """Morton codes of (N, 3) cell coordinates in ``[0, cells)`` (x the most significant of
    each bit triple); a table look-up per axis when ``cells <= 2**16``."""
    global _SPREAD_16
    if cells > 1 << 16:
        u = c.astype(np.uint64)
        return (
            _spread(u[:, 0]) << np.uint64(2) | _spread(u[:, 1]) << np.uint64(1) | _spread(u[:, 2])
        )
    if _SPREAD_16 is None:
        _SPREAD_16 = _spread(np.arange(1 << 16, dtype=np.uint64))
    table = _SPREAD_16
    return (table[c[:, 0]] << np.uint64(2)) | (table[c[:, 1]] << np.uint64(1)) | table[c[:, 2]]


def _stable_order(
    code: NDArray[np.uint64], code_bits: int
) -> tuple[NDArray[np.int64], NDArray[np.uint64]]:
    """``(order, code[order])``: ``code`` (values below ``2**code_bits``) sorted, ties in
    input order; what ``argsort(kind="stable")`` gives, in a fraction of its time.

    The input index goes into the low bits of a 64-bit key and the keys are sorted by
    value (numpy's vectorised sort, no indirection); when code and index do not fit in 64
    bits, the ``s`` lowest code bits are sorted first (a stable radix argsort of 16 bits)
    and their rank stands in for the index (least significant digit first: still stable)."""
    n = len(code)
    idx_bits = max(n - 1, 1).bit_length()
    spill = code_bits + idx_bits - 64
    if spill > 16:  # too wide for two passes (over 2**21 points and finer than 2**21 cells)
        order = np.argsort(code, kind="stable")
        return order, code[order]
    first: NDArray[np.int64] | None = None
    high = code
    if spill > 0:
        first = np.argsort((code & np.uint64((1 << spill) - 1)).astype(np.uint16), kind="stable")
        high = code[first] >> np.uint64(spill)
    key = (high << np.uint64(idx_bits)) | np.arange(n, dtype=np.uint64)
    key.sort()
    order = (key & np.uint64((1 << idx_bits) - 1)).astype(np.int64)
    if first is not None:
        order = first[order]
    return order, code[order]


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
    node in input order: a scan's order, which LAZ compresses best). Exact integer
    arithmetic: node ``k`` of depth ``d`` holds ``k * edge / 2**d <= u < (k + 1) * edge /
    2**d`` on each axis; a node takes the first point (in input order) of each cell of its
    ``resolution``-cubed grid, or all its points when at most ``leaf_points`` are left, or
    at the finest depth (cells at the lattice step, or as fine as the Morton code of one
    64-bit sort key allows beside the point index: ``3 * depth`` bits + index bits <= 64,
    at least 2 mm over a 33 m cube for 2 M points). ``resolution`` is a power of two.

    One sort: cells of every depth are prefixes of the finest cells' Morton codes
    (``floor(floor(x) / 2) == floor(x / 2)``), so each depth is a pass over runs.
    """
    if resolution < 1 or resolution & (resolution - 1):
        raise ValueError(f"resolution {resolution} is not a power of two")
    n = len(ijk)
    edge = max(int(edge), 1)
    r_bits = resolution.bit_length() - 1
    # The finest depth: its cells at least the lattice step, and its Morton codes (3 bits a
    # depth) beside the point index in 64 bits, so that one sort of values orders them.
    idx_bits = max(n - 1, 1).bit_length()
    most = min(_MORTON_BITS, (64 - idx_bits) // 3)
    finest = 0
    while (resolution << finest) < edge and (resolution << (finest + 1)) <= 1 << most:
        finest += 1
    cells = resolution << finest
    c = np.minimum((np.asarray(ijk, dtype=np.int64) * cells) // edge, cells - 1)
    morton = _morton(c, cells)
    order, code = _stable_order(morton, 3 * (r_bits + finest))
    del c, morton
    node_of_point = np.full(n, -1, dtype=np.int64)
    keys: list[NDArray[np.int64]] = []
    grouped: list[NDArray[np.int64]] = []
    count = 0
    for depth in range(finest + 1):  # code, order: the points left, in sorted order
        if not len(code):
            break
        cell = code >> np.uint64(3 * (finest - depth))
        node = cell >> np.uint64(3 * r_bits)
        if depth == finest:
            take = np.ones(len(code), dtype=bool)
        else:
            node_start = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
            sizes = np.diff(np.r_[node_start, len(code)])
            take = np.repeat(sizes <= leaf_points, sizes)
            cell_start = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
            # the first point in input order of each cell (a run is in finest-cell order):
            # where the input index is its run's least (indices are distinct)
            first = np.minimum.reduceat(order, cell_start)
            take |= order == np.repeat(first, np.diff(np.r_[cell_start, len(code)]))
        taken_order = order[take]
        taken_node = node[take]
        starts = np.r_[True, taken_node[1:] != taken_node[:-1]]
        index = np.cumsum(starts) - 1
        # within a node, input order (a scan's order: LAZ compresses it better)
        if 2 * idx_bits <= 64:
            by_node = (index.astype(np.uint64) << np.uint64(idx_bits)) | taken_order.astype(
                np.uint64
            )
            by_node.sort()
            members = (by_node & np.uint64((1 << idx_bits) - 1)).astype(np.int64)
        else:  # over 2**32 points
            members = taken_order[np.lexsort((taken_order, index))]
        node_of_point[members] = count + index
        grouped.append(members)
        unique_nodes = taken_node[starts]
        x, y, z = (_compact(unique_nodes >> np.uint64(2 - axis)) for axis in range(3))
        keys.append(np.column_stack([np.full(len(unique_nodes), depth), x, y, z]).astype(np.int64))
        count += len(unique_nodes)
        left = ~take
        code, order = code[left], order[left]
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
    _check_octree(out, resolution, leaf_points)
    if out.exists() and not overwrite:  # before any work; atomic_output checks again
        from standgrid.errors import OVERWRITE_HINT, OutputExistsError

        raise OutputExistsError(f"exists ({OVERWRITE_HINT})", path=out)
    encoded, core, n_buffer = encode_tile(
        out,
        core,
        crs=crs,
        buffer=buffer,
        lattice_origin=lattice_origin,
        intensity_scale=intensity_scale,
    )
    _write_copc(
        encoded.las,
        out,
        extent=encoded.extent,
        overwrite=overwrite,
        durable=durable,
        resolution=resolution,
        leaf_points=leaf_points,
    )
    return tile_info(out, core, n_buffer, encoded, True, crs, core_bounds)


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
    header.vlrs = [v for v in header.vlrs if _user_id(v) not in _OWN_USER_IDS]
    header.evlrs = [v for v in (header.evlrs or []) if _user_id(v) not in _OWN_USER_IDS]
    set_tile_fields(record, fields, source=source)
    _write_copc(
        record,
        out,
        extent=None,
        overwrite=True,
        durable=durable,
        resolution=RESOLUTION,
        leaf_points=LEAF_POINTS,
    )


_OWN_USER_IDS = (COPC_USER_ID.decode(), LAZ_USER_ID.decode())


def _user_id(vlr: Any) -> str:
    return str(getattr(vlr, "user_id", "")).rstrip("\x00")


def _check_octree(out: Path, resolution: int, leaf_points: int) -> None:
    if resolution < 1 or resolution & (resolution - 1) or leaf_points < 1:
        raise PointCloudFormatError(
            f"resolution {resolution} must be a power of two, leaf_points {leaf_points} positive",
            path=out,
        )


def _write_copc(
    las: Any,
    out: Path,
    *,
    extent: LasExtent | None,
    overwrite: bool,
    durable: bool,
    resolution: int,
    leaf_points: int,
) -> None:
    """Write the record ``las`` (a laspy ``LasData`` of an uncompressed tile) to ``out``
    atomically as COPC (see the module docstring); ``extent``: the encoder's (or None: the
    header is updated from the points)."""
    import lazrs

    header_block = _uncompressed_header(las, extent)
    records = las.points.array
    n = len(records)
    # The cube readers check nodes against (copclib derives it from the header bounds, laspy
    # and PDAL take it from the COPC info): corner at the minimum, edge the largest extent
    # (in lattice steps).
    axes = [records[c] for c in ("X", "Y", "Z")]
    corner = np.array([int(a.min()) for a in axes] if n else [0, 0, 0], dtype=np.int64)
    edge = max(int(a.max()) - int(lo) for a, lo in zip(axes, corner, strict=True)) if n else 1
    ijk = np.empty((n, 3), dtype=np.int64)
    for axis, values in enumerate(axes):
        np.subtract(values, corner[axis], out=ijk[:, axis], dtype=np.int64)
    keys, node_of_point, order = octree_nodes(
        ijk, edge, resolution=resolution, leaf_points=leaf_points
    )
    del ijk
    counts = np.bincount(node_of_point, minlength=len(keys)) if n else np.zeros(0, np.int64)
    starts = np.r_[0, np.cumsum(counts)]
    # the records grouped by node, coarse to fine; a chunk per node (views: no copies)
    size = records.dtype.itemsize
    rows = np.frombuffer(records, np.uint8).reshape(n, size)  # byte rows: a plain take
    data = np.take(rows, order, axis=0).reshape(-1)
    chunks = [data[starts[k] * size : starts[k + 1] * size] for k in range(len(keys))]

    scales = np.asarray(las.header.scales)
    half_m = max(edge, 1) * float(scales.max()) / 2  # the tile's scales are equal (SCALE)
    center = np.asarray(las.header.offsets) + corner * scales + half_m
    gps = (float(records["gps_time"].min()), float(records["gps_time"].max())) if n else (0.0, 0.0)
    point_format = las.header.point_format
    laz_vlr = lazrs.LazVlr.new_for_compression(
        point_format.id, point_format.num_extra_bytes, use_variable_size_chunks=True
    )
    own_vlrs = [_vlr_bytes(v) for v in _parse_vlrs(header_block, out)]
    info = bytearray(_vlr_bytes((COPC_USER_ID, COPC_INFO_RECORD, b"COPC info", bytes(160))))
    laz = _vlr_bytes(
        (LAZ_USER_ID, LAZ_RECORD, b"lazrs variable size chunks", laz_vlr.record_data())
    )
    point_start = _HEADER_SIZE + len(info) + sum(map(len, own_vlrs)) + len(laz)
    header = bytearray(header_block[:_HEADER_SIZE])
    header[104] |= 0x80  # point data compressed (LAZ)
    struct.pack_into("<II", header, 96, point_start, 2 + len(own_vlrs))
    with (
        atomic_output(out, overwrite=overwrite, durable=durable) as tmp,
        open(tmp, "w+b") as raw,
        _errors_kept(raw, out) as stream,
    ):
        stream.write(b"".join([header, info, *own_vlrs, laz]))
        _compress_nodes(stream, laz_vlr, chunks, parallel=n >= PARALLEL_POINTS)
        stream.seek(point_start)
        table = lazrs.read_chunk_table(stream, laz_vlr)
        if [p for p, _ in table] != counts.tolist():
            raise PointCloudFormatError(
                f"the LAZ chunk table lists {len(table)} chunks, not the octree's "
                f"{len(keys)} nodes",
                path=out,
            )
        # The hierarchy: one page, an entry per node naming its chunk.
        sizes = np.array([b for _, b in table], dtype=np.int64)
        entries = np.zeros(len(keys), dtype=_ENTRY_DTYPE)
        entries["key"] = keys
        entries["offset"] = point_start + 8 + np.cumsum(sizes) - sizes  # after the table offset
        entries["bytes"] = sizes
        entries["points"] = counts
        evlr_start = stream.seek(0, os.SEEK_END)
        stream.write(
            struct.pack(
                "<H16sHQ32s",
                0,
                COPC_USER_ID,
                COPC_HIERARCHY_RECORD,
                entries.nbytes,
                b"EPT hierarchy",
            )
        )
        stream.write(entries.tobytes())
        # The COPC info: the cube, the root's spacing, the (only) hierarchy page and the GPS
        # time range; then the header's EVLR pointer.
        struct.pack_into(
            "<5dQQdd",
            info,
            _VLR_HEADER,
            *map(float, center),
            half_m,
            2 * half_m / resolution,
            evlr_start + _EVLR_HEADER,
            entries.nbytes,
            *gps,
        )
        stream.seek(_HEADER_SIZE)
        stream.write(info)
        stream.seek(235)
        stream.write(struct.pack("<QI", evlr_start, 1))
        stream.flush()


def _compress_nodes(stream: Any, laz_vlr: Any, chunks: list[Any], *, parallel: bool) -> None:
    """Compress ``chunks`` (the nodes' point bytes) as variable-size LAZ chunks, one each,
    the offset to the chunk table first and the table after them (lazrs writes both)."""
    import lazrs

    if not chunks:  # no points: the offset to an empty table, the table
        stream.write(struct.pack("<q", stream.tell() + 8))
        lazrs.write_chunk_table(stream, [], laz_vlr)
        return
    if parallel and len(chunks) > 1:
        pool = lazrs.ParLasZipCompressor(stream, laz_vlr)
        pool.compress_chunks(chunks)
        pool.done()
        return
    # (lazrs's own LasZipCompressor.compress_chunks closes a chunk after the last one, and
    # done() one more: an empty chunk that no node names.)
    compressor = lazrs.LasZipCompressor(stream, laz_vlr)
    for k, chunk in enumerate(chunks):
        if k:
            compressor.finish_current_chunk()
        compressor.compress_many(chunk)
    compressor.done()


_ENTRY_DTYPE = np.dtype(
    [("key", "<i4", (4,)), ("offset", "<u8"), ("bytes", "<i4"), ("points", "<i4")]
)


def _uncompressed_header(las: Any, extent: LasExtent | None) -> bytes:
    """The LAS header and VLRs laspy writes for ``las`` uncompressed (the same header a
    plain tile has: extremes, counts by return, extra-bytes statistics)."""
    import io

    header = las.header
    if extent is not None and len(las.points):
        header.partial_reset()
        _grow(header, extent, las.points)
    else:
        las.update_header()
        header.start_of_first_evlr, header.number_of_evlrs = 0, 0
    header.are_points_compressed = False
    with io.BytesIO() as stream:
        header.write_to(stream)
        return stream.getvalue()


def _parse_vlrs(block: bytes, path: Path) -> list[tuple[bytes, int, bytes, bytes]]:
    """``(user_id, record_id, description, data)`` of every VLR of a LAS header block."""
    header_size, point_offset, count = struct.unpack_from("<HII", block, 94)
    vlrs = []
    pos = header_size
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
    if pos != point_offset:
        raise PointCloudFormatError("the VLRs do not end where the point data starts", path=path)
    return vlrs


def _vlr_bytes(vlr: tuple[bytes, int, bytes, bytes]) -> bytes:
    user_id, record_id, description, data = vlr
    return struct.pack("<H16sHH32s", 0, user_id, record_id, len(data), description) + data
