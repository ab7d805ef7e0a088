"""What every stage that walks many points shares: progress, the memory budget, executors.

Core module (no imports from the stages): the tiling partition engine and the catalog's
chunk engine both take a :class:`Progress`, a :class:`MemoryBudget` and an
:class:`Executor` (one process, or a dask.distributed cluster).
"""

from standgrid.engine.budget import DEFAULT_MEMORY_BUDGET, MemoryBudget
from standgrid.engine.executor import Executor, SerialExecutor, open_executor
from standgrid.engine.progress import SILENT, CallbackProgress, Progress

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "SILENT",
    "CallbackProgress",
    "Executor",
    "MemoryBudget",
    "Progress",
    "SerialExecutor",
    "open_executor",
]
