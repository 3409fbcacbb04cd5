"""Fixtures of the session tests; also registers the shared helper module ``session_data``.

``session_data`` is loaded by file path so ``from session_data import ...`` works under any pytest import mode
(prepend or importlib) without touching ``sys.path``.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

if "session_data" not in sys.modules:
    _spec = importlib.util.spec_from_file_location("session_data", Path(__file__).with_name("session_data.py"))
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["session_data"] = _module
    _spec.loader.exec_module(_module)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
