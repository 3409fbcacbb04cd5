"""Fixed seeds of ``benchmarks/fuzz_capture.py`` (loaded by path): every corruption kind through decoder + writer
+ recovery without an exception, the intact prefix kept, live and recovered files equal, the time span bounded;
and the kept share at the issue's garbage rate."""

from __future__ import annotations

import logging
import warnings

import numpy as np
import pytest


@pytest.fixture(autouse=True)
def quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # each damaged stream warns once per kind of damage
        logging.disable(logging.WARNING)
        yield
        logging.disable(logging.NOTSET)


def test_corruptions_damage_from_the_reported_byte(fuzz_capture):
    rng = np.random.default_rng(3)
    _, data = fuzz_capture.clean_stream(3, 2000, 300_000)
    for kind in fuzz_capture.KINDS:
        damaged, first = fuzz_capture.corrupt(data, kind, rng)
        assert damaged[:first] == data[:first], kind
        assert damaged != data or kind == "truncation" and first == len(data), kind


@pytest.mark.parametrize("seed", range(14))  # each kind twice
def test_fixed_seeds_pass_every_check(fuzz_capture, tmp_path, seed):
    kind = fuzz_capture.KINDS[seed % len(fuzz_capture.KINDS)]
    result = fuzz_capture.run_case(seed, kind, tmp_path, 3000, 300_000)
    assert result.error == ""
    assert result.prefix_kept == result.prefix_events
    assert result.files_equal
    assert result.ms_entries <= result.ms_bound


def test_garbage_rate_1e4_keeps_99_percent_of_valid_events(fuzz_capture, tmp_path):
    valid, kept = fuzz_capture.garbage_kept(0, 1e-4, tmp_path)
    assert valid == fuzz_capture.MAX_DISTINCT_EVENTS and kept / valid >= 0.99


def test_main_prints_the_figures(fuzz_capture, tmp_path, capsys):
    assert fuzz_capture.main(["--seeds", "7", "--events", "500", "--garbage-seeds", "0", "--memory-limit-mb", "0",
                              "--workdir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert out.count("exceptions 0") == 8 and "peak RSS" in out
