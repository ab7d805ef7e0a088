"""Set-up of each worker process of the local dask cluster (a dask preload).

Ctrl-C in a terminal interrupts every process of the foreground process group: the worker
processes would each print a ``KeyboardInterrupt`` traceback. The client alone handles the
interrupt (it cancels the tasks and closes the cluster), so workers ignore SIGINT, and do
not log the tasks the client cancels as warnings.

Threads that wait for work sleep, not spin (:func:`standgrid.wait_passively`): importing
this module (``standgrid``) sets the policy where it is not set, before the worker loads
the OpenMP runtimes of its tasks; a LocalCluster's nanny also starts each worker with it
(:func:`standgrid.engine.executor.open_executor`), before numpy's OpenBLAS loads.
"""

from __future__ import annotations

import logging
import signal
import threading
from typing import Any


def _not_a_cancelled_task(record: logging.LogRecord) -> bool:
    return "ended with CancelledError" not in record.getMessage()


def dask_setup(worker: Any) -> None:
    """Called by dask in the worker process as it starts."""
    from standgrid._threads import wait_passively

    wait_passively()  # (done on import already; a worker started by hand, too)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("distributed.worker.state_machine").addFilter(_not_a_cancelled_task)
