"""The installed package: every module imports with the declared dependencies, every command answers --help/--version.

Run in CI's fresh virtual environment (``.ci/run``, installed exactly as the README says), this catches an import
of a package that pyproject.toml does not declare and a console script that fails before doing anything.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import pkgutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

import davis_rig
from davis_rig.cli.common import EXIT_CODES_TEXT

REPO = Path(__file__).resolve().parents[1]

#: Top-level import names that only an optional extra of pyproject.toml installs -> that extra.
OPTIONAL_IMPORTS = {"torch": "torch", "dv_processing": "aedat4", "matplotlib": "report",
                    "PIL": "report", "reportlab": "export", "smplx": "smpl"}

MODULES = sorted(info.name for info in pkgutil.walk_packages(davis_rig.__path__, prefix="davis_rig."))


def _console_scripts() -> dict[str, str]:
    """``name -> "module:function"`` of the installed davis_rig console scripts (its entry points)."""
    scripts = {ep.name: ep.value for ep in importlib.metadata.entry_points(group="console_scripts")
               if ep.value.startswith("davis_rig.")}
    return dict(sorted(scripts.items()))


SCRIPTS = _console_scripts()
TOOLS = sorted(p.name for p in (REPO / "tools").glob("*.py"))


def _env() -> dict[str, str]:
    """The subprocess environment: this checkout first on the import path (the tests' view of the package)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


def test_the_package_has_modules_and_commands():
    assert len(MODULES) > 50 and "davis_rig.cli.common" in MODULES
    assert {"davis-record", "davis-label", "davis-eval", "davis-eval-dataset", "davis-train", "davis-make-dataset",
            "davis-attack"} <= set(SCRIPTS), "davis_rig is not installed (pip install -e .), or a script is missing"


@pytest.mark.parametrize("name", MODULES)
def test_every_module_imports(name):
    try:
        importlib.import_module(name)
    except ModuleNotFoundError as exc:
        top = (exc.name or "").split(".")[0]
        if top in OPTIONAL_IMPORTS:
            pytest.skip(f"{name} needs the '{OPTIONAL_IMPORTS[top]}' extra ({top} is not installed)")
        raise AssertionError(f"{name} imports {exc.name!r}, which pyproject.toml does not declare") from exc


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, env=_env(), cwd=REPO, timeout=300,
                          stdin=subprocess.DEVNULL)


def _script(name: str) -> list[str]:
    """The installed executable of console script ``name`` (beside this interpreter, as pip installs it)."""
    path = Path(sys.executable).parent / name
    assert path.exists(), f"{name}: the entry point is declared but {path} is not installed"
    return [str(path)]


def _commands() -> list[tuple[str, list[str]]]:
    commands = [(name, _script(name)) for name in SCRIPTS]
    commands += [(tool, [sys.executable, str(REPO / "tools" / tool)]) for tool in TOOLS]
    return commands


def test_every_command_answers_help_and_version():
    """Each console script and tools/*.py: ``--help`` (with the exit codes) and ``--version``, exit 0."""
    commands = _commands()
    jobs = [(label, flag, argv + [flag]) for label, argv in commands for flag in ("--help", "--version")]
    with ThreadPoolExecutor(max_workers=4) as pool:
        done = list(pool.map(lambda job: (job[0], job[1], _run(job[2])), jobs))
    failures = []
    for label, flag, result in done:
        if result.returncode != 0 or "Traceback" in result.stderr:
            failures.append(f"{label} {flag}: exit {result.returncode}\n{result.stderr[-2000:]}")
        elif flag == "--help" and EXIT_CODES_TEXT.splitlines()[0] not in result.stdout:
            failures.append(f"{label} --help: no exit-code paragraph")
        elif flag == "--version" and result.stdout.strip() != f"{label} (davis_rig {davis_rig.__version__})":
            failures.append(f"{label} --version: printed {result.stdout.strip()!r}")
    assert not failures, "\n".join(failures)
