"""The catalog folder: create/open, grid checks, atomic transactions and recovery."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from standgrid.catalog import Catalog, TilingSettings, grid_fingerprint, recover
from standgrid.errors import (
    CatalogBusyError,
    CatalogConflictError,
    CatalogError,
    CatalogNotFoundError,
    EpochNotFoundError,
    GridMismatchError,
    OutputExistsError,
    OutputNotWritableError,
)

GRID = {"crs": "EPSG:32632", "cell_size": 20.0, "origin": [500000.0, 6000000.0], "levels": 3}


def make(tmp_path: Path) -> Catalog:
    return Catalog.create(tmp_path / "cat", GRID, "EPSG:32632", "grid")


def ingest(catalog: Catalog, name: str, epoch: str, tiles: dict[str, bytes]) -> int:
    with catalog.transaction() as txn:
        number = txn.mission_number(name)
        for rel, data in tiles.items():
            txn.stage(rel).write_bytes(data)
        txn.record_mission(
            name,
            epoch=epoch,
            date=epoch,
            path=f"/missions/{name}",
            georeference={"method": "yaw2d", "rmse_m": 0.05},
            payload_count=3,
            point_count=100,
            tiles=list(tiles),
        )
    return number


def test_create_open_round_trip(tmp_path: Path) -> None:
    created = make(tmp_path)
    number = ingest(
        created, "2024-05-01-wytham-anymal", "2024-05-01", {"tiles/2024-05-01/a.laz": b"A"}
    )
    assert number == 1
    opened = Catalog.open(tmp_path / "cat")
    assert opened.grid_definition == GRID
    assert opened.fingerprint == grid_fingerprint(GRID) == created.fingerprint
    assert opened.crs == "EPSG:32632" and opened.scheme == "grid"
    record = opened.missions["2024-05-01-wytham-anymal"]
    assert record["number"] == 1 and record["georeference"]["rmse_m"] == 0.05
    assert record["payload_count"] == 3 and record["tiles"] == ["tiles/2024-05-01/a.laz"]
    assert opened.epochs == {
        "2024-05-01": {"date": "2024-05-01", "missions": ["2024-05-01-wytham-anymal"]}
    }
    assert opened.tiles("2024-05-01") == ["tiles/2024-05-01/a.laz"]
    assert opened.path("tiles/2024-05-01/a.laz").read_bytes() == b"A"
    assert not (tmp_path / "cat" / ".staging").exists()
    with pytest.raises(EpochNotFoundError):
        opened.tiles("1999")


def test_open_missing_or_not_a_catalog(tmp_path: Path) -> None:
    with pytest.raises(CatalogNotFoundError):
        Catalog.open(tmp_path / "nowhere")
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "catalog.json").write_text('{"something": "else"}')
    with pytest.raises(CatalogNotFoundError, match="not a standgrid catalog"):
        Catalog.open(tmp_path / "plain")
    (tmp_path / "plain" / "catalog.json").write_text("{broken")
    with pytest.raises(CatalogError, match=r"catalog\.json:1: malformed"):
        Catalog.open(tmp_path / "plain")


def test_grid_mismatch_names_both_fingerprints(tmp_path: Path) -> None:
    catalog = make(tmp_path)
    catalog.check_grid(dict(reversed(list(GRID.items()))))  # key order does not matter
    other = {**GRID, "cell_size": 25.0}
    with pytest.raises(GridMismatchError) as info:
        catalog.check_grid(other)
    assert catalog.fingerprint in str(info.value) and grid_fingerprint(other) in str(info.value)
    with pytest.raises(GridMismatchError):
        Catalog.open_or_create(tmp_path / "cat", other, "EPSG:32632")
    assert (
        Catalog.open_or_create(tmp_path / "cat", GRID, "EPSG:32632").fingerprint
        == catalog.fingerprint
    )


def test_mission_numbers_are_stable_and_never_reused(tmp_path: Path) -> None:
    catalog = make(tmp_path)
    assert ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"1"}) == 1
    assert ingest(catalog, "m-b", "e1", {"tiles/e1/y.laz": b"2"}) == 2
    # re-ingest: same number, tiles and record replaced, no duplicate in the epoch
    assert ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"1b", "tiles/e1/z.laz": b"3"}) == 1
    reopened = Catalog.open(catalog.root)
    assert reopened.mission_number("m-a") == 1 and reopened.mission_number("new") is None
    assert reopened.tiles_of("m-a") == ["tiles/e1/x.laz", "tiles/e1/z.laz"]
    assert reopened.epochs["e1"]["missions"] == ["m-a", "m-b"]
    assert reopened.path("tiles/e1/x.laz").read_bytes() == b"1b"
    with reopened.transaction() as txn:
        txn.remove_mission("m-b")
    assert ingest(reopened, "m-c", "e2", {}) == 3


def test_exception_inside_transaction_changes_nothing(tmp_path: Path) -> None:
    catalog = make(tmp_path)
    ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"old"})
    before = (catalog.root / "catalog.json").read_text()
    with pytest.raises(RuntimeError, match="boom"), catalog.transaction() as txn:
        txn.stage("tiles/e1/x.laz").write_bytes(b"new")
        txn.record_mission("m-b", epoch="e1", date="e1")
        raise RuntimeError("boom")
    assert (catalog.root / "catalog.json").read_text() == before
    assert catalog.path("tiles/e1/x.laz").read_bytes() == b"old"
    assert not (catalog.root / ".staging").exists()
    assert "m-b" not in Catalog.open(catalog.root).missions


REPO = Path(__file__).resolve().parents[1]
#: A second transaction, run in a child process that kills itself at a commit point.
CHILD = """
import sys
from standgrid.catalog import Catalog
with Catalog.writing(sys.argv[1]) as catalog, catalog.transaction() as txn:
    txn.stage("tiles/e1/x.laz").write_bytes(b"new-x")
    txn.stage("tiles/e2/y.laz").write_bytes(b"new-y")
    txn.delete("tiles/e1/gone.laz")
    txn.record_mission("m-b", epoch="e2", date="2025-01-01", tiles=["tiles/e2/y.laz"])
