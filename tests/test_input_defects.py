"""Defective inputs end in one typed error, not a traceback or a mission tiled far away.

Swapped or scattered GNSS logs, a "billion laughs" metadata.yaml, a full disk while writing
LAZ and GeoPackage, enrich/compare pointed at a folder that is no catalog, stale or
ill-chosen epochs in compare, a raster pixel that does not fit the catalog, Ctrl-C.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from standgrid.cli import cli
from standgrid.errors import (
    CatalogNotFoundError,
    EnrichError,
    InsufficientGnssError,
    MetadataError,
    MisplacedMissionError,
)
from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT
from tests.pipeline_fixtures import CRS, build_small_catalog

MISSION = "2024-05-14-wytham-anymal-coyote"


def _mission_with_fixes(root: Path, edit: str) -> Path:
    """A copy of the bundled 2024 mission whose gnss/fixes.txt is ``edit``-ed: ``swap``
    (latitude and longitude columns exchanged) or ``scatter`` (each fix moved up to 300 m
    at random, stated as RTK fixed, 2 cm)."""
    folder = shutil.copytree(BUNDLED_MISSIONS / MISSION, root / MISSION)
    log = folder / "gnss" / "fixes.txt"
    rng = np.random.default_rng(0)
    lines = log.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        parts = [p.strip() for p in line.split(",")]
        if edit == "swap":
            parts[2], parts[3] = parts[3], parts[2]
        else:
            parts[2] = repr(float(parts[2]) + rng.uniform(-300, 300) / 111_000)
            parts[3] = repr(float(parts[3]) + rng.uniform(-300, 300) / 69_000)
            parts[5:8] = ["4", "0.02", "0.03"]
        out.append(", ".join(parts))
    log.write_text("\n".join(out) + "\n")
    return folder


# --- 1. latitude and longitude swapped ---------------------------------------------------


def test_swapped_gnss_log_is_refused_with_the_swap_hint(tmp_path: Path) -> None:
    """Swapped columns put the mission in the Indian Ocean, thousands of km from the
    location its metadata.yaml gives: refused, naming the log and saying it is swapped;
    --accept-poor-georeference still places it (an explicit override)."""
    from standgrid.georeference.placement import place_mission
    from standgrid.mission.opening import open_mission

    mission = open_mission(_mission_with_fixes(tmp_path, "swap"))
    with pytest.raises(MisplacedMissionError) as info:
        place_mission(mission)
    message = str(info.value)
    assert info.value.path == mission.path / "gnss" / "fixes.txt"
    assert "km from the location its metadata" in message and "metadata.yaml" in message
    assert "(swapped)" in message and "latitude and longitude swapped" in message
    assert place_mission(mission, accept_poor=True).fit is not None


def test_swapped_mission_outside_the_catalog_crs_gets_the_swap_hint(tmp_path: Path) -> None:
    """Tiling into an existing catalog: a mission outside the area of use of its CRS is
    refused, and read the other way round it lies by the catalog's missions: said."""
    from standgrid.catalog import Catalog
    from standgrid.errors import CRSError
    from standgrid.georeference import fit_from_anchor
    from standgrid.georeference.placement import Placement
    from standgrid.tiling.setup import check_area_of_use

    catalog = Catalog.create(
        tmp_path / "catalog", {"scheme": "voronoi", "crs": CRS}, CRS, "voronoi"
    )
    here = fit_from_anchor(51.7732, -1.3374, 150.0, 0.0)
    with catalog.transaction() as txn:
        txn.record_mission(
            MISSION,
            epoch="2024",
            date="2024-05-14",
            tiles=[],
            point_count=0,
            payload_count=0,
            georeference=here.to_dict(),
        )
    catalog = Catalog.open(catalog.root)
    swapped = Placement(fit_from_anchor(-1.3374, 51.7732, 150.0, 0.0))
    with pytest.raises(CRSError, match=r"outside the area of use.*\(swapped\).*swapped"):
        check_area_of_use(catalog, [("swapped", swapped)])
    check_area_of_use(catalog, [("here", Placement(here))])  # in place: accepted


