"""A payload's enrichment, read back from the catalog: its layers.

Enrichment writes into the epoch's tiles, tables and rasters; this module serves what it
computed for one mission payload, in that payload's own terms:

- per-point fields (layers ``ground``, ``height``, ``trees``): the tiles' ``classification``
  (2 ground, 1 other), ``height_above_ground`` and ``tree_id`` of the payload's points,
  one value per point of the payload cloud as its file holds it (points its file flags
  withheld were never tiled: they get ``classification`` 0, NaN, tree 0 and ``tiled``
  False);
- ``trees``: the epoch's tree list rows the payload's points belong to or whose position
  lies in the payload's footprint, with positions in the catalog CRS and the payload frame;
- ``terrain``: the window of ``rasters/<epoch>/dtm.tif`` under the payload, as a grid in the
  catalog CRS and each pixel centre on the terrain in the payload frame.

The points are matched exactly. The payload's points are placed as the tiler placed them
(the catalog's record of the mission's placement, the node pose, snapped to the tiles' 1 mm
lattice), and each is paired with the tile point of the same ``payload_id`` (core points
only; a tile's buffer copies are withheld) at the same lattice coordinates; points with the
same coordinates pair in order (the partition keeps a payload's points in arrival order
within a cell). The pairing must be one to one over every point of the payload, else
:class:`~standgrid.errors.StaleLayersError` (the payload changed since it was tiled).

Nothing is cached: every call reads the catalog as its last commit left it, inside one
consistent snapshot (:meth:`Catalog.reading`), and refuses an epoch that is not enriched or
was re-tiled since (:class:`~standgrid.errors.StaleLayersError`). The payload frame is the
node's base frame (:meth:`Mission.load_base`), or the clouds' own projected CRS for a
mission of projected clouds.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.catalog import paths
from standgrid.catalog.records import ENRICHED
from standgrid.errors import OptionError, PayloadNotTiledError, StaleLayersError
from standgrid.storage.objects import source_of

if TYPE_CHECKING:
    import pandas as pd

    from standgrid.catalog import Catalog, MissionRecord
    from standgrid.georeference.placement import ToCatalog
    from standgrid.mission.model import Mission
    from standgrid.mission.payload import Payload
    from standgrid.pointcloud import PointCloud
    from standgrid.rastergrid import RasterGrid

#: The layers a payload can carry, in this order.
LAYERS = ("ground", "height", "trees", "terrain")
#: Layer -> the per-point tile field it carries.
POINT_FIELDS = {"ground": "classification", "height": "height_above_ground", "trees": "tree_id"}
#: A point's field value where the catalog has none (a point its file flags withheld).
FILL = {"classification": 0, "height_above_ground": np.nan, "tree_id": 0}
#: Columns of :attr:`PayloadLayers.trees`.
PAYLOAD_TREE_COLUMNS = (
    "tree_id",
    "tree_uid",
    "x",
    "y",
    "z",
    "x_payload",
    "y_payload",
    "z_payload",
    "height_m",
    "dbh_m",
    "dbh_source",
    "detected_by",
    "payload_points",
    "in_footprint",
)
#: Core points of tiles one retrieval keeps decoded for its other payloads (~40 bytes each).
CACHED_TILE_POINTS = 4_000_000


def parse_layers(layers: str | Iterable[str] | None) -> tuple[str, ...]:
    """Layer names (a comma-separated text or names; None or ``all``: every one) in
    :data:`LAYERS` order; an unknown name is an :class:`OptionError` (option ``layers``)."""
    if layers is None:
        return LAYERS
    names = layers.split(",") if isinstance(layers, str) else list(layers)
    wanted = {str(n).strip().lower() for n in names if str(n).strip()}
    if wanted == {"all"}:
        return LAYERS
    unknown = sorted(wanted - set(LAYERS))
    if unknown or not wanted:
        what = f"unknown layer {unknown[0][:40]!r}" if unknown else "no layer named"
        raise OptionError("layers", f"{what}; layers: {', '.join(LAYERS)} (or all)")
    return tuple(n for n in LAYERS if n in wanted)


@dataclass(frozen=True)
class TerrainWindow:
    """The epoch's DTM under a payload: ``heights`` (north-up rows, NaN where the terrain was
    not observed) on ``grid`` (lower-left corner and pixel size in ``crs``), and
    ``payload_xyz``: each pixel centre on the terrain, row by row, in the payload frame
    (NaN where there is no height)."""

    heights: NDArray[np.float64]
    grid: RasterGrid
    crs: str
    payload_xyz: NDArray[np.float64]

    @property
    def transform(self) -> Any:
        """The grid's affine (rasterio ``Affine``: pixel -> CRS)."""
        return self.grid.transform

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN -> null)."""
        g = self.grid
        return {
            "crs": self.crs,
            "x0": g.x0,
            "y0": g.y0,
            "pixel_size": g.pixel_size,
            "ncols": g.ncols,
            "nrows": g.nrows,
            "heights": _nulls(self.heights),
            "payload_xyz": _nulls(self.payload_xyz),
        }


@dataclass(frozen=True)
class PayloadLayers:
    """A payload with its enrichment from the catalog (module doc).

    ``fields``: the asked per-point layers (``classification``, ``height_above_ground``,
    ``tree_id``), one value per point of ``cloud`` (the payload in its frame, as its file
    holds it); ``tiled``: which of its points are in the catalog. ``xyz_crs``: each point in
    the catalog CRS, as its tile stores it (a point not tiled: through the exact chain)."""

    payload: Payload
    mission: str
    payload_id: int
    epoch: str
    #: The enrichment these values come from (``enrichment_id`` of the epoch).
    enrichment_id: str | None
    layers: tuple[str, ...]
    crs: str
    cloud: PointCloud
    tiled: NDArray[np.bool_]
    xyz_crs: NDArray[np.float64]
    fields: dict[str, NDArray[Any]] = field(default_factory=dict)
    #: Tiles the points were read from (catalog-relative).
    tiles: tuple[str, ...] = ()
    trees: pd.DataFrame | None = None
    terrain: TerrainWindow | None = None

    @property
    def point_count(self) -> int:
        return len(self.cloud)

    def layered_cloud(self) -> PointCloud:
        """``cloud`` with the per-point layers as fields (the catalog's ``classification``
        replaces a payload's own)."""
        return self.cloud.with_fields(**self.fields)

    def summary(self) -> dict[str, Any]:
        """JSON-ready headline: ids, counts, the trees' and terrain's sizes."""
        out: dict[str, Any] = {
            "mission": self.mission,
            "payload_id": self.payload_id,
            "stamp": str(self.payload.stamp),
            "epoch": self.epoch,
            "enrichment_id": self.enrichment_id,
            "layers": list(self.layers),
            "crs": self.crs,
            "points": self.point_count,
            "points_tiled": int(self.tiled.sum()),
            "tiles": list(self.tiles),
        }
        if "ground" in self.fields or "classification" in self.fields:
            out["ground_points"] = int((self.fields["classification"] == 2).sum())
        if "tree_id" in self.fields:
            out["tree_points"] = int((self.fields["tree_id"] != 0).sum())
        if self.trees is not None:
            out["trees"] = len(self.trees)
        if self.terrain is not None:
            out["terrain_pixels"] = int(np.isfinite(self.terrain.heights).sum())
        return out

    def to_dict(self, *, points: bool = False) -> dict[str, Any]:
        """:meth:`summary` with the trees and terrain (and with ``points``, every point's
        payload-frame ``xyz`` and layer fields)."""
        out = self.summary()
        if self.trees is not None:
            out["tree_list"] = [
                {k: _json_value(v) for k, v in row.items()} for row in self.trees.to_dict("records")
            ]
        if self.terrain is not None:
            out["terrain"] = self.terrain.to_dict()
        if points:
            out["xyz"] = _nulls(self.cloud.xyz)
            out["fields"] = {k: _nulls(v) for k, v in self.fields.items()}
        return out


def payload_layers(
    catalog: str | os.PathLike[str] | Catalog,
    mission: str | os.PathLike[str] | Mission,
    payload: Payload,
    layers: str | Iterable[str] | None = None,
) -> PayloadLayers:
    """``payload`` of ``mission`` with its ``layers`` (default: all) from ``catalog``.

    Raises :class:`~standgrid.errors.PayloadNotTiledError` when the catalog holds no such
    mission (from this folder) or payload, :class:`~standgrid.errors.StaleLayersError` when
    its epoch is not enriched, was re-tiled since, or the payload's points no longer match
    its tiles, and :class:`~standgrid.errors.OptionError` for an unknown layer.
    """
    return layers_of(catalog, mission, [payload], layers)[0]


def layers_of(
    catalog: str | os.PathLike[str] | Catalog,
    mission: str | os.PathLike[str] | Mission,
    payloads: Sequence[Payload],
    layers: str | Iterable[str] | None = None,
) -> list[PayloadLayers]:
    """:func:`payload_layers` of several payloads of one mission, read in one snapshot."""
    from standgrid.catalog import Catalog
    from standgrid.mission.model import Mission
    from standgrid.mission.opening import open_mission

    wanted = parse_layers(layers)
    opened = mission if isinstance(mission, Mission) else open_mission(Path(mission), strict=False)
    root = catalog.root if isinstance(catalog, Catalog) else Path(catalog)
    with Catalog.reading(root) as snapshot:
        reader = _Reader(snapshot, opened, wanted)
        return [reader.layers(p) for p in payloads]


class _Reader:
    """One mission's payloads read against one catalog snapshot."""

    def __init__(self, catalog: Catalog, mission: Mission, wanted: tuple[str, ...]) -> None:
        from standgrid.catalog.index import CatalogIndex
        from standgrid.catalog.partition import catalog_partition
        from standgrid.georeference.placement import cloud_payloads

        self.catalog, self.mission, self.wanted = catalog, mission, wanted
        self.record = _mission_record(catalog, mission)
        epoch = self.record.epoch
        state = catalog.epoch(epoch)
        if state.state != ENRICHED:
            why = (
                f"was re-tiled since it was enriched ({state.invalidated.get('reason', '')})"
                if state.invalidated
                else "is not enriched"
            )
            raise StaleLayersError(
                f"epoch {epoch} of mission {mission.name!r} {why}: its layers would not be "
                f"the catalog's (run `standgrid enrich` on it)",
                path=catalog.root,
            )
        self.epoch = epoch
        self.enrichment_id = catalog.epochs[epoch].get("enrichment_id")
        index = CatalogIndex(catalog)
        self.payload_rows = index.read("payloads", epoch)
        cells = index.read("cells", epoch)
        holding = cells["missions"].astype(str).map(lambda t: mission.name in t.split(","))
        self.cells = cells[holding.to_numpy(bool)].reset_index(drop=True)
        self.clouds = cloud_payloads(mission)
        self.origin = catalog_partition(catalog, epoch, coverage=False).lattice_origin
        self.to_catalog = _to_catalog(self.record, mission, catalog.crs)
        self._tree_list: pd.DataFrame | None = None
        self._tiles: dict[str, dict[str, NDArray[Any]]] = {}
        self._cached_points = 0

    # --- one payload ---------------------------------------------------------------------

    def layers(self, payload: Payload) -> PayloadLayers:
        from standgrid.tiling.mission_rows import payload_id

        index = next(
            (
                k
                for k, p in enumerate(self.clouds)
                if p.stamp == payload.stamp and p.path == payload.path
            ),
            None,
        )
        if index is None:
            raise PayloadNotTiledError(
                f"{payload.path.name} ({payload.stamp}) is not a point-cloud payload of "
                f"mission {self.mission.name!r}: only payload clouds are tiled",
                path=payload.path,
            )
        ident = payload_id(self.record.number, index, self.mission)
        row = self.payload_rows[self.payload_rows["payload_id"].astype(np.int64) == ident]
        if not len(row):
            raise PayloadNotTiledError(
                f"the catalog holds no payload {ident} ({payload.stamp}) of mission "
                f"{self.mission.name!r} in epoch {self.epoch}: tile the mission again",
                path=self.catalog.root,
            )
        expected = int(row["point_count"].iloc[0])
        cloud, kept, xyz = self._placed(payload)
        keys = _lattice_keys(xyz, self.origin)
        tiles, values, tile_keys = self._tile_points(ident, xyz)
        order = _pair(keys, tile_keys)
        if order is None or len(xyz) != expected:
            raise StaleLayersError(
                f"payload {payload.stamp} of mission {self.mission.name!r}: its {len(xyz)} "
                f"points do not match the {len(tile_keys)} points the catalog's tiles hold "
                f"for it (expected {expected}): the payload or its placement changed since "
                "it was tiled; tile the mission again",
                path=payload.path,
            )
        n = len(cloud)
        tiled = np.zeros(n, dtype=bool)
        tiled[kept] = True
        xyz_crs = np.empty((n, 3))
        xyz_crs[kept] = xyz
        if not tiled.all():  # points its file flags withheld: placed by the exact chain
            xyz_crs[~tiled] = self._to_crs(payload, cloud.xyz[~tiled])
        fields = {}
        for name in (POINT_FIELDS[w] for w in self.wanted if w in POINT_FIELDS):
            stored = values[name]
            full = np.full(n, FILL[name], dtype=stored.dtype)
            full[kept] = stored[order]
            fields[name] = full
        trees = terrain = None
        if "trees" in self.wanted:
            ids = values["tree_id"][order]
            trees = self._trees(payload, ids, xyz)
        if "terrain" in self.wanted:
            terrain = self._terrain(payload, xyz)
        return PayloadLayers(
            payload=payload,
            mission=self.mission.name,
            payload_id=ident,
            epoch=self.epoch,
            enrichment_id=self.enrichment_id,
            layers=self.wanted,
            crs=self.catalog.crs,
            cloud=cloud,
            tiled=tiled,
            xyz_crs=xyz_crs,
            fields=fields,
            tiles=tuple(tiles),
            trees=trees,
            terrain=terrain,
        )

    def _placed(self, payload: Payload) -> tuple[PointCloud, NDArray[np.intp], NDArray[np.float64]]:
        """The payload cloud in its frame, the rows of it that were tiled (its file's
        withheld points were not), and those rows placed as the tiler placed them
        (:func:`standgrid.partition.chunks.payload_chunk`): in the catalog CRS, snapped."""
        from standgrid.clouds import read_cloud
        from standgrid.clouds.las import read_las_part
        from standgrid.las_fields import las_dimension_values
        from standgrid.partition.lattice import snap_to_storage
        from standgrid.partition.schema import WITHHELD
        from standgrid.pointcloud import PointCloud

        mission, to_catalog = self.mission, self.to_catalog
        if payload.span is not None:
            raw = read_las_part(payload.path, payload.span, payload.window)
        else:
            raw = read_cloud(payload.path)
        kept = np.arange(len(raw))
        if WITHHELD in raw.fields:
            flags = las_dimension_values(WITHHELD, raw.fields[WITHHELD], payload.path)
            kept = np.flatnonzero(~np.asarray(flags, dtype=bool))
        source = raw.xyz[kept]
        if to_catalog.fit is None:
            cloud = raw  # projected clouds: their frame is their CRS
            xyz = to_catalog.projected_points(source)
        else:
            to_base = mission.file_to_base(payload)
            cloud = raw if to_base is None else raw.transformed(to_base)
            if to_base is not None:
                source = PointCloud(source, {}).transformed(to_base).xyz
            xyz = to_catalog.base_points(np.array(source), mission.pose_of(payload))
        xyz = snap_to_storage(xyz, self.origin)
        return cloud, kept, xyz

    def _tile_points(
        self, ident: int, xyz: NDArray[np.float64]
    ) -> tuple[list[str], dict[str, NDArray[Any]], NDArray[np.int64]]:
        """The core points of payload ``ident`` in the tiles whose cells meet the box of its
        placed points ``xyz``: tiles read, their layer fields and lattice keys."""
        import shapely

        names = list(POINT_FIELDS.values())
        parts: dict[str, list[NDArray[Any]]] = {name: [] for name in names}
        key_parts: list[NDArray[np.int64]] = []
        read: list[str] = []
        if len(xyz):
            box = shapely.box(*xyz[:, 0:2].min(axis=0), *xyz[:, 0:2].max(axis=0))
            meets = shapely.intersects(np.asarray(self.cells.geometry.values), box)
            candidates = sorted(self.cells["tile_path"][meets].astype(str))
        else:
            candidates = []
        for rel in candidates:
            tile = self._tile(rel)
            mine = tile["payload_id"] == ident
            if not mine.any():
                continue
            read.append(rel)
            key_parts.append(tile["keys"][mine])
            for name in names:
                parts[name].append(tile[name][mine])
        values = {
            name: np.concatenate(parts[name]) if parts[name] else np.zeros(0) for name in names
        }
        keys = np.concatenate(key_parts) if key_parts else np.zeros((0, 3), dtype=np.int64)
        return read, values, keys

    def _tile(self, rel: str) -> dict[str, NDArray[Any]]:
        """A tile's core points (buffer copies are withheld): lattice keys, ``payload_id``
        and the layer fields; only those dimensions are decompressed, and tiles stay cached
        for the other payloads of this snapshot (up to :data:`CACHED_TILE_POINTS`)."""
        import laspy

        from standgrid.export.las import read_tile_record

        cached = self._tiles.pop(rel, None)
        if cached is not None:
            self._tiles[rel] = cached  # most recently used last
            return cached
        path = self.catalog.path(rel)
        selection = laspy.DecompressionSelection
        las = read_tile_record(
            path,
            decompression_selection=selection.XY_RETURNS_CHANNEL
            | selection.Z
            | selection.CLASSIFICATION
            | selection.FLAGS
            | selection.ALL_EXTRA_BYTES,
        )
        names = list(POINT_FIELDS.values())
        present = set(las.point_format.dimension_names)
        missing = [n for n in (*names, "payload_id") if n not in present]
        if missing:
            raise StaleLayersError(
                f"{rel} has no {', '.join(missing)}: not an enriched standgrid tile", path=path
            )
        core = ~np.asarray(las.withheld, dtype=bool)
        xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])[core]
        tile = {
            "keys": _lattice_keys(xyz, self.origin),
            "payload_id": np.asarray(las["payload_id"])[core],
        }
        for name in names:
            tile[name] = np.asarray(las[name])[core]
        self._tiles[rel] = tile
        self._cached_points += len(xyz)
        while self._cached_points > CACHED_TILE_POINTS and len(self._tiles) > 1:
            oldest = next(iter(self._tiles))
            self._cached_points -= len(self._tiles.pop(oldest)["keys"])
        return tile

    def _trees(
        self, payload: Payload, point_ids: NDArray[Any], xyz: NDArray[np.float64]
    ) -> pd.DataFrame:
        """The tree list rows the payload's points belong to, or whose position lies in the
        convex hull of its points (:data:`PAYLOAD_TREE_COLUMNS`)."""
        import pandas as pd
        import shapely

        table = self._tree_table()
        ids, counts = np.unique(np.asarray(point_ids, dtype=np.int64), return_counts=True)
        per_tree = dict(zip(ids.tolist(), counts.tolist(), strict=True))
        per_tree.pop(0, None)
        tree_ids = table["tree_id"].astype(np.int64).to_numpy()
        points = np.array([per_tree.get(int(t), 0) for t in tree_ids], dtype=np.int64)
        hull = _hull(xyz)
        x, y = table["x"].to_numpy(np.float64), table["y"].to_numpy(np.float64)
        inside = shapely.intersects_xy(hull, x, y) if hull is not None else np.zeros(len(x), bool)
        keep = (points > 0) | inside
        chosen = table[keep]
        position = np.column_stack(
            [
                chosen["x"].to_numpy(np.float64),
                chosen["y"].to_numpy(np.float64),
                chosen["z_ground"].to_numpy(np.float64),
            ]
        )
        local = self._to_payload(payload, position)
        out = pd.DataFrame(
            {
                "tree_id": chosen["tree_id"].astype(np.int64).to_numpy(),
                "tree_uid": chosen["tree_uid"].to_numpy() if "tree_uid" in chosen else None,
                "x": position[:, 0],
                "y": position[:, 1],
                "z": position[:, 2],
                "x_payload": local[:, 0],
                "y_payload": local[:, 1],
                "z_payload": local[:, 2],
                "height_m": chosen["height_m"].to_numpy(np.float64),
                "dbh_m": chosen["dbh_m"].to_numpy(np.float64),
                "dbh_source": chosen.get("dbh_source", pd.Series([None] * len(chosen))).values,
                "detected_by": chosen["detected_by"].astype(str).to_numpy(),
                "payload_points": points[keep],
                "in_footprint": inside[keep],
            }
        )
        return out.reset_index(drop=True)

    def _tree_table(self) -> pd.DataFrame:
        import pandas as pd

        if self._tree_list is None:
            path = self.catalog.path(paths.tree_list(self.epoch, "parquet"))
            if not path.is_file():
                raise StaleLayersError(f"epoch {self.epoch} has no tree list: enrich it", path=path)
            self._tree_list = pd.read_parquet(path)
        return self._tree_list

    def _terrain(self, payload: Payload, xyz: NDArray[np.float64]) -> TerrainWindow:
        """The DTM pixels under the box of the payload's points (module doc)."""
        from standgrid.geotiff import read_grid, read_window

        path = self.catalog.path(paths.raster(self.epoch, "dtm"))
        if not path.is_file():
            raise StaleLayersError(f"epoch {self.epoch} has no terrain model", path=path)
        grid = read_grid(path)
        lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
        window = grid.window((float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
        heights = read_window(path, window)
        sub = grid.window_grid(window)
        xx, yy = sub.centers()
        centres = np.column_stack([xx.ravel(), yy.ravel(), heights.ravel()])
        local = np.full_like(centres, np.nan)
        seen = np.isfinite(centres[:, 2])
        if seen.any():
            local[seen] = self._to_payload(payload, centres[seen])
        return TerrainWindow(heights, sub, self.catalog.crs, local)

    def _to_crs(self, payload: Payload, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        """Payload-frame points -> the catalog CRS (exact chain, not snapped)."""
        from standgrid.geometry import transform_points

        if self.to_catalog.fit is None:
            return self.to_catalog.projected_points(xyz)
        xyz_map = transform_points(self.mission.pose_of(payload), xyz)
        return self.to_catalog.projector.exact(xyz_map)

    def _to_payload(self, payload: Payload, xyz_crs: NDArray[np.float64]) -> NDArray[np.float64]:
        """Catalog-CRS points -> the payload frame (exact chain; module doc)."""
        from standgrid.geometry import invert_pose, transform_points

        if not len(xyz_crs):
            return np.zeros((0, 3))
        to_catalog = self.to_catalog
        if to_catalog.fit is None:
            transformer = to_catalog.transformer()
            if transformer is None:
                return np.array(xyz_crs, dtype=np.float64)
            from pyproj.enums import TransformDirection

            x, y = transformer.transform(
                xyz_crs[:, 0],
                xyz_crs[:, 1],
                direction=TransformDirection.INVERSE,
                errcheck=True,
            )
            return np.column_stack([np.asarray(x), np.asarray(y), xyz_crs[:, 2]])
        xyz_map = to_catalog.projector.to_map(xyz_crs)
        return transform_points(invert_pose(self.mission.pose_of(payload)), xyz_map)


def _mission_record(catalog: Catalog, mission: Mission) -> MissionRecord:
    """The catalog's record of ``mission``, tiled from the same folder."""
    record = catalog.mission_records.get(mission.name)
    if record is None:
        raise PayloadNotTiledError(
            f"the catalog holds no mission {mission.name!r} (missions: "
            f"{sorted(catalog.mission_records)}): tile it first",
            path=catalog.root,
        )
    if record.path and record.path != source_of(mission.path):
        raise PayloadNotTiledError(
            f"the catalog's mission {mission.name!r} was tiled from {record.path}, not from "
            f"{mission.path}",
            path=catalog.root,
        )
    return record


def _to_catalog(record: MissionRecord, mission: Mission, crs: str) -> ToCatalog:
    """The recipe the tiler placed the mission's points with, from its catalog record."""
    from standgrid.crs import CRS
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.placement import Placement, projected_crs

    held = dict(record.georeference or {})
    if held.get("method") == "projected" or not held:
        given = held.get("source_crs")
        source = CRS.of(given) if given else projected_crs(mission, crs)
        return Placement(None, source).to_catalog(crs, mission.name)
    try:
        transform = np.array(held["T_enu_map"], dtype=np.float64).reshape(4, 4)
        lla = tuple(float(v) for v in held["lla_ref"])
    except (KeyError, TypeError, ValueError) as exc:
        raise StaleLayersError(
            f"malformed placement record of mission {mission.name!r}: {exc!r}", path=mission.path
        ) from exc
    fit = GeoreferenceFit.without_fixes(lla, transform, str(held.get("method", "")))  # type: ignore[arg-type]
    return Placement(fit).to_catalog(crs, mission.name)


def _lattice_keys(xyz: NDArray[np.float64], origin: tuple[float, float]) -> NDArray[np.int64]:
    """Millimetres from the lattice origin, per axis: a tile's stored coordinates exactly
    (they lie on the 1 mm lattice; :func:`~standgrid.partition.lattice.snap_to_storage`)."""
    offset = np.array([origin[0], origin[1], 0.0])
    return np.rint((np.asarray(xyz, dtype=np.float64) - offset) * 1000.0).astype(np.int64)


def _pair(keys: NDArray[np.int64], tile_keys: NDArray[np.int64]) -> NDArray[np.intp] | None:
    """Per payload point, its row in the tile points: the one at the same lattice key (same
    keys pair in order); None unless the two are the same multiset of keys."""
    if len(keys) != len(tile_keys):
        return None
    if not len(keys):
        return np.zeros(0, dtype=np.intp)
    mine = np.lexsort(keys.T[::-1])  # stable: equal keys keep their order
    theirs = np.lexsort(tile_keys.T[::-1])
    if not np.array_equal(keys[mine], tile_keys[theirs]):
        return None
    order = np.empty(len(keys), dtype=np.intp)
    order[mine] = theirs
    return order


def _hull(xyz: NDArray[np.float64]) -> Any:
    """The convex hull of the points' x/y (None without an area)."""
    import shapely
    from scipy.spatial import ConvexHull, QhullError

    if len(xyz) < 3:
        return None
    xy = xyz[:, :2]
    try:
        hull = ConvexHull(xy)
    except QhullError:
        return None
    return shapely.Polygon(xy[hull.vertices])


def _nulls(values: NDArray[Any]) -> Any:
    """An array as nested lists, NaN as None (JSON)."""
    array = np.asarray(values)
    if array.dtype.kind == "f":
        kept = array.astype(object)
        kept[~np.isfinite(array)] = None
        return kept.tolist()
    return array.tolist()


def _json_value(value: Any) -> Any:
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def write_layered_cloud(
    layered: PayloadLayers, path: str | os.PathLike[str], *, frame: str = "crs"
) -> Path:
    """The payload's points with their per-point layers as a LAS/LAZ file (by suffix):
    ``frame`` ``crs`` (the catalog CRS, coordinates as the tiles store them, the CRS in the
    header) or ``payload`` (the payload frame, no CRS). ``classification`` is the LAS
    classification; ``height_above_ground``, ``tree_id`` (and a non-LAS intensity, exactly,
    as ``intensity_raw``) are extra dimensions."""
    from standgrid.clouds import write_cloud
    from standgrid.clouds.las_write import intensity_is_native
    from standgrid.pointcloud import PointCloud

    if frame not in ("crs", "payload"):
        raise OptionError("frame", f"{frame!r} is not crs or payload")
    cloud = layered.layered_cloud()
    fields = {k: v for k, v in cloud.fields.items() if k != "withheld"}
    intensity = fields.get("intensity")
    if intensity is not None and not intensity_is_native(intensity):
        fields["intensity_raw"] = fields.pop("intensity")
    out = Path(path)
    if frame == "crs":
        write_cloud(PointCloud(layered.xyz_crs, fields), out, crs=layered.crs)
    else:
        write_cloud(PointCloud(cloud.xyz, fields), out)
    return out