"""


def run_child(root: Path, crash_at: str | None, code: str = CHILD) -> int:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("STANDGRID_CRASH_AT", None)
    if crash_at is not None:
        env["STANDGRID_CRASH_AT"] = crash_at
    done = subprocess.run([sys.executable, "-c", code, str(root)], env=env, cwd=REPO, timeout=60)
    return done.returncode


def two_states(tmp_path: Path) -> Catalog:
    catalog = make(tmp_path)
    ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"old", "tiles/e1/gone.laz": b"G"})
    return catalog


def assert_old(root: Path) -> None:
    reader = Catalog.open(root)
    assert sorted(reader.missions) == ["m-a"]
    assert reader.path("tiles/e1/x.laz").read_bytes() == b"old"
    assert reader.path("tiles/e1/gone.laz").read_bytes() == b"G"
    assert not (root / "tiles/e2/y.laz").exists()


def assert_new(root: Path) -> None:
    reader = Catalog.open(root)
    assert sorted(reader.missions) == ["m-a", "m-b"]
    assert reader.missions["m-b"]["number"] == 2
    assert reader.path("tiles/e1/x.laz").read_bytes() == b"new-x"
    assert reader.path("tiles/e2/y.laz").read_bytes() == b"new-y"
    assert not (root / "tiles/e1/gone.laz").exists()


def test_a_kill_before_the_journal_leaves_the_old_state(tmp_path: Path) -> None:
    catalog = two_states(tmp_path)
    assert run_child(catalog.root, "staged") == -signal.SIGKILL
    assert (catalog.root / ".staging").is_dir()  # the dead writer's staging
    assert_old(catalog.root)
    with Catalog.writing(catalog.root):  # the next writer discards it
        assert not (catalog.root / ".staging").exists()
    assert run_child(catalog.root, None) == 0  # and a re-run completes
    assert_new(catalog.root)


@pytest.mark.parametrize(
    "point", ["journal", "rename-0", "rename-1", "before-catalog-json", "rename-2", "applied"]
)
def test_a_kill_after_the_journal_rolls_forward_for_readers(tmp_path: Path, point: str) -> None:
    catalog = two_states(tmp_path)
    assert run_child(catalog.root, point) == -signal.SIGKILL
    assert (catalog.root / ".staging").is_dir()
    assert_new(catalog.root)  # a reader completes the dead commit first
    assert not (catalog.root / ".staging").exists()
    assert recover(catalog.root) == []  # nothing left to do
    assert Catalog.open(catalog.root).generation == 2


@pytest.mark.parametrize("torn", [b"", b'{"journal": {"renames": ["tiles/e1/x.laz"'])
def test_a_torn_or_empty_journal_is_discarded(tmp_path: Path, torn: bytes) -> None:
    """A power loss can leave a journal torn; it is detected and the old state kept."""
    catalog = two_states(tmp_path)
    assert run_child(catalog.root, "journal") == -signal.SIGKILL
    (journal,) = (catalog.root / ".staging").glob("*/journal.json")
    journal.write_bytes(torn)
    assert_old(catalog.root)
    assert not (catalog.root / ".staging").exists()
    assert run_child(catalog.root, None) == 0
    assert_new(catalog.root)


def test_a_planted_journal_cannot_reach_outside_the_catalog(tmp_path: Path) -> None:
    catalog = two_states(tmp_path)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    for target in ("../../../victim.txt", str(victim), "tiles/../../victim.txt"):
        folder = catalog.root / ".staging" / "X"
        (folder / "files").mkdir(parents=True, exist_ok=True)
        body = {"renames": [target], "deletes": [], "txn": "X"}
        digest = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
        (folder / "journal.json").write_text(json.dumps({"journal": body, "sha256": digest}))
        with pytest.raises(CatalogError, match="escapes the catalog"):
            Catalog.open(catalog.root)
        with pytest.raises(CatalogError, match="escapes the catalog"):
            Catalog.writing(catalog.root).__enter__()
        assert victim.read_text() == "precious"
        shutil.rmtree(folder)
    # an old-style journal naming its own sources is torn for this format: discarded
    folder = catalog.root / ".staging" / "Y"
    folder.mkdir(parents=True)
    (folder / "journal.json").write_text(
        json.dumps({"renames": [["../../victim.txt", "tiles/e1/v.txt"]], "deletes": []})
    )
    assert_old(catalog.root)
    assert victim.read_text() == "precious" and not (catalog.root / "tiles/e1/v.txt").exists()


def test_a_journal_older_than_the_catalog_is_discarded_not_replayed(tmp_path: Path) -> None:
    """A finished commit's journal that comes back (its removal never reached the disk)
    after later commits must not delete their files again."""
    catalog = two_states(tmp_path)
    assert run_child(catalog.root, None) == 0  # generation 2: tiles/e1/gone.laz deleted
    with Catalog.writing(catalog.root) as writer, writer.transaction() as txn:
        txn.stage("tiles/e1/gone.laz").write_bytes(b"back")  # generation 3 writes it again
    folder = catalog.root / ".staging" / "old"
    (folder / "files").mkdir(parents=True)
    body = {"txn": "old", "generation": 2, "renames": [], "deletes": ["tiles/e1/gone.laz"]}
    digest = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
    (folder / "journal.json").write_text(json.dumps({"journal": body, "sha256": digest}))
    reader = Catalog.open(catalog.root)
    assert reader.generation == 3
    assert reader.path("tiles/e1/gone.laz").read_bytes() == b"back"
    assert not folder.exists()


def test_a_symlinked_folder_inside_the_catalog_is_not_written_through(tmp_path: Path) -> None:
    catalog = two_states(tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    (catalog.root / "tiles" / "e2").symlink_to(outside, target_is_directory=True)
    with pytest.raises(CatalogError, match="symlink"), catalog.transaction() as txn:
        txn.stage("tiles/e2/y.laz").write_bytes(b"new-y")
    assert list(outside.iterdir()) == []
    assert_old(catalog.root)


def test_hand_edited_or_incomplete_catalog_json_is_refused(tmp_path: Path) -> None:
    catalog = two_states(tmp_path)
    path = catalog.root / "catalog.json"
    state = json.loads(path.read_text())
    path.write_text(json.dumps({**state, "fingerprint": "0" * 64}))
    with pytest.raises(CatalogError, match="edited by hand"):
        Catalog.open(catalog.root)
    del state["missions"]
    path.write_text(json.dumps(state))
    with pytest.raises(CatalogError, match="lacks missions"):
        Catalog.open(catalog.root)


def test_a_leftover_temporary_catalog_json_is_removed(tmp_path: Path) -> None:
    catalog = two_states(tmp_path)
    leftover = catalog.root / ".catalog.json.999999-deadbeef.tmp"  # no process 999999
    leftover.write_text("{half")
    ingest(Catalog.open(catalog.root), "m-c", "e1", {})
    assert not leftover.exists()


WRITER = """
import sys, time
from standgrid.catalog import Catalog
root, name, go = sys.argv[1], sys.argv[2], float(sys.argv[3])
while time.time() < go:
    time.sleep(0.001)