# --- 2. fixes scattered by hundreds of metres --------------------------------------------


def test_scattered_gnss_fixes_are_a_typed_error(tmp_path: Path) -> None:
    """RTK-quality fixes scattered by hundreds of metres left RANSAC no inliers and ended in
    an IndexError in weighted_median; now a GeoreferenceError naming the log."""
    from standgrid.georeference import georeference_mission
    from standgrid.mission.opening import open_mission

    mission = open_mission(_mission_with_fixes(tmp_path, "scatter"))
    with pytest.raises(InsufficientGnssError, match="too scattered to fit") as info:
        georeference_mission(mission)
    assert info.value.path == mission.path / "gnss" / "fixes.txt"


# --- 3. billion laughs ---------------------------------------------------------------------


def _billion_laughs() -> str:
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i, name in enumerate("bcdefghi"):
        lines.append(f"{name}: &{name} [" + ",".join([f"*{'abcdefghi'[i]}"] * 9) + "]")
    return "\n".join(lines) + "\n"


def test_billion_laughs_metadata_is_refused(tmp_path: Path) -> None:
    """Nested aliases (a few hundred bytes, 9**9 strings expanded) are refused while
    composing, naming the file and the line of the first alias; `info` stays quick."""
    from standgrid.mission.metadata import read_metadata

    folder = tmp_path / MISSION
    folder.mkdir()
    meta = folder / "metadata.yaml"
    meta.write_text(_billion_laughs())
    assert meta.stat().st_size < 600
    with pytest.raises(MetadataError, match=r"alias \*a refused") as info:
        read_metadata(meta)
    assert info.value.path == meta and info.value.line == 2
    start = time.monotonic()
    result = CliRunner().invoke(cli, ["info", str(folder)])
    assert time.monotonic() - start < 5
    assert result.exit_code == 0, result.output
    assert "metadata.yaml:2: YAML alias *a refused" in result.output


def test_oversized_metadata_is_refused(tmp_path: Path) -> None:
    from standgrid.mission.metadata import MAX_METADATA_BYTES, read_metadata

    meta = tmp_path / "metadata.yaml"
    meta.write_text("date: 2024-05-14\nnotes: " + "x" * MAX_METADATA_BYTES + "\n")
    with pytest.raises(MetadataError, match="larger than"):
        read_metadata(meta)


# --- 4. a full disk ---------------------------------------------------------------------------


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


_LIMITED_CLI = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))
sys.argv = ["standgrid", *sys.argv[2:]]
from standgrid.cli import main
main()
"""


@pytest.mark.slow  # a child enrich under a file-size limit: ~5 s
def test_file_size_limit_while_enriching_is_one_line_and_keeps_the_catalog(
    tmp_path: Path,
) -> None:
    """The rewritten LAZ tiles (~29 kB) cannot be written under a 24 kB file-size limit:
    one OutOfSpaceError line, no traceback, the catalog exactly as it was."""
    catalog = build_small_catalog(tmp_path / "catalog")
    before = _digest(catalog)
    done = subprocess.run(
        [sys.executable, "-c", _LIMITED_CLI, "24000", "enrich", str(catalog), "--quiet"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO_ROOT,
    )
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: OutOfSpaceError: "), done.stderr
    assert "the previous state is kept" in lines[0]
    assert _digest(catalog) == before


_SMALL_DISK = """
import json, os, subprocess, sys
from pathlib import Path
root = Path(sys.argv[1])
subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(root)], check=True)
import numpy as np
import geopandas as gpd
import shapely
from standgrid.errors import OutOfSpaceError
from standgrid.export.gpkg import IndexWriter
from standgrid.export.las import write_tile
from standgrid.pointcloud import PointCloud

out = {}
rng = np.random.default_rng(0)
small = gpd.GeoDataFrame({"v": [1]}, geometry=[shapely.Point(0, 0)], crs=sys.argv[2])
with IndexWriter(root / "index.gpkg", sys.argv[2]) as writer:
    writer.write_layer("small", small)
before = (root / "index.gpkg").read_bytes()
n = 40000
big = gpd.GeoDataFrame({"v": np.arange(n), "text": ["x" * 40] * n},
                       geometry=shapely.points(rng.uniform(0, 100, (n, 2))), crs=sys.argv[2])
