"""The shared option vocabulary, validators, exit codes and error messages of every command."""

from __future__ import annotations

import argparse
import pickle
import subprocess
import sys
import textwrap

import pytest

from davis_rig import __version__
from davis_rig.cli import common
from davis_rig.errors import (CheckpointError, ConfigError, DeviceNotFoundError, FormatError,
                              MissingDependencyError, SessionError)


def _parser(**kwargs) -> argparse.ArgumentParser:
    parser = common.new_parser("davis-demo", "A demo command.", "examples:\n  davis-demo x\n")
    common.add_quiet(parser)
    common.add_threads(parser)
    common.add_detector(parser, aliases=("--model", "--weights"))
    common.add_threshold(parser, aliases=("--thresholds", "--conf"), **kwargs)
    common.add_out(parser, help="where to write", aliases=("--report",))
    parser.add_argument("files", nargs="*")
    return parser


def test_help_lists_the_exit_codes_and_hides_the_old_spellings(capsys):
    assert common.run_main(_parser(), ["--help"], lambda args: 0) == 0
    text = capsys.readouterr().out
    assert "exit codes: 0 ok, 1 internal error, 2 usage" in text and "130 interrupted" in text
    assert "davis-demo x" in text  # the examples stay before the exit codes
    for hidden in ("--model", "--weights", "--thresholds", "--conf", "--report", "--no-progress"):
        assert hidden not in text
    for shown in ("--quiet", "--threads", "--detector", "--threshold", "--out", "--version"):
        assert shown in text


def test_version_names_the_command_and_the_package(capsys):
    assert common.run_main(_parser(), ["--version"], lambda args: 0) == 0
    assert capsys.readouterr().out.strip() == f"davis-demo (davis_rig {__version__})"


def test_threshold_takes_one_value_per_occurrence_comma_lists_and_aliases():
    parser = _parser(default=(0.25,))
    args = common.parse(parser, ["--threshold", "0.1,0.25", "a.h5", "--conf", "0.5", "--thresholds", "1", "b.h5"])
    assert args.threshold == (0.1, 0.25, 0.5, 1.0) and args.files == ["a.h5", "b.h5"]
    assert parser.parse_args(["a.h5"]).threshold == (0.25,)  # the default, untouched
    assert parser.parse_args(["--threshold", "0.5"]).threshold == (0.5,)  # the first use replaces the default
    assert parser.parse_args(["--conf", "0.5"]).threshold == (0.5,)  # an alias too
    assert _parser().parse_args([]).threshold is None


def test_aliases_fill_the_same_destination():
    args = _parser().parse_args(["--model", "m.onnx", "--report", "R", "--no-progress"])
    assert args.detector == "m.onnx" and args.out == "R" and args.quiet
    args = _parser().parse_args(["--weights", "w.ckpt", "-q", "--threads", "2"])
    assert args.detector == "w.ckpt" and args.quiet and args.threads == 2
    args = _parser().parse_args([])
    assert args.detector is None and args.out is None and not args.quiet and args.threads is None


@pytest.mark.parametrize("argv, option, why", [
    (["--threads", "0"], "--threads", "expected an integer >= 1, got '0'"),
    (["--threads", "-2"], "--threads", "expected an integer >= 1, got '-2'"),
    (["--threads", "two"], "--threads", "expected an integer, got 'two'"),
    (["--threshold", "1.5"], "--threshold", "expected a number in [0, 1], got '1.5'"),
    (["--threshold", "nan"], "--threshold", "expected a finite number, got 'nan'"),
    (["--conf", "-1"], "--conf", "expected a number in [0, 1], got '-1'"),
    (["--threshold", "0.1,,0.2"], "--threshold", "expected numbers in [0, 1] separated by commas"),
])
def test_a_bad_value_is_one_line_naming_the_option_and_exit_2(capsys, argv, option, why):
    assert common.run_main(_parser(), argv, lambda args: 0) == common.EXIT_USAGE
    err = capsys.readouterr().err
    assert f"davis-demo: error: argument {option}: {why}" in err
    assert "Traceback" not in err and err.count("error:") == 1 and err.strip().splitlines()[-1].startswith(
        "davis-demo: error: argument")  # argparse's usage, then the one error line


@pytest.mark.parametrize("text, value", [("0", 0.0), ("2.5", 2.5), ("1e3", 1000.0)])
def test_float_in_accepts_the_interval(text, value):
    assert common.float_in(0, None)(text) == value


@pytest.mark.parametrize("check, text", [
    (common.float_in(0, None, low_open=True), "0"), (common.float_in(0, 1, high_open=True), "1"),
    (common.non_negative_float, "-0.5"), (common.non_negative_float, "inf"), (common.positive_float, "nan"),
    (common.non_negative_int, "-1"), (common.positive_int, "1.5"),
])
def test_validators_refuse_out_of_range_and_non_finite(check, text):
    with pytest.raises(argparse.ArgumentTypeError):
        check(text)


