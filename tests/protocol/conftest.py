"""Shared fixtures for the protocol tests: the DAVIS346 test vectors and small stream helpers.

Helpers are exposed as fixtures (``proto``) rather than importable functions so the tests work under any pytest
import mode. Any test taking a ``vector`` argument is parametrised over every committed test vector. A module that
uses ``each_decoder_kernel`` (``pytestmark = pytest.mark.usefixtures("each_decoder_kernel")``) runs every test once
per decoder kernel: compiled and numpy.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import pytest

from davis_rig.protocol import DecodedChunk, SensorLayout, StreamDecoder
from davis_rig.protocol.decoder import KERNEL_ENV, KERNELS, compiled_kernel_available

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


#: Set (to anything) where a C compiler is present, e.g. in CI: the compiled decoder kernel must then be built.
REQUIRE_KERNEL_ENV = "DAVIS_RIG_REQUIRE_DECODER_KERNEL"


def require_compiled_kernel() -> None:
    """Skip (or fail, where :data:`REQUIRE_KERNEL_ENV` is set) when the compiled decoder kernel is not built."""
    if compiled_kernel_available():
        return
    message = "the compiled decoder kernel is not built (no C compiler at pip install)"
    if os.environ.get(REQUIRE_KERNEL_ENV):
        pytest.fail(f"{message}, but {REQUIRE_KERNEL_ENV} is set")
    pytest.skip(message)


@pytest.fixture(params=KERNELS)
def each_decoder_kernel(request, monkeypatch) -> str:
    """The decoder kernel every StreamDecoder of the test uses (through the environment variable)."""
    if request.param == "compiled":
        require_compiled_kernel()
    monkeypatch.setenv(KERNEL_ENV, request.param)
    return request.param


@pytest.fixture(scope="session")
def compiled_kernel() -> None:
    """Skip (or fail where required) a test that compares against the compiled kernel when it is not built."""
    require_compiled_kernel()


@pytest.fixture
def davis346() -> SensorLayout:
    return SensorLayout.davis346()