catalog = Catalog.open_or_create(root, {"cell_size": 20.0}, "EPSG:32632")
with Catalog.writing(root, lock_timeout=30) as catalog, catalog.transaction() as txn:
    time.sleep(0.3)  # a slow writer: the other arrives meanwhile
    txn.stage(f"tiles/e1/{name}.laz").write_bytes(name.encode())
    txn.record_mission(name, epoch="e1", date="e1", tiles=[f"tiles/e1/{name}.laz"])
"""


def test_concurrent_writers_creating_one_catalog_both_land(tmp_path: Path) -> None:
    """Two processes create and write the same new catalog at once: both missions stay."""
    root = tmp_path / "new"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    go = f"{time.time() + 1.5:.3f}"
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(root), name, go], env=env, cwd=REPO)
        for name in ("m1", "m2", "m3")
    ]
    assert [p.wait(timeout=60) for p in procs] == [0, 0, 0]
    reader = Catalog.open(root)
    assert sorted(reader.missions) == ["m1", "m2", "m3"]
    assert sorted(n["number"] for n in reader.missions.values()) == [1, 2, 3]
    assert reader.generation == 3


def test_a_second_writer_times_out_with_a_typed_error(tmp_path: Path) -> None:
    catalog = two_states(tmp_path)
    hold = (
        "import sys, time\nfrom standgrid.catalog import Catalog\n"
        "with Catalog.writing(sys.argv[1]):\n    print('held', flush=True); time.sleep(5)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    holder = subprocess.Popen(
        [sys.executable, "-c", hold, str(catalog.root)],
        env=env,
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        started = time.monotonic()
        with pytest.raises(CatalogBusyError, match="another process is writing"):
            Catalog.writing(catalog.root, lock_timeout=0.5).__enter__()
        assert 0.4 < time.monotonic() - started < 4
        stale = Catalog.open(catalog.root)
        stale.lock_timeout = 0
        with pytest.raises(TimeoutError):  # the builtin it also is
            stale.transaction().__enter__()
    finally:
        holder.kill()
        holder.wait()
    ingest(Catalog.open(catalog.root), "m-c", "e1", {})  # the lock died with its holder


def test_a_transaction_on_a_stale_view_is_refused(tmp_path: Path) -> None:
    """State read before another writer's commit is not committed over it."""
    catalog = two_states(tmp_path)
    stale = Catalog.open(catalog.root)
    assert run_child(catalog.root, None) == 0
    with pytest.raises(CatalogConflictError, match="changed since it was opened"):
        ingest(stale, "m-c", "e1", {})
    assert_new(catalog.root)


