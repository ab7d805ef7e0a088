"""The catalog's GeoPackage index (``index.gpkg``) and virtual point cloud (``tiles_<epoch>.vpc``).

:class:`IndexWriter` copies the current index to a temporary sibling, writes layers into the
copy with pyogrio, adds QGIS default styles, and renames the copy onto the index only when
every layer was written: readers see the old index or the new one, never a mix.

Layers (all geometry in the catalog CRS; ``LAYER_COLUMNS`` lists the required columns):

- ``cells``: cell_id, level, cell_size, epoch, point_count, density (core points per m²),
  z_min, z_max, z_mean, z_p95, tile_path (relative to the catalog), missions (comma list);
  polygon = the cell's core bounds.
- ``payloads``: payload_id, mission, stamp_sec, stamp_nsec, time (ISO 8601 UTC), node_id,
  point_count (points tiled), x, y, z, yaw (and withheld_left_out: points the source flags
  withheld, left out; source_digest); polygon = the payload footprint.
- ``trajectories``: mission, epoch; LineString.
- ``gnss_fixes``: mission, stamp_sec, stamp_nsec, quality, residual_e, residual_n,
  residual_u, residual_h, inlier; projected Point.
- ``missions``: mission, number, epoch, date, robot, place, unit, sensors, fit_method,
  rmse_m, n_used, n_rejected, grid_fingerprint, crs (and placement_offset_m, see
  docs/METRICS.md); attribute table (or a point).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, NamedTuple

from standgrid._atomic import atomic_output, write_text_atomic
from standgrid.crs import CRS, CRSLike
from standgrid.errors import CatalogError, CRSError, short_of_room_error
from standgrid.export import styles

if TYPE_CHECKING:
    import geopandas as gpd
    import pandas as pd

    from standgrid.export.las import TileInfo

LAYER_COLUMNS: dict[str, tuple[str, ...]] = {
    "cells": (
        "cell_id",
        "level",
        "cell_size",
        "epoch",
        "point_count",
        "density",
        "z_min",
        "z_max",
        "z_mean",
        "z_p95",
        "tile_path",
        "missions",
    ),
    "payloads": (
        "payload_id",
        "mission",
        "stamp_sec",
        "stamp_nsec",
        "time",
        "node_id",
        "point_count",
        "x",
        "y",
        "z",
        "yaw",
    ),
    "trajectories": ("mission", "epoch"),
    "gnss_fixes": (
        "mission",
        "stamp_sec",
        "stamp_nsec",
        "quality",
        "residual_e",
        "residual_n",
        "residual_u",
        "residual_h",
        "inlier",
    ),
    "missions": (
        "mission",
        "number",
        "epoch",
        "date",
        "robot",
        "place",
        "unit",
        "sensors",
        "fit_method",
        "rmse_m",
        "n_used",
        "n_rejected",
        "grid_fingerprint",
        "crs",
    ),
}
#: GeoPackage version of new index files (the widest-read one with everything we use).
GPKG_VERSION = "1.2"
#: Layers that must carry a geometry.
GEOMETRY_LAYERS = frozenset({"cells", "payloads", "trajectories", "gnss_fixes"})


def _parse_crs(crs: CRSLike) -> CRS:
    try:
        return CRS.of(crs)
    except CRSError as exc:
        raise CRSError(f"unusable CRS {crs!r}: {exc.message}") from exc


def index_layer_names(path: str | os.PathLike[str]) -> set[str]:
    """The layer names of a GeoPackage; a garbage file raises :class:`CatalogError` naming it."""
    import pyogrio

    try:
        return {str(name) for name, _ in pyogrio.list_layers(path)}
    except Exception as exc:  # pyogrio/GDAL raise their own error classes
        raise CatalogError(f"unreadable GeoPackage index ({exc})", path=path) from exc


def read_index_layer(path: str | os.PathLike[str], layer: str) -> Any:
    """One layer of a GeoPackage as a GeoDataFrame (:class:`CatalogError` naming the file)."""
    import pyogrio

    try:
        return pyogrio.read_dataframe(path, layer=layer)
    except Exception as exc:
        raise CatalogError(
            f"unreadable layer {layer!r} of the GeoPackage index ({exc})", path=path
        ) from exc


def cell_row(
    cell_id: str,
    info: TileInfo,
    *,
    level: int,
    cell_size: float,
    epoch: str,
    missions: Iterable[str],
    catalog_root: str | os.PathLike[str] | None = None,
    tile_path: str | None = None,
    geometry: Any = None,
) -> dict[str, Any]:
    """One ``cells`` row from a written tile; geometry defaults to ``info.core_bounds``.

    ``tile_path`` is the tile's path relative to the catalog; without it, it is
    ``info.path`` relative to ``catalog_root`` (pass ``tile_path`` for a staged tile).
    """
    if tile_path is None:
        if catalog_root is None:
            raise CatalogError(f"cell {cell_id}: give tile_path or catalog_root", path=info.path)
        tile_path = Path(os.path.relpath(info.path, catalog_root)).as_posix()
    polygon = geometry if geometry is not None else info.core_bounds
    if polygon is None:
        raise CatalogError(f"cell {cell_id}: no core bounds polygon", path=info.path)
    area = float(polygon.area)
    return {
        "cell_id": cell_id,
        "level": int(level),
        "cell_size": float(cell_size),
        "epoch": epoch,
        "point_count": int(info.core_count),
        "density": info.core_count / area if area > 0 else math.nan,
        "z_min": info.z_min,
        "z_max": info.z_max,
        "z_mean": info.z_mean,
        "z_p95": info.z_p95,
        "tile_path": tile_path,
        "missions": ",".join(sorted(set(missions))),
        "geometry": polygon,
    }


def layer_frame(
    layer: str, rows: Sequence[Mapping[str, Any]] | pd.DataFrame, crs: CRSLike
) -> gpd.GeoDataFrame | pd.DataFrame:
    """A frame for a standard layer, columns in schema order; missing columns raise.

    Rows are dicts (a ``geometry`` key for geometry layers) or a (Geo)DataFrame.
    """
    import geopandas as gpd
    import pandas as pd

    frame = rows if isinstance(rows, pd.DataFrame) else pd.DataFrame(list(rows))
    required = LAYER_COLUMNS.get(layer, ())
    has_geometry = "geometry" in frame.columns
    if len(frame) == 0 and not len(frame.columns):
        frame = pd.DataFrame(
            {c: [] for c in (*required, *(["geometry"] if layer in GEOMETRY_LAYERS else []))}
        )
        has_geometry = layer in GEOMETRY_LAYERS
    missing = [c for c in required if c not in frame.columns]
    if layer in GEOMETRY_LAYERS and not has_geometry:
        missing.append("geometry")
    if missing:
        raise CatalogError(f"layer {layer!r} lacks columns {missing}")
    order = [*required, *(c for c in frame.columns if c not in required and c != "geometry")]
    if not has_geometry:
        return frame[order].reset_index(drop=True)
    if isinstance(frame, gpd.GeoDataFrame) and frame.crs is not None:
        return gpd.GeoDataFrame(frame[[*order, "geometry"]], geometry="geometry", crs=frame.crs)
    crs_value = _parse_crs(crs).pyproj_crs
    return gpd.GeoDataFrame(frame[[*order, "geometry"]], geometry="geometry", crs=crs_value)


class IndexWriter:
    """Atomic writer of ``index.gpkg``: use as a context manager.

    ``base`` is the index to start from (default: ``gpkg_path`` itself when it exists); its
    layers are kept unless rewritten. On a clean exit the new file replaces ``gpkg_path`` in
    one rename; on an exception nothing changes. ``durable=False``: a file staged in a
    catalog transaction, whose commit fsyncs it (:func:`~standgrid._atomic.atomic_output`).
    """

    def __init__(
        self,
        gpkg_path: str | os.PathLike[str],
        crs: CRSLike,
        *,
        base: str | os.PathLike[str] | None = None,
        durable: bool = True,
    ) -> None:
        self.path = Path(gpkg_path)
        self.durable = durable
        self.crs = _parse_crs(crs)
        self.base = Path(base) if base is not None else (self.path if self.path.exists() else None)
        self._stack: contextlib.ExitStack | None = None
        self._tmp: Path | None = None
        self._final_tmp = self.path

    def __enter__(self) -> IndexWriter:
        stack = contextlib.ExitStack()
        self._final_tmp = stack.enter_context(atomic_output(self.path, durable=self.durable))
        # GDAL warns about a GeoPackage without the .gpkg suffix: work under such a name and
        # hand the result to atomic_output's temporary at the end.
        self._tmp = self._final_tmp.with_name(self._final_tmp.name + ".gpkg")
        self._stack = stack
        if self.base is not None and self.base.exists():
            shutil.copyfile(self.base, self._tmp)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        assert self._stack is not None and self._tmp is not None
        try:
            if exc_type is None:
                os.replace(self._tmp, self._final_tmp)
        finally:
            self._tmp.unlink(missing_ok=True)
            self._stack.__exit__(exc_type, exc, tb)
            self._stack = self._tmp = None

    @property
    def working_path(self) -> Path:
        """The temporary file being written (valid inside the ``with`` block)."""
        if self._tmp is None:
            raise CatalogError("IndexWriter used outside its with-block", path=self.path)
        return self._tmp

    def write_layer(
        self,
        name: str,
        frame: gpd.GeoDataFrame | pd.DataFrame | Sequence[Mapping[str, Any]],
        *,
        style: str | None = None,
        style_name: str | None = None,
    ) -> None:
        """Write (or replace) a layer; standard layers are checked against ``LAYER_COLUMNS``.

        Geometry must already be in the index CRS (a frame without CRS is taken to be in it).
        ``style`` (QML) becomes the layer's default QGIS style.
        """
        import geopandas as gpd
        import pyogrio

        data = (
            layer_frame(name, frame, self.crs)
            if (name in LAYER_COLUMNS or not hasattr(frame, "columns"))
            else frame
        )
        if isinstance(data, gpd.GeoDataFrame):
            if data.crs is None:
                data = data.set_crs(self.crs.pyproj_crs)
            elif not self.crs.pyproj_crs.equals(data.crs):
                raise CRSError(
                    f"layer {name!r} is in {data.crs.to_string()}, the index is in {self.crs}",
                    path=self.path,
                )
        # A new file is GeoPackage 1.2: GDAL < 3.8 (still in many QGIS installs) opens 1.4
        # files with a "may only be partially supported" warning.
        options = {} if self.working_path.exists() else {"VERSION": GPKG_VERSION}
        try:
            pyogrio.write_dataframe(
                data, self.working_path, layer=name, driver="GPKG", dataset_options=options
            )
        except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError, ValueError) as exc:
            self._refuse_when_full(exc)
            raise CatalogError(f"cannot write layer {name!r}: {exc}", path=self.path) from exc
        if style is not None:
            self.add_style(name, style, style_name=style_name)

    def add_style(
        self,
        layer: str,
        qml: str,
        *,
        style_name: str | None = None,
        default: bool = True,
        description: str = "",
    ) -> None:
        """Add a QGIS style to a layer of the index being written."""
        try:
            styles.add_layer_style(
                self.working_path,
                layer,
                qml,
                style_name=style_name,
                default=default,
                description=description,
            )
        except CatalogError as exc:  # SQLite's error, maybe "database or disk is full"
            self._refuse_when_full(exc)
            raise

    def _refuse_when_full(self, exc: BaseException) -> None:
        """Raise :class:`OutOfSpaceError` (naming the index) when a GeoPackage write failed
        for want of room: SQLITE_FULL's "database or disk is full", or GDAL's vaguer errors
        ("failed to commit", "no such table" after a failed CREATE) with the disk full."""
        full = short_of_room_error(exc, self.working_path, self.path)
        if full is not None:
            raise full from exc


def write_index(
    gpkg_path: str | os.PathLike[str],
    *,
    crs: CRSLike,
    cells: Any = None,
    payloads: Any = None,
    trajectories: Any = None,
    gnss_fixes: Any = None,
    missions: Any = None,
    base: str | os.PathLike[str] | None = None,
) -> Path:
    """Write the standard layers that are given (frames or lists of row dicts) with styles.

    Layers not given are kept from ``base`` / the existing index. One atomic replace.
    """
    given = {
        "cells": cells,
        "payloads": payloads,
        "trajectories": trajectories,
        "gnss_fixes": gnss_fixes,
        "missions": missions,
    }
    with IndexWriter(gpkg_path, crs, base=base) as writer:
        for name, rows in given.items():
            if rows is not None:
                write_standard_layer(writer, name, rows)
    return Path(gpkg_path)


def write_standard_layer(writer: IndexWriter, name: str, rows: Any) -> None:
    """Write one of the standard layers (:data:`LAYER_COLUMNS`) with its QGIS styles."""
    frame = layer_frame(name, rows, writer.crs)
    if name == "cells":
        writer.write_layer("cells", frame, style=styles.load_qml("cells"))
        density = frame["density"].dropna()
        if len(density):
            writer.add_style(
                "cells",
                styles.density_style(float(density.min()), float(density.max())),
                style_name="cells by density",
                default=False,
                description="points per square metre",
            )
    elif name == "trajectories":
        names = sorted(str(m) for m in frame["mission"].unique())
        writer.write_layer(
            "trajectories",
            frame,
            style=styles.categorized_style("mission", names, geometry="line"),
        )
    elif name in ("payloads", "gnss_fixes"):
        writer.write_layer(name, frame, style=styles.load_qml(name))
    else:
        writer.write_layer(name, frame)


def iso_time(sec: int, nsec: int) -> str:
    """``(sec, nsec)`` UNIX stamp -> ISO 8601 UTC with nanoseconds (``...T22:13:20.000000005Z``)."""
    base = datetime.fromtimestamp(int(sec), UTC).strftime("%Y-%m-%dT%H:%M:%S")
    return f"{base}.{int(nsec):09d}Z"


# --- virtual point cloud -----------------------------------------------------------------


class VpcTile(NamedTuple):
    """One tile of a VPC: file, bounds (2D or 3D) in ``crs``, point count, ISO datetime."""

    path: str | os.PathLike[str]
    bounds: Sequence[float]
    crs: CRSLike
    point_count: int
    datetime: str | None = None


_PC_EXT = "https://stac-extensions.github.io/pointcloud/v1.0.0/schema.json"
_PROJ_EXT = "https://stac-extensions.github.io/projection/v1.1.0/schema.json"


def _ring(xmin: float, ymin: float, xmax: float, ymax: float) -> list[list[float]]:
    return [[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax], [xmin, ymin]]


def write_vpc(
    vpc_path: str | os.PathLike[str],
    tiles: Iterable[VpcTile | Sequence[Any]],
    *,
    durable: bool = True,
) -> Path:
    """Write a virtual point cloud: a STAC ItemCollection as QGIS 3.32+ and PDAL wrench read.

    Each tile is an Item with the ``pc`` and ``proj`` extensions; ``geometry``/``bbox`` in
    EPSG:4326 (the native bounds transformed, edges densified), ``proj:bbox``/
    ``proj:geometry`` native, ``assets.data.href`` relative to the VPC's folder (a relative
    tile path is taken as already relative to it, so a staged VPC can name final tiles).
    ``durable=False``: a VPC staged in a catalog transaction (its commit fsyncs it).
    """
    out = Path(vpc_path)
    root = out.parent.resolve()
    features = []
    for raw in tiles:
        tile = VpcTile(*raw)
        crs = _parse_crs(tile.crs)
        b = [float(v) for v in tile.bounds]
        if len(b) == 6:
            xmin, ymin, zmin, xmax, ymax, zmax = b
        elif len(b) == 4:
            xmin, ymin, xmax, ymax = b
            zmin = zmax = 0.0
        else:
            raise CatalogError(f"tile bounds must have 4 or 6 values, got {len(b)}", path=tile.path)
        lon0, lat0, lon1, lat1 = crs.transformer_to("EPSG:4326").transform_bounds(
            xmin, ymin, xmax, ymax, densify_pts=21
        )
        if Path(tile.path).is_absolute():
            relative = Path(os.path.relpath(Path(tile.path).resolve(), root)).as_posix()
        else:  # already relative to the VPC's folder (e.g. a catalog-relative tile path)
            relative = Path(tile.path).as_posix()
        href = "./" + relative
        laz = relative.lower().endswith(".laz")
        copc = relative.lower().endswith(".copc.laz")  # streamable by QGIS 3.26+ and PDAL
        encoding = (
            "application/vnd.laszip+copc"
            if copc
            else "application/vnd.laszip"
            if laz
            else "application/vnd.las"
        )
        properties: dict[str, Any] = {
            "datetime": tile.datetime
            or datetime.fromtimestamp(0, UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "pc:count": int(tile.point_count),
            "pc:type": "lidar",
            "pc:encoding": encoding,
            "pc:schemas": [],
            "proj:bbox": [xmin, ymin, zmin, xmax, ymax, zmax],
            "proj:geometry": {"type": "Polygon", "coordinates": [_ring(xmin, ymin, xmax, ymax)]},
            "proj:wkt2": crs.wkt2,
        }
        epsg = crs.epsg
        if epsg is not None:
            properties["proj:epsg"] = epsg
        rel_id = relative.removesuffix(".copc.laz").removesuffix(".laz").removesuffix(".las")
        feature: dict[str, Any] = {
            "type": "Feature",
            "stac_version": "1.0.0",
            "stac_extensions": [_PC_EXT, _PROJ_EXT],
            "id": rel_id,
            "geometry": {"type": "Polygon", "coordinates": [_ring(lon0, lat0, lon1, lat1)]},
            "bbox": [lon0, lat0, zmin, lon1, lat1, zmax],
            "properties": properties,
            "links": [],
            "assets": {
                "data": {
                    "href": href,
                    "roles": ["data"],
                    "type": properties["pc:encoding"],
                }
            },
        }
        features.append(feature)
    document = {"type": "FeatureCollection", "features": features}
    write_text_atomic(out, json.dumps(document, indent=2) + "\n", durable=durable)
    return out
