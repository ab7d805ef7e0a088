"""Digest a catalog's content, leaving out what differs between two identical runs.

Two runs over the same inputs must give the same digest: the tile bytes, the rasters, the
tables byte for byte; ``catalog.json`` without its timestamps and random enrichment ids; the
GeoPackage's rows without ``gpkg_contents.last_change`` and ingest times; the QGIS project's
XML without its creation stamps. Used to show that a redesign keeps outputs bit for bit:

    python benchmarks/catalog_digest.py CATALOG              # one digest per file
    python benchmarks/catalog_digest.py OLD_CATALOG NEW_CATALOG   # differences; exit 1 if any
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sqlite3
import sys
import zipfile
from pathlib import Path
from typing import Any

_VOLATILE_KEYS = {"created", "ingested", "enrichment_id", "updated", "committed"}
_VOLATILE_COLUMNS = {"last_change", "update_time", "ingested", "created", "enrichment_id"}


def _scrub(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _scrub(v) for k, v in sorted(value.items()) if k not in _VOLATILE_KEYS}
    if isinstance(value, list):
        return [_scrub(v) for v in value]
    return value


def _gpkg_digest(path: Path) -> str:
    digest = hashlib.sha256()
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        tables = [
            r[0]
            for r in con.execute("SELECT name FROM sqlite_master WHERE type='table' ORDER BY name")
        ]
        for table in tables:
            if table.startswith("sqlite_") or table.startswith("rtree_"):
                continue
            columns = [r[1] for r in con.execute(f'PRAGMA table_info("{table}")')]
            kept = [c for c in columns if c not in _VOLATILE_COLUMNS]
            digest.update(f"{table}:{','.join(kept)}\n".encode())
            if not kept:
                continue
            select = ",".join(f'"{c}"' for c in kept)
            rows = con.execute(f'SELECT {select} FROM "{table}"').fetchall()
            for row in sorted(rows, key=repr):
                digest.update(repr(row).encode())
    finally:
        con.close()
    return digest.hexdigest()


def _qgz_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with zipfile.ZipFile(path) as archive:
        for name in sorted(archive.namelist()):
            data = archive.read(name)
            if name.endswith(".qgs"):
                text = data.decode("utf-8", "replace")
                text = re.sub(
                    r'(saveDateTime|creationDateTime|creation|id)="[^"]*"', r'\1=""', text
                )
                text = re.sub(r"<creation>.*?</creation>", "", text, flags=re.S)
                # the project is named after its folder
                text = re.sub(r'projectname="[^"]*"', 'projectname=""', text)
                text = re.sub(r"<title>[^<]*</title>", "<title/>", text)
                data = text.encode()
            digest.update(name.encode() + b"\0" + hashlib.sha256(data).digest())
    return digest.hexdigest()


def digest_file(path: Path) -> str:
    """The digest of one catalog file, volatile parts left out."""
    if path.name == "catalog.json" or path.suffix == ".vpc":
        return hashlib.sha256(
            json.dumps(_scrub(json.loads(path.read_text())), sort_keys=True).encode()
        ).hexdigest()
    if path.suffix == ".gpkg":
        return _gpkg_digest(path)
    if path.suffix == ".qgz":
        return _qgz_digest(path)
    return hashlib.sha256(path.read_bytes()).hexdigest()


def digest_catalog(root: Path) -> dict[str, str]:
    """Relative path -> digest for every file of a catalog (locks and staging left out)."""
    out: dict[str, str] = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if not path.is_file() or rel.startswith(".") or "/." in rel or rel.endswith(".lock"):
            continue
        out[rel] = digest_file(path)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("catalogs", nargs="+", type=Path)
    args = parser.parse_args(argv)
    if len(args.catalogs) == 1:
        for rel, value in digest_catalog(args.catalogs[0]).items():
            print(f"{value}  {rel}")
        return 0
    old, new = (digest_catalog(p) for p in args.catalogs[:2])
    differs = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    for rel in differs:
        state = "only in old" if rel not in new else "only in new" if rel not in old else "differs"
        print(f"{state}: {rel}")
    print(f"{len(old)} files in old, {len(new)} in new, {len(differs)} differ")
    return 1 if differs else 0


if __name__ == "__main__":
    sys.exit(main())
