"""Tests of ``benchmarks/io.py`` (loaded by path: benchmarks are scripts): queue sizing, the streaming figures, and
a tiny end-to-end run through the real driver, so the capture benchmark keeps running as the code changes."""

from __future__ import annotations

import re

import pytest


def test_queue_depth_is_whole_reads_of_the_nominal_capacity(bench_io):
    assert bench_io.queue_depth(8 * 2**20, 8192) == 1024
    assert bench_io.queue_depth(8 * 2**20, 131072) == 64
    assert bench_io.queue_depth(100, 8192) == 1  # never an unbounded (0) queue


def test_streaming_figures_hand_made_marks(bench_io):
    # 2.0 s of data written in 2.5 s of wall time: real-time factor 0.8, ended 0.5 s behind
    data_s, wall_s, lag_s = bench_io.streaming_figures((10.0, 1_000), (12.5, 2_001_000))
    assert (data_s, wall_s) == (2.0, 2.5) and lag_s == pytest.approx(0.5)


def test_default_queue_holds_well_under_a_second_of_the_peak_stream(bench_io):
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.usb.sources import EncodedSource

    events = bench_io.synthetic_events(600_000, 12e6)  # 50 ms at the 12 M ev/s peak
    span_s = (int(events["t"][-1]) - int(events["t"][0])) / 1e6
    stream = EncodedSource(events, layout=SensorLayout.davis346())
    queue_s = bench_io.DEFAULT_QUEUE_MIB * 2**20 / (stream.total_bytes / span_s)
    assert 0.1 < queue_s < 0.25


def test_end_to_end_only_on_a_tiny_scene_reports_every_figure(bench_io, capsys):
    assert bench_io.main(["--e2e-only", "--rate", "2e5", "--seconds", "0.1", "--queue-mib", "4"]) == 0
    out = capsys.readouterr().out
    assert "compression" not in out and "SessionWriter" not in out
    assert out.count("real-time factor") == 4  # 8 KiB and 128 KiB device transfers, each with both readers
    assert "8 KiB, synchronous reads: queue 512 x <= 8 KiB (4.0 MiB nominal" in out
    assert "128 KiB, synchronous reads: queue 32 x <= 128 KiB" in out
    assert out.count("ring of 8 transfers: queue 128 x <= 32 KiB") == 2
    for line in ("lag behind real time at the end", "CPU-s per data-s", "file close", "start-up"):
        assert line in out
    assert re.findall(r"dropped transfers 0/\d+, recorded (\d+)/(\d+) events", out) == [("20000", "20000")] * 4


def test_end_to_end_with_one_reader(bench_io, capsys):
    assert bench_io.main(["--e2e-only", "--rate", "2e5", "--seconds", "0.1", "--reader", "ring"]) == 0
    out = capsys.readouterr().out
    assert out.count("real-time factor") == 2 and "synchronous reads" not in out


def test_skip_e2e_and_e2e_only_exclude_each_other(bench_io):
    with pytest.raises(SystemExit):
        bench_io.main(["--skip-e2e", "--e2e-only"])
