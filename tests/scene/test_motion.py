"""davis_rig.scene.motion: quaternions, slerp resampling, loops, heading/turning, concatenation, ground contact."""

import math
from dataclasses import replace

import numpy as np
import pytest

from davis_rig.errors import ShapeError
from davis_rig.scene.motion import (
    Motion,
    concatenate,
    contact_slip,
    foot_vertex_ids,
    ground_contact,
    lock_stance_foot,
    lowest_vertex_z,
    loop,
    motion_from_world_rotations,
    quat_from_matrix,
    quat_from_rotvec,
    quat_multiply,
    quat_slerp,
    quat_to_matrix,
    resample,
    rotate_heading,
    rotation_about_z,
    sample,
    turn,
)

torch = pytest.importorskip("torch")


def _random_quats(rng, shape):
    q = rng.normal(size=shape + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _random_motion(rng, frames=7, bones=5, fps=10.0, **kw):
    return Motion(_random_quats(rng, (frames, bones)), rng.normal(size=(frames, 3)), fps, **kw)


# ------------------------------------------------------------------ quaternions
def test_quaternion_matrix_round_trip_and_product():
    rng = np.random.default_rng(0)
    q = _random_quats(rng, (200,))
    m = quat_to_matrix(q)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", m, m), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    q2 = quat_from_matrix(m)
    np.testing.assert_allclose(np.abs(np.sum(q2 * q, -1)), 1.0, atol=1e-12)  # same rotation up to sign
    assert (q2[:, 0] >= 0).all()
    a, b = q[:100], q[100:]
    np.testing.assert_allclose(quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-12)


def test_rotvec_is_rotation_about_axis():
    q = quat_from_rotvec(np.array([[math.radians(30), 0, 0], [0, 0, 0], [0, 0, math.pi]]))
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    np.testing.assert_allclose(quat_to_matrix(q[0]), [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-15)
    np.testing.assert_allclose(q[1], [1, 0, 0, 0])
    np.testing.assert_allclose(quat_to_matrix(q[2]), np.diag([-1.0, -1.0, 1.0]), atol=1e-15)
    np.testing.assert_allclose(rotation_about_z(math.pi / 2) @ [0, -1, 0], [1, 0, 0], atol=1e-15)


def test_slerp_unit_norm_endpoints_and_constant_speed():
    rng = np.random.default_rng(1)
    q0, q1 = _random_quats(rng, (50,)), _random_quats(rng, (50,))
    alpha = rng.uniform(0, 1, 50)
    out = quat_slerp(q0, q1, alpha)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_slerp(q0, q1, np.zeros(50)), q0, atol=1e-12)
    end = quat_slerp(q0, q1, np.ones(50))
    np.testing.assert_allclose(np.abs(np.sum(end * q1, -1)), 1.0, atol=1e-12)
    # angle travelled is alpha times the (shortest) angle between the endpoints
    total = 2 * np.arccos(np.clip(np.abs(np.sum(q0 * q1, -1)), 0, 1))
    part = 2 * np.arccos(np.clip(np.abs(np.sum(q0 * out, -1)), 0, 1))
    np.testing.assert_allclose(part, alpha * total, atol=1e-6)
    same = quat_slerp(q0, q0, alpha)  # degenerate arc
    np.testing.assert_allclose(same, q0, atol=1e-12)


# ------------------------------------------------------------------ Motion, sampling
def test_motion_validates_and_is_immutable():
    rng = np.random.default_rng(2)
    m = _random_motion(rng)
    assert m.num_frames == 7 and m.num_bones == 5 and m.duration_s == pytest.approx(0.6)
    with pytest.raises(ValueError):
        m.rotations_wxyz[0, 0, 0] = 1.0
    with pytest.raises(ShapeError):
        Motion(np.zeros((3, 2, 3)), np.zeros((3, 3)), 10.0)
    with pytest.raises(ShapeError):
        Motion(np.ones((3, 2, 4)), np.zeros((4, 3)), 10.0)
    with pytest.raises(ValueError):
        Motion(np.ones((3, 2, 4)), np.zeros((3, 3)), 0.0)
    with pytest.raises(ShapeError):
        Motion(np.ones((3, 2, 4)), np.zeros((3, 3)), 10.0, cycle_advance_m=np.zeros(2))
    with pytest.raises(ShapeError):
        m.check_rig(["a"] * 4)


def test_resample_is_exact_at_original_frames():
    rng = np.random.default_rng(3)
    m = _random_motion(rng, frames=9, fps=24.0)
    up = resample(m, 240.0)
    assert up.num_frames == 81 and up.fps_hz == 240.0 and not up.is_cycle
    q = up.rotations_wxyz[::10].astype(np.float64)
    sign = np.sign(np.sum(q * m.rotations_wxyz, -1, keepdims=True))
    np.testing.assert_allclose(q * sign, m.rotations_wxyz, atol=1e-6)
    np.testing.assert_allclose(up.root_translation_m[::10], m.root_translation_m, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(up.rotations_wxyz, axis=-1), 1.0, atol=1e-6)
    # the root is linear between frames
    np.testing.assert_allclose(up.root_translation_m[5], 0.5 * (m.root_translation_m[0] + m.root_translation_m[1]),
                               atol=1e-6)
    # clips clamp outside [0, duration]
    rot, root = sample(m, [-1.0, 10.0])
    np.testing.assert_allclose(root, m.root_translation_m[[0, -1]], atol=1e-6)


def test_cycle_wraps_and_advances():
    rng = np.random.default_rng(4)
    adv = np.array([0.0, -1.2, 0.0])
    m = _random_motion(rng, frames=8, fps=8.0, cycle_advance_m=adv)
    assert m.is_cycle and m.duration_s == pytest.approx(1.0) and m.speed_m_s == pytest.approx(1.2)
    rot, root = sample(m, [0.0, 1.0, 2.25, -1.0])
    np.testing.assert_allclose(root[1], m.root_translation_m[0] + adv, atol=1e-6)
    np.testing.assert_allclose(root[2], m.root_translation_m[2] + 2 * adv, atol=1e-6)
    np.testing.assert_allclose(root[3], m.root_translation_m[0] - adv, atol=1e-6)
    np.testing.assert_allclose(np.abs(np.sum(rot[1] * m.rotations_wxyz[0], -1)), 1.0, atol=1e-6)
    # between the last frame and the next period's first frame
    _, mid = sample(m, [7.5 / 8.0])
    np.testing.assert_allclose(mid[0], 0.5 * (m.root_translation_m[7] + m.root_translation_m[0] + adv), atol=1e-6)
    up = resample(m, 200.0)
    assert up.is_cycle and up.num_frames == 200 and up.speed_m_s == pytest.approx(1.2)
    np.testing.assert_allclose(up.root_translation_m[::25], m.root_translation_m, atol=1e-6)
    long = loop(m, 3)
    assert long.num_frames == 24 and np.allclose(long.cycle_advance_m, 3 * adv)
    np.testing.assert_allclose(long.root_translation_m[16:], m.root_translation_m + 2 * adv, atol=1e-6)
    with pytest.raises(ValueError):
        loop(_random_motion(rng), 2)
    with pytest.raises(ValueError):
        sample(_random_motion(rng), [0.0], loop=True)


def test_render_rate_gives_ten_frames_per_window(asset):
    walk = Motion.from_walk_cycle(asset, 0)
    assert walk.speed_m_s == pytest.approx(float(asset.walk_speed_m_s[0]), rel=1e-6)
    clip = resample(walk, 200.0, duration_s=0.5)
    assert clip.num_frames == 101
    t_us = np.round(clip.frame_times_s[:-1] * 1e6).astype(np.int64)
    per_window = np.bincount(t_us // 50_000)  # half-open 50 ms windows
    assert (per_window == 10).all()


def test_motion_accepts_rotation_matrices():
    from davis_rig.scene.body import quaternion_to_matrix

    rng = np.random.default_rng(0)
    q = _random_quats(rng, (10, 5))
    q[..., 0] = np.abs(q[..., 0])
    q[0, :3] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]  # identity and 180-degree turns (w = 0)
    m = quaternion_to_matrix(torch.as_tensor(q)).numpy()
    root = rng.normal(size=(10, 3))
    from_matrices = Motion(m, root, 30.0)
    assert from_matrices.rotations_wxyz.shape == (10, 5, 4) and from_matrices.rotations_wxyz.dtype == np.float32
    np.testing.assert_allclose(from_matrices.rotations_wxyz, q, atol=1e-6)  # w >= 0 -> the same sign as q
    np.testing.assert_allclose(quat_to_matrix(from_matrices.rotations_wxyz), m, atol=1e-6)
    with pytest.raises(ShapeError, match=r"\[T, J, 4\]"):
        Motion(m[..., :2], root, 30.0)  # [T, J, 3, 2] is neither


# ------------------------------------------------------------------ heading, turning, concatenation
def test_rotate_heading_rotates_the_posed_body(asset, model64):
    walk = loop(Motion.from_walk_cycle(asset, 0), 1)
    frames = resample(walk, walk.fps_hz, duration_s=3 / walk.fps_hz, loop=True)
    turned = rotate_heading(frames, math.pi / 2, pivot_m=(0.3, -0.2), root_rest_pose=asset.rest_bone_poses[0, 0])
    v0 = model64.pose(0, torch.as_tensor(frames.rotations_wxyz.copy()), torch.as_tensor(frames.root_translation_m.copy()))
    v1 = model64.pose(0, torch.as_tensor(turned.rotations_wxyz.copy()), torch.as_tensor(turned.root_translation_m.copy()))
    centre = np.array([0.3, -0.2, 0.0])
    expected = (v0.numpy() - centre) @ rotation_about_z(math.pi / 2).T + centre
    np.testing.assert_allclose(v1.numpy(), expected, atol=2e-6)  # float32 storage of the motion
    cyc = rotate_heading(walk, math.pi / 2)
    np.testing.assert_allclose(cyc.cycle_advance_m, [-walk.cycle_advance_m[1], 0, 0], atol=1e-12)


def test_turn_bends_the_path_and_keeps_the_speed():
    frames = 101
    root = np.zeros((frames, 3))
    root[:, 1] = -np.linspace(0, 1.0, frames)  # 1 m straight towards -Y in 1 s
    m = Motion(np.tile([1.0, 0, 0, 0], (frames, 3, 1)), root, 100.0)
    rate = math.pi / 2
    t = turn(m, rate)
    steps = np.diff(t.root_translation_m[:, :2].astype(np.float64), axis=0)
    np.testing.assert_allclose(np.linalg.norm(steps, axis=1), 0.01, rtol=1e-5)
    heading = np.arctan2(steps[:, 0], -steps[:, 1])
    np.testing.assert_allclose(heading, rate * (np.arange(100) + 0.5) / 100, atol=1e-5)
    # the root's orientation turns with it
    q_end = t.rotations_wxyz[-1, 0].astype(np.float64)
    np.testing.assert_allclose(quat_to_matrix(q_end), rotation_about_z(rate), atol=1e-6)
    np.testing.assert_array_equal(t.rotations_wxyz[:, 1:], m.rotations_wxyz[:, 1:])


def test_concatenate_continues_the_path():
    rng = np.random.default_rng(5)
    a = _random_motion(rng, frames=6, fps=10.0, name="a")
    b = _random_motion(rng, frames=5, fps=10.0, name="b")
    cat = concatenate([a, b])
    assert cat.num_frames == 11 and cat.name == "a+b"
    step = a.root_translation_m[-1] - a.root_translation_m[-2]
    np.testing.assert_allclose(cat.root_translation_m[6, :2], a.root_translation_m[-1, :2] + step[:2], atol=1e-6)
    np.testing.assert_allclose(cat.root_translation_m[6, 2], b.root_translation_m[0, 2], atol=1e-6)
    np.testing.assert_allclose(np.diff(cat.root_translation_m[6:], axis=0), np.diff(b.root_translation_m, axis=0),
                               atol=1e-5)
    blended = concatenate([a, b], blend_frames=2)
    assert blended.num_frames == 9
    np.testing.assert_allclose(np.linalg.norm(blended.rotations_wxyz, axis=-1), 1.0, atol=1e-6)
    with pytest.raises(ValueError):
        concatenate([a, _random_motion(rng, fps=12.0)])
    with pytest.raises(ShapeError):
        concatenate([a, _random_motion(rng, fps=10.0, bones=4)])
    with pytest.raises(ValueError):
        concatenate([])


# ------------------------------------------------------------------ ground contact, world rotations
def test_ground_contact_modes(asset, model):
    walk = Motion.from_walk_cycle(asset, 0)
    bob = 0.3 + 0.02 * np.sin(np.linspace(0, 2 * np.pi, 10, endpoint=False))  # the stored walk is grounded
    lifted = Motion(walk.rotations_wxyz[::4], walk.root_translation_m[::4] + bob[:, None] * [0, 0, 1],
                    walk.fps_hz / 4, cycle_advance_m=walk.cycle_advance_m)  # 10 frames per cycle: fast
    per_frame = ground_contact(lifted, model, 0, mode="frame")
    np.testing.assert_allclose(lowest_vertex_z(per_frame, model, 0), 0.0, atol=1e-5)
    per_clip = ground_contact(lifted, model, 0, mode="clip")
    low = lowest_vertex_z(per_clip, model, 0)
    assert abs(low.min()) < 1e-5 and low.max() > 0.005  # one offset: the bob is kept
    per_cycle = ground_contact(loop(lifted, 2), model, 0, mode="cycle")
    low2 = lowest_vertex_z(per_cycle, model, 0)
    np.testing.assert_allclose([low2[:10].min(), low2[10:].min()], 0.0, atol=1e-5)
    with pytest.raises(ValueError):
        ground_contact(walk, model, 0, mode="sideways")


@pytest.fixture(scope="module")
def clean_gait(asset):
    from davis_rig.scene.gait import GaitParams, generate_gait

    walk = generate_gait(GaitParams(speed_m_s=1.2), asset, 0)
    return resample(walk, 50.0)  # fewer frames keep the skinning cheap


def test_foot_vertex_ids_split_the_feet(asset):
    feet = foot_vertex_ids(asset)
    assert len(feet["L"]) > 50 and len(feet["L"]) == len(feet["R"])
    assert (asset.rest_vertices_m[0, feet["L"], 0] > 0).all() and (asset.rest_vertices_m[0, feet["R"], 0] < 0).all()
    assert (asset.rest_vertices_m[0, np.concatenate([feet["L"], feet["R"]]), 2].max()
            < asset.rest_vertices_m[0, :, 2].min() + 0.2)  # low on the body


def test_lock_stance_foot_removes_injected_skating(clean_gait, model):
    slip, left = contact_slip(clean_gait, model, 0)
    assert slip.shape == (clean_gait.num_frames, 2) and left.any() and (~left).any()  # a cycle: T steps
    speed = np.linalg.norm(slip, axis=1) * clean_gait.fps_hz
    assert np.median(speed) < 0.01  # the generator's walk does not skate (1.2 m/s walking speed)
    t = np.arange(clean_gait.num_frames)
    wobble = np.zeros((clean_gait.num_frames, 3))
    wobble[:, 1] = 0.015 * np.sin(2 * np.pi * 2 * t / clean_gait.num_frames)  # +-1.5 cm twice a cycle (0.18 m/s)
    skating = replace(clean_gait, root_translation_m=clean_gait.root_translation_m + wobble)
    skate_speed = np.linalg.norm(contact_slip(skating, model, 0)[0], axis=1) * clean_gait.fps_hz
    assert np.median(skate_speed) > 0.05
    locked = lock_stance_foot(skating, model, 0)
    assert locked.metadata["stance_locked"] and locked.num_frames == skating.num_frames
    locked_speed = np.linalg.norm(contact_slip(locked, model, 0)[0], axis=1) * clean_gait.fps_hz
    assert locked_speed.max() < 1e-3
    np.testing.assert_array_equal(locked.root_translation_m[:, 2], skating.root_translation_m[:, 2])
    np.testing.assert_array_equal(locked.rotations_wxyz, skating.rotations_wxyz)
    np.testing.assert_allclose(locked.cycle_advance_m, clean_gait.cycle_advance_m, atol=0.02)  # ~1 stride kept
    # a clip (no wrap step) gets T - 1 steps and the same lock
    clip = replace(skating, cycle_advance_m=None)
    clip_slip, _ = contact_slip(clip, model, 0)
    assert clip_slip.shape == (clip.num_frames - 1, 2)
    clip_locked = lock_stance_foot(clip, model, 0)
    assert clip_locked.cycle_advance_m is None
    assert np.abs(contact_slip(clip_locked, model, 0)[0]).max() * clip.fps_hz < 1e-3


def test_bundled_walk_is_settled_on_the_ground(asset, model):
    """The asset's walk (advancing at its speed) keeps the planted foot still and a foot on the floor."""
    feet = foot_vertex_ids(asset)
    for shape in (0, 17):
        walk = Motion.from_walk_cycle(asset, shape, advance=True)
        slip, planted_left = contact_slip(walk, model, shape)
        assert (np.linalg.norm(slip, axis=1) * walk.fps_hz).max() < 0.02 * walk.speed_m_s + 0.01
        np.testing.assert_allclose(lowest_vertex_z(walk, model, shape), 0.0, atol=1e-4)
        with torch.no_grad():
            verts = model.pose(shape, torch.as_tensor(walk.rotations_wxyz.copy()),
                               torch.as_tensor(walk.root_translation_m.copy())).numpy()
        low = {side: verts[:, feet[side], 2].min(axis=1) for side in "LR"}
        planted = np.where(planted_left, low["L"], low["R"])
        np.testing.assert_allclose(planted, 0.0, atol=1e-4)  # the planted foot is on the floor, not hovering
    contact = asset.metadata["walk_contact"]
    assert contact["planted_foot_slip_m_s"]["after"]["slip_max"] < 0.02
    assert contact["planted_foot_above_floor_max_m"]["after"] < 1e-4


def test_world_rotations_give_the_posed_frames(asset, model64):
    rng = np.random.default_rng(6)
    j = asset.num_bones
    g = quat_to_matrix(_random_quats(rng, (2, j)))
    m = motion_from_world_rotations(g, np.zeros((2, 3)), asset.rest_bone_poses[0], asset.bone_parents, 30.0)
    poses, _ = model64.forward_kinematics(0, torch.as_tensor(m.rotations_wxyz.copy()))
    rest = asset.rest_bone_poses[0, :, :3, :3].astype(np.float64)
    np.testing.assert_allclose(poses[..., :3, :3].numpy(), g @ rest, atol=1e-5)
    identity = motion_from_world_rotations(np.broadcast_to(np.eye(3), (1, j, 3, 3)), np.zeros((1, 3)),
                                           asset.rest_bone_poses[0], asset.bone_parents, 30.0)
    np.testing.assert_allclose(np.abs(identity.rotations_wxyz[..., 0]), 1.0, atol=1e-6)
    with pytest.raises(ShapeError):
        motion_from_world_rotations(g[:, :3], np.zeros((2, 3)), asset.rest_bone_poses[0], asset.bone_parents, 30.0)


def test_save_load_round_trip(tmp_path, asset):
    from davis_rig.errors import FormatError

    walk = Motion.from_walk_cycle(asset, 0)
    walk = Motion(walk.rotations_wxyz, walk.root_translation_m, walk.fps_hz, name=walk.name, source=walk.source,
                  cycle_advance_m=walk.cycle_advance_m, bone_names=walk.bone_names, metadata={"a": [1, 2]})
    walk.save(tmp_path / "walk.npz")
    back = Motion.load(tmp_path / "walk.npz")
    np.testing.assert_array_equal(back.rotations_wxyz, walk.rotations_wxyz)
    np.testing.assert_array_equal(back.root_translation_m, walk.root_translation_m)
    np.testing.assert_array_equal(back.cycle_advance_m, walk.cycle_advance_m)
    assert (back.fps_hz, back.name, back.bone_names, back.metadata) == (walk.fps_hz, walk.name, walk.bone_names,
                                                                         {"a": [1, 2]})
    clip = Motion(np.tile([1.0, 0, 0, 0], (2, 3, 1)), np.zeros((2, 3)), 10.0)
    clip.save(tmp_path / "clip.npz")
    again = Motion.load(tmp_path / "clip.npz")
    assert again.cycle_advance_m is None and again.bone_names is None
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(FormatError, match="lacks"):
        Motion.load(tmp_path / "other.npz")
    with pytest.raises(FileNotFoundError):
        Motion.load(tmp_path / "missing.npz")


def test_in_place_removes_the_cycles_progression():
    from davis_rig.scene.motion import in_place

    rot = np.tile(np.array([1.0, 0, 0, 0]), (4, 2, 1))
    root = np.array([[0.0, 0.0, 0.9], [0.01, -0.3, 0.92], [0.0, -0.6, 0.9], [-0.01, -0.9, 0.92]])
    walk = Motion(rot, root, 4.0, cycle_advance_m=np.array([0.0, -1.2, 0.0]))
    still = in_place(walk)
    assert still.speed_m_s == 0.0 and still.is_cycle and np.array_equal(still.cycle_advance_m, np.zeros(3))
    np.testing.assert_allclose(still.root_translation_m, [[0, 0, 0.9], [0.01, 0, 0.92], [0, 0, 0.9],
                                                          [-0.01, 0, 0.92]], atol=1e-7)
    assert walk.speed_m_s == pytest.approx(1.2)  # the input is unchanged
    with pytest.raises(ValueError, match="not a cycle"):
        in_place(Motion(rot, root, 4.0))
