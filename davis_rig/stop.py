"""Stop requests: SIGINT / SIGTERM turned into a flag that a long loop polls between units of work.

A loop that can save its state (the attack's optimisation, training) must not die in the middle of a step: inside
:class:`StopOnSignal` the first SIGINT (Ctrl-C) or SIGTERM only sets :attr:`StopOnSignal.signal_name`; the loop
finishes the unit it is in, saves its state and stops. A second signal restores the previous handlers and raises
:class:`KeyboardInterrupt` at once (the last saved state stays as it was: it is written atomically).

Handlers can only be installed from the main thread; elsewhere (or with ``enabled=False``) the context manager
installs nothing and the flag stays unset. Work that runs in many small units inside a step (preparing or validating
clips) polls the flag with :func:`check_stop`, which raises :class:`StopRequested` to abandon that work.
"""

from __future__ import annotations

import signal
import threading

__all__ = ["StopOnSignal", "StopRequested", "check_stop"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopOnSignal:
    """Context manager: SIGINT and SIGTERM request a stop instead of interrupting.

    Args:
        enabled: install the handlers (False: a flag that is never set, e.g. for library callers that want
            Ctrl-C to raise as usual).

    Attributes:
        signal_name: ``"SIGINT"`` / ``"SIGTERM"`` once one arrived, else ``None``.

    Example:
        >>> with StopOnSignal() as stop:
        ...     for step in range(3):
        ...         if stop.requested:
        ...             break
    """

    def __init__(self, enabled: bool = True):
        self.enabled = bool(enabled)
        self.signal_name: str | None = None
        self._previous: dict[int, object] = {}

    @property
    def requested(self) -> bool:
        """Whether a stop was requested."""
        return self.signal_name is not None

    def _handle(self, signum, frame) -> None:
        if self.signal_name is not None:  # the second signal: stop now
            self._restore()
            raise KeyboardInterrupt
        self.signal_name = signal.Signals(signum).name

    def _restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    def __enter__(self) -> StopOnSignal:
        if self.enabled and threading.current_thread() is threading.main_thread():
            for signum in _SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()


class StopRequested(Exception):
    """Raised by :func:`check_stop` between the clips of a preparation or validation when a stop was requested."""


def check_stop(stop: StopOnSignal | None) -> None:
    """Raise :class:`StopRequested` if ``stop`` (``None``: never) has a stop request."""
    if stop is not None and stop.requested:
        raise StopRequested
