"""The attack loop: loss falls on a tiny detector, bit-identical resume, best-on-validation selection, EoT pool."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from davis_rig.attack.eot import ClipPool, EoTConfig, draw_scene, prepare_clip, slot_seed, split_shapes
from davis_rig.attack.optimize import AttackConfig, load_attack_detector, optimize_texture
from davis_rig.attack.texture import binarize_ste
from davis_rig.attack.validation import REFINE_SEED_OFFSET, VAL_SEED_OFFSET, better
from davis_rig.errors import CheckpointError, ConfigError
from davis_rig.models.rvt.checkpoint import load_detector
from davis_rig.scene.body import BodyModel

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
# the seeds below were picked with a noisy training sensor on every clip (no test-sensor draws)
TINY_EOT = EoTConfig(supersample=1, test_sensor_probability=0.0)
pytestmark = pytest.mark.usefixtures("one_torch_thread")  # exact resume is checked on one thread


@pytest.fixture(scope="module")
def detector():
    return load_detector(FIXTURE)


@pytest.fixture(scope="module")
def body():
    return BodyModel()


def _tiny(**overrides) -> AttackConfig:
    base = dict(grid_n=4, iterations=4, pool_size=2, refresh_every=2, refresh_fraction=0.5, num_validation_clips=1,
                validate_every=1000, checkpoint_every=2, snapshot_every=2, lr=0.05, eot=TINY_EOT)
    return AttackConfig(**{**base, **overrides})


def _log(path: Path) -> tuple[list[dict], list[dict]]:
    steps, vals = [], []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        (vals if "validation" in rec else steps).append(rec.get("validation", rec))
    return steps, vals


def test_split_shapes_disjoint_and_deterministic():
    train, test = split_shapes(24)
    assert test == (1, 5, 9, 13, 17, 21)
    assert len(train) == 18 and not set(train) & set(test) and sorted(train + test) == list(range(24))
    with pytest.raises(ValueError):
        split_shapes(1)


def test_draw_scene_seeded_and_train_shapes_only():
    a, sa = draw_scene(EoTConfig(), 7, 24)
    b, sb = draw_scene(EoTConfig(), 7, 24)
    assert a == b and sa == sb
    shapes = {draw_scene(EoTConfig(), s, 24)[0].shape_index for s in range(200)}
    assert shapes <= set(split_shapes(24)[0]) and len(shapes) > 10
    thetas = [draw_scene(EoTConfig(), s, 24)[1]["threshold"] for s in range(50)]
    assert min(thetas) >= 0.17 and max(thetas) <= 0.23
    assert slot_seed(0, 1, 2) == slot_seed(0, 1, 2) != slot_seed(0, 1, 3)
    assert a.playback_speed == 1.0
    fast, _ = draw_scene(EoTConfig(playback_speed=5 / 3), 7, 24)
    assert fast == replace(a, playback_speed=5 / 3)  # the same draw, the motion played faster


def test_across_view_probability_draws_walks_across_the_view():
    def headings(config):
        return np.degrees([draw_scene(config, s, 24)[0].heading_rad for s in range(400)])

    def across(deg):  # within 30 degrees of +-90
        return np.mean(np.abs(np.abs(((deg + 180.0) % 360.0) - 180.0) - 90.0) <= 30.0)

    always = headings(EoTConfig(across_view_probability=1.0))
    assert np.all(np.abs(np.abs(always) - 90.0) <= 30.0) and 0.4 < np.mean(always > 0) < 0.6  # both sides
    assert 0.25 < across(headings(EoTConfig())) < 0.42  # uniform headings: a third of them
    assert 0.58 < across(headings(EoTConfig(across_view_probability=0.5))) < 0.76  # 1/2 + 1/2 * 1/3
    # off, the draws are those of every earlier run
    plain = [draw_scene(EoTConfig(), s, 24) for s in range(5)]
    assert plain == [draw_scene(EoTConfig(across_view_probability=0.0), s, 24) for s in range(5)]
    for bad in ({"across_view_probability": 1.5}, {"across_view_spread_rad": 2.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            EoTConfig(**bad)


def test_official_eot_draws_the_official_scene_with_camera_jitter_only(body):
    from davis_rig.scene.shading import Light

    config = replace(EoTConfig.official(), supersample=1)
    for seed in range(20):
        spec, sensor = draw_scene(config, seed, 24)
        assert (spec.advance, spec.offset_m, spec.background, spec.light) == (False, (0.0, 0.0), 1.0, Light.official())
        assert sensor["threshold"] == 0.2 and sensor["threshold_sigma"] == 0.0 and sensor["noise_rate_hz"] == 0.0
    clip = prepare_clip(spec, sensor, body, 4, config=config, seed=19)
    assert torch.all(clip.background == 1.0)


def test_training_motions_drawn_and_rendered(body, tmp_path):
    from davis_rig.attack.eot import amass_motions, prepare_clip
    from davis_rig.scene.gait import generate_gait

    motion = generate_gait()
    drawn = [draw_scene(TINY_EOT, s, 24, (motion,)) for s in range(20)]
    with_motion = [(spec, sensor) for spec, sensor in drawn if spec.motion is not None]
    assert 0 < len(with_motion) < 20  # half of the clips use a training motion
    spec, sensor = with_motion[0]
    clip = prepare_clip(spec, sensor, body, 4, config=TINY_EOT)
    assert np.isfinite(clip.boxes).all() and clip.t_us.shape == (31,)
    with pytest.raises(ValueError, match="no AMASS"):
        amass_motions(tmp_path)
    with pytest.raises(ValueError, match="split"):
        amass_motions(tmp_path, "val")


def test_pool_rebuilds_from_generations_and_splits_slots(body):
    pool = ClipPool(TINY_EOT, body, 4, size=3, base_seed=5)
    refreshed = pool.refresh(step=10, fraction=0.34)
    assert len(refreshed) == 1 and pool.generations.sum() == 1
    again = ClipPool(TINY_EOT, body, 4, size=3, base_seed=5, generations=pool.state_dict()["generations"])
    for slot in range(3):
        assert again.clips[slot].seed == pool.clips[slot].seed
        assert torch.equal(again.clips[slot].lookup.index, pool.clips[slot].lookup.index)
        assert torch.equal(again.clips[slot].raster.shade, pool.clips[slot].raster.shade)
        assert torch.equal(again.clips[slot].noise_cell, pool.clips[slot].noise_cell)
        assert torch.equal(again.clips[slot].noise_count, pool.clips[slot].noise_count)
    half = ClipPool(TINY_EOT, body, 4, size=3, base_seed=5, rank=1, world_size=2)
    assert sorted(half.clips) == [1]
    assert half.clips[1].seed == ClipPool(TINY_EOT, body, 4, size=3, base_seed=5).clips[1].seed
    with pytest.raises(ValueError):
        ClipPool(TINY_EOT, body, 4, size=1, rank=0, world_size=2)


@pytest.mark.parametrize("rule", ["relaxed", "ste"])
def test_loss_decreases_on_tiny_detector(detector, body, tmp_path, rule):
    # the fixture detector has random weights and reacts weakly to the texture: on most clips the loss moves by
    # ~1-5 % in 10 steps; the clip of seed 6 (deterministic on one thread) leaves room to fall by ~8 % with both
    # rules (re-pick the seed when the bundled body asset or the EoT draws change; picked with a constant rate
    # and the bundled walk)
    cfg = _tiny(iterations=10, pool_size=1, refresh_every=1000, dropout=0.0, alpha_schedule="soft",
                box_margin_px=0.0, lr=0.1, checkpoint_every=1000, snapshot_every=1000, v2e_gradient=rule, seed=6,
                lr_schedule="constant", eot=replace(TINY_EOT, walk="bundled"))
    optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    losses = [r["loss"] for r in _log(tmp_path / "log.jsonl")[0]]
    assert len(losses) == 10 and all(math.isfinite(v) for v in losses)
    assert losses[-1] < 0.97 * losses[0]
    assert np.mean(losses[-2:]) < np.mean(losses[:2])


def test_resume_is_bit_identical(detector, body, tmp_path):
    cfg = _tiny()
    full = optimize_texture(cfg, detector, tmp_path / "full", body_model=body, progress=False)
    part = optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False, max_steps=2)
    assert part.steps == 2
    with open(tmp_path / "part" / "log.jsonl", "a") as f:  # a step logged after the last checkpoint (crash)
        f.write(json.dumps({"step": 3, "loss": -1.0}) + "\n")
    rest = optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False, resume=True)
    assert rest.steps == 2
    a = torch.load(tmp_path / "full" / "checkpoints" / "last.pt", weights_only=True)
    b = torch.load(tmp_path / "part" / "checkpoints" / "last.pt", weights_only=True)
    assert a["step"] == b["step"] == 4 and a["pool"] == b["pool"]
    for key in a["generator"]:
        assert torch.equal(a["generator"][key], b["generator"][key]), key
    for key, value in a["optimizer"]["state"].items():
        for name in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(value[name], b["optimizer"]["state"][key][name])
    assert _log(tmp_path / "full" / "log.jsonl")[0] == _log(tmp_path / "part" / "log.jsonl")[0]
    assert np.array_equal(full.texture, rest.texture)
    assert (tmp_path / "full" / "snapshots" / "step_000004.png").is_file()


def test_resume_refuses_other_config(detector, body, tmp_path):
    optimize_texture(_tiny(iterations=2), detector, tmp_path, body_model=body, progress=False)
    with pytest.raises(CheckpointError, match="lr"):
        optimize_texture(_tiny(iterations=4, lr=0.1), detector, tmp_path, body_model=body, progress=False, resume=True)


def test_resume_accepts_checkpoint_written_before_a_field_existed(detector, body, tmp_path):
    optimize_texture(_tiny(iterations=2), detector, tmp_path, body_model=body, progress=False)
    path = tmp_path / "checkpoints" / "last.pt"
    state = torch.load(path, weights_only=True)
    del state["config"]["loss_reduction"]  # a run started before --loss existed
    del state["config"]["eot"]["light"]  # ... and before EoTConfig.light existed
    torch.save(state, path)
    rest = optimize_texture(_tiny(iterations=3), detector, tmp_path, body_model=body, progress=False, resume=True)
    assert rest.steps == 1
    with pytest.raises(CheckpointError, match="loss_reduction"):
        optimize_texture(_tiny(iterations=4, loss_reduction="top"), detector, tmp_path, body_model=body,
                         progress=False, resume=True)


def test_best_on_validation_selection(detector, body, tmp_path):
    cfg = _tiny(iterations=3, validate_every=1, lr=0.5, dropout=0.0)
    result = optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    vals = _log(tmp_path / "log.jsonl")[1]
    assert [v["step"] for v in vals] == [1, 2, 3]
    best = vals[0]
    for v in vals[1:]:
        if better(v, best):
            best = v
    saved = json.loads((tmp_path / "best.json").read_text())
    assert saved == best and result.best_step == best["step"]
    assert np.array_equal(np.load(tmp_path / "best_texture.npy"), result.best_texture)
    assert set(np.unique(result.best_texture)) <= {0.0, 1.0} and result.best_texture.shape == (4, 4)


def test_better_rule():
    assert better({"SeqASR": 0.5, "mean_top_score": 0.9}, None)
    assert better({"SeqASR": 0.5, "mean_top_score": 0.9}, {"SeqASR": 0.25, "mean_top_score": 0.1})
    assert better({"SeqASR": 0.5, "mean_top_score": 0.2}, {"SeqASR": 0.5, "mean_top_score": 0.3})
    assert not better({"SeqASR": 0.5, "mean_top_score": 0.3}, {"SeqASR": 0.5, "mean_top_score": 0.3})
    assert not better({"SeqASR": float("nan"), "mean_top_score": 0.0}, {"SeqASR": 0.0, "mean_top_score": 0.5})
    # select_by="score": the mean top score alone, so one more missed sequence of 8 no longer outranks it
    assert better({"SeqASR": 0.0, "mean_top_score": 0.30}, {"SeqASR": 0.125, "mean_top_score": 0.37}, "score")
    assert not better({"SeqASR": 0.125, "mean_top_score": 0.37}, {"SeqASR": 0.0, "mean_top_score": 0.30}, "score")
    assert not better({"SeqASR": 0.0, "mean_top_score": 0.30}, {"SeqASR": 0.125, "mean_top_score": 0.37})
    with pytest.raises(ValueError, match="select_by"):
        AttackConfig(select_by="ap")


def test_best_on_validation_by_score_keeps_the_lowest_mean_top_score(detector, body, tmp_path):
    cfg = _tiny(iterations=3, validate_every=1, lr=0.5, dropout=0.0, select_by="score")
    result = optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    vals = _log(tmp_path / "log.jsonl")[1]
    lowest = min(vals, key=lambda v: (v["train_top_score"], v["step"]))  # as trained: the clips' own sensors
    assert json.loads((tmp_path / "best.json").read_text()) == lowest and result.best_step == lowest["step"]


def test_load_attack_detector_frozen_and_onnx_hint(tmp_path):
    det = load_attack_detector(FIXTURE)
    assert not det.training and not any(p.requires_grad for p in det.parameters())
    onnx = tmp_path / "model.onnx"
    onnx.write_bytes(b"not used")
    with pytest.raises(CheckpointError, match="ONNX"):
        load_attack_detector(onnx)


def test_bf16_autocast_step_close_to_fp32(detector, body):
    from davis_rig.attack.optimize import attack_loss

    pool = ClipPool(TINY_EOT, body, 4, size=1, base_seed=3)
    grid = torch.full((4, 4), 0.5, requires_grad=True)
    losses, grads = [], []
    for precision in ("fp32", "bf16"):
        grid.grad = None
        loss = attack_loss(grid, pool.sample(0, 1), detector, _tiny(precision=precision))
        loss.total.backward()
        losses.append(loss.total.item())
        grads.append(grid.grad.clone())
    assert loss.total.dtype == torch.float32 and torch.isfinite(grads[1]).all()
    assert losses[1] == pytest.approx(losses[0], rel=0.05)


def test_config_validation():
    with pytest.raises(ValueError):
        AttackConfig(iterations=0)
    with pytest.raises(ValueError):
        AttackConfig(clips_per_step=4, pool_size=2)
    with pytest.raises(ValueError):
        AttackConfig(precision="fp16")
    assert replace(AttackConfig(), grid_n=20).to_dict()["grid_n"] == 20
    with pytest.raises(ValueError, match="start"):
        AttackConfig(start="grey")


def test_clip_histograms_forward_exact_backward_by_rule(body):
    from davis_rig.attack.optimize import clip_histograms
    from davis_rig.events.v2e_torch import OFFICIAL_RELAXED_SCALE, v2e_histograms

    clip = ClipPool(TINY_EOT, body, 4, size=1, base_seed=3).clips[0]
    grid = torch.rand(4, 4, generator=torch.Generator().manual_seed(0))
    weight = torch.rand(3, 20, *clip.raster.hw, generator=torch.Generator().manual_seed(1))
    hists, grads = {}, {}
    for rule in ("ste", "relaxed"):
        g = grid.clone().requires_grad_(True)
        hists[rule] = clip_histograms(g, clip, gradient=rule)
        (hists[rule] * weight).sum().backward()
        grads[rule] = g.grad
    assert torch.equal(hists["ste"], hists["relaxed"])  # the forward value does not depend on the rule
    assert hists["ste"].max() <= 10 and torch.equal(hists["ste"], hists["ste"].round())
    g = grid.clone().requires_grad_(True)
    theta = float(clip.threshold.mean())
    surrogate = v2e_histograms(clip.video(g), clip.t_us, clip.window_end_us, mode="official_relaxed",
                               count_cutoff=None, threshold_on=theta, threshold_off=theta) / OFFICIAL_RELAXED_SCALE
    (surrogate * weight).sum().backward()
    assert torch.allclose(grads["relaxed"], g.grad, rtol=1e-5, atol=1e-6)
    assert grads["relaxed"].abs().sum() > 0 and not torch.allclose(grads["relaxed"], grads["ste"])
    with pytest.raises(ValueError, match="gradient"):
        clip_histograms(grid, clip, gradient="soft")
    with pytest.raises(ValueError, match="v2e_gradient"):
        AttackConfig(v2e_gradient="soft")


def test_clip_histograms_official_relaxed_trains_on_the_relaxed_counts(body):
    # the official code's protocol: the forward value is the relaxed counts themselves, with their own gradient
    from davis_rig.attack.optimize import clip_histograms
    from davis_rig.events.v2e_torch import v2e_histograms

    clip = ClipPool(TINY_EOT, body, 4, size=1, base_seed=3).clips[0]
    empty = torch.zeros(0, dtype=torch.int64)
    uniform = replace(clip, threshold=torch.full_like(clip.threshold, 0.2), noise_cell=empty,
                      noise_count=empty.float())
    weight = torch.rand(3, 20, *clip.raster.hw, generator=torch.Generator().manual_seed(1))
    grids = [torch.rand(4, 4, generator=torch.Generator().manual_seed(0)).requires_grad_(True) for _ in range(2)]
    hist = clip_histograms(grids[0], uniform, mode="official_relaxed", gradient="ste")
    (hist * weight).sum().backward()
    expected = v2e_histograms(uniform.video(grids[1]), clip.t_us, clip.window_end_us, mode="official_relaxed",
                              threshold_on=0.2, threshold_off=0.2)
    (expected * weight).sum().backward()
    assert torch.allclose(hist, expected, atol=1e-6) and hist.max() > 0 and not torch.equal(hist, hist.round())
    assert torch.allclose(grids[0].grad, grids[1].grad, rtol=1e-5, atol=1e-6) and grids[0].grad.abs().sum() > 0
    assert not bool((clip.threshold == clip.threshold.flatten()[0]).all())  # the toolkit's EoT: mismatch on
    with pytest.raises(ValueError, match="one threshold"):
        clip_histograms(grids[0], clip, mode="official_relaxed", gradient="ste")
    with pytest.raises(ValueError, match="events"):
        AttackConfig(events="soft")


def test_pool_clip_video_equals_the_full_raster_composite(body):
    # the pool clip keeps background * (1 - coverage) and drops the coverage: same video and gradient, bit for bit
    from davis_rig.scene.scene import render_clip

    spec, sensor = draw_scene(TINY_EOT, 7, body.num_shapes)
    clip = prepare_clip(spec, sensor, body, 4, config=TINY_EOT)
    full = render_clip(spec, None, model=body)
    lookup = full.raster.lookup(size=1024, mode="nearest", grid_n=4)
    weight = torch.randn(full.raster.num_frames, *full.raster.hw, generator=torch.Generator().manual_seed(2))
    grids, videos = [], []
    for render in (clip.video, lambda g: full.raster.compose(lookup.sample(g, fill=1.0), full.background)):
        grids.append(torch.rand(4, 4, generator=torch.Generator().manual_seed(0)).requires_grad_(True))
        videos.append(render(grids[-1]))
        videos[-1].backward(weight)
    assert clip.raster.coverage is None
    assert torch.equal(videos[0], videos[1]) and torch.equal(grids[0].grad, grids[1].grad)
    # the active box is the tight bounding box of everything the person covers; outside it the video is constant
    y0, y1, x0, x1 = clip.active_box
    seen = (full.raster.coverage > 0).any(dim=0)
    assert seen[y0].any() and seen[y1 - 1].any() and seen[:, x0].any() and seen[:, x1 - 1].any()
    outside = torch.ones_like(seen)
    outside[y0:y1, x0:x1] = False
    assert not seen[outside].any() and 0 < (y1 - y0) * (x1 - x0) < seen.numel()
    assert torch.equal(videos[0][:, outside], videos[0][:1, outside].expand(len(videos[0]), -1))
    assert torch.equal(clip.active_video(grids[0]), videos[0][:, y0:y1, x0:x1])


def test_active_box_of_an_unseen_person_is_one_pixel():
    from davis_rig.attack.eot import _active_box

    assert _active_box(torch.zeros(3, 5, 7)) == (0, 1, 0, 1)
    coverage = torch.zeros(3, 5, 7)
    coverage[0, 1, 2] = 0.25
    coverage[2, 3, 5] = 1.0
    assert _active_box(coverage) == (1, 4, 2, 6)


@pytest.mark.parametrize("rule", ["relaxed", "ste"])
def test_clip_histograms_equals_the_two_pass_computation(body, rule):
    # a step takes the exact counts and the relaxed surrogate from one log video and adds the noise per cell; the
    # plain computation (V2E of the video once per count mode, a dense histogram of the noise events) gives the
    # same bits, forward and backward
    from davis_rig.attack.optimize import clip_histograms
    from davis_rig.events.v2e_torch import OFFICIAL_RELAXED_SCALE, v2e_histograms

    clip = ClipPool(TINY_EOT, body, 4, size=1, base_seed=3).clips[0]
    clip = replace(clip, noise_count=clip.noise_count + torch.arange(clip.noise_count.numel()) % 3)  # 1 .. 3 per cell
    assert clip.noise_count.numel() > 100
    grid = torch.rand(4, 4, generator=torch.Generator().manual_seed(0))
    weight = torch.randn(3, 20, *clip.raster.hw, generator=torch.Generator().manual_seed(1))
    shared = grid.clone().requires_grad_(True)
    hist = clip_histograms(shared, clip, gradient=rule)
    hist.backward(weight)

    events = clip.noise_cell.repeat_interleave(clip.noise_count.long())
    noise = torch.zeros(weight.numel()).index_add_(0, events, torch.ones(events.numel())).view_as(weight)

    def counts(video, threshold):
        return v2e_histograms(video, clip.t_us, clip.window_end_us, count_cutoff=None, threshold_on=threshold,
                              threshold_off=threshold)

    two_pass = grid.clone().requires_grad_(True)
    video = clip.video(two_pass)
    with torch.no_grad():  # the value: counts in float64, as the exact simulator takes them
        value = counts(video.double(), clip.threshold.double()).float()
    if rule == "ste":
        ste = counts(video, clip.threshold)
        expected = torch.clamp(value + (ste - ste.detach()) + noise, max=10.0)
    else:
        theta = float(clip.threshold.mean())
        surrogate = v2e_histograms(video, clip.t_us, clip.window_end_us, mode="official_relaxed", count_cutoff=None,
                                   threshold_on=theta, threshold_off=theta) / OFFICIAL_RELAXED_SCALE
        expected = torch.clamp(value + noise, max=10.0) + (surrogate - surrogate.detach())
    expected.backward(weight)
    assert torch.equal(hist, expected) and torch.equal(shared.grad, two_pass.grad)
    assert shared.grad.abs().sum() > 0


def test_with_the_test_sensor_the_step_counts_the_exact_simulators_events(body):
    # per pixel and window (the bins may differ: a frame pair's midpoint vs interpolated event times)
    from davis_rig.attack.optimize import clip_histograms
    from davis_rig.events.simulator import simulate_events

    clip = ClipPool(replace(TINY_EOT, test_sensor_probability=1.0), body, 4, size=1, base_seed=3).clips[0]
    assert clip.base_threshold == 0.2 and clip.noise_cell.numel() == 0
    grid = torch.rand(4, 4, generator=torch.Generator().manual_seed(0))
    hist = clip_histograms(grid, clip, gradient="ste").detach()
    events = simulate_events(clip.video(grid).detach(), clip.t_us)
    compared = 0
    for k, end in enumerate(clip.window_end_us):
        inside = events[(events["t"] > end - clip.window_us) & (events["t"] <= end)]
        for polarity in (0, 1):
            expected = np.zeros(clip.raster.hw)
            sel = inside[inside["p"] == polarity]
            np.add.at(expected, (sel["y"], sel["x"]), 1)
            bins = hist[k, polarity * 10 : (polarity + 1) * 10].numpy()
            unclipped = (bins < 10).all(0)  # a bin at 10 may hold more events
            assert np.array_equal(bins.sum(0)[unclipped], expected[unclipped]), (k, polarity)
            compared += int(expected[unclipped].sum())
    assert compared >= len(events) // 3  # the events of pixels with no bin at the clip (38 % here) agree


def test_load_attack_detector_defaults_to_bundled_weights(monkeypatch, tmp_path):
    import davis_rig.models as models
    from davis_rig.errors import MissingDependencyError

    monkeypatch.setattr(models, "DEFAULT_DETECTOR_DIR", tmp_path)
    with pytest.raises(MissingDependencyError, match="rvt_default.safetensors"):
        load_attack_detector()
    (tmp_path / models.DEFAULT_WEIGHTS_FILE).write_bytes(FIXTURE.read_bytes())
    det = load_attack_detector()
    assert not det.training and det.config == load_detector(FIXTURE).config


def test_validate_scores_the_chosen_event_model(body, detector):
    from davis_rig.attack.evaluate import detect_windows
    from davis_rig.attack.optimize import validate

    clip = ClipPool(TINY_EOT, body, 4, size=1, base_seed=3).clips[0]
    grid = np.ones((4, 4), np.float32)
    results = {events: validate(grid, [clip], detector, 0.25, events) for events in ("exact", "official_relaxed")}
    for events, res in results.items():
        assert res["num_sequences"] == 1 and 0.0 <= res["mean_top_score"] <= 1.0
        with torch.no_grad():
            decoded, hist = detect_windows(detector, clip.video(torch.as_tensor(grid)), clip.t_us, clip.window_end_us,
                                           events=events)
        assert hist.dtype == (np.uint8 if events == "exact" else np.float32)
        assert res["mean_top_score"] == pytest.approx(np.mean([(d[:, 4] * d[:, 6]).max() for d in decoded]))
    assert results["exact"]["mean_top_score"] != results["official_relaxed"]["mean_top_score"]


def test_grid_v2e_mode_with_threshold_mismatch_is_refused_up_front(detector, body, tmp_path):
    # "official_relaxed" takes one θ per clip: a per-pixel mismatch used to fail only at the first training step
    with pytest.raises(ValueError, match="threshold_sigma"):
        AttackConfig(v2e_mode="official_relaxed", eot=EoTConfig())
    cfg = _tiny(iterations=1, pool_size=1, v2e_mode="official_relaxed", v2e_gradient="ste",
                events="official_relaxed", eot=replace(TINY_EOT, threshold_sigma=0.0))
    result = optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    assert result.steps == 1 and math.isfinite(_log(tmp_path / "log.jsonl")[0][0]["loss"])


def test_a_new_run_refuses_a_folder_that_holds_a_run(detector, body, tmp_path):
    optimize_texture(_tiny(iterations=1, pool_size=1), detector, tmp_path, body_model=body, progress=False)
    log = (tmp_path / "log.jsonl").read_text()
    with pytest.raises(CheckpointError, match="--resume"):
        optimize_texture(_tiny(iterations=1, pool_size=1), detector, tmp_path, body_model=body, progress=False)
    assert (tmp_path / "log.jsonl").read_text() == log  # nothing of the earlier run was touched


def test_a_run_without_a_checkpoint_never_deletes_another_runs_outputs(detector, body, tmp_path):
    # a folder holding a best texture and records but no log and no checkpoint (another tool's, or a run that left
    # no checkpoint): starting from step 0 there would delete them, so both a new run and a resume are refused
    np.save(tmp_path / "best_texture.npy", np.full((4, 4), 7.0, np.float32))
    (tmp_path / "best.json").write_text(json.dumps({"SeqASR": 1.0, "mean_top_score": 0.0, "step": 1}))
    for resume in (False, True):
        with pytest.raises(CheckpointError, match="holds best_texture.npy, best.json of another run"):
            optimize_texture(_tiny(iterations=1, pool_size=1), detector, tmp_path, body_model=body, progress=False,
                             resume=resume)
    assert np.load(tmp_path / "best_texture.npy")[0, 0] == 7.0 and (tmp_path / "best.json").is_file()


def test_resume_without_a_checkpoint_in_an_empty_folder_starts_a_run(detector, body, tmp_path):
    (tmp_path / "snapshots").mkdir()
    (tmp_path / "snapshots" / "step_000500.png").write_bytes(b"old")
    result = optimize_texture(_tiny(iterations=1, pool_size=1), detector, tmp_path, body_model=body, progress=False,
                              resume=True)
    steps, vals = _log(tmp_path / "log.jsonl")
    assert [s["step"] for s in steps] == [1] and [v["step"] for v in vals] == [1]
    assert not (tmp_path / "snapshots" / "step_000500.png").exists()
    assert set(np.unique(result.best_texture)) <= {0.0, 1.0}
    assert json.loads((tmp_path / "best.json").read_text()) == vals[0]


def test_resume_of_a_log_without_checkpoint_is_refused_and_nothing_is_touched(detector, body, tmp_path):
    # a run killed before its first checkpoint: --resume must not silently restart at step 1 over its log
    log = "".join(json.dumps({"step": s, "loss": -1.0}) + "\n" for s in (1, 2))
    (tmp_path / "log.jsonl").write_text(log)
    with pytest.raises(CheckpointError, match="records 2 steps but there is no"):
        optimize_texture(_tiny(), detector, tmp_path, body_model=body, progress=False, resume=True)
    assert (tmp_path / "log.jsonl").read_text() == log


@pytest.mark.parametrize("content, match", [
    (b"", "unreadable"),
    (b"not a checkpoint at all", "unreadable"),
    ({"step": 2}, "missing or malformed: best, config, generator, optimizer, pool"),
    ({"generator": {}, "optimizer": {}, "step": 2, "pool": {"generations": [0, 0]}, "best": "", "config": {}},
     "malformed pool or config"),
    ([1, 2, 3], "not a dict"),
])
def test_resume_from_a_corrupt_checkpoint_is_a_checkpoint_error_naming_the_file(detector, body, tmp_path, content,
                                                                              match):
    path = tmp_path / "checkpoints" / "last.pt"
    path.parent.mkdir()
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save(content, path)
    with pytest.raises(CheckpointError, match=match) as info:
        optimize_texture(_tiny(), detector, tmp_path, body_model=body, progress=False, resume=True)
    assert str(path) in str(info.value)


def test_resume_from_a_checkpoint_of_another_generator_size_is_a_checkpoint_error(detector, body, tmp_path):
    optimize_texture(_tiny(iterations=1, pool_size=1), detector, tmp_path, body_model=body, progress=False)
    path = tmp_path / "checkpoints" / "last.pt"
    state = torch.load(path, weights_only=True)
    state["generator"]["fc1.weight"] = torch.zeros(3, 3)
    torch.save(state, path)
    with pytest.raises(CheckpointError, match="does not fit"):
        optimize_texture(_tiny(iterations=2, pool_size=1), detector, tmp_path, body_model=body, progress=False,
                         resume=True)


def _signal_at(monkeypatch, when: str, count: int) -> None:
    """Send SIGINT to this process at the ``count``-th call of ``when`` ("attack_loss", "validate", "clip")."""
    import os
    import signal

    import davis_rig.attack.optimize as opt
    import davis_rig.attack.validation as val
    from davis_rig.attack import eot

    target = {"attack_loss": opt, "validate": val, "clip": eot}[when]
    name = {"attack_loss": "attack_loss", "validate": "window_histograms", "clip": "prepare_clip"}[when]
    original = getattr(target, name)
    calls = []

    def wrapped(*args, **kwargs):
        calls.append(1)
        if len(calls) == count:
            os.kill(os.getpid(), signal.SIGINT)
        return original(*args, **kwargs)

    monkeypatch.setattr(target, name, wrapped)


def test_sigint_checkpoints_the_step_and_resume_continues_exactly(detector, body, tmp_path, monkeypatch):
    from davis_rig.attack.optimize import AttackInterrupted

    cfg = _tiny(iterations=5, checkpoint_every=None, checkpoint_interval_s=1e6, validate_every=2)
    optimize_texture(cfg, detector, tmp_path / "full", body_model=body, progress=False)
    with monkeypatch.context() as patch:
        _signal_at(patch, "attack_loss", 3)  # during step 3
        with pytest.raises(AttackInterrupted) as info:
            optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False)
    assert info.value.step == 3 and info.value.checkpoint == tmp_path / "part" / "checkpoints" / "last.pt"
    assert info.value.signal_name == "SIGINT"
    assert torch.load(info.value.checkpoint, weights_only=True)["step"] == 3
    assert [s["step"] for s in _log(tmp_path / "part" / "log.jsonl")[0]] == [1, 2, 3]
    rest = optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False, resume=True)
    assert rest.steps == 2
    assert (tmp_path / "full" / "log.jsonl").read_text() == (tmp_path / "part" / "log.jsonl").read_text()
    a = torch.load(tmp_path / "full" / "checkpoints" / "last.pt", weights_only=True)
    b = torch.load(tmp_path / "part" / "checkpoints" / "last.pt", weights_only=True)
    for key in a["generator"]:
        assert torch.equal(a["generator"][key], b["generator"][key]), key


def test_sigint_during_validation_validates_first_on_resume(detector, body, tmp_path, monkeypatch):
    from davis_rig.attack.optimize import AttackInterrupted

    cfg = _tiny(iterations=3, num_validation_clips=2, validate_every=2, checkpoint_every=None)
    optimize_texture(cfg, detector, tmp_path / "full", body_model=body, progress=False)
    with monkeypatch.context() as patch:
        _signal_at(patch, "validate", 1)  # the first validation clip of step 2
        with pytest.raises(AttackInterrupted) as info:
            optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False)
    assert info.value.step == 2
    state = torch.load(info.value.checkpoint, weights_only=True)
    assert state["step"] == 2 and state["pending_validation"]
    assert _log(tmp_path / "part" / "log.jsonl")[1] == []  # the abandoned validation left no record
    optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False, resume=True)
    assert (tmp_path / "full" / "log.jsonl").read_text() == (tmp_path / "part" / "log.jsonl").read_text()
    assert (tmp_path / "full" / "best.json").read_text() == (tmp_path / "part" / "best.json").read_text()


def test_sigint_while_preparing_clips_leaves_nothing(detector, body, tmp_path, monkeypatch):
    from davis_rig.attack.optimize import AttackInterrupted

    _signal_at(monkeypatch, "clip", 1)
    with pytest.raises(AttackInterrupted) as info:
        optimize_texture(_tiny(), detector, tmp_path / "run", body_model=body, progress=False)
    assert info.value.step == 0 and info.value.checkpoint is None and not (tmp_path / "run").exists()


def test_a_new_run_that_fails_before_its_first_checkpoint_leaves_nothing(detector, body, tmp_path, monkeypatch):
    import davis_rig.attack.optimize as opt

    original = opt.attack_loss
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("out of memory")
        return original(*args, **kwargs)

    monkeypatch.setattr(opt, "attack_loss", failing)
    cfg = _tiny(checkpoint_every=None, checkpoint_interval_s=1e6)
    with pytest.raises(RuntimeError, match="out of memory"):
        optimize_texture(cfg, detector, tmp_path / "run", body_model=body, progress=False)
    assert not (tmp_path / "run").exists()


def test_checkpoint_period_in_steps_or_wall_time(detector, body, tmp_path, monkeypatch):
    import davis_rig.attack.optimize as opt

    saved = []
    original = opt.atomic_save
    monkeypatch.setattr(opt, "atomic_save", lambda state, path: saved.append(state["step"]) or original(state, path))
    optimize_texture(_tiny(iterations=5, checkpoint_every=2), detector, tmp_path / "steps", body_model=body,
                     progress=False)
    assert saved == [2, 4, 5]  # every 2 steps and after the last one
    saved.clear()
    optimize_texture(_tiny(iterations=3, checkpoint_every=None, checkpoint_interval_s=1e6), detector,
                     tmp_path / "long", body_model=body, progress=False, max_steps=2)
    assert saved == [2]  # none due by time: only after the last step of the call
    saved.clear()
    optimize_texture(_tiny(iterations=3, checkpoint_every=None, checkpoint_interval_s=1e-9), detector,
                     tmp_path / "short", body_model=body, progress=False)
    assert saved == [1, 2, 3]
    # the period is free on resume
    optimize_texture(_tiny(iterations=3, checkpoint_every=5), detector, tmp_path / "long", body_model=body,
                     progress=False, resume=True)


def test_pool_clip_histograms_and_validation_use_the_clip_window(body, detector):
    # EoTConfig.window_us spaces the window ends; the histograms must cover the same span (not the 50 ms default)
    from davis_rig.attack.evaluate import detect_windows
    from davis_rig.attack.optimize import clip_histograms, validate
    from davis_rig.events.v2e_torch import v2e_histograms

    config = replace(TINY_EOT, window_us=25_000)
    spec, sensor = draw_scene(config, 7, body.num_shapes)
    clip = prepare_clip(spec, sensor, body, 4, config=config)
    empty = torch.zeros(0, dtype=torch.int64)
    clip = replace(clip, noise_cell=empty, noise_count=empty.float())
    assert clip.window_us == 25_000 and np.array_equal(np.diff(clip.window_end_us), [25_000, 25_000])
    grid = torch.rand(4, 4, generator=torch.Generator().manual_seed(0))
    expected = torch.clamp(v2e_histograms(clip.video(grid).double(), clip.t_us, clip.window_end_us,
                                          window_us=25_000, count_cutoff=None, threshold_on=clip.threshold.double(),
                                          threshold_off=clip.threshold.double()), max=10.0).float()
    hist = clip_histograms(grid, clip, gradient="ste")
    assert torch.equal(hist, expected) and hist.sum() > 0
    hard = (grid > 0.5).float().numpy()
    with torch.no_grad():
        decoded, _ = detect_windows(detector, clip.video(torch.as_tensor(hard)), clip.t_us, clip.window_end_us,
                                    window_us=25_000)
    top = np.mean([(d[:, 4] * d[:, 6]).max() for d in decoded])
    assert validate(hard, [clip], detector, 0.25)["mean_top_score"] == pytest.approx(top)


def test_validation_and_refinement_clips_draw_the_training_motions(body, monkeypatch):
    # with --amass/--bvh the pool uses a training motion in half of its clips; validation and the refinement's
    # clips must come from the same distribution (they used to be walk cycles only); without motions they are
    # the same draws as before
    import davis_rig.attack.validation as val
    from davis_rig.scene.gait import generate_gait

    motion = generate_gait()
    drawn = []
    monkeypatch.setattr(val, "prepare_clip", lambda spec, *a, **kw: drawn.append(spec) or spec)
    cfg = _tiny()
    val.validation_clips(cfg, body, None, 8, motions=(motion,))
    assert any(spec.motion is motion for spec in drawn)
    seeds = [slot_seed(cfg.seed + VAL_SEED_OFFSET, i, 0) for i in range(8)]
    assert drawn == [draw_scene(cfg.eot, s, body.num_shapes, (motion,))[0] for s in seeds]
    drawn.clear()
    val.validation_clips(cfg, body, None, 8)
    assert drawn == [draw_scene(cfg.eot, s, body.num_shapes)[0] for s in seeds]
    assert all(spec.motion is None for spec in drawn)


def test_optimize_passes_the_training_motions_to_validation_and_refinement(detector, body, tmp_path, monkeypatch):
    import davis_rig.attack.optimize as opt
    from davis_rig.scene.gait import generate_gait

    motions = (generate_gait(),)
    seen = []
    original = opt.validation_clips

    def recording(config, model, mask, num, seed_offset=VAL_SEED_OFFSET, motions=(), on_clip=None):
        seen.append((seed_offset, motions))
        return original(config, model, mask, num, seed_offset, motions, on_clip)

    monkeypatch.setattr(opt, "validation_clips", recording)
    cfg = _tiny(iterations=1, pool_size=1, refine_passes=1, refine_clips=1, grid_n=2)
    optimize_texture(cfg, detector, tmp_path, body_model=body, motions=motions, progress=False)
    assert seen == [(VAL_SEED_OFFSET, motions), (REFINE_SEED_OFFSET, motions)]


def test_the_official_lr_schedule_is_the_default_and_a_run_before_it_resumes_as_constant(detector, body, tmp_path):
    from davis_rig.attack.lr_schedule import cosine_restarts_lr

    assert (AttackConfig().lr_schedule, AttackConfig().lr_min) == ("cosine_restarts", 1e-7)
    cfg = _tiny(iterations=3, lr=0.05)
    optimize_texture(cfg, detector, tmp_path / "cos", body_model=body, progress=False)
    assert [r["lr"] for r in _log(tmp_path / "cos" / "log.jsonl")[0]] == [cosine_restarts_lr(k, 0.05, 3)
                                                                          for k in range(3)]
    old = _tiny(iterations=2, lr=0.05, lr_schedule="constant", eot=replace(TINY_EOT, walk="bundled"))
    optimize_texture(old, detector, tmp_path / "old", body_model=body, progress=False)
    path = tmp_path / "old" / "checkpoints" / "last.pt"
    state = torch.load(path, weights_only=True)
    for name in ("lr_schedule", "lr_min", "lr_period"):  # a run written before the schedule existed ...
        del state["config"][name]
    for name in ("walk", "test_sensor_probability"):  # ... the natural walk and the test sensor
        del state["config"]["eot"][name]
    torch.save(state, path)
    with pytest.raises(CheckpointError, match="lr_schedule"):
        optimize_texture(replace(old, lr_schedule="cosine_restarts", iterations=3), detector, tmp_path / "old",
                         body_model=body, progress=False, resume=True)
    for eot in (replace(old.eot, walk="natural"), replace(old.eot, test_sensor_probability=0.5)):
        with pytest.raises(CheckpointError, match="eot"):
            optimize_texture(replace(old, eot=eot, iterations=3), detector, tmp_path / "old", body_model=body,
                             progress=False, resume=True)
    optimize_texture(replace(old, iterations=3), detector, tmp_path / "old", body_model=body, progress=False,
                     resume=True)
    assert [r["lr"] for r in _log(tmp_path / "old" / "log.jsonl")[0]] == [0.05] * 3


def test_the_test_sensor_is_drawn_inside_the_training_distribution():
    mixed, noisy = EoTConfig(), EoTConfig(test_sensor_probability=0.0)
    assert mixed.test_sensor_probability == 0.5
    draws = [(draw_scene(mixed, s, 24), draw_scene(noisy, s, 24)) for s in range(200)]
    test = [m[1] for m, _ in draws if m[1]["test_sensor"]]
    assert 70 < len(test) < 130  # about half
    assert all(t["threshold"] == 0.2 and t["threshold_sigma"] == 0.0 and t["noise_rate_hz"] == 0.0 for t in test)
    assert all(m[0] == n[0] for m, n in draws)  # the scenes are the same draws whatever the probability
    assert all(m[1] == n[1] for m, n in draws if not m[1]["test_sensor"])
    with pytest.raises(ValueError, match="test_sensor_probability"):
        EoTConfig(test_sensor_probability=1.5)


def test_validation_scores_as_trained_and_as_tested_batched(body, detector):
    from davis_rig.attack.optimize import validate

    ideal = replace(TINY_EOT, test_sensor_probability=1.0)
    clips = [ClipPool(eot, body, 4, size=1, base_seed=3).clips[0] for eot in (ideal, TINY_EOT, TINY_EOT)]
    assert clips[1].noise_cell.numel() > 0  # a noisy training sensor
    grid = np.ones((4, 4), np.float32)
    train = ("dvs", "interval")
    same = validate(grid, clips[:1], detector, 0.25, train_path=train)
    assert same["transfer_gap"] == same["mean_top_score"] - same["train_top_score"]
    both = validate(grid, clips, detector, 0.25, train_path=train, batch=2)
    alone = [validate(grid, [c], detector, 0.25, train_path=train, batch=1) for c in clips]
    for key in ("mean_top_score", "train_top_score"):
        assert both[key] == pytest.approx(np.mean([a[key] for a in alone]), abs=1e-5)
    assert validate(grid, clips[:1], detector, 0.25)["mean_top_score"] == pytest.approx(same["mean_top_score"])
    assert set(validate(grid, clips[:1], detector, 0.25, train_path=train, test_path=False)) == {
        "train_SeqASR", "train_top_score"}


def test_validation_records_carry_the_transfer_gap_and_selection_uses_the_training_path(detector, body, tmp_path):
    cfg = _tiny(iterations=2, validate_every=1, num_validation_clips=2, eot=replace(TINY_EOT,
                                                                                  test_sensor_probability=0.5))
    result = optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    vals = _log(tmp_path / "log.jsonl")[1]
    for v in vals:
        assert v["transfer_gap"] == pytest.approx(v["mean_top_score"] - v["train_top_score"])
    assert result.final_validation == vals[-1]
    assert better({"SeqASR": 0.0, "mean_top_score": 0.9, "train_SeqASR": 0.5, "train_top_score": 0.1},
                   {"SeqASR": 1.0, "mean_top_score": 0.1, "train_SeqASR": 0.0, "train_top_score": 0.9})


def test_person_anchor_loss_scores_the_anchors_on_the_persons_box(detector, body):
    from davis_rig.attack.loss import anchor_cells, anchors_on_boxes
    from davis_rig.attack.optimize import attack_loss

    clips = ClipPool(TINY_EOT, body, 4, size=2, base_seed=3).sample(0, 2)
    grid = torch.full((4, 4), 0.5)
    every, person = (attack_loss(grid, clips, detector, _tiny(pool_size=2, clips_per_step=2, loss_anchors=anchors))
                     for anchors in ("all", "person"))
    cells = anchor_cells(detector.config.in_res_hw, detector.config.head_strides)
    boxes = torch.as_tensor(np.stack([c.boxes for c in clips], axis=1))
    expected = int(anchors_on_boxes(cells, boxes).sum())
    assert 0 < int(person.num_anchors) == expected < int(every.num_anchors)
    assert person.total.item() != every.total.item()
    with pytest.raises(ValueError, match="loss_anchors"):
        AttackConfig(loss_anchors="box")


@pytest.mark.parametrize("events", ["exact", "official_relaxed"])
def test_validation_simulates_the_active_box_only_with_the_whole_frames_result(body, detector, events):
    from davis_rig.attack.evaluate import detect_windows
    from davis_rig.attack.optimize import validate

    clip = ClipPool(TINY_EOT, body, 4, size=1, base_seed=3).clips[0]
    grid = (np.random.default_rng(1).random((4, 4)) > 0.5).astype(np.float32)
    with torch.no_grad():
        decoded, _ = detect_windows(detector, clip.video(torch.as_tensor(grid)), clip.t_us, clip.window_end_us,
                                    events=events)
    whole_frame = np.mean([(d[:, 4] * d[:, 6]).max() for d in decoded])
    assert validate(grid, [clip], detector, 0.25, events)["mean_top_score"] == pytest.approx(whole_frame, abs=1e-6)


def test_detector_step_runs_the_fixed_shape_loss_and_resumes_under_another(detector, body, tmp_path, monkeypatch):
    """config.detector_step other than eager: the loop calls FixedShapeAttackLoss (built once) and learns what the
    eager loop learns; the mode only changes speed, so a run resumes under another one."""
    import davis_rig.attack.optimize as opt
    from davis_rig.attack.fixed_step import FixedShapeAttackLoss

    built = []

    def recording(det, config, mode):  # CPU: the "compile" mode's contract, run eagerly
        built.append(mode)
        return FixedShapeAttackLoss(det, config, mode="eager")

    monkeypatch.setattr(opt, "FixedShapeAttackLoss", recording)
    eager = optimize_texture(_tiny(), detector, tmp_path / "eager", body_model=body, progress=False)
    fixed = optimize_texture(_tiny(detector_step="compile"), detector, tmp_path / "fixed", body_model=body,
                             progress=False, max_steps=2)
    assert built == ["compile"]
    rest = optimize_texture(_tiny(), detector, tmp_path / "fixed", body_model=body, progress=False, resume=True)
    assert (fixed.steps, rest.steps) == (2, 2)
    assert _log(tmp_path / "eager" / "log.jsonl")[0] == _log(tmp_path / "fixed" / "log.jsonl")[0]
    assert np.array_equal(eager.texture, rest.texture)


@pytest.mark.parametrize("start, value", [("white", 1.0), ("black", 0.0)])
def test_a_plain_start_optimises_from_the_plain_texture(detector, body, tmp_path, start, value):
    cfg = _tiny(iterations=1, pool_size=1, refresh_every=1000, lr=1e-9, lr_min=0.0, start=start,
                checkpoint_every=1000, snapshot_every=1000)
    optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    plain = np.full((cfg.grid_n, cfg.grid_n), value, np.float32)
    assert np.array_equal(np.load(tmp_path / "texture.npy"), plain)
    # the plain start is itself a candidate: validated at step 0 (and after the last step)
    _, vals = _log(tmp_path / "log.jsonl")
    assert [v["step"] for v in vals] == [0, 1]
    assert np.array_equal(np.load(tmp_path / "best_texture.npy"), plain)


def test_a_grid_start_optimises_from_that_grid_and_is_checked_against_the_cells(detector, body, tmp_path):
    from davis_rig.errors import ConfigError

    cfg = _tiny(iterations=1, pool_size=1, refresh_every=1000, lr=1e-9, lr_min=0.0, checkpoint_every=1000,
                snapshot_every=1000)
    grid = (np.arange(cfg.grid_n ** 2).reshape(cfg.grid_n, cfg.grid_n) % 3 == 0).astype(np.float32)
    cfg = replace(cfg, start="grid", start_grid=tuple(map(tuple, grid.tolist())))
    optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    assert np.array_equal(np.load(tmp_path / "texture.npy"), grid)
    _, vals = _log(tmp_path / "log.jsonl")
    assert [v["step"] for v in vals] == [0, 1]  # validated at step 0, as a plain start
    with pytest.raises(ConfigError, match="start_grid"):
        replace(cfg, start_grid=None)
    with pytest.raises(ConfigError, match="start_grid"):
        replace(cfg, start_grid=((0.0, 1.0), (1.0, 0.0)))  # not grid_n x grid_n
    with pytest.raises(ConfigError, match="start_grid"):
        replace(cfg, start="white")  # a grid given for a plain start


def test_a_stop_during_the_plain_starts_validation_leaves_nothing(detector, body, tmp_path, monkeypatch):
    import davis_rig.attack.optimize as opt
    from davis_rig.stop import StopRequested

    def stopped(*args, **kwargs):
        raise StopRequested()

    monkeypatch.setattr(opt, "validate", stopped)
    cfg = _tiny(iterations=1, pool_size=1, refresh_every=1000, start="black", checkpoint_every=1000,
                snapshot_every=1000)
    with pytest.raises(opt.AttackInterrupted) as info:
        optimize_texture(cfg, detector, tmp_path / "run", body_model=body, progress=False)
    assert info.value.checkpoint is None and not (tmp_path / "run").exists()


def test_sampled_binarization_cuts_every_step_afresh_and_resumes_exactly(detector, body, tmp_path, monkeypatch):
    import davis_rig.attack.optimize as optimize_module
    from davis_rig.attack.step import binarization_threshold

    seen = []

    def recording_binarize(u, alpha=1.0, threshold=0.5):
        seen.append(threshold)
        return binarize_ste(u, alpha, threshold)

    monkeypatch.setattr(optimize_module, "binarize_ste", recording_binarize)
    cfg = _tiny(binarize="sample", alpha_schedule="hard")
    full = optimize_texture(cfg, detector, tmp_path / "full", body_model=body, progress=False)
    cuts = seen[:4]
    assert all(isinstance(c, torch.Tensor) and c.shape == (4, 4) for c in cuts)
    assert all(torch.equal(c, binarization_threshold("sample", cfg.seed, step, c)) for step, c in enumerate(cuts))
    assert not any(torch.equal(cuts[i], cuts[j]) for i in range(4) for j in range(i + 1, 4))
    optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False, max_steps=2)
    rest = optimize_texture(cfg, detector, tmp_path / "part", body_model=body, progress=False, resume=True)
    assert _log(tmp_path / "full" / "log.jsonl")[0] == _log(tmp_path / "part" / "log.jsonl")[0]
    assert np.array_equal(full.texture, rest.texture)
    seen.clear()
    optimize_texture(_tiny(iterations=1), detector, tmp_path / "paper", body_model=body, progress=False)
    assert seen == [0.5]  # the paper's cut by default
    with pytest.raises(ValueError, match="binarize"):
        AttackConfig(binarize="gumbel")


def test_a_resume_against_other_weights_is_refused(detector, body, tmp_path):
    import copy

    optimize_texture(_tiny(iterations=1, pool_size=1), detector, tmp_path, body_model=body, progress=False)
    other = copy.deepcopy(detector)
    with torch.no_grad():
        next(other.parameters()).mul_(1.05)
    with pytest.raises(CheckpointError, match="written against another detector"):
        optimize_texture(_tiny(iterations=2, pool_size=1), other, tmp_path, body_model=body, progress=False,
                         resume=True)
    result = optimize_texture(_tiny(iterations=2, pool_size=1), detector, tmp_path, body_model=body, progress=False,
                              resume=True)  # the run's own detector continues it
    assert result.steps == 1
