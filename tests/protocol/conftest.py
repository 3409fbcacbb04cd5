"""Shared fixtures for the protocol tests: the DAVIS346 test vectors and small stream helpers.

Helpers are exposed as fixtures (``proto``) rather than importable functions so the tests work under any pytest
import mode. Any test taking a ``vector`` argument is parametrised over every committed test vector.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from davis_rig.protocol import DecodedChunk, SensorLayout, StreamDecoder

from tests.helpers.davis346_vectors import VECTOR_IDS, VECTORS, events_as_lists, vector_layout, vector_transfers


def pytest_generate_tests(metafunc):
    if "vector" in metafunc.fixturenames:
        metafunc.parametrize("vector", VECTORS, ids=VECTOR_IDS)


def _decode_all(layout: SensorLayout, transfers, **kwargs) -> tuple[DecodedChunk, StreamDecoder]:
    decoder = StreamDecoder(layout, **kwargs)
    chunk = DecodedChunk.concatenate([decoder.feed(t) for t in transfers])
    return chunk, decoder


def _words(*values: int) -> bytes:
    return np.array(values, dtype="<u2").tobytes()


@pytest.fixture(scope="session")
def vectors() -> list[dict]:
    """Every vector of the committed copy of the shared DAVIS346 test vectors."""
    return VECTORS


@pytest.fixture(scope="session")
def proto() -> SimpleNamespace:
    """Helpers: ``layout(vector)``, ``transfers(vector)``, ``decode_all(layout, transfers, **kw)``,
    ``events_as_lists(events)``, ``words(*w) -> bytes``."""
    return SimpleNamespace(
        layout=vector_layout,
        transfers=vector_transfers,
        decode_all=_decode_all,
        events_as_lists=events_as_lists,
        words=_words,
    )


@pytest.fixture
def davis346() -> SensorLayout:
    return SensorLayout.davis346()
