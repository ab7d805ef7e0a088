"""A process-wide setting held by concurrent threads stays until the last of them leaves."""

from __future__ import annotations

import os
import threading

from threadpoolctl import threadpool_info

from standgrid.engine.shared import ONE_THREAD_POOLS, ProcessWide
from standgrid.enrich.ground import _QUIET_STDOUT


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


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
        with ONE_THREAD_POOLS.held(), _QUIET_STDOUT.held():
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
