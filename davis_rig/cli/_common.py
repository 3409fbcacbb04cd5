"""What every command shares: turning errors into one message and an exit code, in one place."""

from __future__ import annotations

import sys
from typing import Callable

#: Exit codes of every davis_rig command.
EXIT_OK = 0
EXIT_ERROR = 1  # any other DavisRigError
EXIT_USAGE = 2  # argparse's own code for bad arguments
EXIT_DEVICE = 3  # camera missing, busy, no permission, unsupported firmware, transfer failure
EXIT_DATA = 4  # a file is malformed or cannot be written (session.h5, replay, journal, checkpoint)
EXIT_MISSING_DEPENDENCY = 5
EXIT_INTERRUPTED = 130  # Ctrl-C outside a clean stop


def exit_code_for(exc: BaseException) -> int:
    """Map an exception onto the command's exit code (see the ``EXIT_*`` constants)."""
    from davis_rig.errors import DeviceError, FormatError, MissingDependencyError

    if isinstance(exc, MissingDependencyError):
        return EXIT_MISSING_DEPENDENCY
    if isinstance(exc, DeviceError):
        return EXIT_DEVICE
    if isinstance(exc, FormatError):
        return EXIT_DATA
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    return EXIT_ERROR


def run_command(name: str, action: Callable[[], int | None]) -> int:
    """Run one command's action; print a one-line ``<name>: error: ...`` on stderr for the toolkit's errors.

    Args:
        name: the command name shown in messages (``davis-record``).
        action: runs the command and returns its exit code (``None`` = 0).

    Returns:
        The exit code. Errors that are not ``DavisRigError`` (bugs) propagate with their traceback.
    """
    from davis_rig.errors import DavisRigError

    try:
        code = action()
    except DavisRigError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return exit_code_for(exc)
    except OSError as exc:  # e.g. the output directory does not exist
        print(f"{name}: error: {exc}", file=sys.stderr)
        return EXIT_DATA
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK if code is None else int(code)
