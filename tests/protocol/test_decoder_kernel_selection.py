"""Which decoder kernel a StreamDecoder uses: the parameter, then DAVIS_RIG_DECODER_KERNEL, then compiled if built."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ConfigError, MissingDependencyError
from davis_rig.protocol import StreamDecoder, decoder
from davis_rig.protocol.decoder import KERNEL_ENV


def test_selection_default_and_environment(monkeypatch, davis346):
    monkeypatch.delenv(KERNEL_ENV, raising=False)
    expected = "compiled" if decoder.compiled_kernel_available() else "numpy"
    assert StreamDecoder(davis346).kernel == expected
    monkeypatch.setenv(KERNEL_ENV, "numpy")
    assert StreamDecoder(davis346).kernel == "numpy"
    monkeypatch.setenv(KERNEL_ENV, "fortran")
    with pytest.raises(ConfigError, match=KERNEL_ENV):
        StreamDecoder(davis346)
    with pytest.raises(ConfigError, match="kernel: expected one of compiled, numpy"):
        StreamDecoder(davis346, kernel="fast")


def test_selection_without_the_compiled_kernel_falls_back(monkeypatch, davis346):
    monkeypatch.setattr(decoder, "_decode_kernel", None)
    monkeypatch.delenv(KERNEL_ENV, raising=False)
    assert not decoder.compiled_kernel_available()
    dec = StreamDecoder(davis346)
    assert dec.kernel == "numpy"
    assert len(dec.feed(np.array([0x8005, 0x1003, 0x2007], "<u2").tobytes()).events) == 1
    with pytest.raises(MissingDependencyError, match="pip install"):
        StreamDecoder(davis346, kernel="compiled")
