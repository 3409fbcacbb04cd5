"""SIGINT / SIGTERM as a stop request: the first sets a flag, the second interrupts, handlers are restored."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from davis_rig.stop import StopOnSignal


@pytest.mark.parametrize("signum, name", [(signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")])
def test_first_signal_requests_a_stop_second_interrupts(signum, name):
    before = signal.getsignal(signum)
    with StopOnSignal() as stop:
        assert not stop.requested
        os.kill(os.getpid(), signum)
        assert stop.requested and stop.signal_name == name
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signum)
        assert signal.getsignal(signum) is before  # the second signal gave the handlers back
    assert signal.getsignal(signum) is before


def test_disabled_or_off_the_main_thread_installs_nothing():
    before = signal.getsignal(signal.SIGINT)
    with StopOnSignal(enabled=False) as stop:
        assert signal.getsignal(signal.SIGINT) is before and not stop.requested
    seen = []

    def worker():
        with StopOnSignal() as inner:
            seen.append(signal.getsignal(signal.SIGINT))
            seen.append(inner.requested)

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen == [before, False]
