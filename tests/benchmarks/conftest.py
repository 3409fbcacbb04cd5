"""Fixtures loading the benchmark scripts by path (benchmarks are scripts, not a package)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCHMARKS_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def _load_script(stem: str):
    """Import ``benchmarks/<stem>.py`` with ``benchmarks/`` on ``sys.path`` (scripts import ``_common`` by name)."""
    sys.path.insert(0, str(BENCHMARKS_DIR))
    try:
        spec = importlib.util.spec_from_file_location(f"benchmarks_{stem}", BENCHMARKS_DIR / f"{stem}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCHMARKS_DIR))


@pytest.fixture(scope="module")
def bench_io():
    yield from _load_script("io")


@pytest.fixture(scope="module")
def digital_cost():
    yield from _load_script("digital_cost")


@pytest.fixture(scope="module")
def run_all():
    yield from _load_script("run_all")


@pytest.fixture(scope="module")
def fuzz_capture():
    yield from _load_script("fuzz_capture")
