"""The catalog's static STAC catalog, ``stac/``: staged by every commit from what it commits.

:func:`stage_stac` runs in :meth:`Transaction.commit` (so tile, enrich, compare and run all
leave a STAC catalog consistent with the index): it describes each epoch from its VPC (the
tiles' paths, point counts and file bounds as written), its tiles' headers (their
dimensions), its rasters' headers and the tables the transaction will commit, builds the
documents (:func:`standgrid.export.stac.build_stac`) and stages only those whose bytes
change, deleting the documents of tiles, rasters or epochs that are gone.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from standgrid.catalog import paths

if TYPE_CHECKING:
    from standgrid.catalog.transaction import Transaction
    from standgrid.export.stac import StacAsset, StacGroup, StacRaster, StacTile

STAC, STAC_ROOT = paths.STAC, paths.STAC_ROOT
#: An epoch's rasters and their units (raster extension ``unit``; None: unitless).
RASTER_UNITS: dict[str, str | None] = {
    "dtm": "m",
    "chm": "m",
    "density": "1/m^2",
    "observed": None,
    paths.ELEVATION_MAP: "m",
}
_TABLE_WORDS = {"csv": "CSV", "parquet": "Parquet"}


def _tiles(txn: Transaction, epoch: str) -> list[StacTile]:
    """The epoch's tiles from its VPC as this transaction commits it."""
    from standgrid.errors import CatalogError
    from standgrid.export.stac import StacTile, tile_schemas

    vpc = txn.current(paths.vpc(epoch))
    if vpc is None:
        return []
    try:
        features = json.loads(vpc.read_text("utf-8"))["features"]
    except (ValueError, KeyError) as exc:
        raise CatalogError(f"unreadable VPC: {exc}", path=vpc) from exc
    tiles = []
    for feature in features:
        rel = str(feature["assets"]["data"]["href"]).removeprefix("./")
        found = txn.current(rel)
        if found is None:  # listed, not there: left out (status reports it)
            continue
        cell_id = Path(rel).name.split(".", 1)[0]
        props = feature["properties"]
        schemas = None
        if not found.is_relative_to(txn.folder):  # not rewritten: as its item says
            schemas = _committed_schemas(txn, item_path(epoch, cell_id))
        tiles.append(
            StacTile(
                cell_id=cell_id,
                path=rel,
                count=int(props["pc:count"]),
                bounds=tuple(float(v) for v in props["proj:bbox"]),
                schemas=tile_schemas(found) if schemas is None else schemas,
            )
        )
    return tiles


def epoch_collection(epoch: str) -> str:
    """The id of an epoch's STAC collection."""
    return f"epoch-{epoch}"


def item_path(epoch: str, cell_id: str) -> str:
    """The catalog-relative path of the STAC item of a tile."""
    from standgrid.export.stac import item_id

    return paths.stac_item(epoch_collection(epoch), item_id(epoch, cell_id))


