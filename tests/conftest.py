"""Fixtures and helper modules shared by every test folder.

``one_torch_thread``: a module opts in with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``.
Torch is imported only when a test uses it. ``fresh_python``: run a snippet in a new interpreter (import checks).

Helper modules registered here by file path (``from camera_reads import ...`` works under any import mode):
``camera_reads`` (read a camera over the virtual DAVIS346 until drained).
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

if "camera_reads" not in sys.modules:
    _spec = importlib.util.spec_from_file_location("camera_reads", Path(__file__).with_name("camera_reads.py"))
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["camera_reads"] = _module
    _spec.loader.exec_module(_module)


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run the module's tests on one torch intra-op thread, then restore the previous count.

    Multi-threaded CPU reductions are not bit-reproducible run to run (exact-resume checks need one thread), and
    on a shared 2-core machine oversubscribed threads make rendering ~20x slower.
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