def test_readers_never_see_a_half_applied_commit(tmp_path: Path) -> None:
    """A reader inside Catalog.reading() sees one generation's files while commits run."""
    catalog = make(tmp_path)
    writer = """
import sys, time
from pathlib import Path
from standgrid.catalog import Catalog
while not Path(sys.argv[1], "..", "ready").exists():
    time.sleep(0.01)
for k in range(1, 16):
    time.sleep(0.05)  # readers get in between commits too
    with Catalog.writing(sys.argv[1]) as catalog, catalog.transaction() as txn:
        for i in range(8):
            txn.stage(f"tiles/e1/t{i}.laz").write_bytes(str(k).encode())
        txn.record_mission("m", epoch="e1", date="e1", round=k,
                           tiles=[f"tiles/e1/t{i}.laz" for i in range(8)])
"""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", writer, str(catalog.root)], env=env, cwd=REPO)
    seen = set()
    (tmp_path / "ready").touch()
    try:
        while proc.poll() is None:
            with Catalog.reading(catalog.root) as snapshot:
                record = snapshot.missions.get("m")
                if record is None:
                    continue
                contents = {snapshot.path(t).read_bytes() for t in record["tiles"]}
                assert contents == {str(record["round"]).encode()}
                seen.add(record["round"])
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == 0 and len(seen) >= 2


