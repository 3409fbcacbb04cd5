"""The background-thread prefetch of the physical evaluation: order, errors, early stop."""

from __future__ import annotations

import threading
from contextlib import closing

import pytest

from davis_rig.evaluation.prefetch import prefetch


def test_yields_every_item_in_order_from_another_thread():
    threads = []

    def source():
        for i in range(50):
            threads.append(threading.current_thread())
            yield i

    assert list(prefetch(source(), depth=3)) == list(range(50))
    assert all(t is not threading.main_thread() for t in threads)


def test_producer_error_is_raised_at_its_position():
    def source():
        yield 1
        yield 2
        raise KeyError("bad chunk")

    got = []
    with pytest.raises(KeyError, match="bad chunk"):
        for item in prefetch(source()):
            got.append(item)
    assert got == [1, 2]


def test_early_stop_ends_the_producer_and_joins_it():
    produced = []
    finished = threading.Event()

    def source():
        try:
            for i in range(10_000):
                produced.append(i)
                yield i
        finally:
            finished.set()

    with closing(prefetch(source(), depth=2)) as items:
        for item in items:
            if item == 3:
                break
    # the producer ran at most depth + 2 items ahead (queue, the item in hand, the one being put), closed its
    # source and its thread is gone
    assert len(produced) <= 3 + 1 + 2 + 2
    assert finished.is_set()  # the source generator was closed
    assert not any(t.name == "prefetch" for t in threading.enumerate())


def test_depth_must_be_positive():
    with pytest.raises(ValueError, match="depth"):
        prefetch([1], depth=0)
