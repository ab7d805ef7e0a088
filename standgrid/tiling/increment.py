"""Re-tiling an epoch in place: only the tiles whose points change are rewritten.

When missions already in an epoch are tiled again (a robot that sent more payloads, a
re-run), a payload whose source is unchanged (the same cloud file, frame, node pose, stamp,
payload id, mission placement and field schema: :func:`source_digest`, stored in the
``payloads`` layer) has its points in the tiles already, exactly as they would be written
again. Only tiles holding points of changed or dropped payloads (found by their
``payload_id``) and tiles of the cells the changed payloads' new points fall in are
rewritten; every other tile stays as it is, byte for byte, with its row in the index.

The whole epoch is re-tiled instead when any of this does not hold: grid cells (a Voronoi
site that moves moves every edge around it), no tile buffer (a copy reaches neighbours),
the same tiling settings and field schema as the tiles, every mission of the run already in
the epoch and no other mission leaving it, a digest for every old payload, and at most
half of the payloads changed.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from standgrid.catalog.invalidate import ENRICH_POINT_FIELDS

if TYPE_CHECKING:
    import pandas as pd
    from numpy.typing import NDArray

    from standgrid.catalog.records import TilingSettings
    from standgrid.catalog.store import Catalog
    from standgrid.engine import Executor
    from standgrid.export.las import TileInfo
    from standgrid.partition.chunks import PayloadTask
    from standgrid.partition.protocol import Partition


def placement_digest(placement: dict[str, Any]) -> str:
    """What of a mission placement's record (:meth:`Placement.record`) its points depend on,
    hashed once per mission: the transform ``T_enu_map`` about ``lla_ref`` of a fit, the
    source CRS of projected clouds (exact floats). A fit's per-fix residuals are not in it:
    a fix that arrives without moving the transform (or the transform a catalog keeps under
    a placement tolerance, re-evaluated on more fixes) leaves the payloads unchanged."""
    placed = {key: placement.get(key) for key in ("T_enu_map", "lla_ref", "source_crs")}
    text = json.dumps(placed, sort_keys=True, default=str)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


#: Version of how a payload's fields reach its tiles (``partition.chunks.source_fields``):
#: bumped when a rule changes, so the payloads carrying those fields are read again (2:
#: source-withheld points left out, scan_angle_rank as scan_angle, the source's
#: point_source_id kept). Payloads without them keep their digest (and their tiles).
SOURCE_FIELD_RULES = 2
#: The fields those rules apply to.
SOURCE_RULE_FIELDS = frozenset({"withheld", "scan_angle_rank", "point_source_id"})


def source_digest(source: dict[str, Any], placement: str, schema: Any) -> str:
    """What a payload's points in the catalog depend on, hashed: its cloud file (by identity:
    device, inode, size, modification and change times, as git and make tell a changed file;
    any write changes them, a copied folder has new ones), frame, file -> base transform and
    node pose (to 1e-9), stamp (GPS time), mission number, payload id, the mission's
    placement (:func:`placement_digest`), the epoch's field schema and, for a cloud with
    fields those rules apply to, the version of the rules bringing a source's fields to the
    tiles (:data:`SOURCE_FIELD_RULES`)."""
    from standgrid.clouds import check_cloud_file
    from standgrid.errors import PointCloudFormatError

    path = Path(source["path"])
    check_cloud_file(path)
    try:
        st = path.stat()
    except OSError as exc:
        raise PointCloudFormatError(f"cannot read: {exc.strerror or exc}", path=path) from exc
    digest = hashlib.blake2b(digest_size=16)
    identity = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    digest.update(repr(identity).encode())
    for key in ("file_to_base", "pose"):
        value = source[key]
        # to 1e-9 (m, and rotation entries): a graph written again as text may move a pose
        # by round-off (1e-16), which no point of the 1 mm lattice can show
        rounded = None if value is None else np.round(np.asarray(value, np.float64), 9) + 0.0
        digest.update(b"-" if rounded is None else rounded.tobytes())
    described = {
        "frame": source["frame"],
        "gps_time": float(source["gps_time"]).hex(),
        "point_source_id": int(source["point_source_id"]),
        "payload_id": int(source["payload_id"]),
        "placement": placement,
        # the fields the points are written with; enrichment's own fields (reset in every
        # rewritten tile, added to the epoch's schema by enrich) are not the payload's
        "schema": {
            name: np.dtype(dtype).str
            for name, dtype in dict(schema).items()
            if name not in (*ENRICH_POINT_FIELDS, "classification")
        },
    }
    if source.get("span") is not None:  # a plain scan's part of its file
        described["part"] = [source["span"], source.get("window")]
    if source.get("time_offset"):  # a plain scan's week seconds made adjusted standard
        described["time_offset"] = float(source["time_offset"]).hex()
        described["time_wrap"] = source.get("time_wrap")
    if _has_rule_fields(path):
        described["source_field_rules"] = SOURCE_FIELD_RULES
    digest.update(json.dumps(described, sort_keys=True, default=str).encode())
    return digest.hexdigest()


def _has_rule_fields(path: Path) -> bool:
    """Whether the cloud's header names a field :data:`SOURCE_FIELD_RULES` applies to (an
    unreadable header counts as yes: reading the payload will say what is wrong)."""
    from standgrid.clouds import read_cloud_header
    from standgrid.errors import StandgridError

    try:
        return bool(SOURCE_RULE_FIELDS & set(read_cloud_header(path).fields))
    except StandgridError:
        return True


@dataclass(frozen=True)
class Increment:
    """What an in-place re-tile keeps and rewrites."""

    #: ids of payloads whose points stay where they are
    unchanged: frozenset[int]
    #: ids of payloads whose old points are taken out (changed or no longer sent)
    dropped: frozenset[int]
    #: ``payloads`` rows of the unchanged payloads, as stored (point count, footprint)
    kept_rows: pd.DataFrame


def plan_increment(
    catalog: Catalog,
    epoch: str,
    missions: Iterable[str],
    rows: Sequence[dict[str, Any]],
    old_payloads: pd.DataFrame,
    tiling: TilingSettings,
    renewed: Iterable[str],
) -> Increment | None:
    """The in-place re-tile of ``epoch`` for ``missions`` (their new payload ``rows``, each
    with its ``source_digest``), or None when the whole epoch must be re-tiled (see the
    module doc). ``old_payloads``: the epoch's stored rows of those missions; ``renewed``:
    every mission of the run (one leaving this epoch forces a whole re-tile)."""
    names = set(missions)
    record = catalog.epoch_records.get(epoch)
    if record is None or catalog.scheme != "grid" or tiling.buffer or not rows:
        return None
    if not names <= set(record.missions) or (set(renewed) - names) & set(record.missions):
        return None
    if record.tiling != tiling:
        return None
    if not len(old_payloads) or "source_digest" not in old_payloads.columns:
        return None
    stored = old_payloads["source_digest"]
    if stored.isna().any():
        return None
    old = dict(zip(old_payloads["payload_id"].astype(np.int64), stored.astype(str), strict=True))
    unchanged = frozenset(
        int(r["payload_id"]) for r in rows if old.get(int(r["payload_id"])) == r["source_digest"]
    )
    if 2 * len(unchanged) < len(rows):
        return None
    dropped = frozenset(old) - unchanged
    kept = old_payloads[old_payloads["payload_id"].astype(np.int64).isin(unchanged)]
    return Increment(unchanged, dropped, kept.reset_index(drop=True))


def landing_keys(job: tuple[PayloadTask, Partition]) -> NDArray[np.int64]:
    """The cell keys a payload's points fall in (a pure task: runs on a worker)."""
    from standgrid.partition.chunks import payload_chunk

    task, partition = job
    xyz = payload_chunk(task).cloud.xyz
    return np.unique(partition.assign(xyz[:, 0], xyz[:, 1]))


