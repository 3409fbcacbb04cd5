"""Tests of ``benchmarks/digital_cost.py``: the amortisation arithmetic, the report, and a smoke run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def test_clips_prepared_per_step_counts_the_pool_and_every_refresh(digital_cost):
    # 5 steps (0..4), refresh at steps 2 and 4 (step > 0 and step % 2 == 0), 2 of 4 slots each: 4 + 2 * 2 clips
    small = digital_cost.Schedule(pool_size=4, refresh_every=2, refresh_fraction=0.5, iterations=5,
                                  clips_per_step=2, seq_len=3)
    assert digital_cost.clips_prepared_per_step(small) == pytest.approx(8 / 5)
    assert digital_cost.preparations_per_window(small) == pytest.approx(8 / 5 / 6)
    # the attack's defaults: 32 clips, then 8 every 50 steps over 11,500 steps (229 refreshes)
    paper = digital_cost.Schedule(32, 50, 0.25, 11_500, 1, 3)
    assert digital_cost.clips_prepared_per_step(paper) == pytest.approx((32 + 229 * 8) / 11_500)


def test_cost_lines_ratios_and_goal_verdict(digital_cost):
    timing = digital_cost.Timing
    per_window = {"prep": timing(4.0, 1.0, 3.0), "step": timing(5.0, 0.5, 4.5)}
    lines = digital_cost.cost_lines(per_window, timing(100.0, 2.0, 98.0), 10, combined=("prep", "step"))
    assert len(lines) == 1 + 3 + 1
    assert lines[1].split()[:2] == ["prep", "4.00"] and lines[1].endswith("4.00%")
    assert lines[2].split()[3] == "0.500"  # ms per frame
    assert lines[-1] == "combined (prep + step): 9.00 ms = 9.00 % of RVT fwd+bwd (goal <= 10 %: met)"
    over = digital_cost.cost_lines(per_window, timing(80.0, 0.0, 80.0), 10, combined=("prep", "step"))
    assert over[-1].endswith("11.25 % of RVT fwd+bwd (goal <= 10 %: not met)")


@pytest.mark.slow
def test_smoke_run_prints_every_case_and_the_combined_ratio():
    proc = subprocess.run(
        [sys.executable, str(_DIR / "digital_cost.py"), "--model", "mini", "--repeats", "1", "--warmup", "0",
         "--threads", "1", "--device", "cpu"],
        cwd=_DIR.parent, capture_output=True, text=True, check=False, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    for case in ("clip preparation, amortised", "texture step", "V2E relaxed (default) fwd+bwd", "V2E ste fwd+bwd",
                 "texture + V2E relaxed, one clip_histograms call", "RVT fwd+bwd (3-window sequence / 3)"):
        assert case in proc.stdout, case
    assert proc.stdout.count("% of RVT fwd+bwd (goal <= 10 %: ") == 2
