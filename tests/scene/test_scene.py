"""Scene composition: clip timing, placement, heading, motions, jitter, labels, gradients to the texture."""

import math

import numpy as np
import pytest
import torch

from davis_rig.scene.camera import EgoMotion, EoTJitter
from davis_rig.scene.motion import Motion, loop, sample
from davis_rig.scene.scene import OFFICIAL_PLAYBACK_SPEED, SceneSpec, render_clip, scene_camera, scene_vertices
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID


def test_clip_timing_and_render_rate():
    spec = SceneSpec(duration_s=0.05, t0_us=1000)
    assert spec.num_frames == 10  # one 50 ms window at 200 fps = 10 frames
    assert spec.frame_times_us().tolist() == [1000 + 5000 * k for k in range(10)]
    assert SceneSpec(render_rate_hz=240, duration_s=0.05).num_frames == 12
    with pytest.raises(ValueError, match="render_rate_hz"):
        SceneSpec(render_rate_hz=120)


def test_render_clip_outputs(model):
    spec = SceneSpec(duration_s=0.02, supersample=1, background="random", light="random", seed=3)
    clip = render_clip(spec, model=model, part_labels=True)
    t, h, w = clip.video.shape
    assert (t, h, w) == (4, 240, 304)
    assert clip.video.dtype == torch.float32
    assert float(clip.video.min()) >= 0.0 and float(clip.video.max()) <= 1.0
    assert clip.t_us.tolist() == [0, 5000, 10000, 15000]
    assert np.isfinite(clip.boxes).all()
    heights = clip.boxes[:, 3] - clip.boxes[:, 1]
    person_m = float(model.asset.metadata["heights_m"][0]) if "heights_m" in model.asset.metadata else 1.75
    assert np.all(np.abs(heights - 150 * person_m / 1.75) < 15)  # middle scale, walking posture
    centre = (clip.boxes[:, 0] + clip.boxes[:, 2]) / 2
    assert np.all(np.abs(centre - 152) < 30)  # mid-clip at the optical axis
    assert clip.part_labels.shape == (4, 240, 304) and clip.part_labels.dtype == np.uint8
    labels = clip.labels()
    assert labels.dtype == BBOX_DTYPE and len(labels) == 4
    assert np.all(labels["class_id"] == PEDESTRIAN_CLASS_ID)
    np.testing.assert_allclose(labels["h"], heights)
    # same seed -> same clip
    again = render_clip(spec, model=model)
    assert torch.equal(again.video, clip.video)


def test_heading_walks_right_and_towards_camera(model):
    spec = SceneSpec(duration_s=0.3, supersample=1, heading_rad=math.pi / 2, walk="bundled")
    v = scene_vertices(spec, model)
    x = v[:, :, 0].mean(1).numpy()
    assert x[-1] - x[0] == pytest.approx(model.asset.walk_cycle(0).speed_m_s * (spec.num_frames - 1) / 200, rel=0.15)
    towards = scene_vertices(SceneSpec(duration_s=0.3, heading_rad=0.0), model)
    y = towards[:, :, 1].mean(1).numpy()
    assert y[-1] < y[0]  # the camera is on the -Y side


def test_motion_equals_the_walk_cycle_in_place(model):
    walk = model.asset.walk_cycle(2)
    motion = Motion(np.array(walk.rotations_wxyz), np.array(walk.root_translation_m), walk.fps_hz)
    spec_walk = SceneSpec(shape_index=2, advance=False, duration_s=0.1, walk="bundled")
    spec_motion = SceneSpec(shape_index=2, motion=motion, duration_s=0.1)
    a = scene_vertices(spec_walk, model)
    b = scene_vertices(spec_motion, model)
    # the Motion path centres the root at mid-clip; compare shapes of the body up to that translation. Between
    # stored frames the walk path nlerps and the Motion path slerps: where the settled walk's knee flexes by up to
    # ~50 degrees in one 24 Hz frame (toe-off), the two interpolants differ by up to ~0.6 mm at the foot
    shift = (a - b).mean(dim=1, keepdim=True)
    np.testing.assert_allclose((a - b - shift).numpy(), 0.0, atol=1e-3)
    rot, root = sample(motion, np.array([0.0, 1.0 / walk.fps_hz, 100.0]))
    np.testing.assert_allclose(rot[1], walk.rotations_wxyz[1] * np.sign((rot[1] * walk.rotations_wxyz[1]).sum(-1))[:, None], atol=1e-6)
    np.testing.assert_allclose(root[2], walk.root_translation_m[-1], atol=1e-6)  # clamped at the end


