"""A catalog never loses a mission: concurrent and interrupted runs (real processes, real
SIGKILLs at the transaction's commit points), hostile files, overlapping outputs, full
disks. One test (or more) per defect of issue 8."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyogrio
import pytest

from standgrid.catalog import Catalog
from standgrid.clouds import read_cloud, write_cloud
from standgrid.errors import (
    CatalogError,
    InsufficientGnssError,
    OutputOverlapsInputError,
    PointCloudFormatError,
    PoorGeoreferenceError,
)
from standgrid.pipeline.enrich import enrich_catalog
from standgrid.pipeline.tile import tile_missions
from standgrid.pointcloud import PointCloud
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT

BIG1 = BUNDLED_MISSIONS / "2024-05-14-wytham-anymal-coyote"
BIG2 = BUNDLED_MISSIONS / "2028-05-20-wytham-frontier-v15"
CLI = "from standgrid.cli import main; main()"


def _small(mission: Path, root: Path, keep: int = 3) -> Path:
    """A copy of a bundled mission with only its first ``keep`` payload clouds (fast runs)."""
    copy = root / mission.name
    shutil.copytree(mission, copy)
    for cloud in sorted((copy / "payload_clouds").glob("*.pcd"))[keep:]:
        cloud.unlink()
    return copy


@pytest.fixture(scope="module", autouse=True)
def _missions(tmp_path_factory: pytest.TempPathFactory) -> None:
    global M1, M2
    root = tmp_path_factory.mktemp("missions")
    M1, M2 = _small(BIG1, root), _small(BIG2, root)


M1 = BIG1
M2 = BIG2


def cli(*args: str | Path, crash_at: str | None = None, fsize: int | None = None) -> Any:
    """Run ``standgrid ARGS`` in a child process (optionally killed at a commit point, or
    with a file-size limit: writes beyond it fail with EFBIG, as on a full disk)."""
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    env.pop("STANDGRID_CRASH_AT", None)
    if crash_at:
        env["STANDGRID_CRASH_AT"] = crash_at

    def limit() -> None:
        if fsize is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    return subprocess.run(
        [sys.executable, "-c", CLI, *map(str, args)],
        env=env,
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
    )


def spawn(*args: str | Path) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    env.pop("STANDGRID_CRASH_AT", None)
    return subprocess.Popen(
        [sys.executable, "-c", CLI, *map(str, args)],
        env=env,
        cwd=REPO_ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def renamed_copy(mission: Path, root: Path, name: str) -> Path:
    """A copy of a bundled mission under another name (another mission to the catalog)."""
    target = root / name
    shutil.copytree(mission, target)
    meta = target / "metadata.yaml"
    meta.write_text(meta.read_text().replace(mission.name, name))
    return target


def missions_everywhere(catalog: Path) -> dict[str, int]:
    """Mission -> points, checked to agree between catalog.json, index.gpkg and the tiles."""
    state = json.loads((catalog / "catalog.json").read_text())
    layer = pyogrio.read_dataframe(catalog / "index.gpkg", layer="missions")
    assert sorted(layer["mission"]) == sorted(state["missions"])
    numbers = {r["number"]: name for name, r in state["missions"].items()}
    on_disk: dict[str, int] = dict.fromkeys(state["missions"], 0)
    for tile in sorted(catalog.glob("tiles/*/*.la[sz]")):
        las = laspy.read(tile)
        core = ~np.asarray(las.withheld, dtype=bool)
        ids, counts = np.unique(np.asarray(las.point_source_id)[core], return_counts=True)
        for number, count in zip(ids, counts, strict=True):
            on_disk[numbers[int(number)]] += int(count)
    for name, record in state["missions"].items():
        assert on_disk[name] == record["point_count"], name
    return on_disk


# --- 1. two runs creating one new catalog ------------------------------------------------


def test_1_two_runs_creating_one_catalog_both_keep_their_mission(tmp_path: Path) -> None:
    out = tmp_path / "new"
    runs = [spawn("tile", M1, "-o", out, "-q"), spawn("tile", M2, "-o", out, "-q")]
    codes = [run.wait(timeout=300) for run in runs]
    assert codes == [0, 0], [run.stderr.read() for run in runs if run.stderr]
    assert sorted(missions_everywhere(out)) == [M1.name, M2.name]


# --- 2. a crash inside --overwrite --------------------------------------------------------


@pytest.mark.parametrize("point", ["publish", "exchanged"])
def test_2_a_kill_inside_overwrite_leaves_a_catalog(tmp_path: Path, point: str) -> None:
    out = tmp_path / "cat"
    tile_missions([M1], out)
    killed = cli("tile", M2, "-o", out, "--overwrite", "-q", crash_at=point)
    assert killed.returncode == -signal.SIGKILL
    expected = [M1.name] if point == "publish" else [M2.name]
    assert sorted(Catalog.open(out).missions) == expected  # the old one, or the new one
    # the next ordinary run keeps it and adds to it
    tile_missions([M1], out)
    assert sorted(missions_everywhere(out)) == sorted({M1.name, *expected})
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


def test_2_a_catalog_moved_aside_by_a_killed_overwrite_is_put_back(tmp_path: Path) -> None:
    """Where there is no atomic exchange the old catalog is moved aside first; a kill right
    then leaves no catalog at the path: the next run puts the old one back, never deletes it."""
    out = tmp_path / "cat"
    tile_missions([M1], out)
    aside = tmp_path / ".cat.old-999999-0123abcd.tmp"  # no process 999999
    os.rename(out, aside)
    build = tmp_path / ".cat.build-999999-4567cdef.tmp"  # its half-built replacement
    shutil.copytree(aside, build)
    tile_missions([M2], out)
    assert sorted(missions_everywhere(out)) == [M1.name, M2.name]
    assert not aside.exists() and not build.exists()


# --- 3. state read under the lock ---------------------------------------------------------


def test_3_concurrent_adds_to_one_catalog_lose_nothing(tmp_path: Path) -> None:
    out = tmp_path / "cat"
    tile_missions([M1], out)
    other = renamed_copy(M1, tmp_path, "2024-05-15-wytham-anymal-coyote")
    runs = [spawn("tile", M2, "-o", out, "-q"), spawn("tile", other, "-o", out, "-q")]
    assert [run.wait(timeout=300) for run in runs] == [0, 0]
    assert sorted(missions_everywhere(out)) == sorted([M1.name, M2.name, other.name])


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_3_enrich_and_tile_at_once_lose_nothing(tmp_path: Path) -> None:
    out = tmp_path / "cat"
    tile_missions([M1], out)
    runs = [
        spawn("enrich", out, "-q", "--lock-timeout", "600"),
        spawn("tile", M2, "-o", out, "-q", "--lock-timeout", "600"),
    ]
    assert [run.wait(timeout=300) for run in runs] == [0, 0]
    assert sorted(missions_everywhere(out)) == [M1.name, M2.name]


# --- 4. header counts before allocating ---------------------------------------------------


@pytest.mark.parametrize("claim", [300_000_000, 10**12])
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_4_las_header_counts_are_checked_against_the_file(
    tmp_path: Path, suffix: str, claim: int
) -> None:
    path = tmp_path / f"cloud{suffix}"
    rng = np.random.default_rng(0)
    cloud = PointCloud(rng.uniform(0, 10, (5000, 3)), {"intensity": np.ones(5000, np.uint16)})
    if suffix == ".laz":
        from standgrid.export.las import write_tile

        write_tile(path, cloud, crs="EPSG:32632", laz=True)
    else:
        write_cloud(cloud, path)
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, 0)  # legacy count
    struct.pack_into("<Q", data, 247, claim)  # LAS 1.4 64-bit count
    path.write_bytes(data)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(PointCloudFormatError, match=f"header says {claim} points") as info:
        read_cloud(path)
    assert info.value.path == path
    # nothing near claim x 30 bytes was allocated (ru_maxrss is in KiB)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000


@pytest.mark.parametrize("text", [True, False])
def test_4_ply_header_counts_are_checked_against_the_file(tmp_path: Path, text: bool) -> None:
    from plyfile import PlyData, PlyElement

    data = np.zeros(100, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    path = tmp_path / "cloud.ply"
    PlyData([PlyElement.describe(data, "vertex")], text=text).write(str(path))
    raw = path.read_bytes().replace(b"element vertex 100\n", b"element vertex 1000000000000\n")
    path.write_bytes(raw)
    with pytest.raises(PointCloudFormatError, match="1000000000000 vertex rows") as info:
        read_cloud(path)
    assert info.value.path == path


# --- 5. a nonsense georeference -----------------------------------------------------------


def displaced(mission: Path, root: Path, degrees: float, seed: int = 3) -> Path:
    """A copy whose GNSS fixes are displaced at random by up to ``degrees``."""
    copy = root / mission.name
    shutil.copytree(mission, copy)
    fixes = copy / "gnss" / "fixes.txt"
    rng = np.random.default_rng(seed)
    lines = fixes.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        cols = [c.strip() for c in line.split(",")]
        cols[2] = repr(float(cols[2]) + rng.uniform(-degrees, degrees))
        cols[3] = repr(float(cols[3]) + rng.uniform(-degrees, degrees))
        out.append(", ".join(cols))
    fixes.write_text("\n".join(out) + "\n")
    return copy


def test_5_a_nonsense_georeference_is_refused_unless_accepted(tmp_path: Path) -> None:
    bad = displaced(M1, tmp_path, 0.01)
    out = tmp_path / "cat"
    with pytest.raises(PoorGeoreferenceError, match=r"RMSE of .* m over") as info:
        tile_missions([bad], out)
    assert info.value.path == bad / "gnss" / "fixes.txt"
    assert not out.exists()
    done = cli("tile", bad, "-o", out, "-q")
    assert done.returncode == 1 and "PoorGeoreferenceError" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    report = tile_missions([bad], out, TileOptions(accept_poor_georeference=True))
    assert report.missions[bad.name]["georeference"]["rmse_horizontal_m"] > 100


def test_5_ordinary_gnss_noise_is_accepted(tmp_path: Path) -> None:
    noisy = displaced(M1, tmp_path, 1e-5)  # ~1 m, within the fixes' stated accuracy
    report = tile_missions([noisy], tmp_path / "cat")
    assert report.points_in == report.points_out


# --- 7. outputs never overlap inputs ------------------------------------------------------


def test_7_an_output_overlapping_a_mission_is_refused(tmp_path: Path) -> None:
    mission = shutil.copytree(M1, tmp_path / "missions" / M1.name)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    for out in (mission, mission.parent, tmp_path, mission / "inside"):
        with pytest.raises(OutputOverlapsInputError):
            tile_missions([mission], out, TileOptions(overwrite=True))
    done = cli("tile", ".", "-o", ".", "--overwrite")  # -o . run from inside the mission
    assert done.returncode != 0
    os.chdir(mission)
    try:
        done = cli("tile", ".", "-o", ".", "--overwrite")
    finally:
        os.chdir(REPO_ROOT)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_7_minus_o_dot_in_an_empty_folder_makes_the_catalog_there(tmp_path: Path) -> None:
    here = tmp_path / "here"
    here.mkdir()
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    done = subprocess.run(
        [sys.executable, "-c", CLI, "tile", str(M1), "-o", ".", "-q"],
        cwd=here,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert sorted(missions_everywhere(here)) == [M1.name]


def test_7_a_symlinked_epoch_folder_is_not_written_through(tmp_path: Path) -> None:
    mission = shutil.copytree(M1, tmp_path / M1.name)
    out = tmp_path / "cat"
    tile_missions([mission], out)
    outside = tmp_path / "elsewhere"
    shutil.move(out / "tiles" / "2024", outside)
    (out / "tiles" / "2024").symlink_to(outside, target_is_directory=True)
    before = {p.name: p.read_bytes() for p in outside.iterdir()}
    tile_missions([mission], out)  # unchanged: re-tiled in place, no tile written
    assert {p.name: p.read_bytes() for p in outside.iterdir()} == before
    sorted((mission / "payload_clouds").glob("*.pcd"))[2].unlink()  # a payload dropped
    with pytest.raises(CatalogError, match="symlink"):
        tile_missions([mission], out)
    assert {p.name: p.read_bytes() for p in outside.iterdir()} == before


# --- 8. every failure a one-line typed error ----------------------------------------------


def test_8_out_of_space_is_a_typed_error_and_keeps_the_catalog(tmp_path: Path) -> None:
    """Simulated with RLIMIT_FSIZE (SIGXFSZ is ignored by Python, so writes get EFBIG)."""
    out = tmp_path / "cat"
    tile_missions([M1], out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    for limit in (30_000,):
        done = cli("tile", M2, "-o", out, "-q", fsize=limit)
        assert done.returncode == 1, done.stderr
        assert "OutOfSpaceError" in done.stderr and "Traceback" not in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    tile_missions([M2], out)
    assert sorted(missions_everywhere(out)) == [M1.name, M2.name]


def test_8_out_of_space_on_a_small_tmpfs(tmp_path: Path) -> None:
    """A real ENOSPC where a tmpfs can be mounted (root); skipped elsewhere."""
    mount = tmp_path / "small"
    mount.mkdir()
    if (
        os.geteuid() != 0
        or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=1200k", "tmpfs", str(mount)], capture_output=True
        ).returncode
    ):
        pytest.skip("cannot mount a tmpfs here")
    try:
        out = mount / "cat"
        assert cli("tile", M1, "-o", out, "-q").returncode == 0
        before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
        done = cli("tile", M2, "-o", out, "-q", "--las")
        assert done.returncode == 1 and "OutOfSpaceError" in done.stderr, done.stderr
        assert "No space left" in done.stderr and "Traceback" not in done.stderr
        assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    finally:
        subprocess.run(["umount", str(mount)], check=False)


def test_8_damaged_catalog_files_are_typed_errors(tmp_path: Path) -> None:
    out = tmp_path / "cat"
    tile_missions([M1], out)
    tile = sorted(out.glob("tiles/2024/*.laz"))[0]
    data = tile.read_bytes()
    tile.write_bytes(data[: len(data) // 2])
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions([M2], out, TileOptions(epoch="2024"))
    assert info.value.path is not None and info.value.path.name == tile.name
    tile.write_bytes(data)
    (out / "index.gpkg").write_bytes(b"garbage" * 100)
    done = cli("tile", M2, "-o", out)
    assert done.returncode == 1 and "CatalogError" in done.stderr and "index.gpkg" in done.stderr
    assert "Traceback" not in done.stderr
    with pytest.raises(CatalogError, match=r"index\.gpkg"):
        enrich_catalog(out)


# --- 9. readers and kills mid-commit ------------------------------------------------------


@pytest.mark.parametrize("point", ["staged", "rename-3"])
def test_9_a_tile_killed_mid_commit_shows_readers_old_or_new(tmp_path: Path, point: str) -> None:
    out = tmp_path / "cat"
    tile_missions([M1], out)
    assert cli("tile", M2, "-o", out, "-q", crash_at=point).returncode == -signal.SIGKILL
    with Catalog.reading(out) as snapshot:  # rolls a journaled commit forward first
        expected = [M1.name] if point == "staged" else [M1.name, M2.name]
        assert sorted(snapshot.missions) == expected
        assert sorted(missions_everywhere(out)) == expected
    tile_missions([M2], out)
    assert sorted(missions_everywhere(out)) == [M1.name, M2.name]


# --- 10. smaller ones ---------------------------------------------------------------------


def test_10_a_folder_named_like_a_payload_is_not_silently_dropped(tmp_path: Path) -> None:
    mission = shutil.copytree(M1, tmp_path / M1.name)
    cloud = sorted((mission / "payload_clouds").glob("*.pcd"))[2]
    cloud.unlink()
    cloud.mkdir()
    with pytest.raises(PointCloudFormatError, match="is a folder") as info:
        tile_missions([mission], tmp_path / "cat")
    assert info.value.path == cloud


def test_10_garbled_binary_pcd_names_the_file(tmp_path: Path) -> None:
    mission = shutil.copytree(M1, tmp_path / M1.name)
    cloud = sorted((mission / "payload_clouds").glob("*.pcd"))[2]
    data = bytearray(cloud.read_bytes())
    start = data.index(b"DATA binary\n") + len(b"DATA binary\n")
    rng = np.random.default_rng(1)
    data[start + 4000 : start + 8000] = rng.integers(0, 256, 4000, dtype=np.uint8).tobytes()
    cloud.write_bytes(bytes(data))
    with pytest.raises(PointCloudFormatError) as info:
        tile_missions([mission], tmp_path / "cat")
    assert info.value.path == cloud


def test_10_too_few_fixes_names_the_gnss_file(tmp_path: Path) -> None:
    mission = shutil.copytree(M1, tmp_path / M1.name)
    fixes = mission / "gnss" / "fixes.txt"
    fixes.write_text("\n".join(fixes.read_text().splitlines()[:6]) + "\n")
    with pytest.raises(InsufficientGnssError) as info:
        tile_missions([mission], tmp_path / "cat")
    assert info.value.path == fixes
