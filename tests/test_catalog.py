"""The catalog folder: create/open, grid checks, atomic transactions and recovery."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from standgrid.errors import (
    CatalogError,
    CatalogNotFoundError,
    EpochNotFoundError,
    GridMismatchError,
    OutputExistsError,
    OutputNotWritableError,
)
from standgrid.export.catalog import Catalog, grid_fingerprint, recover

GRID = {"crs": "EPSG:32632", "cell_size": 20.0, "origin": [500000.0, 6000000.0], "levels": 3}


def make(tmp_path: Path) -> Catalog:
    return Catalog.create(tmp_path / "cat", GRID, "EPSG:32632", "grid")


def ingest(catalog: Catalog, name: str, epoch: str, tiles: dict[str, bytes]) -> int:
    with catalog.transaction() as txn:
        number = txn.mission_number(name)
        for rel, data in tiles.items():
            txn.stage(rel).write_bytes(data)
        txn.record_mission(name, epoch=epoch, date=epoch, path=f"/missions/{name}",
                           georeference={"method": "yaw2d", "rmse_m": 0.05}, payload_count=3,
                           point_count=100, tiles=list(tiles))  # fmt: skip
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


def test_crash_before_journal_is_discarded_on_open(tmp_path: Path) -> None:
    catalog = make(tmp_path)
    ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"old"})
    txn = catalog.transaction().__enter__()
    txn.stage("tiles/e1/x.laz").write_bytes(b"half")
    # crash: the process stops here, no journal (its death releases the writer lock)
    txn._lock.__exit__(None, None, None)
    reopened = Catalog.open(catalog.root)
    assert reopened.path("tiles/e1/x.laz").read_bytes() == b"old"
    assert not (catalog.root / ".staging").exists()
    # a re-run completes
    ingest(reopened, "m-a", "e1", {"tiles/e1/x.laz": b"new"})
    assert Catalog.open(catalog.root).path("tiles/e1/x.laz").read_bytes() == b"new"


@pytest.mark.parametrize("renames_done", [0, 1, 2])
def test_crash_after_journal_rolls_forward_on_open(tmp_path: Path, renames_done: int) -> None:
    catalog = make(tmp_path)
    ingest(catalog, "m-a", "e1", {"tiles/e1/x.laz": b"old", "tiles/e1/gone.laz": b"G"})
    txn = catalog.transaction().__enter__()
    txn.stage("tiles/e1/x.laz").write_bytes(b"new-x")
    txn.stage("tiles/e2/y.laz").write_bytes(b"new-y")
    txn.delete("tiles/e1/gone.laz")
    txn.record_mission("m-b", epoch="e2", date="2025-01-01", tiles=["tiles/e2/y.laz"])
    journal_path = txn.prepare()
    journal = json.loads(journal_path.read_text())
    assert [r[1] for r in journal["renames"]] == ["tiles/e1/x.laz", "tiles/e2/y.laz"]
    # crash part-way through apply: some renames done, catalog.json not yet rewritten
    for source, target in journal["renames"][:renames_done]:
        (catalog.root / target).parent.mkdir(parents=True, exist_ok=True)
        os.replace(catalog.root / source, catalog.root / target)
    assert "m-b" not in json.loads((catalog.root / "catalog.json").read_text())["missions"]
    txn._lock.__exit__(None, None, None)  # the dead process's lock is gone

    reopened = Catalog.open(catalog.root)
    assert reopened.path("tiles/e1/x.laz").read_bytes() == b"new-x"
    assert reopened.path("tiles/e2/y.laz").read_bytes() == b"new-y"
    assert not (catalog.root / "tiles/e1/gone.laz").exists()
    assert reopened.missions["m-b"]["number"] == 2
    assert reopened.epochs["e2"]["missions"] == ["m-b"]
    assert not (catalog.root / ".staging").exists()
    assert recover(catalog.root) == []  # nothing left to do


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
    assert (folder / "notes.txt").exists()
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
            rows.append(cell_row(f"L0_{i}_0", info, level=0, cell_size=20.0, epoch="e1",
                                 missions=["m-a"], tile_path=rel))  # fmt: skip
            entries.append((rel, info.file_bounds, catalog.crs, info.point_count, None))
            tiles.append(rel)
        traj = [{"mission": "m-a", "epoch": "e1",
                 "geometry": LineString([(500_000, 6_000_000), (500_040, 6_000_010)])}]  # fmt: skip
        write_index(txn.stage("index.gpkg"), crs=catalog.crs, cells=rows, trajectories=traj,
                    base=txn.current("index.gpkg"))  # fmt: skip
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
        with pytest.raises(CatalogError, match="another process is writing"):
            catalog.transaction().__enter__()
    assert Catalog.open(catalog.root).path("tiles/e1/x.laz").read_bytes() == b"staged"
