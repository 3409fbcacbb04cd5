"""davis_rig.scene.mocap.bvh on small hand-written CMU-style BVH files."""

import math

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.scene.mocap.bvh import CMU_UNITS_TO_M, bvh_global_rotations, load_bvh, read_bvh
from davis_rig.scene.mocap.retarget import ground_offsets

torch = pytest.importorskip("torch")


def _rx(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rz(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_parse_hierarchy_and_motion(tmp_path, bvh_writer):
    path = bvh_writer(tmp_path / "02_01.bvh", [{}, {"pos": (1.0, 17.0, 2.0)}], frame_time_s=1 / 120)
    skel = read_bvh(path)
    assert skel.names[:3] == ("Hips", "LHipJoint", "LeftUpLeg") and len(skel.names) == 25
    assert skel.parents[skel.index("LeftLeg")] == skel.index("LeftUpLeg")
    assert skel.channels[0][:3] == ("Xposition", "Yposition", "Zposition") and len(skel.channels[1]) == 3
    assert skel.num_frames == 2 and skel.frame_time_s == pytest.approx(1 / 120)
    np.testing.assert_allclose(skel.end_offsets[skel.index("Head")], [0, 1.5, 0])
    np.testing.assert_allclose(skel.child_direction(skel.index("LeftArm")), [5, 0, 0])
    with pytest.raises(KeyError, match="Hips"):
        skel.index("Tail")


def test_euler_channel_order(tmp_path, bvh_writer):
    # "Zrotation Yrotation Xrotation": R = Rz Ry Rx; children compose with their parents
    path = bvh_writer(tmp_path / "e.bvh", [{"Hips": (90.0, 0.0, 0.0), "LeftUpLeg": (0.0, 0.0, 20.0),
                                             "LeftLeg": (10.0, 0.0, 30.0)}])
    world, root = bvh_global_rotations(read_bvh(path))
    skel = read_bvh(path)
    np.testing.assert_allclose(world[0, skel.index("Hips")], _rz(90), atol=1e-12)
    np.testing.assert_allclose(world[0, skel.index("LeftLeg")], _rz(90) @ _rx(20) @ _rz(10) @ _rx(30), atol=1e-12)
    np.testing.assert_allclose(root[0], [0, 17, 0])


def _frames(model64, motion):
    poses, _ = model64.forward_kinematics(0, torch.as_tensor(motion.rotations_wxyz.copy()),
                                          torch.as_tensor(motion.root_translation_m.copy()))
    return poses.numpy()


def _direction(frames, asset, a, b):
    d = frames[:, asset.bone_index(b), :3, 3] - frames[:, asset.bone_index(a), :3, 3]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_knee_flexion_and_t_pose_retarget(tmp_path, bvh_writer, asset, model64):
    frames_in = [{}, {"LeftLeg": (0.0, 0.0, 30.0), "pos": (1.0, 17.0, 2.0)}]
    motion = load_bvh(bvh_writer(tmp_path / "walk.bvh", frames_in), asset, ground=None)
    assert motion.name == "walk" and motion.fps_hz == pytest.approx(120.0, rel=1e-6)
    assert motion.metadata["units_to_m"] == pytest.approx(CMU_UNITS_TO_M)
    f = _frames(model64, motion)
    np.testing.assert_allclose(_direction(f, asset, "upperarm01.L", "lowerarm01.L"), [[1, 0, 0]] * 2, atol=1e-6)
    np.testing.assert_allclose(_direction(f, asset, "upperleg01.R", "lowerleg01.R"), [[0, 0, -1]] * 2, atol=1e-6)
    for bone in ("lowerleg01.L", "foot.L"):
        i = asset.bone_index(bone)
        np.testing.assert_allclose(f[1, i, :3, :3] @ f[0, i, :3, :3].T, _rx(30), atol=1e-5)
    shin = _direction(f, asset, "lowerleg01.L", "foot.L")
    assert math.degrees(math.acos(shin[0] @ shin[1])) == pytest.approx(30.0, abs=1e-3)
    # BVH Y up / +Z forward -> anny Z up / -Y forward
    np.testing.assert_allclose(motion.root_translation_m[1, :2] - motion.root_translation_m[0, :2],
                               [1.0 * CMU_UNITS_TO_M, -2.0 * CMU_UNITS_TO_M], atol=1e-6)


def test_ground_and_translation_modes(tmp_path, bvh_writer, asset):
    frames_in = [{"pos": (0.0, 17.0, 0.0)}, {"pos": (0.0, 18.0, 3.0)}]
    path = bvh_writer(tmp_path / "hop.bvh", frames_in)
    clip = load_bvh(path, asset)
    low = ground_offsets(clip, asset, 0)
    np.testing.assert_allclose(low, [0.0, CMU_UNITS_TO_M], atol=1e-6)
    in_place = load_bvh(path, asset, translation="in_place", ground="frame", units_to_m=0.05)
    np.testing.assert_allclose(in_place.root_translation_m[:, :2], 0.0)
    np.testing.assert_allclose(ground_offsets(in_place, asset, 0), 0.0, atol=1e-6)


def test_malformed_files(tmp_path, bvh_writer, asset):
    good = bvh_writer(tmp_path / "g.bvh", [{}]).read_text()
    (tmp_path / "short.bvh").write_text(good.rsplit("\n", 2)[0] + " 1.0\n")
    with pytest.raises(FormatError, match="values"):
        read_bvh(tmp_path / "short.bvh")
    (tmp_path / "nomotion.bvh").write_text(good.split("MOTION")[0])
    with pytest.raises(FormatError, match="MOTION"):
        read_bvh(tmp_path / "nomotion.bvh")
    (tmp_path / "token.bvh").write_text(good.replace("OFFSET", "OFSET", 1))
    with pytest.raises(FormatError, match="token"):
        read_bvh(tmp_path / "token.bvh")
    (tmp_path / "renamed.bvh").write_text(good.replace("LeftForeArm", "LeftElbow"))
    with pytest.raises(KeyError, match="LeftForeArm"):
        load_bvh(tmp_path / "renamed.bvh", asset)
    with pytest.raises(FileNotFoundError):
        read_bvh(tmp_path / "missing.bvh")
