"""Tiling on dask.distributed gives what one process gives: a real LocalCluster of 2 worker
processes (through the CLI's --workers), and a real ``dask scheduler`` + ``dask worker``
started here on 127.0.0.1 (through --scheduler). Every tile is compared point by point with
laspy, every index layer row by row with pyogrio, every VPC as JSON."""

from __future__ import annotations

import contextlib
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
from typing import Any

import laspy
import numpy as np
import pyogrio
import pytest
from click.testing import CliRunner

from standgrid.cli import cli
from standgrid.engine import Execution, open_executor
from standgrid.errors import PointCloudFormatError
from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT

pytest.importorskip("distributed")

MISSIONS = sorted(BUNDLED_MISSIONS.iterdir())
LAYERS = ("cells", "payloads", "trajectories", "gnss_fixes", "missions")
#: A buffer, so buffer copies travel to the workers too.
OPTIONS = TileOptions(buffer=2.0)


@pytest.fixture(scope="module")
def one_process(tmp_path_factory: pytest.TempPathFactory) -> Path:
    catalog = tmp_path_factory.mktemp("serial") / "catalog"
    report = tile_missions(MISSIONS, catalog, OPTIONS)
    assert report.workers == 1 and report.points_in == report.points_out > 0
    return catalog


def _sorted_points(path: Path) -> np.ndarray:
    las = laspy.read(path)
    record = las.points.array
    return np.sort(record, order=list(record.dtype.names))


def assert_same_catalog(expected: Path, actual: Path) -> None:
    """The same tiles with the same points, the same index rows, the same VPCs."""
    tiles = sorted(p.relative_to(expected).as_posix() for p in expected.glob("tiles/*/*.la[sz]"))
    got = sorted(p.relative_to(actual).as_posix() for p in actual.glob("tiles/*/*.la[sz]"))
    assert tiles and got == tiles
    for rel in tiles:
        a, b = _sorted_points(expected / rel), _sorted_points(actual / rel)
        assert a.dtype == b.dtype and len(a) == len(b) > 0, rel
        assert np.array_equal(a, b), rel
    for layer in LAYERS:
        a = pyogrio.read_dataframe(expected / "index.gpkg", layer=layer)
        b = pyogrio.read_dataframe(actual / "index.gpkg", layer=layer)
        assert list(a.columns) == list(b.columns), layer
        assert len(a) == len(b) > 0, layer
        for column in a.columns:
            if column == "geometry":
                assert a.geometry.geom_equals_exact(b.geometry, 0).all(), layer
            else:
                assert a[column].equals(b[column]), (layer, column)
    vpcs = sorted(p.name for p in expected.glob("*.vpc"))
    assert vpcs and sorted(p.name for p in actual.glob("*.vpc")) == vpcs
    for name in vpcs:
        assert json.loads((expected / name).read_text()) == json.loads((actual / name).read_text())


def test_local_cluster_of_two_workers_matches_one_process(
    one_process: Path, tmp_path: Path
) -> None:
    catalog = tmp_path / "catalog"
    args = ["tile", *map(str, MISSIONS), "-o", str(catalog), "--buffer", "2", "--workers", "2"]
    result = CliRunner().invoke(cli, [*args, "--json", "-q"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["workers"] == 2 and report["conserved"] is True
    assert_same_catalog(one_process, catalog)
    assert not (catalog / ".staging").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def scheduler() -> Iterator[str]:
    """A ``dask scheduler`` and a ``dask worker`` (2 processes) on 127.0.0.1, stopped after."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), *sys.path])}
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    started = [
        subprocess.Popen(
            [*dask, "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        ),
    ]
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline or started[0].poll() is not None:
                    pytest.fail("the dask scheduler did not start")
                time.sleep(0.2)
        started.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "distributed.cli.dask_worker",
                    address,
                    "--nworkers",
                    "2",
                    "--nthreads",
                    "1",
                    "--no-dashboard",
                    "--host",
                    "127.0.0.1",
                ],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,
            )
        )
        from distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        # the worker first (its nanny and processes: the whole group), then the scheduler;
        # a graceful dask shutdown takes ~8 s, nothing of it is under test
        for process in reversed(started):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()


def test_existing_scheduler_matches_one_process(
    one_process: Path, scheduler: str, tmp_path: Path
) -> None:
    from distributed import get_task_stream

    catalog = tmp_path / "catalog"
    with open_executor(scheduler=scheduler) as executor:
        with get_task_stream(executor.client) as stream:  # type: ignore[attr-defined]
            on_cluster = Execution(executor=executor)
            report = tile_missions(MISSIONS, catalog, OPTIONS, execution=on_cluster)
        workers = set(executor.client.scheduler_info()["workers"])  # type: ignore[attr-defined]
    assert report.workers == 2
    payloads = sum(m["payloads"] for m in report.missions.values())
    cells = sum(e["cells"] for e in report.epochs.values())
    # every payload was read, and every tile written, by a task on the cluster's workers
    assert len(stream.data) == payloads + cells
    assert {task["worker"] for task in stream.data} <= workers
    assert_same_catalog(one_process, catalog)


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_voronoi_reingest_on_cluster_matches_one_process(tmp_path: Path) -> None:
    """Voronoi cells, two missions in one epoch, then one re-ingested: old tiles are read,
    their other mission's points kept, on the workers as in one process."""
    options = TileOptions(scheme="voronoi", epoch="all", laz=False)
    serial, clustered = tmp_path / "serial", tmp_path / "cluster"
    tile_missions(MISSIONS, serial, options)
    again = tile_missions(MISSIONS[:1], serial, options)
    kept = again.epochs["all"]["points_kept_from_catalog"]
    assert 0 < kept < again.points_in  # the other mission's points came from the old tiles
    broken = tmp_path / "broken" / MISSIONS[0].name
    shutil.copytree(MISSIONS[0], broken)
    victim = sorted((broken / "payload_clouds").glob("*.pcd"))[3]
    victim.write_bytes(victim.read_bytes()[:-5000])  # header intact, points cut short
    with open_executor(workers=2) as executor:
        on_cluster = Execution(executor=executor)
        tile_missions(MISSIONS, clustered, options, execution=on_cluster)
        report = tile_missions(MISSIONS[:1], clustered, options, execution=on_cluster)
        before = {p: p.stat().st_mtime_ns for p in clustered.rglob("*")}
        with pytest.raises(PointCloudFormatError) as error:  # raised on a worker
            tile_missions(  # the same mission from another folder: replacing it
                [broken], clustered, replace(options, replace_missions=True), execution=on_cluster
            )
        assert victim.name in str(error.value)
        assert {p: p.stat().st_mtime_ns for p in clustered.rglob("*")} == before

    def figures(epochs: dict[str, Any]) -> dict[str, Any]:  # run files count as spilled
        return {k: v for k, v in epochs["all"].items() if k != "bytes_spilled"}

    assert report.workers == 2 and figures(report.epochs) == figures(again.epochs)
    assert_same_catalog(serial, clustered)
