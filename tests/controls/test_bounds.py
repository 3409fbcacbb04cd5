"""Controls before an attack: the fingerprint's textures, the hinge, the exact-value / relaxed-gradient counts and
the free-appearance bound on a tiny detector."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from davis_rig.attack.evaluate import EvalConfig, evaluation_scenes, prepare_scenes, window_histograms
from davis_rig.events.simulator import SimulatorConfig
from davis_rig.controls.bounds import (BoundConfig, fingerprint_textures, free_appearance_bound, hinge_loss,
                                       optimise_appearance, optimise_shared_texture, relaxed_event_histograms)
from davis_rig.models.rvt.checkpoint import load_detector
from davis_rig.models.rvt.detector import pad_to_input
from davis_rig.scene.body import BodyModel

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
TINY = EvalConfig(scales=("small",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,), supersample=1)
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_fingerprint_textures_are_the_baselines_plus_random_and_checker():
    specs = fingerprint_textures(10)
    assert list(specs) == ["white", "black", "random 60x60", "random 10x10", "checker 10x10"]
    assert specs["checker 10x10"].grid.mean() == 0.5 and specs["random 10x10"].grid.shape == (10, 10)


def test_hinge_loss_counts_only_anchors_above_half_the_threshold():
    out = torch.zeros(1, 3, 7)
    out[0, :, 4] = torch.tensor([1.0, 0.5, 0.1])  # obj
    out[0, :, 6] = torch.tensor([0.5, 0.2, 1.0])  # p_ped: scores 0.5, 0.1, 0.1
    assert float(hinge_loss([out, out], 0.25)) == pytest.approx(2 * (0.5 - 0.125))
    assert float(hinge_loss([out], 0.99)) == pytest.approx(0.5 - 0.495)
    out.requires_grad_(True)
    hinge_loss([out], 0.25).backward()
    assert out.grad[0, 0, 4] == pytest.approx(0.5) and out.grad[0, 1:, 4].abs().sum() == 0


def test_relaxed_event_histograms_count_the_exact_simulators_events_with_the_relaxed_gradient():
    t_us = np.arange(0, 50_001, 5_000, dtype=np.int64)
    ramp = torch.linspace(0.2, 0.9, len(t_us)).view(-1, 1, 1).expand(-1, 4, 5).contiguous()
    video = ramp.clone().requires_grad_(True)
    hist = relaxed_event_histograms(video, t_us, np.array([50_000]))
    exact = window_histograms(ramp, t_us, np.array([50_000]))
    # the same events per window, polarity and pixel (the simulator interpolates timestamps inside a frame pair,
    # so events may sit in a neighbouring bin)
    per_polarity = hist.detach().numpy().reshape(1, 2, 10, 4, 5).sum(2)
    assert per_polarity.sum() > 0 and np.array_equal(per_polarity, exact.reshape(1, 2, 10, 4, 5).sum(2))
    hist.sum().backward()
    assert video.grad.abs().sum() > 0


def test_free_appearance_bound_on_a_tiny_detector():
    detector = load_detector(FIXTURE)
    model = BodyModel()
    scenes = prepare_scenes(evaluation_scenes(TINY, model.num_shapes), model, TINY)
    res = free_appearance_bound(scenes, detector, TINY, BoundConfig(steps=2, grid_n=4))
    names = [r["appearance"] for r in res["rows"]]
    assert names == ["white", "black", "per-pixel", "per-frame texture", "static texture", "static per-texel"]
    assert res["scenes"] == 1
    for row in res["rows"]:
        assert 0.0 <= row["SeqASR"] <= 1.0 and row["num_sequences"] == 1
    # the optimised appearances keep the lowest loss seen, which includes their start
    assert set(res["per_scene"][0]) >= set(names)


def test_static_appearances_are_one_texture_in_every_frame():
    from davis_rig.controls.bounds import _appearance

    model = BodyModel()
    scene = prepare_scenes(evaluation_scenes(TINY, model.num_shapes), model, TINY)[0]
    config = BoundConfig(grid_n=4)
    grid = torch.randn(4, 4, generator=torch.Generator().manual_seed(0), dtype=scene.raster.shade.dtype)
    static, render_static = _appearance(scene, "static texture", config, None)
    texel, render_texel = _appearance(scene, "static per-texel", config, None)
    frames, render_frames = _appearance(scene, "per-frame texture", config, None)
    num_frames = scene.raster.num_frames
    assert tuple(static.shape) == (4, 4) and tuple(texel.shape) == (1024, 1024)
    assert tuple(frames.shape) == (num_frames, 4, 4)
    with torch.no_grad():
        video = render_static(grid)
        # the per-frame texture holding the same grid in every frame, and the per-texel one holding its texels
        assert torch.equal(video, render_frames(grid.expand(num_frames, 4, 4)))
        assert torch.equal(video, render_texel(grid.repeat_interleave(256, 0).repeat_interleave(256, 1)))
        # and a per-frame texture that changes is another video
        changing = grid.expand(num_frames, 4, 4).clone()
        changing[-1] = -changing[-1]
        assert not torch.equal(video, render_frames(changing))


def test_bound_config_kinds_are_checked():
    with pytest.raises(ValueError, match="kinds"):
        BoundConfig(kinds=("static texture", "static texture"))
    with pytest.raises(ValueError, match="kinds"):
        BoundConfig(kinds=("per-frame",))


def test_bound_config_events_are_checked():
    assert BoundConfig().events == "exact"
    with pytest.raises(ValueError, match="events"):
        BoundConfig(events="relaxed")


OTHER_SENSOR = SimulatorConfig(intensity_scale=100.0, lin_log_threshold=4.0)  # another 8-bit scale and lin-log knee


@pytest.mark.parametrize("simulator", [SimulatorConfig(), OTHER_SENSOR], ids=["ideal", "other_scale_and_knee"])
def test_official_relaxed_hinge_runs_on_the_evaluations_relaxed_counts_with_their_gradient(simulator):
    from davis_rig.controls.bounds import _appearance, _scene_hinge

    config = EvalConfig(scales=("small",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,), supersample=1,
                        events="official_relaxed", simulator=simulator)
    detector = load_detector(FIXTURE).eval()
    model = BodyModel()
    scene = prepare_scenes(evaluation_scenes(config, model.num_shapes), model, config)[0]
    bound = BoundConfig(grid_n=4, events="official_relaxed")
    logits, render = _appearance(scene, "static texture", bound, None)
    video = render(logits)
    seen = []
    original = detector.forward
    detector.forward = lambda x, states=None: seen.append(x.detach().clone()) or original(x, states)
    loss = _scene_hinge(video, scene, detector, replace(bound, threshold=0.01), config)
    # the detector saw exactly the evaluation's inputs: the relaxed counts window_histograms scores, with the
    # evaluation's sensor (a hinge on the default sensor differs from the second case's counts)
    scored = window_histograms(video.detach(), scene.t_us, scene.window_end_us, config.simulator, config.events)
    assert scored.dtype == np.float32 and not np.array_equal(scored, np.round(scored))  # continuous, not events
    assert len(seen) == scored.shape[0]
    for k, x in enumerate(seen):
        expected = pad_to_input(torch.from_numpy(scored[k : k + 1]), detector.config.in_res_hw)
        assert torch.equal(x, expected)
    loss.backward()
    assert float(loss.detach()) > 0 and logits.grad.abs().sum() > 0


def test_the_relaxed_counts_depend_on_the_sensor_the_hinge_is_given():
    t_us = np.arange(21, dtype=np.int64) * 5_000  # 200 Hz frames, two 50 ms windows
    video = torch.full((21, 8, 8), 0.02, dtype=torch.float32)  # dark: inside the lin-log knees
    video[1::2] *= 0.5  # flicker: every frame change crosses thresholds
    ends = np.array([50_000, 100_000], dtype=np.int64)
    ideal = window_histograms(video, t_us, ends, SimulatorConfig(), "official_relaxed")
    other = window_histograms(video, t_us, ends, OTHER_SENSOR, "official_relaxed")
    assert ideal.sum() > 0 and not np.array_equal(ideal, other)  # so the parametrized test above can fail


def test_the_bound_refuses_an_event_model_other_than_the_evaluations():
    config = replace(TINY, events="official_relaxed")
    with pytest.raises(ValueError, match="same event model"):
        free_appearance_bound([], None, config, BoundConfig())
    with pytest.raises(ValueError, match="theta"):
        free_appearance_bound([], None, config, BoundConfig(events="official_relaxed", theta=0.3))
    scene = prepare_scenes(evaluation_scenes(TINY, BodyModel().num_shapes), BodyModel(), TINY)[0]
    for optimise in (lambda: optimise_appearance(scene, None, "per-pixel", BoundConfig(), eval_config=config),
                     lambda: optimise_shared_texture([scene], None, BoundConfig(), eval_config=config)):
        with pytest.raises(ValueError, match="same event model"):
            optimise()


def test_free_appearance_bound_scores_official_relaxed_counts_when_asked():
    config = replace(TINY, events="official_relaxed", thresholds=(0.25,))
    detector = load_detector(FIXTURE)
    model = BodyModel()
    scenes = prepare_scenes(evaluation_scenes(config, model.num_shapes), model, config)
    res = free_appearance_bound(scenes, detector, config, BoundConfig(steps=0, grid_n=4, kinds=("per-pixel",),
                                                                      events="official_relaxed"))
    exact = free_appearance_bound(scenes, detector, TINY, BoundConfig(steps=0, grid_n=4, kinds=("per-pixel",)))
    # white scored on the relaxed counts is another detection than on exact events
    assert res["per_scene"][0]["white"] != exact["per_scene"][0]["white"]
