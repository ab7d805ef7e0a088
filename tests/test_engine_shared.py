"""A process-wide setting held by concurrent threads stays until the last of them leaves."""

from __future__ import annotations

import os
import threading

import pytest
from threadpoolctl import threadpool_info

from standgrid.engine.executor import run_limited
from standgrid.engine.shared import ONE_THREAD_BLAS, ProcessWide
from standgrid.enrichment.ground import _QUIET_STDOUT


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def _openmp_threads(_: object = None) -> list[int]:
    """The OpenMP thread count the calling thread would use (libgomp keeps it per thread)."""
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "openmp"]


def test_overlapping_users_keep_the_setting_until_the_last_leaves() -> None:
    state: list[str] = []

    def apply() -> object:
        state.append("on")
        return lambda: state.append("off")

    shared = ProcessWide(apply)  # type: ignore[arg-type]
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen_by_b: list[list[str]] = []

    def a() -> None:
        with shared.held():
            a_in.set()
            b_in.wait(5)
        a_out.set()

    def b() -> None:
        a_in.wait(5)
        with shared.held():
            b_in.set()
            a_out.wait(5)
            seen_by_b.append(list(state))  # A has left; B is still inside

    threads = [threading.Thread(target=a), threading.Thread(target=b)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert seen_by_b == [["on"]]  # applied once, not undone while B was inside
    assert state == ["on", "off"]  # undone once, by the last to leave


def test_pool_limit_and_quiet_stdout_are_restored_after_concurrent_use() -> None:
    before_blas = _blas_threads()
    before_fd = os.fstat(1)
    barrier = threading.Barrier(2)
    inside: list[list[int]] = []

    def task() -> None:
        with ONE_THREAD_BLAS.held(), _QUIET_STDOUT.held():
            barrier.wait(5)
            inside.append(_blas_threads())
            barrier.wait(5)

    threads = [threading.Thread(target=task) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert all(set(limits) <= {1} for limits in inside) and len(inside) == 2
    assert _blas_threads() == before_blas
    after_fd = os.fstat(1)
    assert (after_fd.st_dev, after_fd.st_ino) == (before_fd.st_dev, before_fd.st_ino)


def test_every_concurrent_task_thread_runs_openmp_on_one_thread() -> None:
    """CSF's cloth is not deterministic on two OpenMP threads: a second task thread, entering
    while the first is inside, must be limited too (libgomp's limit is per thread)."""
    pytest.importorskip("CSF")  # loads the OpenMP runtime CSF uses
    from standgrid.enrichment.ground import one_thread

    if not _openmp_threads():
        pytest.skip("no OpenMP runtime loaded")
    first_in, second_done = threading.Event(), threading.Event()
    seen: dict[str, list[int]] = {}

    def first() -> None:
        def hold(_: object) -> None:
            first_in.set()
            second_done.wait(10)

        run_limited(hold, None)

    def second() -> None:
        first_in.wait(10)
        seen["run_limited"] = run_limited(_openmp_threads, None)
        with one_thread("openmp"):
            seen["one_thread"] = _openmp_threads()
        second_done.set()

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert seen["run_limited"] and set(seen["run_limited"]) == {1}
    assert set(seen["one_thread"]) == {1}


def _second_leaves_last() -> None:
    """Two threads hold the BLAS limit; the one that set it leaves first."""
    first_in, second_in, first_out = threading.Event(), threading.Event(), threading.Event()

    def first() -> None:
        with ONE_THREAD_BLAS.held():
            first_in.set()
            second_in.wait(5)
        first_out.set()

    def second() -> None:
        first_in.wait(5)
        with ONE_THREAD_BLAS.held():
            second_in.set()
            first_out.wait(5)  # the first (which set the limit) has left: this one is last

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)


def test_the_pool_limit_is_restored_whichever_thread_leaves_last() -> None:
    """The last thread out restores the BLAS limit the first one set, whichever it is (the
    restore used to run on the leaving thread, and did not take when that was not the
    thread that had set it: the process stayed at one BLAS thread)."""
    before = _blas_threads()
    for _ in range(6):
        _second_leaves_last()
        assert _blas_threads() == before
