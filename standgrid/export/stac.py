"""A static STAC catalog of a catalog folder (``stac/``), built with pystac.

:func:`build_stac` turns plain descriptions of the epochs (their tiles, rasters and tables)
and comparisons into STAC JSON documents, keyed by their path relative to the ``stac/``
folder; every href in them (links and assets) is relative, so the folder can be moved or
served as it is. Nothing in them depends on the time it was built: the same catalog gives
the same bytes (:func:`dumps`).

The root catalog links to the index and the project; one collection per epoch has the VPC,
the index and the tables as assets, and an item per tile (pointcloud and projection
extensions) and per raster (raster and projection); one collection per comparison has its
tables as assets and an item per raster (the CHM difference). Where each document goes is
the caller's :class:`StacLayout` (``standgrid.catalog.paths`` spells it).

:func:`tile_schemas` and :func:`raster_bands` read what the items say from a file's header.
"""

from __future__ import annotations

import json
import math
import os
import posixpath
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from standgrid.crs import CRS

if TYPE_CHECKING:
    import pystac


@dataclass(frozen=True)
class StacLayout:
    """Where the documents go: catalog-relative paths of the root, of a collection (by id)
    and of an item (by collection id and item id)."""

    root: str
    collection: Callable[[str], str]
    item: Callable[[str, str], str]


#: Media types of the assets (the STAC best-practice ones where one exists).
MEDIA_TYPES = {
    ".laz": "application/vnd.laszip",
    ".las": "application/vnd.las",
    ".copc.laz": "application/vnd.laszip+copc",
    ".tif": "image/tiff; application=geotiff; profile=cloud-optimized",
    ".vpc": "application/geo+json",
    ".gpkg": "application/geopackage+sqlite3",
    ".csv": "text/csv",
    ".parquet": "application/vnd.apache.parquet",
    ".qgz": "application/x-qgis-project",
}
# an absolute stand-in for the catalog folder: pystac relativizes hrefs against it
_BASE = "/catalog"
_EPOCH_ZERO = datetime.fromtimestamp(0, UTC)
#: The end of an interval that claims nothing (an epoch without a date).
_NO_END = datetime(9999, 12, 31, 23, 59, 59, tzinfo=UTC)
_NO_DATE = "the epoch has no date (tiled with an epoch label from missions without one)"


@dataclass(frozen=True)
class Band:
    """One raster band as the raster extension describes it."""

    data_type: str
    #: the no-data value (``"nan"`` for NaN, as the raster extension spells it)
    nodata: float | str | None
    resolution: float
    unit: str | None = None
    description: str | None = None


@dataclass(frozen=True)
class StacTile:
    """One tile: its catalog-relative path, point count, file bounds
    ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in the catalog CRS and dimensions."""

    cell_id: str
    path: str
    count: int
    bounds: tuple[float, ...]
    schemas: tuple[Mapping[str, Any], ...] = ()

    @property
    def encoding(self) -> str:
        name = self.path.lower()
        return "COPC" if name.endswith(".copc.laz") else "LAZ" if name.endswith(".laz") else "LAS"


@dataclass(frozen=True)
class StacRaster:
    """One single-band GeoTIFF: name, catalog-relative path, bounds ``(xmin, ymin, xmax,
    ymax)``, ``shape`` (rows, cols), the GDAL ``transform`` (6 numbers) and its band."""

    name: str
    path: str
    bounds: tuple[float, float, float, float]
    shape: tuple[int, int]
    transform: tuple[float, ...]
    band: Band
    title: str | None = None


@dataclass(frozen=True)
class StacAsset:
    """A file listed as an asset of a collection (the VPC, the index, a table)."""

    key: str
    path: str
    title: str
    roles: tuple[str, ...] = ("data",)


