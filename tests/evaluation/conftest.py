"""Fixtures of the evaluation tests; registers the helper module ``eval_data`` (by file path, any import mode).

``eval_data`` is shared with ``tests/labelers`` and ``tests/cli/test_label.py`` / ``test_eval.py``, which load it
the same way through :func:`load_eval_data`.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest


def load_eval_data():
    """Import ``tests/evaluation/eval_data.py`` as module ``eval_data`` (once)."""
    if "eval_data" not in sys.modules:
        spec = importlib.util.spec_from_file_location("eval_data", Path(__file__).with_name("eval_data.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules["eval_data"] = module
        spec.loader.exec_module(module)
    return sys.modules["eval_data"]


load_eval_data()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)
