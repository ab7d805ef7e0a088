"""The committed viewer bundle (standgrid/serve/static) is the build of web/.

vite's build writes build-manifest.json (web/vite.config.js): the sha256 of every source
file of web/ (node_modules aside: the lock file pins it) and of every output. The fast
tests recompute both without Node: a source edited without rebuilding, or an output edited
by hand, fails. The slow test rebuilds from the lock file (``npm ci && npm run build``, into
a temporary folder) and needs the same manifest: the build is reproducible and the committed
outputs are exactly what the sources give. It is skipped when npm is absent."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from standgrid.serve.viewer import BUILD_MANIFEST, STATIC

WEB = Path(__file__).resolve().parents[1] / "web"


def _hashes(root: Path, skip: set[str]) -> dict[str, str]:
    return {
        path.relative_to(root).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file() and not (set(path.relative_to(root).parts) & skip)
    }


def _manifest(folder: Path) -> dict[str, dict[str, str]]:
    manifest: dict[str, dict[str, str]] = json.loads((folder / BUILD_MANIFEST).read_text())
    return manifest


def test_bundle_was_built_from_the_sources_in_web() -> None:
    manifest = _manifest(STATIC)
    sources = _hashes(WEB, skip={"node_modules"})
    assert {"index.html", "package.json", "package-lock.json", "vite.config.js"} <= set(sources)
    changed = sorted(
        n
        for n in sources.keys() | manifest["sources"].keys()
        if sources.get(n) != manifest["sources"].get(n)
    )
    assert changed == [], f"web/ changed since the bundle was built; npm run build: {changed}"


def test_bundle_files_are_the_build_outputs() -> None:
    manifest = _manifest(STATIC)
    outputs = _hashes(STATIC, skip=set())
    outputs.pop(BUILD_MANIFEST)
    assert outputs == manifest["outputs"]


def test_bundle_loads_nothing_from_elsewhere() -> None:
    """Every script and style of the page comes from the package (no CDN, no web fonts)."""
    page = (STATIC / "index.html").read_text()
    refs = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert refs, page
    for ref in refs:
        if ref.startswith("data:"):
            continue
        assert ref.startswith("/viewer/assets/"), ref
        assert (STATIC / ref.removeprefix("/viewer/")).is_file(), ref
    for css in STATIC.glob("assets/*.css"):
        assert not re.search(r"url\(\s*['\"]?(https?:)?//", css.read_text()), css
        assert "@import" not in css.read_text(), css


@pytest.mark.slow
def test_npm_ci_and_build_reproduce_the_committed_bundle(tmp_path: Path) -> None:
    npm = shutil.which("npm")
    if npm is None:
        pytest.skip("npm is not installed")
    web = tmp_path / "web"
    shutil.copytree(WEB, web, ignore=shutil.ignore_patterns("node_modules"))
    out = tmp_path / "static"
    env = {**os.environ, "STANDGRID_VIEWER_OUT": str(out)}
    for command in ([npm, "ci", "--no-audit", "--no-fund"], [npm, "run", "build"]):
        done = subprocess.run(
            command, cwd=web, env=env, capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0, done.stdout + done.stderr
    assert _manifest(out) == _manifest(STATIC)
