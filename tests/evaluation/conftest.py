"""Fixtures of the evaluation tests (the helper module ``eval_data`` is found through ``tests/conftest.py``)."""

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)
