"""What every stage that walks many points shares: progress, the memory budget, executors.

Core module (no imports from the stages): the tiling partition engine and the catalog's
chunk engine both take a :class:`Progress`, a :class:`MemoryBudget` and an
:class:`Executor` (one process, or a dask.distributed cluster); every stage takes them as one
:class:`Execution`.
"""

from standgrid.engine.budget import DEFAULT_MEMORY_BUDGET, MemoryBudget
from standgrid.engine.execution import DEFAULT_LOCK_TIMEOUT, Execution
from standgrid.engine.executor import Executor, SerialExecutor, open_executor
from standgrid.engine.progress import SILENT, CallbackProgress, Progress

__all__ = [
    "DEFAULT_LOCK_TIMEOUT",
    "DEFAULT_MEMORY_BUDGET",
    "SILENT",
    "CallbackProgress",
    "Execution",
    "Executor",
    "MemoryBudget",
    "Progress",
    "SerialExecutor",
    "open_executor",
]