@dataclass(frozen=True)
class StacGroup:
    """One collection: an epoch (``date`` its day) or a comparison (``dates`` its two)."""

    id: str
    title: str
    description: str
    dates: tuple[str | None, ...]
    tiles: tuple[StacTile, ...] = ()
    rasters: tuple[StacRaster, ...] = ()
    assets: tuple[StacAsset, ...] = ()
    #: the prefix of its items' ids (the epoch label, the comparison key)
    prefix: str = ""
    properties: Mapping[str, Any] = field(default_factory=dict)


def _media_type(path: str) -> str | None:
    name = path.lower()
    for suffix in sorted(MEDIA_TYPES, key=len, reverse=True):
        if name.endswith(suffix):
            return MEDIA_TYPES[suffix]
    return None


def _day(date: str) -> datetime:
    """Midnight UTC of an ISO day (``YYYY-MM-DD...``)."""
    return datetime.fromisoformat(str(date)[:10]).replace(tzinfo=UTC)


def _wgs84(crs: CRS, xmin: float, ymin: float, xmax: float, ymax: float) -> list[float]:
    lon0, lat0, lon1, lat1 = crs.transformer_to("EPSG:4326").transform_bounds(
        xmin, ymin, xmax, ymax, densify_pts=21
    )
    return [float(lon0), float(lat0), float(lon1), float(lat1)]


