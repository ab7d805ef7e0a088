"""A catalog's ``catalog.json``: its format, read and checked, and the values it stores.

``catalog.json`` holds the grid (and its fingerprint), the CRS, the missions and the epochs,
and a ``generation`` every commit increments. Paths inside a catalog are plain relative
POSIX paths whose folders are not symlinks (:func:`relative_path`, :func:`refuse_symlinks`).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import Any

from standgrid.catalog.paths import CATALOG_FILE
from standgrid.errors import CatalogError, CatalogNotFoundError, StandgridError

STAGING_DIR = ".staging"
FORMAT_NAME = "standgrid-catalog"
FORMAT_VERSION = 1
SCHEMES = ("grid", "voronoi")
MAX_MISSION_NUMBER = 65535  # LAS point_source_id is uint16; 0 means "unknown"
#: Keys every catalog.json has.
REQUIRED_KEYS = (
    "format",
    "version",
    "crs",
    "scheme",
    "grid",
    "fingerprint",
    "missions",
    "epochs",
    "next_mission_number",
)


def utc_now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def definition_dict(definition: Mapping[str, Any] | Any) -> dict[str, Any]:
    if hasattr(definition, "to_dict"):
        definition = definition.to_dict()
    if not isinstance(definition, Mapping):
        raise CatalogError(f"grid definition must be a mapping, got {type(definition).__name__}")
    return jsonable(dict(definition))


def _json_default(value: Any) -> Any:
    """numpy arrays and scalars, paths and tuples as JSON (fit dicts often carry numpy)."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def jsonable(value: Any) -> Any:
    """A plain-JSON deep copy (raises CatalogError for values JSON cannot hold)."""
    try:
        return json.loads(json.dumps(value, sort_keys=True, default=_json_default))
    except (TypeError, ValueError) as exc:
        raise CatalogError(f"cannot store in catalog.json: {exc}") from exc


def grid_fingerprint(definition: Mapping[str, Any] | Any) -> str:
    """sha256 hex of the canonical JSON (sorted keys, no spaces) of a grid definition.

    The same text and hash as ``StandGrid.fingerprint`` for ``StandGrid.to_dict()``.
    """
    text = json.dumps(
        definition_dict(definition), sort_keys=True, separators=(",", ":"), allow_nan=False
    )
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def relative_path(rel: str | os.PathLike[str]) -> str:
    """A clean relative POSIX path inside the catalog (no absolute paths, no ``..``)."""
    path = PurePosixPath(Path(rel).as_posix())
    if path.is_absolute() or ".." in path.parts or not path.parts or path.parts[0] == STAGING_DIR:
        raise CatalogError(f"not a path inside the catalog: {rel}")
    return path.as_posix()


def is_standgrid_catalog(root: Path) -> bool:
    """True when ``root/catalog.json`` is a standgrid catalog's (its ``format``); another
    tool's catalog.json (a STAC catalog) is not."""
    try:
        with open(root / CATALOG_FILE, encoding="utf-8") as stream:
            state = json.load(stream)
    except (OSError, ValueError):
        return False
    return isinstance(state, dict) and state.get("format") == FORMAT_NAME


def read_state(path: Path) -> dict[str, Any]:
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CatalogError(
            f"malformed catalog.json: {exc.msg}", path=path, line=exc.lineno
        ) from exc
    except UnicodeDecodeError as exc:
        raise CatalogError(f"catalog.json is not UTF-8 text ({exc.reason})", path=path) from exc
    except OSError as exc:
        raise CatalogNotFoundError(f"cannot read catalog.json: {exc}", path=path) from exc
    if not isinstance(state, dict) or state.get("format") != FORMAT_NAME:
        raise CatalogNotFoundError("catalog.json is not a standgrid catalog", path=path)
    missing = [key for key in REQUIRED_KEYS if key not in state]
    if missing:
        raise CatalogError(f"catalog.json lacks {', '.join(missing)}", path=path)
    for key in ("missions", "epochs", "grid"):
        if not isinstance(state[key], dict):
            raise CatalogError(f"catalog.json: {key!r} is not an object", path=path)
    for name, record in state["missions"].items():
        if not isinstance(record, dict) or not isinstance(record.get("number"), int):
            raise CatalogError(f"catalog.json: mission {name!r} has no number", path=path)
    for epoch, entry in state["epochs"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("missions"), list):
            raise CatalogError(f"catalog.json: epoch {epoch!r} has no mission list", path=path)
    try:
        expected = grid_fingerprint(state["grid"])
    except StandgridError as exc:
        raise CatalogError(f"catalog.json: unusable grid ({exc.message})", path=path) from exc
    if state["fingerprint"] != expected:
        raise CatalogError(
            f"catalog.json: the stored fingerprint {state['fingerprint']} does not match its "
            f"grid (which has {expected}); the file was edited by hand",
            path=path,
        )
    return state


def file_stamp(path: Path) -> tuple[int, int, int] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return (stat.st_ino, stat.st_mtime_ns, stat.st_size)


def refuse_symlinks(root: Path, rel: str) -> None:
    """Refuse a catalog path whose folders inside the catalog are symlinks (writes through a
    symlink would land outside the catalog)."""
    current = root
    parts = PurePosixPath(rel).parts
    for index, part in enumerate(parts):
        current = current / part
        if current.is_symlink() and (index < len(parts) - 1 or part == STAGING_DIR):
            raise CatalogError(
                f"{PurePosixPath(*parts[: index + 1])} is a symlink; the catalog does not write "
                "through symlinks",
                path=current,
            )
        if not current.exists():
            return
