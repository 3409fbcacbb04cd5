"""Fixtures of the evaluation tests (their data come from :mod:`tests.helpers.eval_data`)."""

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)
