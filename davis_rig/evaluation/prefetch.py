"""Run an iterator in a background thread, a few items ahead of its consumer.

The physical evaluation reads and histograms the next chunk of events while onnxruntime (which releases the
GIL) runs the current one; this is the producer side of that overlap.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar

__all__ = ["prefetch"]

T = TypeVar("T")
_POLL_S = 0.05


def prefetch(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """Yield the items of ``items``, produced by a background thread up to ``depth`` items ahead.

    The order is kept. An exception raised while producing an item is re-raised in the consumer at that
    position. When the consumer stops early (``break``, an exception, or ``close()`` of this generator), the
    producer stops at its next item, closes ``items`` if it is a generator, and its thread is joined before
    ``close()`` returns — so wrap the generator in :func:`contextlib.closing` when the source uses a resource
    (an open file) that the consumer closes afterwards.

    Args:
        items: any iterable; it is iterated in the background thread only.
        depth: how many produced items may wait for the consumer (≥ 1).

    Returns:
        A generator of the same items.

    Raises:
        ValueError: ``depth < 1``.
    """
    if depth < 1:
        raise ValueError(f"depth: expected >= 1, got {depth}")
    return _prefetch(items, depth)


def _prefetch(items: Iterable[T], depth: int) -> Iterator[T]:
    slots: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def put(entry) -> bool:
        while not stop.is_set():
            try:
                slots.put(entry, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        iterator = iter(items)
        try:
            for item in iterator:
                if not put((None, item)):
                    return
            put((None, done))
        except BaseException as exc:  # handed to the consumer, re-raised there
            put((exc, None))
        finally:
            close = getattr(iterator, "close", None)  # a generator source runs its cleanup in this thread
            if close is not None:
                close()

    worker = threading.Thread(target=produce, name="prefetch", daemon=True)
    worker.start()
    try:
        while True:
            error, item = slots.get()
            if error is not None:
                raise error
            if item is done:
                return
            yield item
    finally:
        stop.set()
        worker.join()
