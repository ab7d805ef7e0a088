"""The service's writes run in worker processes, so that readers never wait on them.

A robot's requests parse clouds and pose graphs (``LiveMission``: ~10-30 ms of Python per
payload) and its ``tile`` runs :func:`~standgrid.pipeline.tile.tile_missions` (seconds of
Python); in threads of the server they held the GIL that every read needs. Here each runs
in a :class:`WorkerProcess`: a few ``spawn`` processes (started when needed, one kept warm
while another is busy), each running one call at a time: one set for the mission folders,
one for tiling, so a payload lands while a mission tiles, and a payload that hangs its
process does not hold up other robots' writes. Workers take the mission folder's lock and
the catalog's writer lock themselves (both ``flock``: safe across processes).

A watchdog bounds every call (``time_limit``): a call still running then has its process
killed (its whole process group), and the request gets a problem (``limit_status``: 400 for
data the writer could not read in bounded time). A worker may also run under an address-space
limit (``memory_limit``, ``RLIMIT_AS``): a ``MemoryError`` is the same problem. A library
error comes back as the problem it maps to; a worker that dies (killed, out of memory) is
replaced at the next call, and the commit it was writing is finished or discarded by the
catalog's recovery, as for a killed server. Workers end with the server: stopped with the
app, killed at interpreter exit, and (Linux) killed by the kernel when the server dies.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import multiprocessing
import os
import signal
import threading
import time
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import EllipsisType
from typing import Any

from standgrid.serve.problems import Problem

_log = logging.getLogger("standgrid.serve")

#: Seconds one mission-folder write (create, payload, graph, GNSS) may take before its worker
#: is killed: a payload of the largest body parses in a few seconds.
DEFAULT_WRITE_TIME_LIMIT_S = 60.0
#: Address space of a mission-folder writer (``RLIMIT_AS``): a 64 MiB LAZ body decompresses
#: to well under 2 GiB of points; a header announcing more fails fast instead of swapping.
DEFAULT_WRITE_MEMORY_LIMIT = 8 * 1024**3
#: Seconds a new worker process may take to start (its imports) before it is given up.
STARTUP_LIMIT_S = 120.0
#: Seconds :meth:`WorkerProcess.shutdown` waits for running calls before it kills them.
SHUTDOWN_GRACE_S = 5.0
#: Every worker process alive, killed at interpreter exit (before multiprocessing joins them).
_alive: weakref.WeakSet[_Process] = weakref.WeakSet()


def _relay(function: Callable[..., Any], args: tuple[Any, ...]) -> dict[str, Any]:
    """In the worker: ``function(*args)`` as ``{"result": ...}``, or ``{"problem": {status,
    detail}}`` for a library error, worded as the service's handler words one (its class and
    message, no server path); ``{"memory": True}`` past the memory limit; ``{"error": ...}``
    for any other exception (its class and message)."""
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
    except MemoryError:
        return {"memory": True}
    except Exception as exc:
        _log.error("%s failed", function.__name__, exc_info=exc)
        return {"error": type(exc).__name__}


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
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    live = LiveMission(Path(folder))
    options = TileOptions(placement_tolerance=placement_tolerance)
    with live.locked():  # no payload lands half-way through the tiling
        report = tile_missions([live.path], Path(catalog), options)
    result: dict[str, Any] = json.loads(json.dumps(report.to_dict(), default=str))
    return result


def _start_worker(parent: int, niceness: int, memory_limit: int | None) -> None:
    """In the worker, as it starts: leave Ctrl-C to the server, lead its own process group
    (the watchdog kills the group: anything it started goes too), die with the server as a
    thread of it would (Linux), yield the CPU to the server's readers (``nice``) and bound its
    address space (``memory_limit`` bytes)."""
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.setpgid(0, 0)
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
        if os.getppid() != parent:  # the server died before the line above
            os._exit(1)
    if niceness:
        os.nice(niceness)
    if memory_limit is not None:
        import resource

        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        if hard != resource.RLIM_INFINITY:
            memory_limit = min(memory_limit, hard)
        resource.setrlimit(resource.RLIMIT_AS, (memory_limit, hard))


def _serve(conn: Any, parent: int, niceness: int, memory_limit: int | None) -> None:
    """The worker's loop: ``ready`` once started, then ``(function, args)`` in,
    :func:`_relay`'s answer out, until the server closes its end."""
    _start_worker(parent, niceness, memory_limit)
    conn.send("ready")
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        except Exception as exc:  # a request that does not unpickle here
            conn.send({"error": type(exc).__name__})
            continue
        answer = _relay(*request)
        try:
            conn.send(answer)
        except (EOFError, OSError):
            return
        except Exception as exc:  # a result that does not pickle
            conn.send({"error": f"unpicklable result ({type(exc).__name__})"})


