"""Fixtures of the session tests (their data come from :mod:`tests.helpers.session_data`)."""

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
