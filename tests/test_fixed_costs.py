"""Small jobs pay no needless fixed costs (issue 22): no heavy imports before they are used,
each staged file fsynced once per commit, and native thread pools that sleep, not spin."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import standgrid
from standgrid.catalog.store import Catalog
from tests.conftest import REPO_ROOT


def _python(code: str, env: dict[str, str] | None = None) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code],
        check=True,
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        env=env if env is not None else dict(os.environ),
        timeout=60,
    )
    return out.stdout


def test_cli_and_tile_command_import_no_pandas() -> None:
    """``import standgrid.cli`` and the tile command's modules load no pandas/geopandas,
    scipy or numpy: they come with the work that needs them."""
    code = (
        "import sys, json\n"
        "import standgrid.cli\n"
        "from standgrid.cli import LazyGroup\n"
        "LazyGroup._load('tile')\n"
        "import standgrid.pipeline.tile, standgrid.catalog.index, standgrid.tiling.vpcs\n"
        "import standgrid.tiling.mission_rows, standgrid.export.gpkg\n"
        "heavy = ['pandas', 'geopandas', 'pyarrow', 'scipy', 'standgrid.alignment']\n"
        "print(json.dumps([m for m in heavy if m in sys.modules]))\n"
    )
    assert json.loads(_python(code)) == []


def test_wait_policy_set_on_import_without_overriding() -> None:
    env = {k: v for k, v in os.environ.items() if k not in standgrid.WAIT_POLICY}
    env.pop("OMP_NUM_THREADS", None)
    code = (
        "import os, json, standgrid\n"
        "names = [*standgrid.WAIT_POLICY, *standgrid.THREAD_COUNTS]\n"
        "print(json.dumps({n: os.environ.get(n) for n in names}))\n"
    )
    got = json.loads(_python(code, env))
    assert got["OMP_WAIT_POLICY"] == "PASSIVE"
    assert got["GOMP_SPINCOUNT"] == "0"
    assert got["OPENBLAS_THREAD_TIMEOUT"] == "4"
    assert got["OMP_NUM_THREADS"] == str(len(os.sched_getaffinity(0)))
    # a user's explicit choice stays, and its spinning is not turned off behind its back
    mine = {**env, "OMP_WAIT_POLICY": "ACTIVE", "OPENBLAS_NUM_THREADS": "1"}
    got = json.loads(_python(code, mine))
    assert got["OMP_WAIT_POLICY"] == "ACTIVE"
    assert got["GOMP_SPINCOUNT"] is None
    assert got["OPENBLAS_NUM_THREADS"] == "1"


def test_wait_passively_keeps_given_values() -> None:
    environ = {"GOTO_THREAD_TIMEOUT": "10", "MKL_NUM_THREADS": "3"}
    done = standgrid.wait_passively(environ)
    assert "OPENBLAS_THREAD_TIMEOUT" not in environ and environ["MKL_NUM_THREADS"] == "3"
    assert environ["OMP_WAIT_POLICY"] == "PASSIVE" and "MKL_NUM_THREADS" not in done


def test_wait_policy_reaches_the_openmp_runtime() -> None:
    """The policy is in place before an OpenMP runtime loads: libgomp (CSF's) reads it."""
    code = (
        "import standgrid, ctypes, CSF\n"
        "from threadpoolctl import threadpool_info\n"
        "libs = [i['filepath'] for i in threadpool_info() if i['internal_api'] == 'openmp']\n"
        "import os; print(os.environ['OMP_WAIT_POLICY'], len(libs))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in standgrid.WAIT_POLICY}
    policy, loaded = _python(code, env).split()
    assert policy == "PASSIVE" and int(loaded) >= 1


def test_wait_policy_in_a_spawned_worker() -> None:
    """A LocalCluster worker runs with the policy (the nanny sets it before numpy loads)."""
    pytest.importorskip("distributed")
    from standgrid.engine import open_executor

    names = ["OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OPENBLAS_THREAD_TIMEOUT"]
    with open_executor(workers=1) as executor:
        got = dict(executor.map(os.getenv, names))
    assert [got[k] for k in range(len(names))] == [os.environ[n] for n in names]
    assert got[0] in ("PASSIVE", "passive") or "OMP_WAIT_POLICY" in os.environ


def _fsyncs(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    calls: list[str] = []
    real = os.fsync

    def counting(fd: int) -> None:
        calls.append(os.readlink(f"/proc/self/fd/{fd}"))
        real(fd)

    monkeypatch.setattr(os, "fsync", counting)
    return calls


def test_commit_fsyncs_each_staged_file_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from standgrid.catalog import build_folder, publish, writer_lock
    from standgrid.partition import StandGrid

    grid = StandGrid(cell_size=20.0, crs="EPSG:32630")
    final = tmp_path / "catalog"
    with writer_lock(final) as lock:
        build = build_folder(final)
        catalog = Catalog.build(build, grid.to_dict(), "EPSG:32630", "grid", final=final, held=lock)
        calls = _fsyncs(monkeypatch)
        with catalog.transaction() as txn:
            for k in range(5):
                txn.stage(f"tiles/2024/t{k}.las").write_bytes(b"x" * (100 + k))
            txn.stage("tiles_2024.vpc").write_text("{}")
        publish(build, final)
    # each tile's and the VPC's data once (staged, before the journal), publish included
    names = [os.path.basename(p) for p in calls]
    for k in range(5):
        assert names.count(f"t{k}.las") == 1, names
    assert names.count("tiles_2024.vpc") == 1, names
    folders = [p for p in calls if os.path.basename(p) == "2024"]
    assert len(folders) == 3, calls  # staged folder, target folder after the renames, publish
    assert (final / "tiles" / "2024" / "t4.las").read_bytes() == b"x" * 104
    assert Catalog.open(final).generation == 1


def test_publish_fsyncs_a_file_changed_after_its_commit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only files the commit left as they are skip publish's fsync."""
    from standgrid.catalog import build_folder, publish, writer_lock
    from standgrid.partition import StandGrid

    grid = StandGrid(cell_size=20.0, crs="EPSG:32630")
    final = tmp_path / "catalog"
    with writer_lock(final) as lock:
        build = build_folder(final)
        catalog = Catalog.build(build, grid.to_dict(), "EPSG:32630", "grid", final=final, held=lock)
        with catalog.transaction() as txn:
            txn.stage("a.txt").write_text("a")
            txn.stage("b.txt").write_text("b")
        (build / "b.txt").write_text("changed")  # not through a transaction
        calls = _fsyncs(monkeypatch)
        publish(build, final)
    names = [os.path.basename(p) for p in calls]
    assert "b.txt" in names and "a.txt" not in names
