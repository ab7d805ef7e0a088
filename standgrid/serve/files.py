"""The catalog's files over HTTP with range requests (``/files/<catalog-relative path>``).

Only files the catalog publishes are served: the index, each epoch's VPC, tiles, rasters
(and their QGIS styles) and tree lists, the stand metrics tables and the outputs of each
comparison, the QGIS project and the static STAC catalog (``/files/stac/catalog.json``:
its relative links and asset hrefs resolve to ``/files/...``, so a STAC client walks it
over HTTP), all spelled by :mod:`standgrid.catalog.paths`, recorded in catalog.json or
written under ``stac/`` by the last commit. A
requested path is looked up in that set; it never becomes a path by itself. The VPC's
relative tile links resolve to ``/files/tiles/...``, so QGIS and PDAL follow them.

Ranges (206 Partial Content, ``Accept-Ranges``, ``Content-Range``, multipart for several)
are Starlette's ``FileResponse``; a range this module finds unsatisfiable or malformed is a
416 or 400 problem document.
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, JSONResponse

from standgrid.catalog import Catalog, paths
from standgrid.catalog.stac import STAC, is_stac_file, stac_files
from standgrid.serve.problems import Problem
from standgrid.serve.snapshot import snapshot

MEDIA_TYPES = {
    ".laz": "application/vnd.laszip",
    ".las": "application/vnd.las",
    ".tif": "image/tiff; application=geotiff",
    ".qml": "text/xml",
    ".vpc": "application/json",
    ".csv": "text/csv",
    ".parquet": "application/vnd.apache.parquet",
    ".gpkg": "application/geopackage+sqlite3",
    ".qgz": "application/x-qgis-project",
    ".json": "application/json",
}
_RANGE = re.compile(r"^\s*(\d*)\s*-\s*(\d*)\s*$")
#: Most ranges one request may ask for (GDAL asks for a few; hundreds is an attack).
MAX_RANGES = 16

router = APIRouter(tags=["Files"])


def published_files(catalog: Catalog, *, stac: bool = True) -> set[str]:
    """Catalog-relative paths of every file the service may serve (existing or not); with
    ``stac``, the STAC documents under ``stac/`` too (found by walking that folder)."""
    rels = {
        paths.INDEX,
        paths.QGIS_PROJECT,
        *(paths.stand_metrics(ext) for ext in paths.TABLE_FORMATS),
    }
    if stac:
        rels.update(stac_files(catalog.root))
    for epoch in catalog.epochs:
        rels.add(paths.vpc(epoch))
        rels.update(catalog.tiles(epoch))
        rels.update(paths.tree_list(epoch, ext) for ext in paths.TABLE_FORMATS)
        folder = catalog.path(paths.rasters_folder(epoch))
        if folder.is_dir():
            for file in folder.iterdir():
                if file.suffix == ".tif":
                    rels.update(
                        {paths.raster(epoch, file.stem), paths.raster_style(epoch, file.stem)}
                    )
    for entry in catalog.comparisons.values():
        rels.update(str(rel) for rel in (entry.get("outputs") or {}).values())
    return rels


def check_range(header: str | None, size: int) -> None:
    """A 400 problem for a malformed ``Range``, a 416 when no range of it is satisfiable."""
    if header is None:
        return
    unit, _, spec = header.partition("=")
    if unit.strip().lower() != "bytes" or not spec.strip():
        raise Problem(400, f"Range: {header!r} is not 'bytes=<start>-<end>[, ...]'")
    parts = spec.split(",")
    if len(parts) > MAX_RANGES:
        raise Problem(400, f"Range: {len(parts)} ranges; at most {MAX_RANGES} per request")
    satisfiable = False
    for part in parts:
        match = _RANGE.match(part)
        if match is None or (match[1] == "" and match[2] == ""):
            raise Problem(400, f"Range: {part.strip()!r} is not '<start>-<end>'")
        start, end = match[1], match[2]
        if start and end and int(end) < int(start):
            raise Problem(400, f"Range: {part.strip()!r} ends before it starts")
        if (start and int(start) < size) or (not start and int(end) > 0 and size > 0):
            satisfiable = True
    if not satisfiable:
        raise Problem(
            416,
            f"Range: {header!r} lies outside the file's {size} bytes",
            headers={"Content-Range": f"bytes */{size}"},
        )


@router.get("/files", summary="The files the catalog publishes, with their URLs")
def listing(request: Request) -> JSONResponse:
    root = request.app.state.catalog_root
    with snapshot(root, with_index=False) as snap:
        present = sorted(r for r in published_files(snap.catalog) if snap.catalog.path(r).is_file())
        sizes = {r: snap.catalog.path(r).stat().st_size for r in present}
    base = str(request.base_url).rstrip("/")
    return JSONResponse(
        {"files": [{"path": r, "size": sizes[r], "href": f"{base}/files/{r}"} for r in present]}
    )


_FILE_RESPONSES: dict[int | str, dict[str, Any]] = {
    206: {"description": "the requested byte ranges"},
    416: {"description": "no requested range is inside the file"},
}


# one operation per method: OpenAPI operation ids are unique
@router.get(
    "/files/{relative:path}",
    operation_id="get_file",
    responses=_FILE_RESPONSES,
    summary="One file of the catalog (HTTP range requests supported)",
)
@router.head(
    "/files/{relative:path}",
    operation_id="head_file",
    responses=_FILE_RESPONSES,
    summary="One file's headers (size, type, Accept-Ranges)",
)
def file(request: Request, relative: str) -> Any:
    root = request.app.state.catalog_root
    with snapshot(root, with_index=False) as snap:
        in_stac = relative.startswith(f"{STAC}/")  # that one path checked: no walk
        if in_stac and not is_stac_file(snap.catalog.root, relative):
            raise Problem(404, f"the catalog publishes no file {relative!r} (see /files)")
        if not in_stac and relative not in published_files(snap.catalog, stac=False):
            raise Problem(404, f"the catalog publishes no file {relative!r} (see /files)")
        path = snap.catalog.path(relative)
        try:
            # Opened under the readers lock: a commit renaming a new file in later does
            # not change what this response sends.
            handle = path.open("rb")
        except FileNotFoundError as exc:
            raise Problem(404, f"{relative!r} is not in the catalog (yet)") from exc
    size = handle.seek(0, 2)
    handle.seek(0)
    try:
        check_range(request.headers.get("range"), size)
    except Problem:
        handle.close()
        raise
    return _OpenFileResponse(handle, path, media_type=MEDIA_TYPES.get(path.suffix))


class _OpenFileResponse(FileResponse):
    """A FileResponse reading from a file opened earlier (its inode is fixed)."""

    def __init__(self, handle: Any, path: Any, **kwargs: Any) -> None:
        import os

        self._handle = handle
        # Linux: the descriptor's own path, so the bytes sent are those of the opened inode;
        # elsewhere the path itself (a commit in between could then change the file).
        fd_path = f"/proc/self/fd/{handle.fileno()}"
        source = fd_path if os.path.exists(fd_path) else str(path)
        super().__init__(source, stat_result=os.fstat(handle.fileno()), **kwargs)
        self.headers.setdefault("content-disposition", f'inline; filename="{path.name}"')

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._handle.close()
