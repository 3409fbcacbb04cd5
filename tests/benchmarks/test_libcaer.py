"""``benchmarks/_libcaer.py``: building libcaer's translator from a checkout (given as ``LIBCAER_SRC``) and its checks.

The build test needs a libcaer source checkout, which this repository does not ship: it runs where ``LIBCAER_SRC``
names one and is skipped otherwise.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from davis_rig.protocol import SensorLayout, StreamDecoder

BENCHMARKS_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def libcaer():
    spec = importlib.util.spec_from_file_location("benchmarks_libcaer", BENCHMARKS_DIR / "_libcaer.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # NamedTuple classes look their module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]


def test_a_folder_without_libcaer_sources_is_refused(libcaer, tmp_path):
    (tmp_path / "src").mkdir()
    with pytest.raises(ValueError, match="not a libcaer source checkout.*davis_common.h"):
        libcaer.build_translator(tmp_path, tmp_path / "build")


def test_version_comes_from_the_project_line(libcaer, tmp_path):
    cmake = "CMAKE_MINIMUM_REQUIRED(VERSION 3.10.0)\nPROJECT(libcaer\n\tVERSION 3.3.9\n\tLANGUAGES C CXX)\n"
    (tmp_path / "CMakeLists.txt").write_text(cmake)
    assert libcaer.libcaer_version(tmp_path) == "3.3.9"
    (tmp_path / "CMakeLists.txt").write_text("PROJECT(other VERSION 1.0.0)\n")
    with pytest.raises(ValueError, match="no 'PROJECT\\(libcaer VERSION"):
        libcaer.libcaer_version(tmp_path)


@pytest.mark.skipif(not os.environ.get("LIBCAER_SRC"), reason="LIBCAER_SRC names no libcaer source checkout")
def test_translator_decodes_the_same_events_as_the_decoder(libcaer, tmp_path):
    rng = np.random.default_rng(0)
    n = 30_000
    words = np.where(rng.random(n) < 0.4, 0x8000 | rng.integers(0, 0x8000, n),
                     np.where(rng.random(n) < 0.3, 0x1000 | rng.integers(0, 260, n),
                              0x2000 | rng.integers(0, 2, n) << 12 | rng.integers(0, 346, n)))
    words[::5000] = 0x7001
    data = words.astype("<u2").tobytes()
    translator = libcaer.LibcaerTranslator(libcaer.build_translator(Path(os.environ["LIBCAER_SRC"]), tmp_path))
    run = translator.run(data, 8192)
    assert run.polarity_events == len(StreamDecoder(SensorLayout.davis346()).feed(data).events)
    assert run.special_events == 0 and run.translator_s > 0
