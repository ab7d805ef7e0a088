"""Process-wide settings that concurrent threads share.

A thread-pool limit (``threadpoolctl``) or a redirected file descriptor belongs to the whole
process. Entered and left by two threads at once, each thread's exit restores the state the
other saved: a pool limit lifted while the other still computes (CSF's cloth is not
deterministic on two OpenMP threads), standard output left on ``/dev/null`` for good.
:class:`ProcessWide` enters the setting for the first of its concurrent users and restores
it when the last one leaves.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator


class ProcessWide:
    """A setting ``apply()`` (which returns its undo) held while any thread is inside."""

    def __init__(self, apply: Callable[[], Callable[[], None]]) -> None:
        self._apply = apply
        self._lock = threading.Lock()
        self._users = 0
        self._undo: Callable[[], None] | None = None

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        with self._lock:
            if self._users == 0:
                self._undo = self._apply()
            self._users += 1
        try:
            yield
        finally:
            with self._lock:
                self._users -= 1
                if self._users == 0 and self._undo is not None:
                    undo, self._undo = self._undo, None
                    undo()


def _limit_all_pools() -> Callable[[], None]:
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1).restore_original_limits


#: BLAS and OpenMP pools of this process at one thread while any task runs.
ONE_THREAD_POOLS = ProcessWide(_limit_all_pools)
