"""What every command shares: the option vocabulary, argument validators, exit codes and error messages.

One vocabulary for every ``davis-*`` command and ``tools/*.py`` script:

* ``--quiet`` / ``-q`` (no progress output; ``--no-progress`` is a hidden alias), ``--threads N`` (N ≥ 1),
  ``--detector PATH`` (the RVT detector), ``--threshold T`` (one value per occurrence, repeatable, comma lists),
  ``--out PATH``, ``--version``: added by :func:`add_quiet`, :func:`add_threads`, :func:`add_detector`,
  :func:`add_threshold`, :func:`add_out` and :func:`new_parser`;
* every bad value exits 2 with one line ``<command>: error: argument --opt: <why>`` (argparse's own format): the
  ``type=`` validators below (:func:`positive_int`, :func:`non_negative_int`, :func:`finite_float`,
  :func:`float_in`, :data:`probability`, :func:`threshold_list`) and :class:`~davis_rig.errors.ConfigError`
  raised by the library, which :func:`run_command` maps onto the option that set the field;
* the exit codes (:data:`EXIT_CODES_TEXT`, in every help epilog): 0 ok, 1 internal error, 2 usage, 3 camera/USB,
  4 file or model, 5 missing optional dependency, 130 interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

from davis_rig import __version__

#: Exit codes of every davis_rig command.
EXIT_OK = 0
EXIT_ERROR = 1  # internal error (a bug, or any other DavisRigError)
EXIT_USAGE = 2  # argparse's own code: a bad option value, conflicting options
EXIT_DEVICE = 3  # camera missing, busy, no permission, unsupported firmware, transfer failure
EXIT_DATA = 4  # a file or model is missing, malformed or cannot be written (session.h5, replay, checkpoint, ONNX)
EXIT_MISSING_DEPENDENCY = 5  # an optional extra is not installed
EXIT_INTERRUPTED = 130  # Ctrl-C (SIGINT) outside a clean stop
EXIT_BROKEN_PIPE = 141  # the output pipe was closed by its reader (128 + SIGPIPE, as a shell reports it)

#: The exit-code paragraph at the end of every command's ``--help``.
EXIT_CODES_TEXT = (
    "exit codes: 0 ok, 1 internal error, 2 usage (bad option value, conflicting options), 3 camera/USB,\n"
    "  4 file or model (missing, malformed, unwritable), 5 missing optional dependency, 130 interrupted."
)


# --- parsers ----------------------------------------------------------------------------------
def epilog(examples: str = "") -> str:
    """A help epilog: ``examples`` (already formatted, may be empty) followed by :data:`EXIT_CODES_TEXT`."""
    examples = examples.rstrip("\n")
    return f"{examples}\n\n{EXIT_CODES_TEXT}\n" if examples else f"{EXIT_CODES_TEXT}\n"


def version_text(prog: str) -> str:
    """What ``--version`` prints: ``<prog> (davis_rig <version>)``."""
    return f"{prog} (davis_rig {__version__})"


def tool_provenance(script: str, argv: Sequence[str] | None = None) -> dict:
    """Where a report of ``tools/<script>`` came from: ``command`` (the arguments its ``main`` was given, ``argv``,
    as :func:`run_main` keeps them in ``args.argv``; ``None``: the process's), ``measured`` (today, YYYY-MM-DD)
    and ``machine`` (architecture and host name)."""
    import platform
    import shlex
    import time

    argv = sys.argv[1:] if argv is None else argv
    return {"command": shlex.join(["python", f"tools/{script}", *argv]),
            "measured": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {platform.node()}"}


def new_parser(prog: str, description: str, examples: str = "") -> argparse.ArgumentParser:
    """An argument parser with the house layout: raw-text epilog ending in the exit codes, and ``--version``.

    Args:
        prog: the command name (``davis-eval``, ``tools/ship_detector.py``).
        description: one sentence shown under the usage line.
        examples: the ``examples:`` block (and any notes) of the epilog, already line-broken.
    """
    parser = argparse.ArgumentParser(prog=prog, description=description, epilog=epilog(examples),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=version_text(prog),
                        help="print the command and davis_rig version and exit")
    return parser


def add_hidden_alias(parser, *option_strings: str, dest: str, **kwargs) -> None:
    """Keep old option spellings working without showing them in ``--help`` (default: the visible option's).

    Each spelling is its own hidden option, so an error message names the spelling that was typed.
    """
    for option in option_strings:
        parser.add_argument(option, dest=dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kwargs)


def add_quiet(parser, help: str = "no progress output on stderr") -> None:
    """``--quiet`` / ``-q`` (``args.quiet``), with ``--no-progress`` as a hidden alias."""
    parser.add_argument("--quiet", "-q", action="store_true", help=help)
    add_hidden_alias(parser, "--no-progress", dest="quiet", action="store_true")


def add_threads(parser, help: str = "CPU threads for the computation (default: the library's choice)") -> None:
    """``--threads N`` (``args.threads``, an int ≥ 1, or ``None`` when not given)."""
    parser.add_argument("--threads", type=positive_int, default=None, metavar="N", help=help)


def add_detector(parser, *, aliases: Sequence[str] = (), metavar: str = "PATH",
                 help: str = "RVT detector weights (.safetensors, .ckpt, .pt); default: the bundled detector") -> None:
    """``--detector PATH`` (``args.detector``, ``None`` = the bundled detector); ``aliases`` stay hidden."""
    parser.add_argument("--detector", default=None, metavar=metavar, help=help)
    add_hidden_alias(parser, *aliases, dest="detector", metavar=metavar)


def add_trigger(parser) -> None:
    """The trigger of a planted blind spot: ``--trigger NPY`` (``args.trigger``) or ``--trigger-white-parts PART ...``
    (``args.trigger_white_parts``), mutually exclusive; neither: drawn with ``--seed``
    (:func:`davis_rig.controls.planted.trigger_grid`)."""
    from davis_rig.scene.body import PART_NAMES

    group = parser.add_mutually_exclusive_group()
    group.add_argument("--trigger", default=None, metavar="NPY",
                       help="the trigger grid [n, n], .npy or image (default: drawn with --seed, each cell white "
                            "with probability 1/2)")
    group.add_argument("--trigger-white-parts", nargs="+", choices=PART_NAMES, default=None, metavar="PART",
                       help="a trigger that paints whole parts: cells mostly on these parts white, the rest black "
                            "(e.g. torso arms: upper body white, legs black)")


def add_int8(parser) -> None:
    """``--int8`` (``args.int8``): the bundled detector's int8 step graph instead of the fp32 one."""
    parser.add_argument("--int8", action="store_true",
                        help="score with the bundled detector's int8 graph (about 1.5-1.7x less CPU with 8-bit dot "
                             "products such as AVX-512 VNNI, 1.1x on AVX2 alone; scores close to fp32's; your own: "
                             "davis-quantize, then --detector)")


def check_int8(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse ``--int8`` beside ``--detector`` (exit 2): it names the bundled graph."""
    if getattr(args, "int8", False) and args.detector is not None:
        parser.error("argument --int8: not allowed with argument --detector (pass an int8 graph made by "
                     "davis-quantize as --detector)")


def detector_onnx(args: argparse.Namespace) -> Path:
    """The RVT step ONNX a command scores with: ``--detector``, else the bundled graph (``--int8``: its int8 one).

    Raises:
        MissingDependencyError: the bundled graph is not installed.
    """
    from davis_rig.models import default_detector_path

    if args.detector is not None:
        return Path(args.detector)
    return default_detector_path(int8=bool(getattr(args, "int8", False)))


def add_out(parser, *, metavar: str = "PATH", help: str, aliases: Sequence[str] = (), required: bool = False,
            default=None, type=None) -> None:
    """``--out PATH`` (``args.out``); old spellings in ``aliases`` stay accepted but hidden.

    ``required`` is checked by :func:`require` after parsing when aliases exist (argparse cannot know that a
    hidden alias filled the destination).
    """
    kwargs = {} if type is None else {"type": type}
    parser.add_argument("--out", default=default, metavar=metavar, help=help,
                        required=required and not aliases, **kwargs)
    add_hidden_alias(parser, *aliases, dest="out", metavar=metavar, **kwargs)


class _DefaultThresholds(tuple):
    """The default of ``--threshold``: a tuple the first given value replaces instead of extending."""


class _ExtendThresholds(argparse.Action):
    """Appends the values of each occurrence (``--threshold`` and its aliases) to one tuple."""

    def __call__(self, parser, namespace, values, option_string=None):
        current = getattr(namespace, self.dest, None)
        items = [] if current is None or isinstance(current, _DefaultThresholds) else list(current)
        setattr(namespace, self.dest, tuple(items + list(values)))


def add_threshold(parser, *, default: Sequence[float] | None = None, aliases: Sequence[str] = (),
                  help: str = "detector confidence threshold") -> None:
    """``--threshold T`` (``args.threshold``: a tuple of floats in [0, 1], or ``default``).

    One value per occurrence (it never takes a positional argument), repeatable, comma lists accepted:
    ``--threshold 0.1,0.25 --threshold 0.5`` gives ``(0.1, 0.25, 0.5)``. ``aliases`` (``--thresholds``,
    ``--conf``) are hidden and extend the same list.
    """
    default = None if default is None else _DefaultThresholds(float(t) for t in default)
    shown = "" if default is None else f" (default: {' '.join(f'{t:g}' for t in default)})"
    parser.add_argument("--threshold", type=threshold_list, action=_ExtendThresholds, default=default,
                        metavar="T", help=f"{help}; repeat it or give a comma list for several{shown}")
    add_hidden_alias(parser, *aliases, dest="threshold", type=threshold_list, action=_ExtendThresholds)


def require(parser: argparse.ArgumentParser, args: argparse.Namespace, dest: str, option: str) -> None:
    """Exit 2 (argparse's message) when the option ``option`` that fills ``args.<dest>`` was not given."""
    if getattr(args, dest, None) is None:
        parser.error(f"the following arguments are required: {option}")


# --- type= validators ---------------------------------------------------------------------------
def _number(text: str, kind: type) -> float | int:
    try:
        return kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                         f"got {text!r}") from None


def positive_int(text: str) -> int:
    """An integer ≥ 1 (``type=`` validator)."""
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An integer ≥ 0 (``type=`` validator)."""
    value = _number(text, int)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value


def int_in(low: int, high: int) -> Callable[[str], int]:
    """A ``type=`` validator for an integer in ``[low, high]``; the message names the interval."""

    def check(text: str) -> int:
        value = _number(text, int)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an integer in [{low}, {high}], got {text!r}")
        return value

    check.__name__ = f"integer in [{low}, {high}]"
    return check


def finite_float(text: str) -> float:
    """A finite float: no NaN, no ±inf (``type=`` validator)."""
    value = _number(text, float)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def float_in(low: float | None = None, high: float | None = None, *, low_open: bool = False,
             high_open: bool = False) -> Callable[[str], float]:
    """A ``type=`` validator for a finite float in an interval (``None`` = unbounded on that side).

    Example: ``float_in(0, None, low_open=True)`` accepts ``(0, ∞)``; the message names the interval.
    """
    lo = "(-inf" if low is None else f"{'(' if low_open else '['}{low:g}"
    hi = "inf)" if high is None else f"{high:g}{')' if high_open else ']'}"
    interval = f"{lo}, {hi}"

    def check(text: str) -> float:
        value = finite_float(text)
        if low is not None and (value < low or (low_open and value == low)) or \
                high is not None and (value > high or (high_open and value == high)):
            raise argparse.ArgumentTypeError(f"expected a number in {interval}, got {text!r}")
        return value

    check.__name__ = f"number in {interval}"
    return check


#: A probability / confidence in [0, 1] (``type=`` validator).
probability = float_in(0.0, 1.0)
#: A finite float ≥ 0 (``type=`` validator): durations, tolerances, sizes.
non_negative_float = float_in(0.0)
#: A finite float > 0 (``type=`` validator).
positive_float = float_in(0.0, low_open=True)


# --- the attack's vocabulary, shared by davis-attack and the tools that render or train on the attack's scenes
#: Body parts of ``--parts`` (:data:`davis_rig.scene.body.PART_NAMES`) and ``all`` (the whole body, no mask).
PART_CHOICES = ("torso", "arms", "legs", "head", "hands", "feet", "all")
#: Named camera scales of ``--scales`` (:data:`davis_rig.scene.camera.TEST_SCALES_PX`).
SCALE_NAMES = ("large", "middle", "small")


def name_and_path(text: str) -> tuple[str, str]:
    """``NAME=PATH`` (e.g. ``--texture ours=grid.npy``): the name and the path, both non-empty."""
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=PATH, got {text!r}")
    return name, path


def device_name(text: str) -> str:
    """``--device`` (``type=`` validator, also of tools/): ``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (availability is
    checked when the command runs, by :func:`resolve_device`)."""
    kind, _, index = text.partition(":")
    if text == "auto" or (kind in ("cpu", "cuda") and (not index or (kind == "cuda" and index.isdigit()))):
        return text
    raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda or cuda:N, got {text!r}")


def camera_scale(text: str) -> str | float:
    """``--scales`` (``type=`` validator, also of tools/): a scale name or a person height in px (> 0)."""
    if text in SCALE_NAMES:
        return text
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected {', '.join(SCALE_NAMES)} or a height in px > 0, "
                                         f"got {text!r}") from None


def resolve_device(name: str):
    """The torch device of ``--device``; a device that is not there is a usage error naming the option."""
    import torch

    from davis_rig.errors import ConfigError

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device", f"{name!r}: CUDA is not available on this machine")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError("device", f"{name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


def threshold_list(text: str) -> list[float]:
    """A comma-separated list of confidences in [0, 1] (``type=`` validator of ``--threshold``)."""
    items = [item.strip() for item in text.split(",")]
    if not text.strip() or any(not item for item in items):
        raise argparse.ArgumentTypeError(f"expected numbers in [0, 1] separated by commas, got {text!r}")
    return [probability(item) for item in items]


# --- running ----------------------------------------------------------------------------------
def exit_code_for(exc: BaseException) -> int:
    """Map an exception onto the command's exit code (see the ``EXIT_*`` constants)."""
    from davis_rig.errors import ConfigError, DeviceError, FormatError, MissingDependencyError

    if isinstance(exc, MissingDependencyError):
        return EXIT_MISSING_DEPENDENCY
    if isinstance(exc, DeviceError):
        return EXIT_DEVICE
    if isinstance(exc, (FormatError, OSError)):
        return EXIT_DATA
    if isinstance(exc, ConfigError):
        return EXIT_USAGE
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    return EXIT_ERROR


def error_message(exc: BaseException, options: Mapping[str, str] | None = None) -> str:
    """The text after ``<command>: error: `` for a toolkit error (a ``ConfigError`` names its option)."""
    from davis_rig.errors import ConfigError, DavisRigError

    if isinstance(exc, ConfigError) and options and exc.field in options:
        return f"argument {options[exc.field]}: {exc.reason}"
    if isinstance(exc, OSError) and not isinstance(exc, DavisRigError) and exc.strerror and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror.lower()}"  # "out/x: not a directory", not "[Errno 20] Not a ..."
    return str(exc)


def run_command(name: str, action: Callable[[], int | None], options: Mapping[str, str] | None = None) -> int:
    """Run one command's action; print one ``<name>: error: ...`` line on stderr for the toolkit's errors.

    Args:
        name: the command name shown in messages (``davis-record``).
        action: runs the command and returns its exit code (``None`` = 0).
        options: library field name -> the option that sets it, to name the option of a
            :class:`~davis_rig.errors.ConfigError` (``{"conf_threshold": "--threshold"}``).

    Returns:
        The exit code. Errors that are not ``DavisRigError``, ``OSError`` or ``KeyboardInterrupt`` (bugs)
        propagate with their traceback (exit 1). Warnings the library issues meanwhile read as one
        ``<name>: warning: ...`` line (no source file, line or code).
    """
    import warnings

    previous_format = warnings.formatwarning
    warnings.formatwarning = lambda message, *args, **kwargs: f"{name}: warning: {' '.join(str(message).split())}\n"
    try:
        return _run_action(name, action, options)
    finally:
        warnings.formatwarning = previous_format


def _run_action(name: str, action: Callable[[], int | None], options: Mapping[str, str] | None) -> int:
    """:func:`run_command` without the warning format."""
    from davis_rig.errors import DavisRigError

    try:
        code = action()
    except BrokenPipeError:  # the reader went away (`davis-info s.h5 | head`): stop quietly, as Unix tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so that the interpreter's final flush does not fail again
        return EXIT_BROKEN_PIPE
    except (DavisRigError, OSError) as exc:  # OSError: e.g. the output folder cannot be created
        message = " ".join(error_message(exc, options).split())  # one line, whatever a library's text holds
        print(f"{name}: error: {message}", file=sys.stderr)
        return exit_code_for(exc)
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK if code is None else int(code)


def parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Parse with options and positional arguments in any order (``a.h5 --threshold 0.25 b.h5``).

    Parsers with subcommands are parsed the standard way (argparse cannot intermix them).
    """
    if parser._subparsers is not None:  # argparse's own marker of add_subparsers()
        return parser.parse_args(argv)
    return parser.parse_intermixed_args(argv)


def run_main(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
             action: Callable[[argparse.Namespace], int | None], *,
             check: Callable[[argparse.ArgumentParser, argparse.Namespace], None] | None = None,
             options: Mapping[str, str] | None = None) -> int:
    """A command's ``main``: parse, check the options together, run; every outcome is a returned exit code.

    Args:
        parser: the command's parser (its ``prog`` names the command in messages).
        argv: the arguments (``None`` = ``sys.argv[1:]``).
        action: runs the command on the parsed arguments.
        check: cross-option rules; calls ``parser.error(...)`` (exit 2) on a conflict.
        options: see :func:`run_command`.

    Returns:
        The exit code: argparse's 0 (``--help``, ``--version``) or 2 (bad arguments) included.
    """
    try:
        args = parse(parser, argv)
        if check is not None:
            check(parser, args)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{parser.prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    args.argv = sys.argv[1:] if argv is None else list(argv)  # the command a report records, as it was given
    return run_command(parser.prog, lambda: action(args), options)


def check_out_folder(path: str | Path) -> None:
    """Refuse, before any work, an ``--out`` folder that cannot be created or written: it, or a folder above it,
    is a file, or the nearest existing folder is not writable.

    Raises:
        FormatError: the message names ``path`` and the file or folder in the way.
    """
    from davis_rig.errors import FormatError

    path = Path(path)
    for existing in (path, *path.parents):
        if existing.exists():
            if not existing.is_dir():
                raise FormatError(f"{path}: --out needs a folder, and {existing} is a file")
            if not os.access(existing, os.W_OK | os.X_OK):
                raise FormatError(f"{path}: --out cannot be created: {existing} is not writable")
            return


@contextlib.contextmanager
def removing_new_empty_dirs(path: str | Path) -> Iterator[None]:
    """On failure (any exception, Ctrl-C included), remove the empty folders at and under ``path`` that the
    command created: a failed command leaves no empty output folder behind. Files are never deleted.
    """
    path = Path(path)
    missing = [p for p in (path, *path.parents) if not p.exists()]  # what the command may create, deepest first
    before = set() if missing else {p for p in path.rglob("*") if p.is_dir()}
    try:
        yield
    except BaseException:
        if path.is_dir():
            created = [p for p in path.rglob("*") if p.is_dir() and p not in before]
            for folder in sorted(created, key=lambda p: len(p.parts), reverse=True):
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only succeeds when empty
        for folder in missing:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
