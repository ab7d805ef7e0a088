"""The service's plumbing for speed: index connections pooled per index file (and dropped
when a commit replaces the file), writes in worker processes (errors relayed as problems,
a dead worker replaced, the tiler at a lower CPU priority)."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import sqlite3
from pathlib import Path

import pytest


def test_index_connections_are_reused_until_the_index_is_replaced(
    enriched_catalog: Path, tmp_path: Path
) -> None:
    from standgrid.serve.snapshot import snapshot

    root = Path(shutil.copytree(enriched_catalog, tmp_path / "catalog"))
    index = root / "index.gpkg"
    with snapshot(root) as first:
        assert first.provider is not None
        conn = first.provider.connection
        robots = {r[0] for r in conn.execute("SELECT robot FROM missions")}
        layer = first.layers["missions"]  # what is kept per index file (its GeoJSON texts)
    with snapshot(root) as again:  # given back, taken again: no new connection
        assert again.provider is not None and again.provider.connection is conn
        with snapshot(root) as concurrent:  # a second request meanwhile gets its own
            assert concurrent.provider is not None
            assert concurrent.provider.connection is not conn
            assert concurrent.layers["missions"] is layer  # one file: its layers shared
    # a commit renames a new index into place: the next snapshot reads the new file
    staged = root / "index.gpkg.staged"
    shutil.copy(index, staged)
    with sqlite3.connect(staged) as edit:
        edit.execute("UPDATE missions SET robot = 'renamed-robot'")
    os.replace(staged, index)
    with snapshot(root) as after:
        assert after.provider is not None and after.provider.connection is not conn
        assert after.layers["missions"] is not layer  # nothing kept from the old file
        assert (
            {r[0] for r in after.provider.connection.execute("SELECT robot FROM missions")}
            == {"renamed-robot"}
            != robots
        )
    with pytest.raises(sqlite3.ProgrammingError):  # the old file's connections are closed
        conn.execute("SELECT 1")


def test_a_snapshot_keeps_its_index_while_a_commit_replaces_it(
    enriched_catalog: Path, tmp_path: Path
) -> None:
    """A request that took its connection before the rename reads the old file to its end."""
    from standgrid.serve.snapshot import snapshot

    root = Path(shutil.copytree(enriched_catalog, tmp_path / "catalog"))
    index = root / "index.gpkg"
    staged = root / "index.gpkg.staged"
    shutil.copy(index, staged)
    with sqlite3.connect(staged) as edit:
        edit.execute("DELETE FROM missions")
    with snapshot(root) as reading:
        assert reading.provider is not None
        conn = reading.provider.connection
        before = conn.execute("SELECT COUNT(*) FROM missions").fetchone()[0]
        os.replace(staged, index)  # (a real commit waits for the readers lock instead)
        assert conn.execute("SELECT COUNT(*) FROM missions").fetchone()[0] == before > 0
    with snapshot(root) as after:
        assert after.provider is not None
        count = after.provider.connection.execute("SELECT COUNT(*) FROM missions").fetchone()
        assert count[0] == 0


def _current_niceness() -> int:
    return os.nice(0)


def test_worker_process_relays_errors_and_replaces_a_dead_worker(tmp_path: Path) -> None:
    from standgrid.serve.problems import Problem
    from standgrid.serve.workers import WorkerProcess, live_mission

    async def scenario() -> None:
        worker = WorkerProcess("test", niceness=3)
        try:
            pid = await worker.call(os.getpid)
            assert pid != os.getpid()
            assert await worker.call(_current_niceness) == min(19, os.nice(0) + 3)
            # a library error in the worker comes back as the problem it maps to
            with pytest.raises(Problem) as missing:
                await worker.call(live_mission, str(tmp_path / "nope"), "set_graph", b"")
            assert missing.value.status == 404 and "MissionNotFoundError" in missing.value.detail
            os.kill(pid, signal.SIGKILL)
            with pytest.raises(Problem) as died:
                await worker.call(os.getpid)
            assert died.value.status == 500 and "test worker died" in died.value.detail
            assert await worker.call(os.getpid) not in (pid, os.getpid())  # a new worker
        finally:
            worker.shutdown()

    asyncio.run(scenario())
