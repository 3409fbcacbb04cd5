"""Fixtures shared by every test folder.

``one_torch_thread``: a module opts in with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``.
Torch is imported only when a test uses it. ``fresh_python``: run a snippet in a new interpreter (import checks).
``load_tool``: import a script of ``tools/`` as a module.

Helper modules shared by tests live in the package :mod:`tests.helpers` and are imported like any module
(``from tests.helpers.eval_data import person_yolo``): ``tests`` is a regular package and pytest puts the
repository root on ``sys.path`` (``pythonpath = ["."]`` in pyproject.toml).
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run the module's tests on one torch intra-op thread, then restore the previous count.

    Float sums split over threads depend on the thread count, so seeds re-picked for a test (and the expected
    values of exact-resume checks) hold on one known count; and on a shared 2-core machine oversubscribed threads
    make rendering ~20x slower.
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _run_fresh_python(code: str) -> str:
    """Run ``code`` with ``python -c`` in a new interpreter (nothing imported yet) at the repository root.

    Returns:
        Its standard output, stripped.

    Raises:
        AssertionError: the interpreter exited with a non-zero status (the message is its standard error).
    """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO_ROOT)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.fixture(scope="session")
def fresh_python():
    """``fresh_python(code) -> stdout``: for checks of what an import pulls in (see :func:`_run_fresh_python`)."""
    return _run_fresh_python


def _load_tool(name: str):
    """Import ``tools/<name>.py`` (a script, not a package) afresh as module ``<name>_tool``.

    The module is entered in ``sys.modules`` before it runs: dataclasses resolve annotations through it.
    """
    spec = importlib.util.spec_from_file_location(f"{name}_tool", REPO_ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def load_tool():
    """``load_tool(name) -> module``: a fresh import of ``tools/<name>.py`` (see :func:`_load_tool`)."""
    return _load_tool


def pytest_addoption(parser):
    parser.addoption("--cli-table", default=None, metavar="FILE",
                     help="write the command x bad input table that tests/cli/test_bad_input_table.py observed "
                          "(markdown) to FILE")
