"""ordered_map: results in item order, in this process (threads) and on a real LocalCluster."""

from __future__ import annotations

import numpy as np
import pytest

from standgrid.engine import SerialExecutor, open_executor
from standgrid.engine.ordered import ordered_map


def cumulative_sum(item: tuple[int, int]) -> float:
    """A result that depends on the item alone (seeded), with items of unequal cost."""
    seed, size = item
    return float(np.random.default_rng(seed).random(size).sum())


def refuse_seven(item: int) -> int:
    if item == 7:
        raise ValueError("seven")
    return item * item


ITEMS = [(seed, 1000 + 40_000 * (seed % 3)) for seed in range(25)]


def test_serial_results_come_in_item_order() -> None:
    expected = [cumulative_sum(item) for item in ITEMS]
    assert list(ordered_map(SerialExecutor(), cumulative_sum, ITEMS)) == expected
    assert list(ordered_map(SerialExecutor(), cumulative_sum, iter(ITEMS), ahead=5)) == expected
    with pytest.raises(ValueError, match="seven"):
        list(ordered_map(SerialExecutor(), refuse_seven, range(10)))


def test_a_caller_that_stops_early_leaves_nothing_running() -> None:
    """Closed after its first result, the generator cancels what has not started and waits
    for what has: nothing runs on behind the caller (a task writing into a transaction that
    is being discarded)."""
    import time
    from contextlib import closing

    started: list[int] = []
    finished: list[int] = []

    def slow(item: int) -> int:
        started.append(item)
        time.sleep(0.2)
        finished.append(item)
        return item

    with closing(ordered_map(SerialExecutor(), slow, range(20), ahead=3)) as results:
        assert next(results) == 0
    # closed: what had started has finished, nothing else starts afterwards
    assert sorted(finished) == sorted(started) and len(started) <= 4
    time.sleep(0.5)
    assert len(started) == len(finished) <= 4


def test_cluster_results_come_in_item_order() -> None:
    pytest.importorskip("distributed")
    expected = [cumulative_sum(item) for item in ITEMS]
    with open_executor(workers=2) as executor:
        assert executor.workers == 2
        assert list(ordered_map(executor, cumulative_sum, ITEMS)) == expected
        got = ordered_map(executor, refuse_seven, range(10))
        assert [next(got) for _ in range(7)] == [k * k for k in range(7)]
        with pytest.raises(ValueError, match="seven"):
            next(got)