class _Process:
    """One worker process and the server's end of its pipe."""

    def __init__(self, name: str, niceness: int, memory_limit: int | None) -> None:
        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe()
        self.process = context.Process(
            target=_serve,
            args=(child, os.getpid(), niceness, memory_limit),
            name=f"standgrid {name} worker",
            daemon=False,
        )
        self.process.start()
        child.close()
        self.ready = False
        _alive.add(self)

    @property
    def pid(self) -> int | None:
        return self.process.pid

    def wait_ready(self) -> None:
        """Wait until the process has started (its imports done; blocking: run in a thread).
        Raises EOFError or OSError when it dies first."""
        if not self.ready:
            if self.conn.recv() != "ready":
                raise EOFError("the worker did not start")
            self.ready = True

    def ask(self, function: Callable[..., Any], args: tuple[Any, ...]) -> dict[str, Any]:
        """Send a call and wait for its answer (blocking: run in a thread). Raises EOFError
        or OSError when the process dies first."""
        self.conn.send((function, args))
        answer: dict[str, Any] = self.conn.recv()
        return answer

    def kill(self) -> None:
        """Kill the process and its process group now, and reap it."""
        pid = self.process.pid
        if pid is not None and self.process.is_alive():
            try:
                os.killpg(pid, signal.SIGKILL)  # the group it leads (anything it started)
            except OSError:
                self.process.kill()  # it had not made its group yet
        self.process.join(5)
        self.close()

    def stop(self, grace: float) -> None:
        """Close its pipe (an idle worker ends at once), wait ``grace`` seconds, then kill."""
        with contextlib.suppress(OSError):
            self.conn.close()
        self.process.join(grace)
        self.kill()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()
        _alive.discard(self)


@atexit.register
def _kill_all() -> None:
    """At interpreter exit (registered after multiprocessing's own hook, so run before it
    joins its children): no worker outlives the server, whatever it was doing."""
    for worker in list(_alive):
        worker.kill()


