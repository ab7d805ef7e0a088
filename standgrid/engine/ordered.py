"""Results of an executor in the order of their items, with bounded memory.

In this process (:class:`SerialExecutor`) up to ``ahead`` items are computed ahead on
threads (numpy, laspy, lazrs and pyproj release the GIL in their inner loops, so on two
cores the next item is read while the caller consumes the current one). On a cluster the
items go in windows of a few per worker; each window's results are yielded in item order as
soon as they are, so at most one window of results is held.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Generator, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from itertools import islice
from typing import TypeVar

from standgrid.engine.executor import Executor, SerialExecutor

T = TypeVar("T")
R = TypeVar("R")

#: Items computed ahead on threads in this process.
AHEAD = 2
#: Items per window on a cluster, per worker.
WINDOW_PER_WORKER = 4


def ordered_map(
    executor: Executor, func: Callable[[T], R], items: Iterable[T], *, ahead: int = AHEAD
) -> Generator[R, None, None]:
    """``func(item)`` for every item, yielded in item order (the same order whatever runs
    them, so what is built from the results is the same). Close the generator when done
    (``contextlib.closing``): a caller that stops early then leaves nothing running behind
    it (no task writes into a transaction being discarded)."""
    if isinstance(executor, SerialExecutor):
        yield from _threaded(func, items, ahead)
        return
    iterator = iter(items)
    size = max(1, WINDOW_PER_WORKER * executor.workers)
    while window := list(islice(iterator, size)):
        done: dict[int, R] = {}
        following = 0
        for index, result in executor.map(func, window):
            done[index] = result
            while following in done:
                yield done.pop(following)
                following += 1


def _threaded(func: Callable[[T], R], items: Iterable[T], ahead: int) -> Generator[R, None, None]:
    iterator = iter(items)
    with ThreadPoolExecutor(max_workers=max(1, ahead)) as pool:
        pending: deque[Future[R]] = deque()
        try:
            for item in islice(iterator, max(1, ahead)):
                pending.append(pool.submit(func, item))
            while pending:
                result = pending.popleft().result()
                for item in islice(iterator, 1):
                    pending.append(pool.submit(func, item))
                yield result
        finally:  # an error, or a caller that stops reading: items not started never run,
            for future in pending:  # and the pool's exit waits for the running ones
                future.cancel()
