"""The service's writes run in worker processes, so that readers never wait on them.

A robot's requests parse clouds and pose graphs (``LiveMission``: ~10-30 ms of Python per
payload) and its ``tile`` runs :func:`~standgrid.pipeline.tile.tile_missions` (seconds of
Python); in threads of the server they held the GIL that every read needs. Here each runs
in a :class:`WorkerProcess` (one ``spawn`` process, started at its first call, stopped with
the app, killed with the server): one for the mission folders, one for tiling, so a
payload lands while a mission tiles. Workers take the mission folder's lock and the
catalog's writer lock themselves (both ``flock``: safe across processes). A library error
comes back as the problem it maps to; a worker that dies (killed, out of memory) is
replaced at the next call, and the commit it was writing is finished or discarded by the
catalog's recovery, as for a killed server.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import threading
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from standgrid.serve.problems import Problem

_log = logging.getLogger("standgrid.serve")


def _relay(function: Callable[..., Any], args: tuple[Any, ...]) -> dict[str, Any]:
    """In the worker: ``function(*args)`` as ``{"result": ...}``, or ``{"problem": {status,
    detail}}`` for a library error, worded as the service's handler words one (its class and
    message, no server path)."""
    from standgrid.errors import StandgridError
    from standgrid.serve.problems import status_of

    try:
        return {"result": function(*args)}
    except StandgridError as exc:
        status = status_of(exc)
        if status >= 500:
            _log.error("%s failed: %s", function.__name__, exc, exc_info=exc)
        detail = exc.detail if isinstance(exc, Problem) else f"{type(exc).__name__}: {exc.message}"
        return {"problem": {"status": status, "detail": detail}}


def live_mission(folder: str, method: str, *args: Any) -> Any:
    """In the worker: ``LiveMission(folder).<method>(*args)``."""
    from standgrid.mission.live import LiveMission

    return getattr(LiveMission(Path(folder)), method)(*args)


def tile_mission(
    folder: str, catalog: str, placement_tolerance: float | None = None
) -> dict[str, Any]:
    """In the worker: tile the mission folder into ``catalog`` under the folder's lock (its
    placement kept while a refit moves it less than ``placement_tolerance`` metres; None:
    exact); the report as JSON values."""
    import json

    from standgrid.mission.live import LiveMission
    from standgrid.pipeline.tile import TileOptions, tile_missions

    live = LiveMission(Path(folder))
    options = TileOptions(placement_tolerance=placement_tolerance)
    with live.locked():  # no payload lands half-way through the tiling
        report = tile_missions([live.path], Path(catalog), options)
    result: dict[str, Any] = json.loads(json.dumps(report.to_dict(), default=str))
    return result


def _start_worker(parent: int, niceness: int) -> None:
    """In the worker, as it starts: leave Ctrl-C to the server (which stops its workers after
    their running call), die with the server as a thread of it would (Linux: a killed
    server leaves no worker behind; a commit cut short is recovered, as for the server), and
    yield the CPU to the server's readers (``nice``)."""
    import os
    import signal
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
        if os.getppid() != parent:  # the server died before the line above
            os._exit(1)
    if niceness:
        os.nice(niceness)


class WorkerProcess:
    """One worker process (``spawn``) running calls one at a time, started when first
    needed; :meth:`shutdown` stops it. ``name`` says what it does, in errors; ``niceness``
    lowers its CPU priority (background work: reads come first on a busy machine)."""

    def __init__(self, name: str, *, niceness: int = 0) -> None:
        self.name = name
        self.niceness = niceness
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def _executor(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                context = multiprocessing.get_context("spawn")
                self._pool = ProcessPoolExecutor(
                    max_workers=1, mp_context=context,
                    initializer=_start_worker, initargs=(os.getpid(), self.niceness),
                )  # fmt: skip
            return self._pool

    async def call(self, function: Callable[..., Any], *args: Any) -> Any:
        """``function(*args)`` in the worker (a module-level function; picklable
        arguments and result). Raises :class:`Problem` for a library error or a worker
        that died."""
        pool = self._executor()
        loop = asyncio.get_running_loop()
        try:
            answer = await loop.run_in_executor(pool, _relay, function, args)
        except BrokenProcessPool as exc:
            self._discard(pool)
            _log.error("the %s worker died in %s", self.name, function.__name__)
            raise Problem(500, f"the {self.name} worker died before it answered; the catalog "
                          "and the mission folders hold their last complete writes (a commit "
                          "cut short is finished or discarded before the next read): send "
                          "the request again") from exc  # fmt: skip
        if "problem" in answer:
            raise Problem(answer["problem"]["status"], answer["problem"]["detail"])
        return answer["result"]

    def _discard(self, pool: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._pool is pool:
                self._pool = None
        pool.shutdown(wait=False, cancel_futures=True)

    def shutdown(self) -> None:
        """Stop the worker, after the call it is running (if any) has finished."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