def _committed_schemas(txn: Transaction, rel: str) -> tuple[dict[str, Any], ...] | None:
    """The ``pc:schemas`` of a tile's committed item (each commit writes the items of the
    tiles it commits, so an unchanged tile's item holds its header's dimensions); None
    when there is none (an older catalog) or it is unreadable."""
    path = txn.catalog.root / rel
    try:
        found = json.loads(path.read_bytes())["properties"]["pc:schemas"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not isinstance(found, list) or not found:
        return None
    wanted = {"name": str, "size": int, "type": str}
    for entry in found:  # a damaged entry: read the tile's header instead
        if not isinstance(entry, dict) or not all(
            isinstance(entry.get(k), t) for k, t in wanted.items()
        ):
            return None
    return tuple(dict(s) for s in found)


def _raster(txn: Transaction, name: str, rel: str, unit: str | None) -> StacRaster | None:
    from standgrid.export.stac import raster_info

    found = txn.current(rel)
    return None if found is None else raster_info(name, rel, found, unit)


def _asset(txn: Transaction, key: str, rel: str, title: str, *roles: str) -> list[StacAsset]:
    from standgrid.export.stac import StacAsset

    if txn.current(rel) is None:
        return []
    return [StacAsset(key, rel, title, tuple(roles) or ("data",))]


def _tables(txn: Transaction, key: str, stem: str, words: str) -> list[StacAsset]:
    return [
        a
        for ext in paths.TABLE_FORMATS
        for a in _asset(txn, f"{key}_{ext}", f"{stem}.{ext}", f"{words} ({_TABLE_WORDS[ext]})")
    ]


def _epoch_group(txn: Transaction, epoch: str) -> StacGroup:
    from standgrid.export.stac import StacGroup

    record = txn.epoch_record(epoch)
    rasters = [
        found
        for name, unit in sorted(RASTER_UNITS.items())
        if (found := _raster(txn, name, paths.raster(epoch, name), unit)) is not None
    ]
    assets = [
        *_asset(txn, "vpc", paths.vpc(epoch), f"virtual point cloud of epoch {epoch}", "data"),
        *_asset(txn, "index", paths.INDEX, "GeoPackage index (every epoch)", "metadata"),
        *_tables(txn, "tree_list", paths.tree_list_stem(epoch), f"tree list of epoch {epoch}"),
        *_tables(txn, "stand_metrics", paths.METRICS_TABLE, "stand metrics (every epoch)"),
    ]
    return StacGroup(
        id=epoch_collection(epoch),
        title=f"Epoch {epoch}",
        description=f"Point-cloud tiles and rasters of epoch {epoch}",
        dates=(record.date if record else None,),
        tiles=tuple(_tiles(txn, epoch)),
        rasters=tuple(rasters),
        assets=tuple(assets),
        prefix=epoch,
        properties={
            "standgrid:epoch": epoch,
            "standgrid:missions": list(record.missions) if record else [],
            "standgrid:enrichment": record.state if record else "",
        },
    )


def _comparison_group(txn: Transaction, key: str, entry: dict[str, Any]) -> StacGroup:
    from standgrid.export.stac import StacGroup

    epoch_from, epoch_to = str(entry.get("from", "")), str(entry.get("to", ""))
    outputs = {str(k): str(v) for k, v in (entry.get("outputs") or {}).items()}
    rasters, assets = [], []
    for name, rel in sorted(outputs.items()):
        if rel.endswith(".tif"):
            found = _raster(txn, Path(rel).stem, rel, "m")
            rasters += [found] if found is not None else []
        elif rel.endswith((".csv", ".parquet")):
            words = f"{Path(rel).stem.replace('_', ' ')} {epoch_from}→{epoch_to}"
            assets += _asset(txn, name, rel, f"{words} ({_TABLE_WORDS[rel.rsplit('.', 1)[1]]})")
        elif rel == paths.INDEX:
            assets += _asset(txn, "index", rel, "GeoPackage index (every epoch)", "metadata")
    dates = []
    for epoch in (epoch_from, epoch_to):
        record = txn.epoch_record(epoch)
        dates.append(record.date if record else None)
    return StacGroup(
        id=f"compare-{key}",
        title=f"Change {epoch_from}→{epoch_to}",
        description=f"Comparison of epoch {epoch_from} with epoch {epoch_to}",
        dates=tuple(dates),
        rasters=tuple(rasters),
        assets=tuple(assets),
        prefix=key,
        properties={"standgrid:from": epoch_from, "standgrid:to": epoch_to},
    )


def stac_documents(txn: Transaction) -> dict[str, bytes] | None:
    """The catalog-relative path and bytes of every STAC document of what ``txn`` commits;
    None before the catalog has a CRS and an index."""
    from standgrid.export.stac import StacAsset, StacLayout, build_stac, dumps

    crs = txn.state.get("crs")
    if not crs or txn.current(paths.INDEX) is None:
        return None
    groups = [_epoch_group(txn, epoch) for epoch in sorted(txn.state.get("epochs", {}))]
    groups += [
        _comparison_group(txn, key, dict(entry))
        for key, entry in sorted(txn.state.get("comparisons", {}).items())
    ]
    links = [
        StacAsset("index", paths.INDEX, "GeoPackage index"),
        *_asset(txn, "project", paths.QGIS_PROJECT, "QGIS project"),
        *_tables(txn, "stand_metrics", paths.METRICS_TABLE, "stand metrics (every epoch)"),
    ]
    layout = StacLayout(paths.STAC_ROOT, paths.stac_collection, paths.stac_item)
    documents = build_stac(txn.catalog.root.name, str(crs), groups, layout, links)
    return {rel: dumps(doc) for rel, doc in documents.items()}


def stac_files(root: str | os.PathLike[str]) -> set[str]:
    """Catalog-relative paths of the STAC documents in the catalog folder ``root`` (regular
    ``.json`` files under ``stac/``, symbolic links never followed)."""
    base = Path(root)
    found: set[str] = set()
    for folder, dirs, files in os.walk(base / STAC):
        here = Path(folder)
        dirs[:] = sorted(d for d in dirs if not (here / d).is_symlink())
        for name in files:
            path = here / name
            if name.endswith(".json") and not path.is_symlink() and path.is_file():
                found.add(path.relative_to(base).as_posix())
    return found


def is_stac_file(root: str | os.PathLike[str], relative: str) -> bool:
    """Whether ``relative`` names a STAC document of the catalog at ``root``: a regular
    ``.json`` file under ``stac/``, reached through no symbolic link and no ``..`` (checked
    on that one path: no walk)."""
    parts = relative.split("/")
    if len(parts) < 2 or parts[0] != STAC or not relative.endswith(".json"):
        return False
    if any(p in ("", ".", "..") for p in parts):
        return False
    path = Path(root)
    for part in parts:
        path = path / part
        if path.is_symlink():
            return False
    return path.is_file()


def stage_stac(txn: Transaction) -> None:
    """Stage the STAC documents of what ``txn`` commits (only those that change) and delete
    those of what is gone; nothing before the catalog has a CRS and an index."""
    documents = stac_documents(txn)
    if documents is None:
        return
    existing = stac_files(txn.catalog.root)
    existing |= {rel for rel in txn._staged if rel.startswith(f"{STAC}/")}
    for rel in sorted(existing - documents.keys()):
        txn.delete(rel)
    for rel, data in sorted(documents.items()):
        current = txn.current(rel)
        if current is not None and current.read_bytes() == data:
            continue
        txn.stage(rel).write_bytes(data)
