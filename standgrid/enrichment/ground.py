"""Ground classification with the Cloth Simulation Filter (Zhang et al. 2016, package ``CSF``).

CSF turns the cloud upside down and drops a cloth of given stiffness onto it; points within
``class_threshold`` of the settled cloth are ground. Defaults are tuned for steep forest
(``rigidness=1``, a soft cloth that follows ~20 deg slopes, with post-processing slope smoothing):
on the real ``las_chablais3`` scan they find > 99 % of the producer's ground points.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.engine.shared import ONE_THREAD_BLAS, ProcessWide, openmp_one_thread
from standgrid.errors import EnrichError
from standgrid.pointcloud import PointCloud

PointsLike = NDArray[np.float64] | PointCloud | ArrayLike

# CSF's bundled OpenMP runtime is initialised on its first import; its default busy-wait
# barriers slow CSF down 5-20x when the cores are shared with other processes (measured on
# a 2-core machine). Passive waiting costs little when the cores are free. Set once, here:
# setting the environment while another thread reads it is not safe.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def as_xyz(points: PointsLike) -> NDArray[np.float64]:
    """The (N, 3) float64 coordinates of an array or a :class:`PointCloud` (finite, checked)."""
    xyz = points.xyz if isinstance(points, PointCloud) else np.asarray(points, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise EnrichError(f"points must have shape (N, 3), got {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise EnrichError(
            f"{int((~np.isfinite(xyz).all(axis=1)).sum())} points have non-finite coordinates"
        )
    return np.ascontiguousarray(xyz, dtype=np.float64)


def one_thread(user_api: str) -> contextlib.AbstractContextManager[Any]:
    """Limit the ``user_api`` ("openmp" or "blas") thread pools to one thread for the
    duration: BLAS for every thread of the process (held until the last concurrent user
    leaves; a task of the engine already holds it), OpenMP for the calling thread (libgomp
    keeps the setting per thread)."""
    if user_api == "openmp":
        return openmp_one_thread()
    if user_api == "blas":
        return ONE_THREAD_BLAS.held()
    raise ValueError(f"no thread pool API {user_api!r}")


def _silence_stdout() -> Callable[[], None]:
    """Send C-level writes to file descriptor 1 to /dev/null; returns the undo."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no fd 1 (embedded interpreter): nothing to silence
        return lambda: None
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        os.close(saved)
        return lambda: None
    try:
        os.dup2(devnull, 1)
    except OSError:
        os.close(saved)
        os.close(devnull)
        return lambda: None

    def undo() -> None:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        try:
            os.dup2(saved, 1)
        finally:
            os.close(saved)
            os.close(devnull)

    return undo


#: C-level standard output silenced while any thread runs CSF (it prints).
_QUIET_STDOUT = ProcessWide(_silence_stdout)


def classify_ground(
    points: PointsLike,
    *,
    method: str = "csf",
    cloth_resolution: float = 0.5,
    rigidness: int = 1,
    slope_smooth: bool = True,
    class_threshold: float = 0.5,
    iterations: int = 500,
    time_step: float = 0.65,
) -> NDArray[np.bool_]:
    """Boolean mask (N,) of ground points.

    ``cloth_resolution`` (m) is the cloth grid spacing (about the point spacing of the ground;
    0.5 m suits ALS at 5-20 pts/m2 and denser robot scans); ``rigidness`` 1 (steep), 2 (relief)
    or 3 (flat); ``slope_smooth`` is CSF's post-processing for steep slopes; ``class_threshold``
    (m) is the distance to the cloth that still counts as ground.
    """
    if method != "csf":
        raise EnrichError(f"unknown ground classification method {method!r} (known: 'csf')")
    if rigidness not in (1, 2, 3):
        raise EnrichError(f"CSF rigidness must be 1, 2 or 3, got {rigidness}")
    if cloth_resolution <= 0 or class_threshold <= 0 or iterations < 1:
        raise EnrichError("cloth_resolution and class_threshold must be > 0, iterations >= 1")
    xyz = as_xyz(points)
    if len(xyz) == 0:
        return np.zeros(0, dtype=bool)
    import CSF

    # a local origin keeps CSF's float arithmetic precise (each column's minimum: the
    # same values as xyz.min(axis=0), which is 20x slower on an (N, 3) array)
    local = xyz - [xyz[:, k].min() for k in range(3)]
    csf = CSF.CSF()
    csf.params.bSloopSmooth = bool(slope_smooth)
    csf.params.cloth_resolution = float(cloth_resolution)
    csf.params.rigidness = int(rigidness)
    csf.params.class_threshold = float(class_threshold)
    csf.params.interations = int(iterations)  # sic: the package's spelling
    csf.params.time_step = float(time_step)
    csf.setPointCloud(local)
    ground, off_ground = CSF.VecInt(), CSF.VecInt()
    # One OpenMP thread: CSF's parallel cloth update is not deterministic (the same points
    # get different labels from run to run with two threads).
    with _QUIET_STDOUT.held(), one_thread("openmp"):
        csf.do_filtering(ground, off_ground, False)  # False: do not write cloth_nodes.txt
    if len(ground) + len(off_ground) != len(xyz):
        raise EnrichError(
            f"CSF returned {len(ground) + len(off_ground)} labels for {len(xyz)} points"
        )
    # the labels come back one by one through SWIG: read the shorter of the two lists
    if len(ground) <= len(off_ground):
        mask = np.zeros(len(xyz), dtype=bool)
        mask[np.fromiter(ground, dtype=np.int64, count=len(ground))] = True
    else:
        mask = np.ones(len(xyz), dtype=bool)
        mask[np.fromiter(off_ground, dtype=np.int64, count=len(off_ground))] = False
    return mask