class WorkerProcess:
    """Up to ``processes`` worker processes (``spawn``) running calls, each one at a time;
    the first started at the first call, another kept warm while all are busy, so a call
    that hangs one process leaves the others to the rest. :meth:`shutdown` stops them.

    ``name`` says what they do, in errors; ``niceness`` lowers their CPU priority
    (background work: reads come first on a busy machine); ``time_limit`` (seconds, None: no
    limit) bounds each call, and ``memory_limit`` (bytes, None: no limit) each process's
    address space: beyond either the process is killed (time) or the call fails (memory)
    and the call raises a :class:`Problem` of ``limit_status``, its detail ending in
    ``limit_hint``."""

    def __init__(
        self,
        name: str,
        *,
        niceness: int = 0,
        processes: int = 1,
        time_limit: float | None = None,
        memory_limit: int | None = None,
        limit_status: int = 503,
        limit_hint: str = "",
    ) -> None:
        if processes < 1:
            raise ValueError(f"processes must be at least 1, got {processes}")
        if time_limit is not None and not time_limit > 0:
            raise ValueError(f"time_limit must be a positive number of seconds, got {time_limit}")
        self.name = name
        self.niceness = niceness
        self.processes = processes
        self.time_limit = time_limit
        self.memory_limit = memory_limit
        self.limit_status = limit_status
        self.limit_hint = limit_hint
        self._idle: list[_Process] = []
        self._busy: set[_Process] = set()
        self._lock = threading.Lock()
        self._threads: ThreadPoolExecutor | None = None  # each waits on one worker's answer
        self._freed: asyncio.Event | None = None

    @property
    def pids(self) -> list[int]:
        """Process ids of the worker processes alive (idle or busy)."""
        with self._lock:
            workers = [*self._idle, *self._busy]
        return [w.pid for w in workers if w.pid is not None and w.process.is_alive()]

    def _spawn(self) -> _Process:
        return _Process(self.name, self.niceness, self.memory_limit)

    async def _take(self) -> _Process:
        """An idle worker, a new one while fewer than ``processes`` exist, else wait. Started
        here, in the event loop's thread: the kernel's parent-death signal follows the
        thread that started a process."""
        while True:
            with self._lock:
                if self._freed is None:
                    self._freed = asyncio.Event()
                if self._threads is None:
                    self._threads = ThreadPoolExecutor(
                        self.processes, thread_name_prefix=f"standgrid-{self.name}"
                    )
                freed = self._freed
                worker = self._idle.pop() if self._idle else None
                if worker is None and len(self._busy) < self.processes:
                    worker = self._spawn()
                if worker is not None:
                    self._busy.add(worker)
                    if not self._idle and len(self._busy) < self.processes:
                        self._idle.append(self._spawn())  # warm for the next caller
                    return worker
            freed.clear()
            await freed.wait()

    def _give_back(self, worker: _Process, *, keep: bool) -> None:
        with self._lock:
            self._busy.discard(worker)
            if keep:
                self._idle.append(worker)
            freed = self._freed
        if not keep:
            worker.kill()
        if freed is not None:
            freed.set()

    async def call(
        self,
        function: Callable[..., Any],
        *args: Any,
        time_limit: float | EllipsisType | None = ...,
    ) -> Any:
        """``function(*args)`` in a worker (a module-level function; picklable arguments and
        result), within ``time_limit`` seconds (default: the worker's; None: no limit).
        Raises :class:`Problem` for a library error, a call over a limit or a worker that
        died."""
        limit = self.time_limit if isinstance(time_limit, EllipsisType) else time_limit
        worker = await self._take()
        threads = self._threads
        loop = asyncio.get_running_loop()
        started = time.monotonic()
        keep = False
        try:  # the limit counts from a started process (not its imports)
            await asyncio.wait_for(
                loop.run_in_executor(threads, worker.wait_ready), STARTUP_LIMIT_S
            )
            started = time.monotonic()
            asked = loop.run_in_executor(threads, worker.ask, function, args)
            answer = await asyncio.wait_for(asked, limit)
            keep = True
        except TimeoutError as exc:
            if not worker.ready:
                detail = f"the {self.name} worker did not start within {STARTUP_LIMIT_S:g} s"
                raise Problem(503, f"{detail}: send the request again") from exc
            _log.error(
                "the %s worker ran %s past its limit of %s s: killed",
                self.name,
                function.__name__,
                limit,
            )
            raise Problem(
                self.limit_status,
                f"the {self.name} worker did not finish within "
                f"its limit of {limit:g} s: stopped, nothing of this request was "
                f"kept{self.limit_hint}",
            ) from exc
        except (EOFError, OSError) as exc:
            _log.error(
                "the %s worker died in %s after %.1f s",
                self.name,
                function.__name__,
                time.monotonic() - started,
            )
            raise Problem(
                500,
                f"the {self.name} worker died before it answered; the catalog "
                "and the mission folders hold their last complete writes (a commit "
                "cut short is finished or discarded before the next read): send "
                "the request again",
            ) from exc
        finally:  # a timeout, a death or a cancelled request: the process goes
            self._give_back(worker, keep=keep)
        if "problem" in answer:
            raise Problem(answer["problem"]["status"], answer["problem"]["detail"])
        if "memory" in answer:
            raise Problem(
                self.limit_status,
                f"the {self.name} worker needed more than its "
                f"memory limit of {(self.memory_limit or 0) >> 20} MiB: nothing of "
                f"this request was kept{self.limit_hint}",
            )
        if "error" in answer:
            raise Problem(500, f"internal error in the {self.name} worker ({answer['error']})")
        return answer["result"]

    def shutdown(self, grace: float = SHUTDOWN_GRACE_S) -> None:
        """Stop the workers: idle ones end (killed if they take over ``grace`` seconds), a
        running call is killed (the server has waited for its requests, or cancelled them).
        The next call starts new ones."""
        with self._lock:
            idle, busy = list(self._idle), list(self._busy)
            self._idle.clear()
            self._busy.clear()
            threads, self._threads, freed, self._freed = self._threads, None, self._freed, None
        if freed is not None:
            freed.set()  # callers waiting for a worker start new ones
        for worker in busy:
            worker.kill()
        deadline = time.monotonic() + grace
        for worker in idle:
            worker.stop(max(0.0, deadline - time.monotonic()))
        if threads is not None:
            threads.shutdown(wait=False, cancel_futures=True)