try:
    with IndexWriter(root / "index.gpkg", sys.argv[2]) as writer:
        writer.write_layer("big", big)
    out["gpkg"] = "written"
except Exception as exc:
    out["gpkg"] = type(exc).__name__ + ": " + str(exc)
out["gpkg_kept"] = (root / "index.gpkg").read_bytes() == before
cloud = PointCloud(rng.uniform(0, 20, (200000, 3)), {})
try:
    write_tile(root / "tile.laz", cloud, crs=sys.argv[2])
    out["laz"] = "written"
except Exception as exc:
    out["laz"] = type(exc).__name__ + ": " + str(exc)
out["left"] = sorted(p.name for p in root.iterdir())
print(json.dumps(out))
"""


def test_full_disk_while_writing_geopackage_and_laz(tmp_path: Path) -> None:
    """On a real, full 512 kB file system (a tmpfs in a private mount namespace; skipped
    where one cannot be made): a GeoPackage layer that does not fit (GDAL/SQLite say
    "database or disk is full", or less) and a LAZ tile that does not fit are
    OutOfSpaceError; the index written before is intact and no temporary is left."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare")
    mount = tmp_path / "small"
    mount.mkdir()
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private mount namespace here: {probe.stderr.decode().strip()}")
    done = subprocess.run(
        ["unshare", "-rm", sys.executable, "-c", _SMALL_DISK, str(mount), CRS],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO_ROOT,
    )
    if done.returncode != 0 and "CalledProcessError" in done.stderr and "mount" in done.stderr:
        pytest.skip("cannot mount a tmpfs here")
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["gpkg"].startswith("OutOfSpaceError: "), out
    assert str(mount / "index.gpkg") in out["gpkg"], out
    assert out["gpkg_kept"] is True
    assert out["laz"].startswith("OutOfSpaceError: "), out
    assert out["left"] == ["index.gpkg"], out