def test_check_errors_use_argparse_format(capsys):
    def check(parser, args):
        if args.out and args.quiet:
            parser.error("argument --quiet: not allowed with --out")

    assert common.run_main(_parser(), ["--out", "x", "-q"], lambda args: 0, check=check) == common.EXIT_USAGE
    assert "davis-demo: error: argument --quiet: not allowed with --out" in capsys.readouterr().err


def test_require_names_the_option(capsys):
    parser = _parser()
    args = parser.parse_args([])
    with pytest.raises(SystemExit) as info:
        common.require(parser, args, "out", "--out")
    assert info.value.code == 2 and "the following arguments are required: --out" in capsys.readouterr().err


@pytest.mark.parametrize("exc, code", [
    (FormatError("x.h5: not a session"), common.EXIT_DATA),
    (CheckpointError("bad keys"), common.EXIT_DATA),
    (FileNotFoundError(2, "No such file or directory", "x.h5"), common.EXIT_DATA),
    (DeviceNotFoundError("no camera"), common.EXIT_DEVICE),
    (MissingDependencyError("pip install torch"), common.EXIT_MISSING_DEPENDENCY),
    (ConfigError("seq_len", "expected >= 1, got 0"), common.EXIT_USAGE),
    (KeyboardInterrupt(), common.EXIT_INTERRUPTED),
    # HDF5's own messages hold a line break (``file write failed: time = <ctime>\n, filename = ...``)
    (SessionError("/dev/full: cannot create the session file: [Errno 28] (file write failed: time = Fri Nov 27 "
                  "06:20:07 2026\n, filename = '/dev/full', errno = 28)"), common.EXIT_DATA),
])
def test_errors_become_one_line_and_their_exit_code(capsys, exc, code):
    def action():
        raise exc

    assert common.run_command("davis-demo", action) == code
    err = capsys.readouterr().err
    assert err.startswith("davis-demo: ") and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_a_config_error_names_the_option_that_set_the_field(capsys):
    def action():
        raise ConfigError("conf_threshold", "expected a number in [0, 1], got 1.5")

    assert common.run_command("davis-demo", action, {"conf_threshold": "--threshold"}) == common.EXIT_USAGE
    assert capsys.readouterr().err.strip() == ("davis-demo: error: argument --threshold: expected a number in "
                                               "[0, 1], got 1.5")
    assert common.run_command("davis-demo", action) == common.EXIT_USAGE  # unmapped: the field's name
    assert "conf_threshold: expected" in capsys.readouterr().err


def test_config_error_is_a_value_error_that_pickles():
    exc = pickle.loads(pickle.dumps(ConfigError("lr", "expected > 0, got nan")))
    assert isinstance(exc, ValueError) and exc.field == "lr" and str(exc) == "lr: expected > 0, got nan"


def test_a_failure_removes_only_the_empty_folders_it_created(tmp_path):
    kept = tmp_path / "run" / "old_empty"
    kept.mkdir(parents=True)
    with pytest.raises(FormatError), common.removing_new_empty_dirs(tmp_path / "run"):
        (tmp_path / "run" / "checkpoints" / "deep").mkdir(parents=True)
        (tmp_path / "run" / "logs").mkdir()
        (tmp_path / "run" / "logs" / "kept.txt").write_text("data")
        raise FormatError("no data")
    assert kept.is_dir() and (tmp_path / "run" / "logs" / "kept.txt").exists()
    assert not (tmp_path / "run" / "checkpoints").exists()
    with pytest.raises(KeyboardInterrupt), common.removing_new_empty_dirs(tmp_path / "new" / "report"):
        (tmp_path / "new" / "report" / "gifs").mkdir(parents=True)
        raise KeyboardInterrupt
    assert not (tmp_path / "new").exists()
    with common.removing_new_empty_dirs(tmp_path / "ok"):  # success: everything stays
        (tmp_path / "ok").mkdir()
    assert (tmp_path / "ok").is_dir()


def test_parse_keeps_subcommand_parsers_working():
    parser = common.new_parser("davis-demo", "Subcommands.")
    sub = parser.add_subparsers(dest="command", required=True)
    common.add_threshold(sub.add_parser("evaluate"), aliases=("--thresholds",))
    assert common.parse(parser, ["evaluate", "--thresholds", "0.1,0.2"]).threshold == (0.1, 0.2)


def test_file_system_errors_read_as_path_and_reason():
    import errno

    assert common.error_message(NotADirectoryError(errno.ENOTDIR, "Not a directory", "a.h5/out")) == \
        "a.h5/out: not a directory"
    assert common.error_message(FileNotFoundError("texture not found: t.npy")) == "texture not found: t.npy"
    from davis_rig.errors import FormatError

    assert common.error_message(FormatError("s.h5: not a session")) == "s.h5: not a session"


def test_a_library_warning_reads_as_one_command_line_without_source_code():
    code = textwrap.dedent("""
        import warnings
        from davis_rig.cli import common

        def action():
            warnings.warn("x.davisreplay: last replay record is incomplete and was skipped", RuntimeWarning)

        raise SystemExit(common.run_command("davis-demo", action))
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0
    assert run.stderr == "davis-demo: warning: x.davisreplay: last replay record is incomplete and was skipped\n"
