"""Enrichment on dask.distributed gives exactly what one process gives.

The bundled pair is tiled once (20 m grid, 2 m tile buffer), then enriched three times from
copies: in this process, on a real ``LocalCluster`` of 2 worker processes, and on a real
``dask scheduler`` + ``dask worker`` started here on 127.0.0.1. Every tile (point by point,
buffer copies included), the tree lists, the stand metrics and every raster must be equal.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pandas as pd
import pytest
import rasterio

from standgrid.engine import Execution
from standgrid.enrichment.chunks import ChunkCell, chunk_side, plan_chunks
from standgrid.enrichment.options import EnrichOptions
from standgrid.enrichment.terrain import ground_reach
from standgrid.pipeline.enrich import enrich_catalog
from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT

#: A small budget, so the 80 m stand is cut into several chunks (the merge is exercised);
#: one epoch keeps the test short.
OPTIONS = EnrichOptions(epochs=("2024",))
SMALL = Execution(memory_mb=64)


@pytest.fixture(scope="module")
def tiled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("dask") / "tiled"
    tile_missions(sorted(BUNDLED_MISSIONS.iterdir()), root, TileOptions(buffer=2.0))
    return root


@pytest.fixture(scope="module")
def single(tiled: Path) -> Path:
    out = tiled.parent / "single"
    shutil.copytree(tiled, out)
    report = enrich_catalog(out, OPTIONS, execution=SMALL)
    assert all(e["chunks"] > 1 for e in report.epochs.values())
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """A real ``dask scheduler`` and one ``dask worker`` process on 127.0.0.1."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    path = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
    env = dict(os.environ, PYTHONPATH=path)
    quiet = {
        "env": env,
        "stdout": subprocess.DEVNULL,
        "stderr": subprocess.DEVNULL,
        "start_new_session": True,
    }
    scheduler_cmd = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    worker_cmd = [sys.executable, "-m", "distributed.cli.dask_worker", address]
    procs = [
        subprocess.Popen(
            [*scheduler_cmd, "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            **quiet,  # type: ignore[call-overload]
        )
    ]
    time.sleep(1.0)
    procs.append(
        subprocess.Popen(
            [
                *worker_cmd,
                "--nthreads",
                "1",
                "--nworkers",
                "2",
                "--memory-limit",
                "2GiB",
                "--no-dashboard",
            ],
            **quiet,  # type: ignore[call-overload]
        )
    )
    try:
        yield address
    finally:
        # each whole process group (a worker's nanny and processes) at once: a graceful
        # dask shutdown takes ~8 s, nothing of it is under test
        for proc in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _points(path: Path) -> pd.DataFrame:
    las = laspy.read(path)
    frame = pd.DataFrame(
        {
            "X": np.asarray(las.X),
            "Y": np.asarray(las.Y),
            "Z": np.asarray(las.Z),
            "withheld": np.asarray(las.withheld, dtype=bool),
            "classification": np.asarray(las.classification),
            "height_above_ground": np.asarray(las["height_above_ground"]),
            "tree_id": np.asarray(las["tree_id"]),
        }
    )
    return frame.sort_values(["X", "Y", "Z", "withheld"]).reset_index(drop=True)


def _assert_same(a: Path, b: Path) -> None:
    tiles_a = sorted(p.relative_to(a) for p in a.glob("tiles/2024/*.la[sz]"))
    tiles_b = sorted(p.relative_to(b) for p in b.glob("tiles/2024/*.la[sz]"))
    assert tiles_a == tiles_b and tiles_a
    for rel in tiles_a:
        pd.testing.assert_frame_equal(_points(a / rel), _points(b / rel), obj=str(rel))
    for table in sorted(p.relative_to(a) for p in a.glob("tables/*.parquet")):
        pd.testing.assert_frame_equal(
            pd.read_parquet(a / table), pd.read_parquet(b / table), obj=str(table)
        )
    rasters = sorted(p.relative_to(a) for p in a.glob("rasters/*/*.tif"))
    assert len(rasters) == 4
    for rel in rasters:
        with rasterio.open(a / rel) as ra, rasterio.open(b / rel) as rb:
            assert ra.transform == rb.transform
            np.testing.assert_array_equal(ra.read(1), rb.read(1), err_msg=str(rel))


def test_the_epoch_is_cut_into_chunks_that_own_every_cell_once(single: Path) -> None:
    import pyogrio

    from standgrid.enrichment.chunks import cells_of

    cells = pyogrio.read_dataframe(single / "index.gpkg", layer="cells")
    cells = cells[cells["epoch"].astype(str) == "2024"]
    records = cells_of(cells)
    grid = json.loads((single / "catalog.json").read_text())["grid"]
    side = chunk_side(records, 20.0, 10.0, SMALL.memory_budget.bytes // 700)
    origin = tuple(grid["origin"])
    reach = functools.partial(ground_reach, lattice=origin)
    chunks = plan_chunks(records, side=side, origin=origin, buffer=10.0, reach=reach)
    owned = [c.cell_id for chunk in chunks for c in chunk.cells]
    assert sorted(owned) == sorted(cells["cell_id"]) and len(chunks) > 1

    def meets(cell: ChunkCell, box: tuple[float, float, float, float]) -> bool:
        x0, y0, x1, y1 = box
        return (
            cell.bounds[0] < x1
            and cell.bounds[2] > x0
            and cell.bounds[1] < y1
            and (cell.bounds[3] > y0)
        )

    for chunk in chunks:  # a neighbour is within the buffer, never an owned cell
        ids = {c.cell_id for c in chunk.cells}
        for n in chunk.neighbours:
            assert n.cell_id not in ids and meets(n, chunk.buffered_bounds)
        # the ring: every 20 m ground square the block touches, with its 10 m halo
        assert chunk.reach_bounds is not None
        x0, y0, x1, y1 = chunk.reach_bounds
        b0, c0, b1, c1 = chunk.buffered_bounds
        assert x0 <= b0 - 10 and x1 >= b1 + 10 and y0 <= c0 - 10 and y1 >= c1 + 10
        assert ((np.array([x0, y0, x1, y1]) - np.tile(origin, 2) + 10) % 20 == 0).all()
        seen = ids | {n.cell_id for n in chunk.neighbours}
        far = {c.cell_id for c in chunk.far}
        assert not far & seen
        assert far == {c.cell_id for c in records if meets(c, chunk.reach_bounds)} - seen


def test_local_cluster_of_two_workers_gives_the_same_catalog(tiled: Path, single: Path) -> None:
    out = tiled.parent / "local-cluster"
    shutil.copytree(tiled, out)
    enrich_catalog(out, OPTIONS, execution=replace(SMALL, workers=2))
    _assert_same(single, out)


def test_dask_scheduler_and_worker_give_the_same_catalog(
    tiled: Path, single: Path, scheduler: str
) -> None:
    out = tiled.parent / "scheduler"
    shutil.copytree(tiled, out)
    enrich_catalog(out, OPTIONS, execution=replace(SMALL, scheduler=scheduler))
    _assert_same(single, out)


def test_workers_started_by_hand_compress_laz_on_one_thread(scheduler: str) -> None:
    from standgrid.engine import open_executor

    with open_executor(scheduler=scheduler) as executor:  # os.getenv runs on the workers
        found = dict(executor.map(os.getenv, ["RAYON_NUM_THREADS"] * 6))
    assert found == dict.fromkeys(range(6), "1")


def test_another_chunk_layout_gives_the_same_catalog(tiled: Path, single: Path) -> None:
    """Another memory budget cuts the epoch into other chunks, and changes nothing: ground
    squares see their whole halo (the chunk reads the lowest points of a wider ring), the
    terrain's triangles are at most :data:`~standgrid.enrichment.terrain.DTM_MARGIN_M` long,
    stems are fitted from their cluster's own corner and stands sum their cells in id order.
    (Before: 0.7 % of heights differed, by up to 0.27 m, where a block's edge cut the
    ground's hull.)"""
    out = tiled.parent / "other-layout"
    shutil.copytree(tiled, out)
    report = enrich_catalog(out, OPTIONS, execution=Execution(memory_mb=512))
    state = json.loads((single / "catalog.json").read_text())
    assert report.epochs["2024"]["chunks"] != state["epochs"]["2024"]["enrichment"]["chunks"]
    _assert_same(single, out)


def test_an_interrupted_enrichment_leaves_no_chunk_running_and_the_catalog_as_it_was(
    tiled: Path,
) -> None:
    """Stopped after its first chunk (as by Ctrl-C in the progress bar), enrichment waits for
    the chunk running beside it before the transaction is discarded: no thread goes on
    writing tiles into a staging folder that is gone, and the catalog is unchanged."""
    import threading
    from collections.abc import Iterable

    from standgrid.engine import CallbackProgress

    class Stop(Exception):
        pass

    def first_chunk_only(items: Iterable[object], total: int, desc: str) -> Iterable[object]:
        for k, item in enumerate(items):
            if k == 1 and desc.endswith("chunks"):
                raise Stop
            yield item

    out = tiled.parent / "interrupted"
    shutil.copytree(tiled, out)
    before = {p.relative_to(out): p.read_bytes() for p in out.glob("tiles/2024/*.la[sz]")}
    with pytest.raises(Stop):
        progress = CallbackProgress(wrap=first_chunk_only)
        enrich_catalog(out, OPTIONS, execution=replace(SMALL, progress=progress))
    assert not [t for t in threading.enumerate() if t.name.startswith("ThreadPoolExecutor")]
    assert not list(out.glob(".staging/*/files"))  # the discarded transaction stays gone
    after = {p.relative_to(out): p.read_bytes() for p in out.glob("tiles/2024/*.la[sz]")}
    assert after == before


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_a_voronoi_catalog_is_the_same_for_any_chunk_layout(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """Voronoi cells cut the lattice's bins at their edges: a bin split between two tiles
    has a lowest point in each, and the block keeps the lower (as the whole epoch does)."""
    root = tmp_path_factory.mktemp("voronoi")
    tiled = root / "tiled"
    tile_missions(sorted(BUNDLED_MISSIONS.iterdir()), tiled, TileOptions(scheme="voronoi"))
    small, large = root / "small", root / "large"
    shutil.copytree(tiled, small)
    shutil.copytree(tiled, large)
    reports = [
        enrich_catalog(out, OPTIONS, execution=Execution(memory_mb=mb))
        for out, mb in ((small, 64), (large, 512))
    ]
    chunks = [report.epochs["2024"]["chunks"] for report in reports]
    assert chunks[0] > chunks[1]
    _assert_same(small, large)


@pytest.mark.slow  # a whole CLI run or a cluster in a subprocess (CI runs it)
def test_ctrl_c_on_a_local_cluster_prints_one_line_and_no_worker_traceback(
    tiled: Path,
) -> None:
    """``standgrid enrich --workers 2`` interrupted as a terminal's Ctrl-C does it (SIGINT to
    the whole process group, the worker processes included): it says so at once, then that
    the catalog keeps its last complete state (exit 130), and no traceback
    or dask log line; no process of the group is left; the catalog is as it was."""
    import signal

    code = "import sys; sys.argv[0] = 'standgrid'; from standgrid.cli import main; main()"
    # a loaded machine may finish the small catalog before the interrupt lands: then again,
    # in smaller (more, so longer) chunks
    for memory in ("64", "16", "8"):
        out = tiled.parent / f"ctrl_c_{memory}"
        shutil.copytree(tiled, out)
        before = (out / "catalog.json").read_bytes()
        proc = subprocess.Popen(
            [sys.executable, "-c", code, "enrich", str(out), "--workers", "2", "--memory", memory],
            cwd=REPO_ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # its own process group, as a terminal's foreground job
        )
        assert proc.stderr is not None
        seen = []
        for line in proc.stderr:  # the cluster is up and its chunks are running
            seen.append(line)
            if "worker(s)" in line:
                break
        with contextlib.suppress(ProcessLookupError):  # the whole group may be done already
            os.killpg(proc.pid, signal.SIGINT)
        rest = proc.communicate(timeout=60)[1]
        err = "".join(seen) + rest
        if proc.returncode != 0 or "interrupted" in err:
            break
    assert proc.returncode == 130, err  # 128 + SIGINT, as a shell reports an interrupt
    assert "interrupting: stopping the chunks in progress" in err, err
    assert err.rstrip().endswith("interrupted: the catalog keeps its last complete state"), err
    for noise in ("Traceback", "KeyboardInterrupt", "CancelledError", "distributed."):
        assert noise not in err, err
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:  # the workers stop with the cluster
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.2)
    else:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("worker processes outlived the interrupted command")
    assert (out / "catalog.json").read_bytes() == before
    assert not list(out.glob(".staging/*/files"))
