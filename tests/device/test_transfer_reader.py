"""TransferReader: order, timeouts, drop counting, error hand-over after data, clean stop."""

import threading

import pytest

from davis_rig.device.reader import TransferReader
from davis_rig.errors import DeviceDisconnectedError


class FakeRead:
    """``read(size, timeout_ms)`` returning scripted items; ``None`` = timeout; an exception is raised."""

    def __init__(self, items, then=None):
        self.items = list(items)
        self.then = then
        self.sizes = []
        self.done = threading.Event()

    def __call__(self, size, timeout_ms):
        self.sizes.append((size, timeout_ms))
        if self.items:
            item = self.items.pop(0)
            if isinstance(item, BaseException):
                raise item
            return item
        self.done.set()
        if self.then is not None:
            raise self.then
        self.done.wait(timeout_ms / 1000)
        return None


def test_delivers_in_order_and_counts_timeouts():
    read = FakeRead([b"a", None, b"bc", b"", b"d"])
    with TransferReader(read, read_bytes=65536, timeout_ms=5) as reader:
        got = [reader.get(1.0) for _ in range(3)]
        assert read.done.wait(1.0)
    assert got == [b"a", b"bc", b"d"]
    stats = reader.stats
    assert (stats.transfers, stats.bytes, stats.dropped_transfers) == (3, 4, 0)
    assert stats.timeouts >= 2  # the None and the empty transfer, plus idle reads
    assert read.sizes[0] == (65536, 5)
    assert not reader.running


def test_error_is_raised_after_the_data_read_before_it():
    read = FakeRead([b"1", b"2"], then=DeviceDisconnectedError("gone"))
    reader = TransferReader(read, timeout_ms=5).start()
    assert reader.get(1.0) == b"1"
    assert reader.get(1.0) == b"2"
    with pytest.raises(DeviceDisconnectedError, match="gone"):
        reader.get(1.0)
    assert reader.finished and reader.get(0.01) is None
    reader.stop()
    assert not reader.running


def test_full_queue_drops_and_counts_with_one_warning():
    read = FakeRead([b"x" * 10] * 5)
    reader = TransferReader(read, timeout_ms=5, queue_transfers=2)
    with pytest.warns(RuntimeWarning, match="dropped"):
        reader.start()
        assert read.done.wait(1.0)
        reader.stop()
    stats = reader.stats
    assert (stats.transfers, stats.dropped_transfers, stats.dropped_bytes) == (2, 3, 30)
    assert [reader.get(0.5), reader.get(0.5)] == [b"x" * 10] * 2
    assert reader.get(0.5) is None and reader.finished


def test_stop_ends_an_idle_reader_and_get_returns_none():
    read = FakeRead([])
    reader = TransferReader(read, timeout_ms=5).start()
    assert reader.get(0.02) is None and not reader.finished  # idle: just nothing yet
    reader.stop()
    assert not reader.running
    assert reader.get(None) is None and reader.finished
    with pytest.raises(RuntimeError, match="already started"):
        reader.start()


def test_ring_queue_defaults_to_the_same_64_mib_as_the_read_thread():
    from davis_rig.device.reader import DEFAULT_QUEUE_BYTES, RingReader

    assert DEFAULT_QUEUE_BYTES == 64 * 2**20 == 512 * TransferReader(FakeRead([])).read_bytes
    assert RingReader(object(), lambda: None, transfer_bytes=32768)._queue.maxsize == 2048
    assert RingReader(object(), lambda: None, transfer_bytes=8192)._queue.maxsize == 8192
    assert RingReader(object(), lambda: None, queue_transfers=7)._queue.maxsize == 7