def test_cyclic_motion_wraps_around_its_period(asset, model):
    """A cycle (``cycle_advance_m`` set) plays on past its last frame: one period later, the same pose."""
    walk = Motion.from_walk_cycle(asset, 0, advance=False)
    period_s = walk.duration_s
    fps = 200.0
    a = scene_vertices(SceneSpec(motion=walk, duration_s=0.02, render_rate_hz=fps), model)
    b = scene_vertices(SceneSpec(motion=walk, motion_start_s=period_s, duration_s=0.02, render_rate_hz=fps), model)
    np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-5)
    twice = loop(walk, 2)
    c = scene_vertices(SceneSpec(motion=twice, motion_start_s=period_s, duration_s=0.02, render_rate_hz=fps), model)
    np.testing.assert_allclose(b.numpy(), c.numpy(), atol=1e-5)


@pytest.mark.parametrize("advance", [False, True])
def test_playback_speed_samples_the_motion_faster(model, advance):
    """Speed 2 at 200 fps poses frame k as real time poses frame 2k (same mid-clip centring when walking)."""
    fast = scene_vertices(SceneSpec(advance=advance, playback_speed=2.0, duration_s=0.05), model)  # 10 frames
    real = scene_vertices(SceneSpec(advance=advance, duration_s=0.095), model)  # 19 frames
    assert fast.shape[0] == 10 and real.shape[0] == 19
    np.testing.assert_allclose(fast.numpy(), real[::2].numpy(), atol=1e-6)
    assert OFFICIAL_PLAYBACK_SPEED == pytest.approx(5 / 3)  # 10 frames at 120 fps in a 50 ms window
    with pytest.raises(ValueError, match="playback_speed"):
        SceneSpec(playback_speed=0.0)


def test_jitter_and_ego_motion_cameras():
    base_r, base_t = scene_camera(SceneSpec(duration_s=0.05))
    assert np.allclose(base_r, base_r[0]) and np.allclose(base_t, base_t[0])
    jitter = EoTJitter(rotation_probability=1.0, distance_probability=1.0)
    r1, t1 = scene_camera(SceneSpec(duration_s=0.05, jitter=jitter, seed=1))
    r2, t2 = scene_camera(SceneSpec(duration_s=0.05, jitter=jitter, seed=1))
    assert np.array_equal(r1, r2) and np.array_equal(t1, t2)
    assert not np.allclose(r1, base_r)
    ego = EgoMotion(pan_amplitude_rad=0.05, period_s=0.2)
    r3, _ = scene_camera(SceneSpec(duration_s=0.05, ego_motion=ego))
    assert not np.allclose(r3[0], r3[5])


def test_texture_gradient_flows_through_the_clip(model):
    from davis_rig.scene.masks import part_mask

    grid = torch.full((10, 10), 0.5, requires_grad=True)
    clip = render_clip(SceneSpec(duration_s=0.01, supersample=1), grid, model=model, mask=part_mask(("torso",)))
    clip.video.sum().backward()
    assert torch.isfinite(grid.grad).all()
    assert (grid.grad > 0).sum() >= 3  # the visible torso cells
    assert (grid.grad == 0).sum() > 50  # cells not on the torso (or not visible) get nothing


def test_ego_motion_moves_the_background(model):
    from davis_rig.scene.background import stripes

    pattern = stripes((240, 304), period_px=16, low=0.0, high=1.0)
    still = render_clip(SceneSpec(duration_s=0.02, supersample=1, background=pattern), model=model)
    assert still.background.shape == (240, 304)
    pan = EgoMotion(pan_amplitude_rad=0.02, period_s=0.2)
    moving = render_clip(SceneSpec(duration_s=0.02, supersample=1, background=pattern, ego_motion=pan), model=model)
    assert moving.background.shape == (4, 240, 304)
    np.testing.assert_allclose(moving.background[0].numpy(), pattern, atol=1e-5)  # first frame: rest pose
    assert not torch.allclose(moving.background[3], moving.background[0], atol=0.05)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)")
def test_render_clip_on_cuda_matches_cpu(model):
    from davis_rig.scene.body import BodyModel

    grid = torch.rand(10, 10)
    spec = SceneSpec(duration_s=0.02, background="random", light="random", seed=4)
    cpu = render_clip(spec, grid, model=model)
    gpu = render_clip(spec, grid.cuda(), model=BodyModel(model.asset, device="cuda"))
    assert (cpu.video - gpu.video.cpu()).abs().mean() < 1e-3
    np.testing.assert_allclose(cpu.boxes, gpu.boxes, atol=1.0)


def test_scene_accepts_a_motion_of_rotation_matrices(model):
    from davis_rig.scene.body import quaternion_to_matrix

    walk = model.asset.walk_cycle(0)
    mats = quaternion_to_matrix(torch.as_tensor(np.array(walk.rotations_wxyz))).numpy()
    a = scene_vertices(SceneSpec(motion=Motion(mats, np.array(walk.root_translation_m), walk.fps_hz), duration_s=0.02), model)
    b = scene_vertices(SceneSpec(motion=Motion(np.array(walk.rotations_wxyz), np.array(walk.root_translation_m), walk.fps_hz), duration_s=0.02), model)
    np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-5)
