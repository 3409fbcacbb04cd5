"""The command lines the docs show use commands, subcommands, tools and options that exist.

Every ``davis-*`` console script (``pyproject.toml``) and every ``python tools/X.py`` / ``python benchmarks/X.py`` in
the README, ``docs/``, ``recordings/``, ``firmware_notes/``, ``benchmarks/README.md`` and the assets' READMEs —
in fenced blocks (continuation lines joined, ``# comments`` cut) and in inline code spans — is checked against its
parser: each ``--option`` must be one the command (or its subcommand) accepts. The console scripts' parsers are
built in-process (``build_parser()``); a tool's options are read off its ``--help``.
"""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), ROOT / "recordings" / "README.md",
        *sorted((ROOT / "firmware_notes").glob("*.md")), ROOT / "benchmarks" / "README.md",
        *sorted((ROOT / "davis_rig" / "assets").rglob("*.md"))]
SCRIPTS = dict(re.findall(r'^(davis-[a-z-]+) = "davis_rig\.cli\.(\w+):main"',
                          (ROOT / "pyproject.toml").read_text(), re.M))
TOOL = re.compile(r"(tools|benchmarks)/\w+\.py$")
OPTION = re.compile(r"--?[A-Za-z][\w-]*")


def doc_command_lines(text: str) -> list[str]:
    """Shell lines of a markdown text: fenced-block lines (``\\`` continuations joined, ``  # comment`` cut) and
    inline code spans outside the fenced blocks, each split at ``&&``, ``||``, ``;`` and ``|``."""
    lines = []
    for block in re.findall(r"```[\w-]*\n(.*?)```", text, re.S):
        lines += [line.split(" #")[0] for line in block.replace("\\\n", " ").splitlines()]
    lines += re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
    return [part.strip() for line in lines for part in re.split(r"\s*(?:&&|\|\||;|\|)\s*", line) if part.strip()]


def command_of(line: str) -> tuple[str, list[str]] | None:
    """``(command, arguments)`` of a line that runs a console script or a tool; ``None`` for anything else."""
    tokens = line.split()
    if tokens and tokens[0] in SCRIPTS:
        return tokens[0], tokens[1:]
    if len(tokens) > 1 and tokens[0] == "python" and TOOL.match(tokens[1]):
        return tokens[1], tokens[2:]
    return None


def _parser_options(parser: argparse.ArgumentParser) -> tuple[frozenset, dict]:
    subcommands = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            subcommands.update({name: _parser_options(sub)[0] for name, sub in action.choices.items()})
    return frozenset(parser._option_string_actions), subcommands


@lru_cache(maxsize=None)
def accepted_options(command: str) -> tuple[frozenset, dict]:
    """``(options, {subcommand: its options})`` of a console script or tool."""
    if command in SCRIPTS:
        return _parser_options(importlib.import_module(f"davis_rig.cli.{SCRIPTS[command]}").build_parser())
    done = subprocess.run([sys.executable, str(ROOT / command), "--help"], capture_output=True, text=True, cwd=ROOT,
                          timeout=120)
    assert done.returncode == 0, f"{command} --help failed: {done.stderr[-500:]}"
    return frozenset(OPTION.findall(done.stdout)), {}


def unknown_options(command: str, arguments: list[str]) -> list[str]:
    """The ``-x`` / ``--name`` tokens of ``arguments`` that ``command`` (and its subcommand, if the first argument
    names one) does not accept; negative numbers are values, not options."""
    options, subcommands = accepted_options(command)
    if subcommands and arguments and arguments[0] in subcommands:
        options = options | subcommands[arguments[0]]
    found = [OPTION.match(a) for a in arguments if a.startswith("-") and not re.match(r"-\.?\d", a)]
    return [m.group(0) for m in found if m and m.group(0) not in options]


def documented_commands() -> list[tuple[str, str, str, list[str]]]:
    """``(doc file, line, command, arguments)`` of every command line in the docs."""
    out = []
    for doc in DOCS:
        for line in doc_command_lines(doc.read_text(encoding="utf-8")):
            if (parsed := command_of(line)) is not None:
                out.append((str(doc.relative_to(ROOT)), line, *parsed))
    return out


def test_doc_command_lines_are_found():
    text = ("Run `davis-eval s.h5 --threshold 0.25`.\n\n```bash\ndavis-record --out s.h5 \\\n  --seconds 5  # a comment "
            "with `davis-eval --bogus`\npython tools/aps_attack.py --out x && davis-info s.h5 --json\nls -la\n```\n")
    lines = doc_command_lines(text)
    assert [command_of(line) for line in lines if command_of(line)] == [
        ("davis-record", ["--out", "s.h5", "--seconds", "5"]), ("tools/aps_attack.py", ["--out", "x"]),
        ("davis-info", ["s.h5", "--json"]), ("davis-eval", ["s.h5", "--threshold", "0.25"])]


def test_unknown_options_are_reported():
    """The check can fail: a stale option, one of another subcommand, a typo."""
    assert unknown_options("davis-eval", ["s.h5", "--threshold", "0.25", "--thresh-old", "-1", "-0.5"]) == ["--thresh-old"]
    assert unknown_options("davis-attack", ["optimize", "--out", "o", "--detector-step", "eager"]) == []
    assert unknown_options("davis-attack", ["export", "--detector-step", "eager"]) == ["--detector-step"]


def test_the_docs_show_commands():
    commands = {command for _, _, command, _ in documented_commands()}
    assert {"davis-record", "davis-eval", "davis-view", "davis-attack"} <= commands
    assert any(TOOL.match(c) for c in commands)


@pytest.mark.parametrize("doc", sorted({str(d.relative_to(ROOT)) for d in DOCS}))
def test_documented_options_exist(doc):
    for _, line, command, arguments in (c for c in documented_commands() if c[0] == doc):
        if TOOL.match(command):
            assert (ROOT / command).is_file(), f"{doc}: `{line}`: no such file {command}"
        bad = unknown_options(command, arguments)
        assert not bad, f"{doc}: `{line}`: {command} has no option {', '.join(bad)}"


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_help_examples_use_existing_options(script):
    """The examples in each command's ``--help`` epilog (and its subcommands') use options that exist."""
    parser = importlib.import_module(f"davis_rig.cli.{SCRIPTS[script]}").build_parser()
    epilogs = [parser.epilog or ""] + [sub.epilog or "" for action in parser._actions
                                       if isinstance(action, argparse._SubParsersAction)
                                       for sub in action.choices.values()]
    examples = [command_of(line.split(" #")[0].strip()) for text in epilogs for line in text.splitlines()]
    examples = [e for e in examples if e is not None]
    assert examples, f"{script} --help shows no example"
    for command, arguments in examples:
        bad = unknown_options(command, arguments)
        assert not bad, f"{script} --help example `{command} {' '.join(arguments)}`: no option {', '.join(bad)}"
