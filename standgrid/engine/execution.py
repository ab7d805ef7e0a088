"""How a stage runs (not what it computes): where, with how much memory, how long it waits
for the catalog's lock, and whom it tells how far it got.

Every stage takes one :class:`Execution` (``stage(input, options, *, execution)``), so a
script (or ``standgrid run``) sets these once for all its stages.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

from standgrid.engine.budget import MemoryBudget
from standgrid.engine.executor import Executor, open_executor
from standgrid.engine.progress import SILENT, Progress
from standgrid.errors import OptionError

#: Seconds a stage waits for another process writing (or reading) the catalog: the one
#: default of every stage, catalog reader and writer.
DEFAULT_LOCK_TIMEOUT = 30.0
#: Least memory budget (MB): below it no engine can hold one chunk.
MIN_MEMORY_MB = 16
#: Most memory budget (MB): 1 TiB, far beyond any machine this runs on (a typo guard).
MAX_MEMORY_MB = 1 << 20
#: A dask scheduler address: ``protocol://host[:port]`` or ``host:port``.
_ADDRESS = re.compile(r"(?:[a-z][a-z0-9+.-]*://[^\s/:]+(?::\d+)?|[^\s/:]+:\d+)/?", re.I)


@dataclass(frozen=True)
class Execution:
    """Where and how a stage runs; validated when made (:class:`~standgrid.errors.OptionError`
    naming the field at fault).

    - ``workers``: a local dask cluster of this many processes; ``scheduler``: the dask
      cluster at this address (``tcp://host:port``; files on storage every worker reaches);
      neither: this process. ``executor``: an executor already open (overrides both).
    - ``memory_mb``: what one process (each dask worker) may hold for a stage's data
      (``None``: a quarter of the available memory, 256 to 4096 MB).
    - ``lock_timeout``: seconds to wait for another writer of the catalog (``None``: for ever).
    - ``progress``: told how far the stage got (:class:`~standgrid.engine.progress.Progress`).
    - ``shared_folder``: the cluster's workers reach this process's folders (the default).
      False: they share none, and exchange what they write through the object storage a
      catalog at a URL lives in (``outbox``, set by the stage: the URL workers put it under).
    """

    workers: int | None = None
    scheduler: str | None = None
    memory_mb: int | None = None
    lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT
    progress: Progress = SILENT
    executor: Executor | None = field(default=None, compare=False, repr=False)
    shared_folder: bool = True
    outbox: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.workers is not None and (
            isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1
        ):
            raise OptionError("workers", f"{self.workers!r}: give a number of processes >= 1")
        if self.scheduler is not None:
            if not isinstance(self.scheduler, str) or not _ADDRESS.fullmatch(self.scheduler):
                raise OptionError(
                    "scheduler", f"{self.scheduler!r}: give an address, tcp://host:port"
                )
            if self.workers is not None:
                raise OptionError(
                    "scheduler", "give either a number of local workers or a scheduler address"
                )
        if self.memory_mb is not None and not (
            isinstance(self.memory_mb, int) and MIN_MEMORY_MB <= self.memory_mb <= MAX_MEMORY_MB
        ):
            raise OptionError(
                "memory_mb",
                f"{self.memory_mb!r}: give megabytes from {MIN_MEMORY_MB} to {MAX_MEMORY_MB}",
            )
        timeout = self.lock_timeout
        if timeout is not None and not (
            isinstance(timeout, int | float)
            and not isinstance(timeout, bool)
            and math.isfinite(timeout)
            and timeout >= 0
        ):
            raise OptionError("lock_timeout", f"{timeout!r}: give seconds >= 0, or None")
        if not isinstance(self.shared_folder, bool):
            raise OptionError("shared_folder", f"{self.shared_folder!r}: give True or False")
        if not all(callable(getattr(self.progress, m, None)) for m in ("track", "status")):
            raise OptionError("progress", f"{self.progress!r} is no Progress (track(), status())")

    @property
    def memory_budget(self) -> MemoryBudget:
        """The memory budget: ``memory_mb``, or the default one."""
        return MemoryBudget() if self.memory_mb is None else MemoryBudget.megabytes(self.memory_mb)

    @contextlib.contextmanager
    def open(self) -> Iterator[Executor]:
        """The executor to run on: ``executor``, or one opened here (closed on exit)."""
        if self.executor is not None:
            yield self.executor
            return
        with open_executor(
            self.workers, self.scheduler, memory_budget=self.memory_budget.bytes
        ) as executor:
            yield executor

    def on(self, executor: Executor) -> Execution:
        """This execution on an open ``executor`` (stages run in turn share one cluster)."""
        return replace(self, executor=executor)