@pytest.mark.parametrize(
    "module, writer, name",
    [("las", "write_tile", "t.laz"), ("copc", "write_copc_tile", "t.copc.laz")],
)
def test_lazrs_errors_keep_the_errno_of_the_failed_write(
    tmp_path: Path, module: str, writer: str, name: str
) -> None:
    """lazrs reports a failed Python write only as "IoError: Failed to call write": the
    stream keeps the OSError, so a full disk is told apart from other LAZ errors (LAZ and
    COPC tiles: both are compressed by lazrs)."""
    script = textwrap.dedent(
        f"""
        import resource, signal, sys
        import numpy as np
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        from standgrid.errors import OutOfSpaceError
        from standgrid.export.{module} import {writer}
        from standgrid.pointcloud import PointCloud
        cloud = PointCloud(np.random.default_rng(0).uniform(0, 20, (200000, 3)), {{}})
        resource.setrlimit(resource.RLIMIT_FSIZE, (100000, resource.RLIM_INFINITY))
        try:
            {writer}(sys.argv[1], cloud, crs="EPSG:32630")
        except OutOfSpaceError as exc:
            print("full", exc.path)
        """
    )
    out = tmp_path / name
    done = subprocess.run(
        [sys.executable, "-c", script, str(out)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO_ROOT,
    )
    assert done.stdout.strip() == f"full {out}", done.stderr
    assert list(tmp_path.iterdir()) == []


# --- 5. a folder that is no catalog ---------------------------------------------------------


def test_enrich_and_compare_of_a_mission_folder_leave_no_lock(tmp_path: Path) -> None:
    """`standgrid enrich data/missions/<mission>` used to leave .<mission>.lock beside it."""
    from standgrid.pipeline.compare import compare_epochs
    from standgrid.pipeline.enrich import enrich_catalog

    folder = shutil.copytree(BUNDLED_MISSIONS / MISSION, tmp_path / "missions" / MISSION)
    with pytest.raises(CatalogNotFoundError, match="not a standgrid catalog"):
        enrich_catalog(folder)
    with pytest.raises(CatalogNotFoundError, match="not a standgrid catalog"):
        compare_epochs(folder)
    result = CliRunner().invoke(cli, ["enrich", str(folder)])
    assert result.exit_code == 1 and "CatalogNotFoundError" in result.output
    assert sorted(p.name for p in folder.parent.iterdir()) == [MISSION]


# --- 6. compare and enrich messages --------------------------------------------------------


@pytest.fixture(scope="module")
def small_enriched(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from standgrid.pipeline.enrich import enrich_catalog

    catalog = build_small_catalog(tmp_path_factory.mktemp("small") / "catalog")
    enrich_catalog(catalog)
    return catalog


def test_compare_says_stale_same_and_reversed_epochs(small_enriched: Path, tmp_path: Path) -> None:
    from standgrid.catalog import Catalog
    from standgrid.catalog.invalidate import invalidate_epochs
    from standgrid.comparison.options import CompareOptions
    from standgrid.comparison.trees import ChangeInputError
    from standgrid.pipeline.compare import compare_epochs

    both = "option epoch_from and option epoch_to are both epoch '2024'"
    with pytest.raises(ChangeInputError, match=both):
        compare_epochs(small_enriched, CompareOptions("2024", "2024"))
    with pytest.raises(ChangeInputError, match=r"'2024' .* is not later than epoch '2028'"):
        compare_epochs(small_enriched, CompareOptions("2028", "2024"))
    catalog = shutil.copytree(small_enriched, tmp_path / "catalog")
    with Catalog.writing(catalog) as opened, opened.transaction() as txn:
        invalidate_epochs(opened, txn, {"2028": "re-tiled: missions m"})
    with pytest.raises(EnrichError, match=r"'2028' is stale: .*re-tiled.*re-run `standgrid enrich"):
        compare_epochs(catalog, CompareOptions("2024", "2028"))


def test_raster_pixel_that_does_not_fit_is_explained(small_enriched: Path, tmp_path: Path) -> None:
    from standgrid.catalog import Catalog
    from standgrid.enrichment.options import EnrichOptions
    from standgrid.pipeline.enrich import check_pixel_size, enrich_catalog

    voronoi = Catalog.create(
        tmp_path / "voronoi", {"scheme": "voronoi", "crs": CRS}, CRS, "voronoi"
    )
    with pytest.raises(EnrichError, match=r"3 m does not divide the 10 m lattice a Voronoi"):
        check_pixel_size(voronoi, 3.0)
    check_pixel_size(voronoi, 2.5)
    catalog = shutil.copytree(small_enriched, tmp_path / "grid")
    before = _digest(catalog)
    with pytest.raises(EnrichError, match=r"20 m cell size .*divisor of 20 m \(.*, 5, 10, 20\)"):
        enrich_catalog(catalog, EnrichOptions(pixel_size=3.0))
    assert _digest(catalog) == before


def test_enrich_help_says_re_enriching_replaces_outputs() -> None:
    result = CliRunner().invoke(cli, ["enrich", "--help"])
    assert "replaces its outputs" in " ".join(result.output.split())


def test_ctrl_c_is_said_at_once_and_exits_130(capfd: pytest.CaptureFixture[str]) -> None:
    """A real SIGINT inside the interruptible block: said at once ("interrupting: ..."),
    then the one-line outcome, exit status 130 (not click's bare "Aborted!")."""
    from standgrid.cli.enrich import INTERRUPTED, interruptible

    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(SystemExit) as info, interruptible():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)  # interrupted long before
    assert info.value.code == 130
    err = capfd.readouterr().err
    assert "interrupting: stopping the chunks in progress" in err and INTERRUPTED in err
    assert signal.getsignal(signal.SIGINT) is before


def test_a_foreign_output_is_refused_before_any_mission_is_read(tmp_path: Path) -> None:
    """The output is checked first: a mission that does not even exist is not reached."""
    from standgrid.errors import OutputExistsError
    from standgrid.pipeline.tile import tile_missions

    out = tmp_path / "notes"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="not a catalog"):
        tile_missions([tmp_path / "no-such-mission"], out)
    assert (out / "notes.txt").read_text() == "mine"
