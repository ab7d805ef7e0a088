"""The memory budget every engine stays within (spilling to disk or cutting smaller chunks).

The budget bounds the whole process's peak RSS (each dask worker's), beyond the interpreter
and its imported modules: whatever a stage keeps in flight (items read ahead, cells encoded
ahead, chunks computed at once) counts against it, not only the engines' buffers.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Generator, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from standgrid.errors import StandgridError

T = TypeVar("T")
R = TypeVar("R")

#: The default budget is this fraction of the memory available (to this process's cgroup,
#: when it has a limit) ...
DEFAULT_FRACTION = 0.25
#: ... within these bounds (MB).
DEFAULT_MIN_MB, DEFAULT_MAX_MB = 256, 4096


def available_memory() -> int | None:
    """Bytes of memory available to this process: the system's ``MemAvailable``, or the room
    left under its cgroup's limit when that is less; None when unknown."""
    found: list[int] = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = Path("/sys/fs/cgroup/memory.current").read_text().strip()
        if limit != "max":
            found.append(max(0, int(limit) - int(used)))
    except (OSError, ValueError):
        pass
    if not found:
        try:
            import os

            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (AttributeError, ValueError, OSError):
            return None
    return min(found)


def default_budget_mb() -> int:
    """The default budget in MB: :data:`DEFAULT_FRACTION` of the memory available, at least
    :data:`DEFAULT_MIN_MB` and at most :data:`DEFAULT_MAX_MB` (2048 when unknown)."""
    available = available_memory()
    if available is None:
        return 2048
    mb = int(available * DEFAULT_FRACTION) >> 20
    return max(DEFAULT_MIN_MB, min(DEFAULT_MAX_MB, mb))


#: Default budget of one stage in one process (see :func:`default_budget_mb`; fixed when
#: this module is imported).
DEFAULT_MEMORY_BUDGET = default_budget_mb() << 20


class BudgetError(StandgridError, ValueError):
    """A memory budget that cannot work."""


@dataclass(frozen=True)
class MemoryBudget:
    """Bytes one process (one dask worker) may hold for a stage's data."""

    bytes: int = DEFAULT_MEMORY_BUDGET

    def __post_init__(self) -> None:
        if self.bytes < 16 << 20:
            raise BudgetError(f"memory budget {self.bytes} B is below the 16 MB minimum")

    @classmethod
    def megabytes(cls, mb: float) -> MemoryBudget:
        return cls(int(mb * 2**20))

    def points(self, bytes_per_point: int) -> int:
        """How many points of ``bytes_per_point`` (all copies a step makes) fit."""
        return max(1, self.bytes // max(1, bytes_per_point))


def bounded_map(
    func: Callable[[T], R],
    items: Iterable[T],
    cost: Callable[[T], float],
    limit: float,
    learn: Callable[[T, R], None] | None = None,
    *,
    threads: int = 2,  # standgrid.engine.ordered.AHEAD
) -> Generator[R, None, None]:
    """``func(item)`` for every item on up to ``threads`` threads, yielded in item order,
    with items in flight (running, or done and not yet taken) while their ``cost`` (the
    bytes each is estimated to hold) stays within ``limit``: always at least one. ``learn``
    is told each item's result as it is taken (before more are started). Close the generator
    when done: items not started never run, and the running ones are waited for."""
    iterator = iter(items)
    end = object()
    following: Any = next(iterator, end)
    pending: deque[tuple[Future[R], float, Any]] = deque()
    held = 0.0
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        try:
            while True:
                while following is not end and len(pending) < max(1, threads):
                    estimate = cost(following)
                    if pending and held + estimate > limit:
                        break
                    pending.append((pool.submit(func, following), estimate, following))
                    held += estimate
                    following = next(iterator, end)
                if not pending:
                    return
                future, estimate, item = pending.popleft()
                result = future.result()
                held -= estimate
                if learn is not None:
                    learn(item, result)
                del item
                yield result
                del result
        finally:  # an error, or a caller that stops reading: items not started never run,
            for future, _, _ in pending:  # and the pool's exit waits for the running ones
                future.cancel()


def release_memory() -> None:
    """Give the allocator's free pages back to the system (glibc ``malloc_trim``; nothing
    elsewhere): arrays freed by a spill or a cell otherwise stay in this process's RSS,
    scattered over the arenas of the threads that made them."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


_TRIM: list[Any] = []


def _malloc_trim() -> Any:
    if not _TRIM:
        try:
            import ctypes

            _TRIM.append(ctypes.CDLL("libc.so.6").malloc_trim)
        except (OSError, AttributeError):
            _TRIM.append(None)
    return _TRIM[0]
