"""Tests of the shared benchmark helpers (``benchmarks/_common.py``, loaded by path: benchmarks are scripts)."""

from __future__ import annotations

import importlib.util
import os
import re
from pathlib import Path

import numpy  # noqa: F401  (loaded, so limit_blas_threads must refuse)
import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "_common.py"
_SPEC = importlib.util.spec_from_file_location("benchmarks_common", _PATH)
common = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(common)


def test_summarize_hand_made_samples():
    # exclusive quartiles of 1..8: positions 2.25 and 6.75 -> Q1 = 2.25, Q3 = 6.75
    timing = common.summarize_ms([8.0, 1.0, 7.0, 2.0, 6.0, 3.0, 5.0, 4.0])
    assert timing == common.Timing(median_ms=4.5, iqr_ms=4.5, min_ms=1.0)


def test_summarize_single_sample_and_empty():
    assert common.summarize_ms([3.0]) == common.Timing(3.0, 0.0, 3.0)
    with pytest.raises(ValueError, match="at least one sample"):
        common.summarize_ms([])


def test_timing_scaled_and_unpacks_as_a_triple():
    median, iqr, low = common.Timing(10.0, 4.0, 8.0).scaled(0.5)
    assert (median, iqr, low) == (5.0, 2.0, 4.0)


def test_time_ms_counts_warmup_and_repeats_and_syncs_around_each_call(monkeypatch):
    clock = iter(range(0, 100))
    monkeypatch.setattr(common.time, "perf_counter", lambda: next(clock) * 1e-3)  # 1 ms per clock read
    calls, syncs = [], []
    timing = common.time_ms(lambda: calls.append(1), warmup=2, repeats=3, sync=lambda: syncs.append(1))
    assert len(calls) == 5 and len(syncs) == 6
    assert timing == common.Timing(1.0, 0.0, 1.0)


def test_time_interleaved_alternates_functions():
    order = []
    out = common.time_interleaved_ms({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, 1, 2)
    assert order == ["a", "b"] * 3
    assert list(out) == ["a", "b"]


@pytest.mark.parametrize("warmup, repeats", [(-1, 3), (0, 0)])
def test_time_ms_rejects_bad_counts(warmup, repeats):
    with pytest.raises(ValueError, match="warmup >= 0 and repeats >= 1"):
        common.time_ms(lambda: None, warmup, repeats)


def test_metadata_line_fields():
    line = common.metadata_line(packages=("numpy", "no-such-distribution-xyz"), repeats="7 (+2 warm-up)")
    assert line.startswith("# commit ")
    assert re.search(r"\| numpy \d+\.\d+", line)
    assert "| no-such-distribution-xyz absent |" in line
    assert "| load average " in line
    assert line.endswith("| repeats 7 (+2 warm-up)")


def test_cpu_description_names_the_model_and_its_int8_dot_product_flags():
    zen3 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse avx avx2 fma\n\nprocessor\t: 1\n"
    assert common.cpu_description(zen3) == "AMD EPYC, int8 dot: none"
    icelake = "model name\t: Intel Xeon\nflags\t: avx2 avx512f avx512_vnni\n"
    assert common.cpu_description(icelake) == "Intel Xeon, int8 dot: avx512_vnni"
    assert "int8 dot" in common.metadata_line(packages=())


def test_limit_blas_threads_refuses_after_numpy_import():
    with pytest.raises(RuntimeError, match="before numpy"):
        common.limit_blas_threads(2)
    with pytest.raises(ValueError, match=">= 1"):
        common.limit_blas_threads(0)
    before = {v: os.environ.get(v) for v in common.BLAS_THREAD_VARIABLES}
    common.limit_blas_threads(None)
    assert {v: os.environ.get(v) for v in common.BLAS_THREAD_VARIABLES} == before


def test_random_detector_is_seeded_frozen_and_in_eval_mode():
    torch = pytest.importorskip("torch")
    model = common.random_detector("mini", seed=3)
    assert model.config.name == "RVT-mini" and not model.training
    assert not any(p.requires_grad for p in model.parameters())
    again = common.random_detector("mini", seed=3)
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), again.state_dict().values()))


def test_detection_score_and_bptt_case():
    torch = pytest.importorskip("torch")
    decoded = torch.tensor([[[0, 0, 0, 0, 0.5, 0.2, 0.6], [0, 0, 0, 0, 1.0, 0.3, 0.1]]])  # (B=1, A=2, 7)
    assert common.detection_score(decoded).item() == pytest.approx(0.5 * 0.6 + 1.0 * 0.3)
    calls = []

    def model(x, states):
        calls.append(states)
        return torch.cat([x, x], dim=-1), len(calls)  # decoded (1, 1, 8) from x (1, 1, 4)

    inputs = [torch.ones(1, 1, 4), 2 * torch.ones(1, 1, 4)]
    common.bptt_case(model, inputs)()
    assert calls == [None, 1]  # states carried from none
    assert all(x.grad is None for x in inputs)  # the caller's inputs are cloned, not touched
