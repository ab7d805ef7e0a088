"""Process-wide settings that concurrent threads share.

A BLAS thread-pool limit (``threadpoolctl``) or a redirected file descriptor belongs to the
whole process. Entered and left by two threads at once, each thread's exit restores the state the
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


def _limit_blas() -> Callable[[], None]:
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1, user_api="blas").restore_original_limits


#: BLAS pools of this process at one thread while any task runs. (An OpenMP limit is the
#: calling thread's own setting in libgomp: each thread limits its own, see
#: :func:`openmp_one_thread`.)
ONE_THREAD_BLAS = ProcessWide(_limit_blas)


@contextlib.contextmanager
def openmp_one_thread() -> Iterator[None]:
    """This thread's OpenMP regions on one thread for the duration (libgomp keeps the
    number per thread, so concurrent threads each limit their own and restore their own)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="openmp"):
        yield