def test_readers_are_held_off_only_for_the_journal_and_renames(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The staged files reach the disk before the commit takes the readers lock: a reader
    arriving meanwhile reads the last commit at once (it waited for the whole fsync)."""
    import standgrid.catalog.transaction as transaction

    catalog = make(tmp_path)
    ingest(catalog, "m-a", "e1", {"tiles/e1/a.laz": b"old"})
    seen: list[object] = []
    real_fsync_tree = transaction.fsync_tree

    def fsync_tree_then_read(root: Path) -> None:
        real_fsync_tree(root)
        if not seen:  # the staged files, synced: a reader comes in now
            with Catalog.reading(catalog.root, lock_timeout=0.5) as snapshot:
                seen.append(snapshot.missions["m-a"].get("round"))

    monkeypatch.setattr(transaction, "fsync_tree", fsync_tree_then_read)
    with catalog.transaction() as txn:
        txn.stage("tiles/e1/a.laz").write_bytes(b"new")
        txn.record_mission("m-a", epoch="e1", date="e1", round=2, tiles=["tiles/e1/a.laz"])
    assert seen == [None]  # the old record, read without waiting for the commit
    assert Catalog.open(catalog.root).missions["m-a"]["round"] == 2
    assert catalog.path("tiles/e1/a.laz").read_bytes() == b"new"


def test_transaction_current_and_bad_paths(tmp_path: Path) -> None:
    catalog = make(tmp_path)
    ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"old"})
    with catalog.transaction() as txn:
        assert txn.current("tiles/e1/x.laz") == catalog.root / "tiles/e1/x.laz"
        staged = txn.stage("tiles/e1/x.laz")
        staged.write_bytes(b"new")
        assert txn.current("tiles/e1/x.laz") == staged
        assert txn.current("tiles/none.laz") is None
        for bad in ("../escape.laz", "/abs/x.laz", ".staging/x"):
            with pytest.raises(CatalogError, match="not a path inside"):
                txn.stage(bad)
    with pytest.raises(CatalogError, match="never written"), catalog.transaction() as txn:
        txn.stage("tiles/e1/empty.laz")
    assert not catalog.path("tiles/e1/empty.laz").exists()


def test_existing_folder_and_overwrite(tmp_path: Path) -> None:
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="folder with files"):
        Catalog.create(folder, GRID, "EPSG:32632")
    with pytest.raises(OutputExistsError, match="overwriting replaces only a catalog"):
        Catalog.create(folder, GRID, "EPSG:32632", overwrite=True)  # never deleted
    assert (folder / "notes.txt").read_text() == "mine"
    make(tmp_path)
    with pytest.raises(OutputExistsError, match="is a catalog"):
        make(tmp_path)
    replaced = Catalog.create(tmp_path / "cat", {**GRID, "levels": 1}, "EPSG:32632", overwrite=True)
    assert Catalog.open(replaced.root).grid_definition["levels"] == 1
    Catalog.create(tmp_path / "empty_ok", GRID, "EPSG:32632", "voronoi")
    with pytest.raises(CatalogError, match="scheme"):
        Catalog.create(tmp_path / "x", GRID, "EPSG:32632", "hexagons")


def test_unwritable_location(tmp_path: Path) -> None:
    parent_file = tmp_path / "a_file"
    parent_file.write_text("x")
    with pytest.raises(OutputNotWritableError):
        Catalog.create(parent_file / "cat", GRID, "EPSG:32632")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through chmod 0o500")
def test_read_only_folder(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(OutputNotWritableError):
            Catalog.create(folder / "cat", GRID, "EPSG:32632")
    finally:
        folder.chmod(0o700)


def test_tiles_index_and_vpc_in_one_transaction(tmp_path: Path) -> None:
    """The wiring the tile pipeline uses: stage tiles, index and VPC, commit once."""
    import geopandas as gpd
    import laspy
    import numpy as np
    from shapely.geometry import LineString, box

    from standgrid.export.gpkg import cell_row, write_index, write_vpc
    from standgrid.export.las import read_tile, write_tile
    from standgrid.pointcloud import PointCloud

    catalog = make(tmp_path)
    rng = np.random.default_rng(4)
    with catalog.transaction() as txn:
        number = txn.mission_number("m-a")
        rows, entries, tiles = [], [], []
        for i in range(2):
            rel = f"tiles/e1/L0_{i}_0.laz"
            cell = box(500_000 + 20 * i, 6_000_000, 500_020 + 20 * i, 6_000_020)
            lo, hi = (500_000 + 20 * i, 6_000_000, 100), (500_020 + 20 * i, 6_000_020, 110)
            xyz = rng.uniform(lo, hi, (100, 3))
            cloud = PointCloud(xyz, {"point_source_id": np.full(100, number, np.uint16)})
            info = write_tile(txn.stage(rel), cloud, crs=catalog.crs, core_bounds=cell)
            rows.append(
                cell_row(
                    f"L0_{i}_0",
                    info,
                    level=0,
                    cell_size=20.0,
                    epoch="e1",
                    missions=["m-a"],
                    tile_path=rel,
                )
            )
            entries.append((rel, info.file_bounds, catalog.crs, info.point_count, None))
            tiles.append(rel)
        traj = [
            {
                "mission": "m-a",
                "epoch": "e1",
                "geometry": LineString([(500_000, 6_000_000), (500_040, 6_000_010)]),
            }
        ]
        write_index(
            txn.stage("index.gpkg"),
            crs=catalog.crs,
            cells=rows,
            trajectories=traj,
            base=txn.current("index.gpkg"),
        )
        write_vpc(txn.stage("index.vpc"), entries)
        txn.record_mission("m-a", epoch="e1", date="2024-05-01", tiles=tiles, point_count=200)
        assert not (catalog.root / "index.gpkg").exists()  # nothing visible before commit

    cells = gpd.read_file(catalog.root / "index.gpkg", layer="cells", engine="pyogrio")
    assert list(cells["tile_path"]) == tiles
    for rel in cells["tile_path"]:
        assert laspy.read(catalog.root / rel).header.point_count == 100
        assert set(read_tile(catalog.root / rel).fields["point_source_id"]) == {1}
    vpc = json.loads((catalog.root / "index.vpc").read_text())
    assert [f["assets"]["data"]["href"] for f in vpc["features"]] == [f"./{t}" for t in tiles]
    assert all((catalog.root / f["assets"]["data"]["href"]).is_file() for f in vpc["features"])
    assert Catalog.open(catalog.root).tiles("e1") == tiles


def test_numpy_values_in_records_are_stored_as_json(tmp_path: Path) -> None:
    import numpy as np

    grid = {**GRID, "origin": np.array([500000.0, 6000000.0])}
    catalog = Catalog.create(tmp_path / "cat", grid, "EPSG:32632")
    assert catalog.fingerprint == grid_fingerprint(GRID)  # numpy origin == list origin
    fit = {"T_enu_map": np.eye(4), "rmse_m": np.float64(0.03), "inliers": np.array([True, False])}
    with catalog.transaction() as txn:
        txn.record_mission("m", epoch="e", date="2024-01-01", georeference=fit, n_fixes=np.int64(2))
    record = Catalog.open(catalog.root).missions["m"]
    assert record["georeference"]["T_enu_map"][3] == [0.0, 0.0, 0.0, 1.0]
    assert record["georeference"]["inliers"] == [True, False] and record["n_fixes"] == 2
    with pytest.raises(CatalogError, match=r"catalog\.json"), catalog.transaction() as txn:
        txn.record_mission("m2", epoch="e", date="d", georeference={"bad": object()})


def test_fingerprint_matches_stand_grid(tmp_path: Path) -> None:
    grid_module = pytest.importorskip("standgrid.partition.grid")
    grid = grid_module.StandGrid(
        crs="EPSG:32632", cell_size=20.0, origin=(500000.0, 6000000.0), levels=(20.0, 100.0)
    )
    catalog = Catalog.create(tmp_path / "cat", grid, "EPSG:32632")
    assert catalog.fingerprint == grid.fingerprint
    assert catalog.grid_definition == grid.to_dict()
    catalog.check_grid(grid)


def test_a_live_transaction_is_not_discarded_by_another_open(tmp_path: Path) -> None:
    """A reader's open() while a writer stages must not touch the writer's staging."""
    catalog = make(tmp_path)
    with catalog.transaction() as txn:
        txn.stage("tiles/e1/x.laz").write_bytes(b"staged")
        Catalog.open(catalog.root)  # e.g. `standgrid compare` reading meanwhile
        assert txn.stage("tiles/e1/x.laz").read_bytes() == b"staged"
        txn.record_mission("m-a", epoch="e1", date="2025-01-01", tiles=["tiles/e1/x.laz"])
        catalog.lock_timeout = 0  # a second transaction of this process waits for the first
        with pytest.raises(CatalogBusyError, match="another process is writing"):
            catalog.transaction().__enter__()
    assert Catalog.open(catalog.root).path("tiles/e1/x.laz").read_bytes() == b"staged"


def test_typed_transaction_writes_commit_and_read_back(tmp_path: Path) -> None:
    catalog = make(tmp_path)
    with catalog.transaction() as txn:
        assert txn.tiling_settings() == TilingSettings(0.0, True, False)  # a new catalog's
        txn.set_tiling_settings(TilingSettings(2.5, False))
        txn.record_mission("m1", epoch="2024", date="2024-05-14", tiles=["tiles/2024/a.las"])
        txn.record_mission("m2", epoch="2024", date="2024-05-12")
        txn.set_mission_tiles("m2", ["tiles/2024/b.las", "tiles/2024/a.las"])
        settled = txn.settle_epoch("2024", TilingSettings(2.5, False))
        assert settled is not None and settled.date == "2024-05-12"  # the earliest mission
        assert txn.settle_epoch("1999", TilingSettings()) is None
        txn.mark_enriched("2024", {"cells": 3, "observed_fraction": np.float64(0.5)})
        txn.record_comparison("2024__2028", {"from": "2024", "to": "2028", "outputs": {}})
    again = Catalog.open(catalog.root)
    epoch = again.epoch("2024")
    assert epoch.enriched and epoch.state == "enriched"
    assert epoch.enrichment == {"cells": 3, "observed_fraction": 0.5}
    assert again.mission_records["m2"].tiles == ("tiles/2024/a.las", "tiles/2024/b.las")
    assert again.comparisons["2024__2028"]["from"] == "2024"
    with again.transaction() as txn:
        assert txn.tiling_settings() == TilingSettings(2.5, False)
        assert again.epoch("2024").tiling == TilingSettings(2.5, False)
        before = txn.begin_enrichment("2024")
        assert before.enriched  # what it was: enriching it again recomputes
