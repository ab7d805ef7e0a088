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
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")


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


_SETTINGS_THREAD: ThreadPoolExecutor | None = None
_SETTINGS_LOCK = threading.Lock()


def _on_settings_thread(call: Callable[[], T]) -> T:
    """Run ``call`` on one long-lived thread of this process: a pool limit restored from
    another thread than the one that set it does not take (threadpoolctl 3.8 with OpenBLAS
    0.3.30: the process stayed at one BLAS thread about half the time)."""
    global _SETTINGS_THREAD
    with _SETTINGS_LOCK:
        if _SETTINGS_THREAD is None:
            _SETTINGS_THREAD = ThreadPoolExecutor(1, thread_name_prefix="standgrid-settings")
        pool = _SETTINGS_THREAD
    return pool.submit(call).result()


def _limit_blas() -> Callable[[], None]:
    from threadpoolctl import threadpool_limits

    limiter = _on_settings_thread(lambda: threadpool_limits(1, user_api="blas"))
    return lambda: _on_settings_thread(limiter.restore_original_limits)


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
