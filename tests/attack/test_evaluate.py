"""Digital evaluation protocol on a tiny configuration: hand-made scoring cases, table shapes, baselines, thresholds."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from davis_rig.attack.evaluate import PAPER_THRESHOLDS, EvalConfig, TextureSpec, baseline_textures, evaluation_scenes
from davis_rig.attack.report import results_markdown, table1, table2, write_visualisations
from davis_rig.attack.scoring import score_detections, window_histograms
from davis_rig.models.rvt.checkpoint import load_detector
from davis_rig.scene.body import BodyModel

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
TINY = EvalConfig(scales=("large", "small"), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,), supersample=1)
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _decoded(score: float, box=(50.0, 40.0, 110.0, 200.0), anchors: int = 3) -> np.ndarray:
    """Decoded head output [A, 7]: anchor 0 = a pedestrian at ``box`` with obj * p_ped = score, others empty."""
    out = np.zeros((anchors, 7), dtype=np.float32)
    x0, y0, x1, y1 = box
    out[0] = ((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, 1.0, 0.0, score)
    out[1:, :4] = (10, 10, 4, 4)
    return out


def test_score_detections_hand_made():
    box = np.array([50.0, 40.0, 110.0, 200.0], dtype=np.float32)
    boxes = np.stack([box] * 3)
    ends = np.array([50_000, 100_000, 150_000])
    # sequence A: a perfect detection with score 0.5 in every window; sequence B: nothing (attack succeeded)
    decoded = [[_decoded(0.5)] * 3, [_decoded(0.0)] * 3]
    res = score_detections(decoded, [boxes, boxes], [ends, ends], (0.01, 0.6), seq_len=3)
    low, high = res[0.01], res[0.6]
    assert low["num_sequences"] == high["num_sequences"] == 2 and low["num_windows"] == 6
    assert low["num_detected"] == 1 and low["SeqASR"] == 0.5
    assert high["num_detected"] == 0 and high["SeqASR"] == 1.0
    assert low["AP"] == pytest.approx(0.5, abs=0.01)  # recall 1/2 at precision 1 -> AP 0.5 (101-point COCO)
    assert high["AP"] == 0.0
    # a window without a person (NaN box) is not a label and breaks the sequence
    gap = boxes.copy()
    gap[1] = np.nan
    assert score_detections([[_decoded(0.5)] * 3], [gap], [ends], (0.01,), seq_len=3)[0.01]["num_sequences"] == 0


def test_window_histograms_exact_events_or_the_official_relaxed_counts():
    # one pixel of a grey video brightens by 0.5 log units between frames 4 and 5 (5 ms frames, 50 ms windows)
    from davis_rig.events.simulator import simulate_events
    from davis_rig.events.histogram import stacked_histograms

    video = np.full((21, 4, 5), 0.5, dtype=np.float32)
    video[5:, 2, 3] = 0.5 * math.exp(0.5)
    t_us = np.arange(21, dtype=np.int64) * 5_000
    ends = np.array([50_000, 100_000], dtype=np.int64)
    exact = window_histograms(video, t_us, ends)
    assert exact.dtype == np.uint8
    assert np.array_equal(exact, stacked_histograms(simulate_events(video, t_us), ends, height=4, width=5))
    assert exact[0, 10:, 2, 3].sum() == 2 and exact.sum() == 2  # floor(0.5 / 0.2) ON events, nothing else
    relaxed = window_histograms(video, t_us, ends, events="official_relaxed")
    assert relaxed.dtype == np.float32 and relaxed.shape == exact.shape
    # continuous 0.5 / 0.2 = 2.5 crossings x 10/27, in the ON bin of the pair's midpoint (22.5 ms -> bin 4)
    assert relaxed[0, 14, 2, 3] == pytest.approx(2.5 * 10 / 27, rel=1e-5)
    assert np.count_nonzero(relaxed) == 1
    with pytest.raises(ValueError, match="events"):
        window_histograms(video, t_us, ends, events="soft")
    with pytest.raises(ValueError, match="events"):
        EvalConfig(events="soft")


def test_test_scenes_grid_uses_test_shapes():
    specs = evaluation_scenes(EvalConfig(), 24)
    assert len(specs) == 3 * 6 * 4 * 2
    assert {s.shape_index for _, s in specs} == {1, 5, 9, 13, 17, 21}
    assert {scale for scale, _ in specs} == {"large", "middle", "small"}
    assert all(s.num_frames == 31 for _, s in specs)


def test_official_scene_is_white_walking_in_place_under_the_official_light():
    from davis_rig.scene.shading import Light

    specs = evaluation_scenes(EvalConfig.official(scales=("middle",)), 24)
    assert len(specs) == 6 * 4 * 2
    assert all(s.background == 1.0 and s.advance is False and s.light == Light.official() for _, s in specs)
    default = evaluation_scenes(EvalConfig(scales=("middle",)), 24)
    assert all(s.background == 0.5 and s.advance is True and s.light is None for _, s in default)
    assert all(s.playback_speed == 1.0 for _, s in default)
    fast = evaluation_scenes(EvalConfig.official(scales=("middle",), playback_speed=5 / 3), 24)
    assert all(s.playback_speed == 5 / 3 for _, s in fast)


def test_table1_and_table2_on_tiny_config(tmp_path):
    detector = load_detector(FIXTURE)
    model = BodyModel()
    rng = np.random.default_rng(0)
    optimized = {10: (rng.random((10, 10)) > 0.5).astype(np.float32)}
    t1 = table1(optimized, detector, tmp_path, config=TINY, model=model, command="davis-attack evaluate --table 1")
    rows = t1["rows"]
    names = list(dict.fromkeys(r["texture"] for r in rows))
    assert names == ["white", "black", "random 60x60", "ours 10x10"]
    assert len(rows) == 4 * 3 * len(PAPER_THRESHOLDS)  # textures x (2 scales + all) x thresholds
    for name in names:
        for scale in ("all", "large", "small"):
            sel = sorted((r for r in rows if r["texture"] == name and r["scale"] == scale),
                         key=lambda r: r["threshold"])
            asr = [r["SeqASR"] for r in sel]
            assert asr == sorted(asr)  # a higher threshold never detects more sequences
            assert all(r["num_sequences"] == (2 if scale == "all" else 1) for r in sel)
            assert all(0.0 <= r["AP"] <= 1.0 for r in sel)
    md = t1["markdown"].read_text()
    assert "davis-attack evaluate --table 1" in md and "| white |" in md and "| ours 10x10 |" in md
    white = next(line for line in md.splitlines() if line.startswith("| white |"))
    assert white.count("|") == 2 + 2 * len(PAPER_THRESHOLDS)
    assert t1["plot"].stat().st_size > 0 and t1["json"].is_file()

    combos = {"torso": optimized[10], "torso+arms+legs": optimized[10]}
    t2 = table2(combos, detector, tmp_path, config=EvalConfig(**{**TINY.__dict__, "thresholds": (0.25,)}), model=model)
    assert [r["texture"] for r in t2["rows"] if r["scale"] == "all"] == ["torso", "torso+arms+legs"]
    assert all(r["threshold"] == 0.25 for r in t2["rows"])


def test_results_markdown_and_baselines():
    base = baseline_textures()
    assert list(base) == ["white", "black", "random 60x60"]
    assert base["random 60x60"].grid.shape == (60, 60) and base["white"].grid.min() == 1.0
    rows = [{"texture": "white", "scale": "all", "threshold": 0.25, "AP": 0.5, "SeqASR": float("nan")}]
    md = results_markdown(rows, (0.25,))
    assert md.splitlines()[2] == "| white | 50.0 | n/a |"


def test_visualisations_written(tmp_path):
    detector = load_detector(FIXTURE)
    textures = {"white": TextureSpec(np.ones((1, 1), np.float32)),
                "checker": TextureSpec(np.indices((4, 4)).sum(0).astype(np.float32) % 2)}
    out = write_visualisations(textures, detector, tmp_path, config=TINY, model=BodyModel())
    assert [p.name for p in out["frames"]] == ["events_white.png", "events_checker.png"]
    from PIL import Image

    with Image.open(out["gif"]) as gif:
        assert gif.n_frames == 31 and gif.size == (304, 240)
    import cv2

    strip = cv2.imread(str(out["frames"][0]))
    assert strip.shape == (240, 3 * 304, 3)


def test_window_histograms_cover_a_non_default_window():
    # 25 ms windows [0, 25] and [25, 50] ms: pixel (1, 1) brightens between frames 2 and 3 (10 -> 15 ms), pixel
    # (2, 3) between frames 6 and 7 (30 -> 35 ms); a 50 ms second window [0, 50] would hold both
    from davis_rig.events.simulator import simulate_events
    from davis_rig.events.histogram import stacked_histograms

    video = np.full((11, 4, 5), 0.5, dtype=np.float32)
    video[3:, 1, 1] = 0.5 * math.exp(0.5)
    video[7:, 2, 3] = 0.5 * math.exp(0.5)
    t_us = np.arange(11, dtype=np.int64) * 5_000
    ends = np.array([25_000, 50_000], dtype=np.int64)
    exact = window_histograms(video, t_us, ends, window_us=25_000)
    expected = stacked_histograms(simulate_events(video, t_us), ends, window_us=25_000, height=4, width=5)
    assert np.array_equal(exact, expected)
    assert exact[0, 10:, 1, 1].sum() == 2 and exact[1, 10:, 2, 3].sum() == 2 and exact.sum() == 4
    assert window_histograms(video, t_us, ends)[1].sum() == 4  # the 50 ms default reaches back into window 1
    relaxed = window_histograms(video, t_us, ends, events="official_relaxed", window_us=25_000)
    # midpoints 12.5 ms and 32.5 ms lie 12.5 ms and 7.5 ms into their 25 ms windows: ON bins 5 and 3 of 10
    assert relaxed[0, 15, 1, 1] == pytest.approx(2.5 * 10 / 27, rel=1e-5)
    assert relaxed[1, 13, 2, 3] == pytest.approx(2.5 * 10 / 27, rel=1e-5) and np.count_nonzero(relaxed) == 2
