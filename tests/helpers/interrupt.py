"""Ctrl-C a command while it works: run it as a subprocess with one per-item call slowed down, send SIGINT.

The command runs as a user runs it (its ``main`` in a new interpreter, the real signal), but on the suite's tiny
inputs it would finish before a signal could reach it; so one call it makes per item (a frame, a window, a
sequence, a step) is wrapped to count the item in a marker file and sleep ``delay_s`` after it. SIGINT goes out
once ``after_items`` items are counted: the command is then between two items, with the items so far done.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]

#: What the subprocess runs: argv = [target "module:Owner.attribute", marker, delay_s, "module:main", *command argv].
_SLOWED_MAIN = """
import functools, importlib, inspect, sys, time
from pathlib import Path

target, marker, delay_s, command, *argv = sys.argv[1:]
module_name, _, attribute = target.partition(":")
owner = importlib.import_module(module_name)
*path, name = attribute.split(".")
for part in path:
    owner = getattr(owner, part)
original = getattr(owner, name)

def pause():
    with open(marker, "a") as file:
        file.write("item\\n")
    time.sleep(float(delay_s))

@functools.wraps(original)
def slowed(*args, **kwargs):
    result = original(*args, **kwargs)
    if inspect.isgenerator(result):
        return _items(result)
    pause()
    return result

def _items(generator):
    for item in generator:
        yield item
        pause()

setattr(owner, name, slowed)
module_name, _, function = command.partition(":")
sys.argv = [module_name] + argv
raise SystemExit(getattr(importlib.import_module(module_name), function)(argv))
"""


def repo_env(**extra: str) -> dict[str, str]:
    """This process's environment with the repository first on ``PYTHONPATH`` (and ``extra`` variables set)."""
    path = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
    return dict(os.environ, PYTHONPATH=path, **extra)


@dataclass
class Interrupted:
    """The outcome of :func:`interrupt_while_working` and :func:`interrupt_after_log_lines`."""

    returncode: int
    stdout: str
    stderr: str

    @property
    def last_line(self) -> str:
        lines = self.stderr.strip().splitlines()
        return lines[-1] if lines else ""


def _interrupt_when(process: subprocess.Popen, lines_in: Path, lines: int, timeout_s: float, poll_s: float,
                    what: str) -> Interrupted:
    """SIGINT ``process`` once the file ``lines_in`` holds ``lines`` lines; kill it if anything goes wrong."""
    try:
        deadline = time.monotonic() + timeout_s
        while not (lines_in.is_file() and lines_in.read_text().count("\n") >= lines):
            if process.poll() is not None or time.monotonic() > deadline:
                out, err = process.communicate(timeout=60) if process.poll() is not None else ("", "")
                raise AssertionError(f"{what} (exit {process.poll()}): {err}")
            time.sleep(poll_s)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    return Interrupted(process.returncode, out, err)


def interrupt_while_working(command: str, argv: list[str], slow: str, tmp_path: Path, *, after_items: int = 1,
                            delay_s: float = 0.5, start_timeout_s: float = 120.0) -> Interrupted:
    """Start ``command`` (``"davis_rig.cli.label:main"``) with ``argv``, SIGINT it after its first slowed item.

    Args:
        command: ``module:function`` of the command's entry point (called with ``argv``, returns the exit code).
        argv: its arguments.
        slow: ``module:Owner.attribute`` of the per-item call to slow down (a function, method or generator).
        tmp_path: a folder for the marker file (``.working``).
        after_items: send SIGINT once this many items are done.
        delay_s: pause after each item, s.
        start_timeout_s: how long the command may take to finish ``after_items`` items.

    Returns:
        Exit code, stdout and stderr of the command.
    """
    marker = tmp_path / ".working"
    process = subprocess.Popen([sys.executable, "-c", _SLOWED_MAIN, slow, str(marker), str(delay_s), command, *argv],
                               cwd=REPO_ROOT, env=repo_env(OMP_NUM_THREADS="1"), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    return _interrupt_when(process, marker, after_items, start_timeout_s, 0.05, f"{command} never reached {slow}")


def interrupt_after_log_lines(argv: list[str], log: Path, *, lines: int = 2,
                              start_timeout_s: float = 240.0) -> Interrupted:
    """Run ``argv`` (a whole command line) unslowed, SIGINT it once ``log`` holds ``lines`` lines.

    For commands whose items are slow enough to catch as they are (an attack step, a search generation): the
    command runs exactly as a user runs it and is stopped between two logged items.

    Args:
        argv: the command line, e.g. ``[sys.executable, "-m", "davis_rig.cli.attack", "search", ...]``.
        log: the file the command appends one line to per item (``log.jsonl``).
        lines: send SIGINT once the log has this many lines.
        start_timeout_s: how long the command may take to log them, s.

    Returns:
        Exit code, stdout and stderr of the command.
    """
    process = subprocess.Popen(argv, env=repo_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return _interrupt_when(process, log, lines, start_timeout_s, 0.2, f"{argv[:5]} never logged {lines} lines")
