"""PartitionEngine: grouping, insertion order, spilling, buffers, conservation, bounded memory."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import shapely

from standgrid.errors import ConservationError, GridError
from standgrid.partition import (
    ChunkSchemaError,
    GridBuffer,
    PartitionEngine,
    StandGrid,
    VoronoiPartition,
)
from standgrid.pointcloud import PointCloud

GRID = StandGrid("EPSG:32632")
X0, Y0 = 600_000.0, 5_700_000.0


def make_chunk(rng: np.random.Generator, n: int, start: int, extent: float = 200.0) -> PointCloud:
    xyz = np.column_stack(
        [
            rng.uniform(X0 - extent / 2, X0 + extent / 2, n),
            rng.uniform(Y0 - extent / 2, Y0 + extent / 2, n),
            rng.normal(100.0, 5.0, n),
        ]
    )
    return PointCloud(
        xyz,
        {
            "serial": np.arange(start, start + n, dtype=np.int64),
            "intensity": rng.integers(0, 65535, n).astype(np.uint16),
            "normal": rng.normal(size=(n, 3)).astype(np.float32),
        },
    )


def run(engine: PartitionEngine, chunks: list[PointCloud]) -> dict[int, PointCloud]:
    for chunk in chunks:
        engine.add(chunk)
    out = {}
    for cell in engine.finalise():
        out[cell.key] = cell.core
    return out


@pytest.fixture
def chunks() -> list[PointCloud]:
    rng = np.random.default_rng(42)
    return [make_chunk(rng, 5000, i * 5000) for i in range(12)]


def test_cells_hold_exactly_their_points_in_insertion_order(tmp_path: Path, chunks):
    engine = PartitionEngine(GRID.cell_keys, tmp_path, memory_budget_bytes=200_000)
    out = run(engine, chunks)
    whole = PointCloud.concat(chunks)
    keys = GRID.cell_keys(whole.xyz[:, 0], whole.xyz[:, 1])
    assert list(out) == sorted(np.unique(keys).tolist())
    for key, cloud in out.items():
        expected = whole.select(keys == key)
        assert np.array_equal(cloud.xyz, expected.xyz)
        for name in ("serial", "intensity", "normal"):
            assert cloud.fields[name].dtype == expected.fields[name].dtype
            assert np.array_equal(cloud.fields[name], expected.fields[name])
        xmin, ymin, xmax, ymax = GRID.bounds(GRID.key_to_cell(key))
        x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
        assert ((xmin <= x) & (x < xmax) & (ymin <= y) & (y < ymax)).all()
    st = engine.stats
    assert st.points_in == st.points_out == len(whole)
    assert st.cells == len(out)
    assert st.bytes_spilled > 0 and st.spill_flushes > 0
    assert st.peak_buffered_bytes <= 200_000 + chunks[0].xyz.nbytes * 3
    assert list(tmp_path.iterdir()) == []  # spill folder removed


def test_spilling_does_not_change_the_result(tmp_path: Path, chunks):
    spilled = run(
        PartitionEngine(GRID.cell_keys, tmp_path / "a", memory_budget_bytes=50_000), chunks
    )
    held_engine = PartitionEngine(GRID.cell_keys, tmp_path / "b")
    held = run(held_engine, chunks)
    assert held_engine.stats.bytes_spilled == 0
    assert spilled.keys() == held.keys()
    for key in held:
        assert np.array_equal(spilled[key].fields["serial"], held[key].fields["serial"])


def test_single_cell_chunks_and_empty_chunks(tmp_path: Path):
    rng = np.random.default_rng(0)
    chunk = make_chunk(rng, 100, 0, extent=1.0)
    chunk = PointCloud(chunk.xyz + np.array([5.0, 5.0, 0.0]), chunk.fields)  # all in one 20 m cell
    empty = chunk.select(np.zeros(100, dtype=bool))
    engine = PartitionEngine(GRID.cell_keys, tmp_path)
    out = run(engine, [empty, chunk, empty, chunk])
    assert len(out) == 1
    (cloud,) = out.values()
    assert cloud.fields["serial"].tolist() == list(range(100)) * 2


def test_chunks_with_other_fields_are_rejected(tmp_path: Path, chunks):
    engine = PartitionEngine(GRID.cell_keys, tmp_path)
    engine.add(chunks[0])
    retyped = chunks[1].with_fields(intensity=chunks[1].fields["intensity"].astype(np.float32))
    with pytest.raises(ChunkSchemaError, match="intensity"):
        engine.add(retyped)
    renamed = PointCloud(chunks[1].xyz, {"serial": chunks[1].fields["serial"]})
    with pytest.raises(ChunkSchemaError):
        engine.add(renamed)
    extra = chunks[1].with_fields(extra=np.zeros(len(chunks[1])))
    with pytest.raises(ChunkSchemaError, match="extra"):
        engine.add(extra)
    reshaped = chunks[1].with_fields(normal=chunks[1].fields["normal"][:, :2])
    with pytest.raises(ChunkSchemaError):
        engine.add(reshaped)
    reordered = PointCloud(chunks[1].xyz, dict(reversed(list(chunks[1].fields.items()))))
    engine.add(reordered)  # the same fields in another order are fine
    with pytest.raises(ChunkSchemaError, match="reserved"):
        PartitionEngine(GRID.cell_keys, tmp_path).add(
            chunks[0].with_fields(withheld=np.zeros(len(chunks[0]), dtype=bool))
        )
    engine.close()


def test_stopping_early_removes_the_spill_folder(tmp_path: Path, chunks):
    with PartitionEngine(GRID.cell_keys, tmp_path, memory_budget_bytes=50_000) as engine:
        for chunk in chunks:
            engine.add(chunk)
        assert any(tmp_path.rglob("*.bin"))
        first = next(iter(engine.finalise()))
        assert len(first.core) > 0
    assert list(tmp_path.iterdir()) == []


def test_bad_keys_from_assign_are_an_error(tmp_path: Path, chunks):
    engine = PartitionEngine(lambda x, y: x, tmp_path)  # type: ignore[arg-type, return-value]
    with pytest.raises(GridError):
        engine.add(chunks[0])


def test_no_points_added_after_finalise(tmp_path: Path, chunks):
    engine = PartitionEngine(GRID.cell_keys, tmp_path)
    run(engine, chunks[:1])
    with pytest.raises(RuntimeError):
        engine.add(chunks[1])


def test_lost_spill_data_raises_conservation_error(tmp_path: Path, chunks):
    engine = PartitionEngine(GRID.cell_keys, tmp_path, memory_budget_bytes=20_000)
    for chunk in chunks:
        engine.add(chunk)
    spill_files = sorted(tmp_path.rglob("*.bin"))
    assert len(spill_files) == 1  # one spill file per store, whatever the number of cells
    victim = spill_files[0]
    data = victim.read_bytes()
    itemsize = 24 + 8 + 2 + 12
    victim.write_bytes(data[: len(data) - itemsize])  # one record lost on disk
    with pytest.raises(ConservationError):
        list(engine.finalise())


def test_grid_buffers_hold_neighbour_points_within_distance(tmp_path: Path, chunks):
    distance = 3.0
    engine = PartitionEngine(
        GRID.cell_keys, tmp_path, memory_budget_bytes=100_000, buffer=GridBuffer(GRID, distance)
    )
    for chunk in chunks:
        engine.add(chunk)
    results = list(engine.finalise())
    whole = PointCloud.concat(chunks)
    serial = whole.fields["serial"]
    points = shapely.points(whole.xyz[:, :2])
    keys = GRID.cell_keys(whole.xyz[:, 0], whole.xyz[:, 1])
    total_buffer = 0
    for cell in results[:: max(1, len(results) // 15)]:
        box = GRID.polygon(GRID.key_to_cell(cell.key))
        near = (shapely.distance(box, points) <= distance) & (keys != cell.key)
        assert cell.buffer is not None
        assert sorted(cell.buffer.fields["serial"].tolist()) == sorted(serial[near].tolist())
        assert cell.buffer.fields["withheld"].all()
        combined = cell.combined()
        assert combined.fields["withheld"].sum() == len(cell.buffer)
        assert np.logical_not(combined.fields["withheld"]).sum() == len(cell.core)
    for cell in results:
        total_buffer += len(cell.buffer) if cell.buffer is not None else 0
    assert engine.stats.buffer_points == total_buffer > 0
    assert engine.stats.points_out == len(whole)


def test_grid_buffer_distance_must_be_below_cell_size():
    with pytest.raises(GridError):
        GridBuffer(GRID, 20.0)
    with pytest.raises(GridError):
        GridBuffer(GRID, 0.0)


def test_voronoi_assignment_through_the_engine(tmp_path: Path, chunks):
    sites = np.array([[X0 - 50, Y0 - 50], [X0 + 50, Y0], [X0, Y0 + 60]])
    part = VoronoiPartition(
        sites,
        ["V_m_1_000000000", "V_m_2_000000000", "V_m_3_000000000"],
        shapely.box(X0 - 100, Y0 - 100, X0 + 100, Y0 + 100),
    )
    engine = PartitionEngine(part.assign, tmp_path, memory_budget_bytes=30_000)
    out = run(engine, chunks)
    assert list(out) == [0, 1, 2]
    for key, cloud in out.items():
        d = ((cloud.xyz[:, None, :2] - sites[None]) ** 2).sum(axis=2)
        assert (d.argmin(axis=1) == key).all()


def test_peak_memory_is_bounded_by_the_budget_not_the_data(tmp_path: Path):
    budget = 16 * 2**20
    n_chunks, chunk_size = 30, 100_000  # 3 M points
    rng = np.random.default_rng(3)
    record_bytes = 24 + 4 + 8
    total_bytes = n_chunks * chunk_size * record_bytes
    tracemalloc.start()
    try:
        engine = PartitionEngine(GRID.cell_keys, tmp_path, memory_budget_bytes=budget)
        for i in range(n_chunks):
            xyz = np.column_stack(
                [
                    rng.uniform(X0, X0 + 400, chunk_size),
                    rng.uniform(Y0, Y0 + 400, chunk_size),
                    rng.uniform(0, 30, chunk_size),
                ]
            )
            fields = {
                "intensity": rng.random(chunk_size, dtype=np.float32),
                "gps_time": np.full(chunk_size, float(i)),
            }
            engine.add(PointCloud(xyz, fields))
            del xyz, fields
        count = 0
        for cell in engine.finalise():
            count += len(cell.core)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == n_chunks * chunk_size
    assert engine.stats.bytes_spilled > total_bytes // 2
    assert peak < 0.4 * total_bytes, (peak, total_bytes)


def test_five_thousand_cells_under_a_low_open_file_limit(tmp_path: Path):
    script = textwrap.dedent(
        f"""
        import resource
        import numpy as np
        from standgrid.partition import PartitionEngine, StandGrid
        from standgrid.pointcloud import PointCloud

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, hard))
        grid = StandGrid("EPSG:32632")
        engine = PartitionEngine(grid.cell_keys, {str(tmp_path)!r}, memory_budget_bytes=200_000)
        rng = np.random.default_rng(0)
        n = 0
        for i in range(10):
            xyz = rng.uniform([0, 0, 0], [100 * 20, 50 * 20, 1], (50_000, 3))
            engine.add(PointCloud(xyz, {{"i": np.full(50_000, i, dtype=np.int32)}}))
            n += 50_000
        cells = sum(1 for _ in engine.finalise())
        assert engine.stats.points_out == n
        print(cells, engine.stats.spill_flushes, resource.getrlimit(resource.RLIMIT_NOFILE)[0])
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    cells, flushes, limit = map(int, out.stdout.split())
    assert cells == 5000 and flushes > 1 and limit == 256


