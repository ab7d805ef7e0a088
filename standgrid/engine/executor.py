"""Run a pure function over many work items: in this process, or on a dask.distributed cluster.

The function and its items must be picklable (module-level function, plain data), because a
cluster ships them to worker processes; the caller alone writes shared state (the catalog),
from the results. Results come back as ``(index, result)`` in completion order with a bounded
number of items in flight, so the caller merges them in a deterministic order of its own and
its memory stays bounded.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, TypeVar

from standgrid.engine.budget import DEFAULT_MEMORY_BUDGET
from standgrid.errors import StandgridError

T = TypeVar("T")
R = TypeVar("R")


class ClusterError(StandgridError, RuntimeError):
    """The dask cluster could not be started or reached."""


class Executor(Protocol):
    """Maps a pure function over items; ``workers`` processes compute at once."""

    workers: int

    def map(self, func: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        """Yield ``(index, func(items[index]))`` for every item, in completion order."""
        ...


def run_limited(func: Callable[[T], R], item: T) -> R:
    """``func(item)`` with BLAS/OpenMP pools limited to one thread (one task per core; the
    BLAS limit holds for the whole process while any thread runs a task, the OpenMP one is
    each thread's own)."""
    from standgrid.engine.shared import ONE_THREAD_BLAS, openmp_one_thread

    with ONE_THREAD_BLAS.held(), openmp_one_thread():
        return func(item)


def run_pickled(func: Callable[[T], R], payload: bytes) -> bytes:
    """:func:`run_limited` on a pickled item, the result pickled.

    Pickled in-band, every array is rebuilt in a fresh (aligned) allocation on arrival;
    arrays dask deserialises out-of-band may be views at unaligned offsets of a network
    frame, where numpy takes other (unaligned) loops whose float sums differ in the last
    bit: a result computed on a worker would not be the one computed here.
    """
    import pickle

    _limit_this_process()
    result = func(pickle.loads(payload))
    return pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)


_LIMITED: list[object] = []


def _limit_this_process() -> None:
    """BLAS/OpenMP pools of this (worker) process limited to one thread, once: entering
    ``threadpool_limits`` inspects every loaded library (~15 ms), too much per task. LAZ
    (lazrs' rayon pool, built at its first use) gets one thread too, unless the worker was
    started with ``RAYON_NUM_THREADS`` set: a worker started by hand (``dask worker``) runs
    its tasks on one core each, as a LocalCluster's do."""
    if not _LIMITED:
        from threadpoolctl import threadpool_limits

        os.environ.setdefault("RAYON_NUM_THREADS", "1")
        _LIMITED.append(threadpool_limits(1))  # kept for the life of the worker


class SerialExecutor:
    """Everything in this process, one item after the other."""

    workers = 1

    def map(self, func: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        for index, item in enumerate(items):
            yield index, run_limited(func, item)


#: Items pickled larger than this are scattered to a worker, not sent in the task graph
#: (through the scheduler).
SCATTER_BYTES = 256 << 10


class DaskExecutor:
    """Items as tasks on a dask.distributed cluster, at most ``2 x workers`` in flight."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.workers = max(1, len(client.scheduler_info().get("workers", {})))

    def map(self, func: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R]]:
        import pickle

        from distributed import as_completed

        pending = iter(enumerate(items))
        in_flight = as_completed()
        index_of: dict[str, int] = {}

        def submit_next() -> bool:
            for index, item in pending:
                payload: Any = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
                if len(payload) > SCATTER_BYTES:  # straight to a worker, not in the graph
                    payload = self.client.scatter(payload, direct=True, hash=False)
                future = self.client.submit(run_pickled, func, payload, pure=False)
                index_of[future.key] = index
                in_flight.add(future)
                return True
            return False

        for _ in range(2 * self.workers):
            if not submit_next():
                break
        try:
            for future in in_flight:
                result = pickle.loads(future.result())  # re-raises the task's own exception
                index = index_of.pop(future.key)
                future.release()
                submit_next()
                yield index, result
        finally:  # an error, or a caller that stops reading: nothing may go on writing
            left = list(in_flight.futures)
            if left:
                self.client.cancel(left)
                with contextlib.suppress(Exception):
                    from distributed import wait

                    wait(left, timeout=60)


@contextlib.contextmanager
def open_executor(
    workers: int | None = None,
    scheduler: str | None = None,
    *,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> Iterator[Executor]:
    """The executor a stage runs on.

    - neither: this process (:class:`SerialExecutor`);
    - ``workers=N``: a dask ``LocalCluster`` of N single-threaded worker processes, each
      limited to ``memory_budget`` plus the interpreter's own ~1 GiB;
    - ``scheduler="tcp://host:port"``: an existing cluster (every worker must reach the
      catalog's folder at the same path).
    """
    if workers is not None and scheduler is not None:
        raise ClusterError("give either a number of local workers or a scheduler address")
    if scheduler is None and not workers:
        yield SerialExecutor()
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise ClusterError("dask.distributed is not installed") from exc
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s", direct_to_workers=True)
        except (OSError, TimeoutError) as exc:
            raise ClusterError(f"cannot reach the dask scheduler at {scheduler}: {exc}") from exc
        try:
            client.wait_for_workers(1, timeout=60)
        except TimeoutError as exc:
            client.close()
            raise ClusterError(f"the dask scheduler at {scheduler} has no workers") from exc
        try:
            yield DaskExecutor(client)
        finally:
            client.close()
        return
    import dask

    # the nanny starts each worker with OMP/MKL/OPENBLAS_NUM_THREADS=1 (dask's default
    # distributed.nanny.pre-spawn-environ); run_limited() also limits every task's pools.
    # Not dask's MALLOC_TRIM_THRESHOLD_: it pins glibc's mmap threshold, so every array
    # over 128 kB is a fresh mmap paid in page faults (tasks ran 1.5-3x slower). One rayon
    # thread (lazrs' LAZ compression) per worker too: a worker is one core.
    # Threads that wait sleep (standgrid.WAIT_POLICY, as this process has it: a user's own
    # setting included), set before the worker's interpreter loads numpy's OpenBLAS.
    from standgrid._threads import WAIT_POLICY, wait_passively

    wait_passively()
    environ = "distributed.nanny.pre-spawn-environ"
    waiting = {f"{environ}.{name}": os.environ[name] for name in WAIT_POLICY if name in os.environ}
    with dask.config.set(
        {f"{environ}.MALLOC_TRIM_THRESHOLD_": None, f"{environ}.RAYON_NUM_THREADS": 1, **waiting}
    ):
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_budget + (1 << 30),
            dashboard_address=None,
            host="127.0.0.1",
            preload=["standgrid.engine.worker_setup"],  # workers leave Ctrl-C to the client
        )
    try:
        with Client(cluster, direct_to_workers=True) as client:
            yield DaskExecutor(client)
    except KeyboardInterrupt:
        with _quiet_dask():  # the shutdown the interrupt asks for is no error to log
            cluster.close()
        raise
    finally:
        cluster.close()


@contextlib.contextmanager
def _quiet_dask() -> Iterator[None]:
    """dask's loggers silenced (errors about tasks and connections cancelled by a close)."""
    import logging

    logger = logging.getLogger("distributed")
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(level)