def _polygon(b: Sequence[float]) -> dict[str, Any]:
    x0, y0, x1, y1 = b
    return {"type": "Polygon", "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}


def _href(path: str) -> str:
    return posixpath.join(_BASE, path)


def _projection(obj: Any, crs: CRS, bbox: Sequence[float]) -> Any:
    from pystac.extensions.projection import ProjectionExtension

    proj = ProjectionExtension.ext(obj, add_if_missing=True)
    authority = crs.authority
    if authority is not None:
        proj.code = f"{authority[0]}:{authority[1]}"
    else:
        proj.wkt2 = crs.wkt2
    proj.bbox = [float(v) for v in bbox]
    return proj


def item_id(prefix: str, name: str) -> str:
    """The id of the item of a tile (``name``: its cell id) or a raster (its name)."""
    return f"{prefix}-{name}"


def _dated(when: datetime | None) -> dict[str, Any]:
    """An item's time: the epoch's day; or, for an epoch without a date, no datetime and
    an interval claiming nothing (any time), with the reason."""
    if when is not None:
        return {"datetime": when}
    return {
        "datetime": None,
        "start_datetime": _EPOCH_ZERO,
        "end_datetime": _NO_END,
    }


def _date_note(when: datetime | None) -> dict[str, Any]:
    return {} if when is not None else {"standgrid:date": None, "standgrid:date_note": _NO_DATE}


def _tile_item(tile: StacTile, prefix: str, crs: CRS, when: datetime | None) -> pystac.Item:
    import pystac
    from pystac.extensions.pointcloud import (
        PhenomenologyType,
        PointcloudExtension,
        Schema,
        SchemaType,
    )

    xmin, ymin, zmin, xmax, ymax, zmax = (float(v) for v in tile.bounds)
    box = _wgs84(crs, xmin, ymin, xmax, ymax)
    item = pystac.Item(
        id=item_id(prefix, tile.cell_id),
        geometry=_polygon(box),
        bbox=[box[0], box[1], zmin, box[2], box[3], zmax],
        **_dated(when),
        properties={"standgrid:cell_id": tile.cell_id, **_date_note(when)},
    )
    pc = PointcloudExtension.ext(item, add_if_missing=True)
    pc.apply(
        count=int(tile.count),
        type=PhenomenologyType.LIDAR,
        encoding=tile.encoding,
        schemas=[
            Schema.create(name=str(s["name"]), size=int(s["size"]), type=SchemaType(s["type"]))
            for s in tile.schemas
        ],
    )
    _projection(item, crs, [xmin, ymin, zmin, xmax, ymax, zmax])
    item.add_asset(
        "data",
        pystac.Asset(
            href=_href(tile.path),
            media_type=_media_type(tile.path),
            roles=["data"],
            title=f"tile {tile.cell_id}",
        ),
    )
    return item


def _raster_item(raster: StacRaster, prefix: str, crs: CRS, when: datetime | None) -> pystac.Item:
    import pystac
    from pystac.extensions.raster import DataType, NoDataStrings, RasterBand, RasterExtension

    box = _wgs84(crs, *raster.bounds)
    item = pystac.Item(
        id=item_id(prefix, raster.name),
        geometry=_polygon(box),
        bbox=box,
        **_dated(when),
        properties={**({"title": raster.title} if raster.title else {}), **_date_note(when)},
    )
    proj = _projection(item, crs, raster.bounds)
    proj.shape = [int(v) for v in raster.shape]
    proj.transform = [float(v) for v in raster.transform]
    asset = pystac.Asset(
        href=_href(raster.path),
        media_type=_media_type(raster.path),
        roles=["data"],
        title=raster.band.description or raster.name,
    )
    item.add_asset("data", asset)
    band = raster.band
    RasterExtension.ext(asset, add_if_missing=True).bands = [
        RasterBand.create(
            nodata=NoDataStrings(band.nodata) if isinstance(band.nodata, str) else band.nodata,
            data_type=DataType(band.data_type),
            spatial_resolution=float(band.resolution),
            unit=band.unit,
        )
    ]
    return item


def _union(boxes: Iterable[Sequence[float]]) -> list[float] | None:
    found = [(b[0], b[1], b[-3], b[-2]) if len(b) == 6 else tuple(b) for b in boxes]
    if not found:
        return None
    return [
        min(b[0] for b in found),
        min(b[1] for b in found),
        max(b[2] for b in found),
        max(b[3] for b in found),
    ]


def _collection(group: StacGroup, crs: CRS) -> pystac.Collection:
    import pystac

    dates = sorted(_day(d) for d in group.dates if d)
    when = dates[0] if dates else None  # no date: said, not made up
    interval: list[list[datetime | None]] = [[dates[0], dates[-1]] if dates else [None, None]]
    items = [_tile_item(t, group.prefix, crs, when) for t in sorted(group.tiles, key=_by_cell)]
    items += [_raster_item(r, group.prefix, crs, when) for r in sorted(group.rasters, key=_by_name)]
    box = _union(item.bbox for item in items if item.bbox) or [-180.0, -90.0, 180.0, 90.0]
    collection = pystac.Collection(
        id=group.id,
        description=group.description,
        title=group.title,
        extent=pystac.Extent(
            pystac.SpatialExtent([box]),
            pystac.TemporalExtent(interval),
        ),
        license="other",
        extra_fields=dict(group.properties) or None,
    )
    for asset in sorted(group.assets, key=lambda a: a.key):
        collection.add_asset(
            asset.key,
            pystac.Asset(
                href=_href(asset.path),
                media_type=_media_type(asset.path),
                roles=list(asset.roles),
                title=asset.title,
            ),
        )
    for item in items:
        collection.add_item(item)
    return collection


def _by_cell(tile: StacTile) -> str:
    return tile.cell_id


def _by_name(raster: StacRaster) -> str:
    return raster.name


def build_stac(
    title: str,
    crs: str,
    groups: Sequence[StacGroup],
    layout: StacLayout,
    links: Sequence[StacAsset] = (),
) -> dict[str, dict[str, Any]]:
    """The STAC documents of a catalog: ``{catalog-relative path: JSON}`` as ``layout``
    places them, every href relative. ``links``: catalog files the root links to
    (``rel: related``)."""
    import pystac

    crs_value = CRS.of(crs)
    root = pystac.Catalog(
        id="standgrid",
        title=title,
        description=f"standgrid catalog {title}: point-cloud tiles, rasters and tables",
        catalog_type=pystac.CatalogType.SELF_CONTAINED,
    )
    root.set_self_href(_href(layout.root))
    for link in sorted(links, key=lambda a: a.key):
        root.add_link(
            pystac.Link(
                "related",
                # kept as it is: relative to the root's folder
                posixpath.relpath(link.path, posixpath.dirname(layout.root)),
                media_type=_media_type(link.path),
                title=link.title,
            )
        )
    collections = [_collection(g, crs_value) for g in sorted(groups, key=lambda g: g.id)]
    for collection in collections:
        root.add_child(collection)
        collection.set_self_href(_href(layout.collection(collection.id)))
        for item in collection.get_items():
            item.set_self_href(_href(layout.item(collection.id, item.id)))
            item.make_asset_hrefs_relative()
        collection.make_asset_hrefs_relative()
    documents: dict[str, dict[str, Any]] = {
        layout.root: root.to_dict(include_self_link=False, transform_hrefs=True)
    }
    for collection in collections:
        documents[layout.collection(collection.id)] = collection.to_dict(
            include_self_link=False, transform_hrefs=True
        )
        for item in collection.get_items():
            documents[layout.item(collection.id, item.id)] = item.to_dict(
                include_self_link=False, transform_hrefs=True
            )
    return documents


def dumps(document: Mapping[str, Any]) -> bytes:
    """A STAC document's bytes in pystac's key order, ending in a newline: the catalog and
    collections indented, items (the many) on one line (JSON's C encoder: 10x faster)."""
    indent = None if document.get("type") == "Feature" else 2
    return (json.dumps(document, indent=indent, ensure_ascii=False) + "\n").encode("utf-8")


# --- what the items say, read from the files' headers ------------------------------------


def tile_schemas(path: str | os.PathLike[str]) -> tuple[dict[str, Any], ...]:
    """The ``pc:schemas`` of a LAS/LAZ/COPC file from its header (no point is read): X, Y, Z
    as 8-byte floats (scaled), bit fields as 1-byte unsigned, the rest as stored."""
    import laspy
    from laspy.point.dims import DimensionKind

    from standgrid.errors import FormatError

    try:
        with laspy.open(os.fspath(path)) as reader:
            dimensions = list(reader.header.point_format.dimensions)
    except (OSError, laspy.errors.LaspyException) as exc:
        raise FormatError(f"cannot read the tile's header: {exc}", path=path) from exc
    kinds = {
        DimensionKind.FloatingPoint: "floating",
        DimensionKind.SignedInteger: "signed",
        DimensionKind.UnsignedInteger: "unsigned",
        DimensionKind.BitField: "unsigned",
    }
    schemas = []
    for dim in dimensions:
        if dim.name in ("X", "Y", "Z"):
            schemas.append({"name": dim.name, "size": 8, "type": "floating"})
        elif dim.kind == DimensionKind.BitField:
            schemas.append({"name": dim.name, "size": 1, "type": "unsigned"})
        else:
            size = max(1, (dim.num_bits * max(1, dim.num_elements or 1)) // 8)
            schemas.append({"name": dim.name, "size": size, "type": kinds[dim.kind]})
    return tuple(schemas)


def raster_info(name: str, rel: str, path: str | os.PathLike[str], unit: str | None) -> StacRaster:
    """A single-band GeoTIFF described from its header (bounds, shape, transform, band)."""
    import rasterio

    from standgrid.errors import FormatError

    try:
        with rasterio.open(os.fspath(path)) as ds:
            nodata = ds.nodata
            band = Band(
                data_type=str(ds.dtypes[0]),
                nodata=None if nodata is None else "nan" if math.isnan(nodata) else float(nodata),
                resolution=float(abs(ds.res[0])),
                unit=unit,
                description=ds.descriptions[0] or None,
            )
            b = ds.bounds
            return StacRaster(
                name=name,
                path=rel,
                bounds=(float(b.left), float(b.bottom), float(b.right), float(b.top)),
                shape=(int(ds.height), int(ds.width)),
                transform=tuple(float(v) for v in ds.transform[:6]),
                band=band,
                title=band.description,
            )
    except rasterio.errors.RasterioError as exc:
        raise FormatError(f"cannot read the raster's header: {exc}", path=path) from exc