def landing_tiles(
    tasks: list[PayloadTask],
    partition: Partition,
    epoch: str,
    tiling: TilingSettings,
    executor: Executor,
) -> set[str]:
    """The tiles (catalog-relative) the payloads' points fall in (each payload is read where
    the executor runs it, only its cells come back; the partition engine reads it again)."""
    from contextlib import closing

    from standgrid.catalog import paths
    from standgrid.engine.ordered import ordered_map

    keys: set[int] = set()
    jobs = [(task, partition) for task in tasks]
    with closing(ordered_map(executor, landing_keys, jobs)) as landed:
        for found in landed:  # keys only come back
            keys.update(found.tolist())
    return {paths.tile(epoch, partition.cell_id(k), laz=tiling.laz, copc=tiling.copc) for k in keys}


def keep_rows(rows: list[dict[str, Any]], kept: Any) -> None:
    """Unchanged payloads keep their stored point count, count of source-withheld points
    left out and footprint."""
    stored = {int(r["payload_id"]): r for r in kept.to_dict("records")}
    for row in rows:
        found = stored.get(int(row["payload_id"]))
        if found is not None:
            row["point_count"] = int(found["point_count"])
            row["withheld_left_out"] = int(found["withheld_left_out"])
            row["geometry"] = found["geometry"]


def tiles_holding(root: Path, tiles: Sequence[str], payload_ids: Iterable[int]) -> set[str]:
    """The tiles (catalog-relative, under ``root``) with at least one point (buffer copies
    included) of ``payload_ids``; only the extra-bytes layer of a LAZ tile is decompressed."""
    import laspy

    from standgrid.export.las import read_tile_record

    wanted = np.fromiter(payload_ids, dtype=np.int64)
    if not len(wanted):
        return set()
    layers = laspy.DecompressionSelection.ALL_EXTRA_BYTES
    found = set()
    for rel in tiles:
        las = read_tile_record(root / rel, decompression_selection=layers)
        if np.isin(np.asarray(las["payload_id"]), wanted).any():
            found.add(rel)
    return found


def kept_tile_info(path: Path, cell: dict[str, Any], crs: str) -> TileInfo:
    """A tile left as it is, described from its header and its ``cells`` row."""
    import laspy

    from standgrid.export.las import TileInfo

    with laspy.open(path) as reader:
        header = reader.header
        total = int(header.point_count)
        file_bounds = (*map(float, header.mins), *map(float, header.maxs))
        point_format = int(header.point_format.id)
        compressed = bool(header.are_points_compressed)
    core = int(cell["point_count"])
    if core > total:
        from standgrid.errors import CatalogError

        raise CatalogError(f"the cells layer says {core} points, the tile holds {total}", path=path)
    nan = float("nan")
    return TileInfo(
        path=path,
        core_count=core,
        buffer_count=total - core,
        bounds=(nan,) * 6,
        file_bounds=file_bounds,
        z_min=float(cell["z_min"]),
        z_max=float(cell["z_max"]),
        z_mean=float(cell["z_mean"]),
        z_p95=float(cell["z_p95"]),
        point_format=point_format,
        compressed=compressed,
        crs=crs,
        core_bounds=cell["geometry"],
    )
