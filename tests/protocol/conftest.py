"""Shared fixtures for the protocol tests: the DAVIS346 test vectors and small stream helpers.

Helpers are exposed as fixtures (``proto``) rather than importable functions so the tests work under any pytest
import mode. Any test taking a ``vector`` argument is parametrised over every committed test vector.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from davis_rig.protocol import DecodedChunk, SensorLayout, StreamDecoder

VECTORS_PATH = Path(__file__).resolve().parents[1] / "fixtures" / "davis346_test_vectors.json"
_VECTORS = json.loads(VECTORS_PATH.read_text())["vectors"]


def pytest_generate_tests(metafunc):
    if "vector" in metafunc.fixturenames:
        metafunc.parametrize("vector", _VECTORS, ids=[v["id"] for v in _VECTORS])


def _vector_layout(vector: dict) -> SensorLayout:
    return SensorLayout.from_mapping(vector["device_info"])


def _vector_transfers(vector: dict) -> list[bytes]:
    return [bytes.fromhex(t) for t in vector["transfers_hex"]]


def _decode_all(layout: SensorLayout, transfers, **kwargs) -> tuple[DecodedChunk, StreamDecoder]:
    decoder = StreamDecoder(layout, **kwargs)
    chunk = DecodedChunk.concatenate([decoder.feed(t) for t in transfers])
    return chunk, decoder


def _events_as_lists(events: np.ndarray) -> list[list[int]]:
    return [[int(e["t"]), int(e["x"]), int(e["y"]), int(e["p"])] for e in events]


def _words(*values: int) -> bytes:
    return np.array(values, dtype="<u2").tobytes()


@pytest.fixture(scope="session")
def vectors() -> list[dict]:
    """Every vector of the committed copy of the shared DAVIS346 test vectors."""
    return _VECTORS


@pytest.fixture(scope="session")
def proto() -> SimpleNamespace:
    """Helpers: ``layout(vector)``, ``transfers(vector)``, ``decode_all(layout, transfers, **kw)``,
    ``events_as_lists(events)``, ``words(*w) -> bytes``."""
    return SimpleNamespace(
        layout=_vector_layout,
        transfers=_vector_transfers,
        decode_all=_decode_all,
        events_as_lists=_events_as_lists,
        words=_words,
    )


@pytest.fixture
def davis346() -> SensorLayout:
    return SensorLayout.davis346()