@pytest.mark.parametrize("span", [3, 40, 400])  # cells per side; 400: > 2**16 cells, int64 sort
def test_chunk_order_is_the_stable_sort_of_the_keys(span: int):
    from standgrid.partition.engine import _stable_order

    rng = np.random.default_rng(span)
    ix = rng.integers(-span // 2, span - span // 2, 50_000)  # negative columns too
    iy = rng.integers(-span // 2, span - span // 2, 50_000)
    x, y = GRID.origin[0] + (ix + 0.5) * 20.0, GRID.origin[1] + (iy + 0.5) * 20.0
    keys = GRID.cell_keys(x, y)
    order = _stable_order(keys)
    assert order is not None
    assert np.array_equal(order, np.argsort(keys, kind="stable"))
    assert _stable_order(np.full(10, keys[0])) is None


def test_added_arrays_are_held_read_only_and_cells_are_fresh(tmp_path: Path, chunks):
    engine = PartitionEngine(GRID.cell_keys, tmp_path, memory_budget_bytes=10**9)
    chunk = chunks[0]
    expected = chunk.fields["serial"].copy()
    engine.add(chunk)
    with pytest.raises(ValueError):  # a change after add would silently change the cells
        chunk.fields["serial"][0] = -1
    cells = list(engine.finalise())
    serials = np.concatenate([c.core.fields["serial"] for c in cells])
    assert np.array_equal(np.sort(serials), np.sort(expected))
    for cell in cells:  # the cells' arrays are their own, writable
        cell.core.xyz[:1] += 0.0
        cell.core.fields["serial"][:1] += 0
