"""How the native libraries' thread pools wait and how large they are, set before they load
(``import standgrid`` runs :func:`wait_passively`; re-exported as ``standgrid.wait_passively``)."""

from __future__ import annotations

import os
from collections.abc import MutableMapping

#: Thread settings of the native libraries that are read once, as each library loads:
#: threads that wait for work sleep (no spin-waiting: on a busy machine spinning threads
#: take the cores from the ones with work, CPU time balloons 3x), and the pools are sized
#: explicitly. A variable the user set is never overridden.
WAIT_POLICY: dict[str, str] = {
    "OMP_WAIT_POLICY": "PASSIVE",  # OpenMP (libgomp of CSF and small_gicp; LLVM libomp)
    "GOMP_SPINCOUNT": "0",  # libgomp: no spinning before sleeping
    "OPENBLAS_THREAD_TIMEOUT": "4",  # OpenBLAS: spin 2**4 cycles (the least), then sleep
    "KMP_BLOCKTIME": "0",  # Intel/LLVM OpenMP: sleep at once
}
#: Thread-count variables set to the cores this process may run on, unless set.
THREAD_COUNTS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def wait_passively(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """Set :data:`WAIT_POLICY` and :data:`THREAD_COUNTS` in ``environ`` where not set; returns
    what was set. Takes effect for libraries loaded afterwards (``import standgrid`` runs it,
    before numpy; dask workers inherit it). A user's choice wins: ``OMP_WAIT_POLICY=ACTIVE``
    (or a ``GOMP_SPINCOUNT``) keeps libgomp spinning, ``GOTO_THREAD_TIMEOUT`` is OpenBLAS's
    older name."""
    given = dict(WAIT_POLICY)
    if "OMP_WAIT_POLICY" in environ or "GOMP_SPINCOUNT" in environ:
        del given["GOMP_SPINCOUNT"]  # OMP_WAIT_POLICY=ACTIVE given: leave its spinning be
    if "GOTO_THREAD_TIMEOUT" in environ:
        del given["OPENBLAS_THREAD_TIMEOUT"]
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    given.update(dict.fromkeys(THREAD_COUNTS, str(max(1, cores))))
    done = {}
    for name, value in given.items():
        if not environ.get(name):
            environ[name] = done[name] = value
    return done
