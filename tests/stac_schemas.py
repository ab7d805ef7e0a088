"""The STAC extension schemas (pointcloud, projection, raster) for validating offline.

pystac ships the core STAC schemas (``pystac/validation/jsonschemas``) but fetches an
extension's schema from its URL. The source distributions of pystac's extension packages
on PyPI (``pystac-ext-pointcloud`` and the others below) carry their tests' recorded HTTP
responses (VCR cassettes, ``tests/cassettes/**.yaml``), which hold those very schemas as
served at their URLs: :func:`extension_schemas` downloads these sdists with pip (once,
cached), takes each schema's recorded body and checks that its ``$id`` is its URL.

``python -m tests.stac_schemas`` fills the cache (``$STANDGRID_STAC_SCHEMAS`` or
``~/.cache/standgrid/stac-schemas``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any

import yaml

#: The sdists (pinned: their cassettes recorded the schemas of these URIs).
SDISTS = (
    "pystac-ext-pointcloud==1.0.1",
    "pystac-ext-projection==2.0.1",
    "pystac-ext-raster==1.1.1",
)
#: A URL that redirects to another (the PROJJSON schema the projection schema refers to).
ALIASES = {
    "https://proj.org/schemas/v0.7/projjson.schema.json": (
        "https://proj.org/en/latest/schemas/v0.7/projjson.schema.json"
    )
}


def cache_folder() -> Path:
    found = os.environ.get("STANDGRID_STAC_SCHEMAS")
    return Path(found) if found else Path.home() / ".cache" / "standgrid" / "stac-schemas"


def required_uris() -> set[str]:
    """The extension schema URIs pystac writes into standgrid's STAC documents."""
    from pystac.extensions import pointcloud, projection, raster

    return {pointcloud.SCHEMA_URI, projection.SCHEMA_URI, raster.SCHEMA_URI}


def _recorded(sdists: Path) -> dict[str, dict[str, Any]]:
    """URI -> JSON body of every 200 response recorded in the sdists' cassettes."""
    found: dict[str, dict[str, Any]] = {}
    for archive in sorted(sdists.glob("*.tar.gz")):
        with tarfile.open(archive) as tar:
            for member in tar.getmembers():
                if "/tests/cassettes/" not in member.name or not member.name.endswith(".yaml"):
                    continue
                handle = tar.extractfile(member)
                assert handle is not None
                for record in yaml.safe_load(handle)["interactions"]:
                    if record["response"]["status"]["code"] != 200:
                        continue
                    body = record["response"]["body"]["string"]
                    try:
                        found[record["request"]["uri"]] = json.loads(body)
                    except ValueError:
                        continue
    for alias, target in ALIASES.items():
        if target in found:
            found.setdefault(alias, found[target])
    return found


def extension_schemas() -> dict[str, dict[str, Any]]:
    """URI -> schema for the extension schemas (and what they refer to), from the cache or
    pip (RuntimeError when neither has them: PyPI unreachable, or other URIs needed)."""
    folder = cache_folder()
    index = folder / "schemas.json"
    needed = required_uris()
    if index.is_file():
        schemas: dict[str, dict[str, Any]] = json.loads(index.read_text("utf-8"))
        if needed <= schemas.keys():
            return schemas
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:"]
        try:
            done = subprocess.run(
                [*command, "--quiet", "--dest", tmp, *SDISTS],
                capture_output=True,
                text=True,
                timeout=90,
            )
        except (subprocess.TimeoutExpired, OSError) as exc:  # a slow or absent registry
            raise RuntimeError(f"pip download {' '.join(SDISTS)}: {exc}") from exc
        if done.returncode != 0:
            raise RuntimeError(f"pip download {' '.join(SDISTS)} failed: {done.stderr[-800:]}")
        schemas = _recorded(Path(tmp))
    missing = needed - schemas.keys()
    if missing:
        raise RuntimeError(f"the sdists {SDISTS} record no schema for {sorted(missing)}")
    for uri in needed:
        if str(schemas[uri].get("$id", "")).rstrip("#") != uri:
            raise RuntimeError(f"the schema recorded for {uri} has $id {schemas[uri].get('$id')}")
    folder.mkdir(parents=True, exist_ok=True)
    index.write_text(json.dumps(schemas, sort_keys=True), encoding="utf-8")
    return schemas


if __name__ == "__main__":
    print("\n".join(sorted(extension_schemas())))
