"""SMPL adapter through smplx on a tiny synthetic model file in the SMPL .pkl layout (no licensed data)."""

import pickle
import sys

import numpy as np
import pytest

from davis_rig.errors import FormatError, MissingDependencyError, ShapeError

torch = pytest.importorskip("torch")

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
LEFT_KNEE, LEFT_ANKLE = 4, 7


def _tiny_smpl(path, num_betas=10, faces=((0, 2, 4), (1, 3, 5), (8, 10, 12))):
    """24 joints on a stick figure (Y up, T-pose), 2 vertices per joint rigidly bound to it, a few triangles."""
    rng = np.random.default_rng(0)
    joints = np.zeros((24, 3))
    offsets = {1: (0.1, -0.1, 0), 2: (-0.1, -0.1, 0), 3: (0, 0.1, 0), 4: (0, -0.4, 0), 5: (0, -0.4, 0),
               6: (0, 0.15, 0), 7: (0, -0.4, 0), 8: (0, -0.4, 0), 9: (0, 0.05, 0), 10: (0, -0.05, 0.12),
               11: (0, -0.05, 0.12), 12: (0, 0.2, 0), 13: (0.08, 0.12, 0), 14: (-0.08, 0.12, 0), 15: (0, 0.1, 0),
               16: (0.1, 0, 0), 17: (-0.1, 0, 0), 18: (0.25, 0, 0), 19: (-0.25, 0, 0), 20: (0.25, 0, 0),
               21: (-0.25, 0, 0), 22: (0.08, 0, 0), 23: (-0.08, 0, 0)}
    for j in range(1, 24):
        joints[j] = joints[SMPL_PARENTS[j]] + offsets[j]
    verts = np.repeat(joints, 2, axis=0) + np.tile([[0.0, 0.0, 0.02], [0.0, 0.0, -0.02]], (24, 1))
    v = len(verts)
    weights = np.zeros((v, 24))
    weights[np.arange(v), np.arange(v) // 2] = 1.0
    regressor = np.zeros((24, v))
    regressor[np.arange(v) // 2, np.arange(v)] = 0.5  # joint = mean of its two vertices
    kintree = np.array([[4294967295] + SMPL_PARENTS[1:], list(range(24))], dtype=np.int64)
    data = {
        "v_template": verts, "shapedirs": rng.normal(0, 1e-3, (v, 3, num_betas)), "posedirs": np.zeros((v, 3, 207)),
        "J_regressor": regressor, "weights": weights, "kintree_table": kintree,
        "f": np.array(faces, dtype=np.int64),
    }
    with open(path, "wb") as f:
        pickle.dump(data, f)
    return verts


@pytest.fixture()
def tiny_model(tmp_path):
    pytest.importorskip("smplx", reason="smplx not installed (optional extra 'smpl')")
    path = tmp_path / "SMPL_TINY.pkl"
    verts = _tiny_smpl(path)
    return path, verts


def test_rest_pose_reproduces_template(tiny_model):
    from davis_rig.scene.smpl import SmplBody

    path, verts = tiny_model
    body = SmplBody(path, dtype=torch.float64)
    assert body.num_vertices == len(verts) and body.pose_size == 72
    out, _ = body.forward(np.zeros((1, 72)), np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(out[0].numpy(), verts + [0, 0, 1.0], atol=1e-12)
    assert body.faces.dtype == torch.int64 and tuple(body.faces.shape) == (3, 3)


def test_knee_flexion_rotates_the_shank_about_the_knee(tiny_model):
    from davis_rig.scene.smpl import SmplBody

    path, verts = tiny_model
    body = SmplBody(path, dtype=torch.float64)
    poses = np.zeros((1, 66))  # an AMASS-style SMPL-H body pose is accepted and padded
    poses[0, 3 * LEFT_KNEE] = np.radians(30)  # flexion about +X
    out = body.forward(poses)[0][0].numpy()
    knee = verts[2 * LEFT_KNEE : 2 * LEFT_KNEE + 2].mean(0)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    ankle_vertices = verts[2 * LEFT_ANKLE : 2 * LEFT_ANKLE + 2]
    np.testing.assert_allclose(out[2 * LEFT_ANKLE : 2 * LEFT_ANKLE + 2], (ankle_vertices - knee) @ rx.T + knee,
                               atol=1e-12)
    # the ankle moves backward (-Z in SMPL's canonical frame, which faces +Z)
    assert out[2 * LEFT_ANKLE, 2] < ankle_vertices[0, 2] - 0.1
    np.testing.assert_allclose(out[: 2 * LEFT_KNEE], verts[: 2 * LEFT_KNEE], atol=1e-12)  # parents unchanged


def test_amass_file_drives_the_model(tiny_model, tmp_path):
    from davis_rig.scene.smpl import SmplBody

    path, verts = tiny_model
    body = SmplBody(path, dtype=torch.float64)
    poses = np.zeros((3, 156))
    trans = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]])
    amass = tmp_path / "01_01_poses.npz"
    np.savez(amass, poses=poses, trans=trans, mocap_framerate=120.0, betas=np.zeros(16), gender="neutral")
    out = body.pose_amass(amass, 1, 3).numpy()
    np.testing.assert_allclose(out, verts[None] + trans[1:3, None], atol=1e-7)
    motion = body.amass_motion(amass, 1, 3)  # the same frames as a Motion for render_clip
    assert motion.fps_hz == 120.0 and motion.name.endswith("/01_01") and motion.num_bones == 24
    np.testing.assert_allclose(body.pose(0, motion.rotations_wxyz, motion.root_translation_m).numpy(), out, atol=1e-7)
    with pytest.raises(ValueError, match="empty frame range"):
        body.amass_motion(amass, 5)


def test_uv_obj_and_errors(tiny_model, tmp_path):
    from davis_rig.scene.smpl import SmplBody, read_obj_uvs

    path, _ = tiny_model
    obj = tmp_path / "uv.obj"
    obj.write_text("vt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\nf 1/1 3/2 5/3\nf 2/2 4/4 6/3\nf 9/1 11/2 13/4\n")
    body = SmplBody(path, uv_obj_path=obj)
    assert tuple(body.face_uvs.shape) == (3, 3, 2)
    np.testing.assert_array_equal(body.face_uvs[2].numpy(), [[0, 0], [1, 0], [1, 1]])
    bad = tmp_path / "quad.obj"
    bad.write_text("vt 0 0\nf 1/1 2/1 3/1 4/1\n")
    with pytest.raises(FormatError, match="triangles"):
        read_obj_uvs(bad)
    with pytest.raises(FormatError, match="faces"):
        read_obj_uvs(obj, num_faces=5)
    with pytest.raises(ShapeError):
        body.forward(np.zeros((2, 10)))
    with pytest.raises(FileNotFoundError):
        SmplBody(tmp_path / "missing.pkl")
    garbage = tmp_path / "garbage.pkl"
    with open(garbage, "wb") as f:
        pickle.dump({"v_template": np.zeros((3, 3))}, f)
    with pytest.raises(FormatError, match="smplx could not read"):
        SmplBody(garbage)


def test_missing_smplx_names_the_extra(tmp_path, monkeypatch):
    from davis_rig.scene.smpl import SmplBody

    path = tmp_path / "m.pkl"
    path.write_bytes(b"")
    monkeypatch.setitem(sys.modules, "smplx", None)
    with pytest.raises(MissingDependencyError, match=r"davis_rig\[smpl\]"):
        SmplBody(path)


def test_quaternion_pose_equals_axis_angle(tiny_model):
    """The render interface's pose (local quaternions of a Motion) reproduces smplx's axis-angle pose."""
    from davis_rig.scene.smpl import SmplBody

    path, _ = tiny_model
    body = SmplBody(path, dtype=torch.float64, betas=np.full(10, 0.5))
    rng = np.random.default_rng(1)
    poses = rng.uniform(-1.0, 1.0, (4, 66))  # an AMASS body pose; the SMPL hand joints stay at rest
    poses[0] = 0.0  # the identity (small-angle branch)
    trans = rng.normal(0.0, 0.3, (4, 3))
    motion = body.motion(poses, trans, 30.0, name="random")
    assert (motion.num_bones, motion.fps_hz, motion.name) == (24, 30.0, "random")
    got = body.pose(0, motion.rotations_wxyz, motion.root_translation_m).numpy()
    np.testing.assert_allclose(got, body.forward(poses, trans)[0].numpy(), atol=1e-6)  # float32 motion storage
    with pytest.raises(IndexError, match="one shape"):
        body.pose(1, motion.rotations_wxyz, motion.root_translation_m)
    with pytest.raises(ShapeError, match="24, 4"):
        body.pose(0, motion.rotations_wxyz[:, :22], motion.root_translation_m)


def _bone_faces():
    """Two double-sided triangles per bone, between the vertex pairs of its two joints (a body-like mesh)."""
    faces = []
    for j in range(1, 24):
        a0, a1, b0, b1 = 2 * SMPL_PARENTS[j], 2 * SMPL_PARENTS[j] + 1, 2 * j, 2 * j + 1
        faces += [(a0, a1, b0), (a1, b1, b0), (a0, b0, a1), (a1, b0, b1)]
    return np.array(faces)


def _bone_uv_obj(path, faces):
    """One UV column per bone (4 faces each), so that parts occupy separate texture regions."""
    lines = []
    for k in range(len(faces) // 4):
        u0, u1 = k / 23 + 0.005, (k + 1) / 23 - 0.005
        lines += [f"vt {u0} 0.1", f"vt {u1} 0.1", f"vt {u0} 0.9"]
    for i, face in enumerate(faces):
        t = 3 * (i // 4)
        lines.append("f " + " ".join(f"{v + 1}/{t + c + 1}" for c, v in enumerate(face)))
    path.write_text("\n".join(lines) + "\n")
    return path


def _walk_poses(num_frames, fps_hz):
    """AMASS-like SMPL poses: root orientation Y-up -> Z-up (facing -Y), hips swinging, walking at 1 m/s."""
    t = np.arange(num_frames) / fps_hz
    poses = np.zeros((num_frames, 72))
    poses[:, 0] = np.pi / 2
    swing = 0.3 * np.sin(2 * np.pi * t)
    poses[:, 3 * 1], poses[:, 3 * 2] = swing, -swing
    trans = np.stack([np.zeros_like(t), -1.0 * t, np.full_like(t, 0.95)], axis=1)  # rest soles at z = 0
    return poses, trans


def test_render_clip_of_an_smpl_body(tmp_path):
    pytest.importorskip("smplx", reason="smplx not installed (optional extra 'smpl')")
    from davis_rig.scene.body import PART_NAMES
    from davis_rig.scene.renderer import EMPTY_PART
    from davis_rig.scene.scene import SceneSpec, render_clip, scene_vertices
    from davis_rig.scene.smpl import SmplBody

    faces = _bone_faces()
    model_path = tmp_path / "SMPL_TINY.pkl"
    verts = _tiny_smpl(model_path, faces=faces)
    obj = _bone_uv_obj(tmp_path / "uv.obj", faces)
    leg_bones = {1, 2, 4, 5, 7, 8, 10, 11}
    bone = np.repeat(np.arange(1, 24), 4)
    parts = np.where(np.isin(bone, list(leg_bones)), PART_NAMES.index("legs"), PART_NAMES.index("torso"))
    body = SmplBody(model_path, uv_obj_path=obj, face_parts=parts)
    motion = body.motion(*_walk_poses(30, 120.0), 120.0)
    spec = SceneSpec(motion=motion, duration_s=0.1, supersample=1)  # heading pi/2: walks to the image right

    clip = render_clip(spec, model=body, part_labels=True)
    assert tuple(clip.video.shape) == (20, 240, 304)
    assert np.isfinite(clip.boxes).all()  # visible in every frame
    figure_m = verts[:, 1].max() - verts[:, 1].min()  # 1.57 m
    heights = clip.boxes[:, 3] - clip.boxes[:, 1]
    assert np.all(np.abs(heights - 150 * figure_m / 1.75) < 8)  # middle scale: 150 px for 1.75 m
    centre = (clip.boxes[:, 0] + clip.boxes[:, 2]) / 2
    assert np.all(np.abs(centre - 152) < 20) and centre[-1] > centre[0] + 4  # mid-clip on the axis, moving right
    np.testing.assert_array_less(np.abs(clip.boxes - clip.vertex_boxes), 3.0)  # thin feet, one sample/px
    z_min = scene_vertices(spec, body)[..., 2].amin(dim=1).numpy()
    assert np.all(np.abs(z_min) < 0.03)  # on the ground (the swinging toes dip ~1 cm)
    labels = np.unique(clip.part_labels)
    assert set(labels.tolist()) == {PART_NAMES.index("torso"), PART_NAMES.index("legs"), EMPTY_PART}

    black = render_clip(spec, torch.zeros(4, 4), model=body)
    person = clip.coverage > 0.5
    assert bool((black.video[person] < clip.video[person] - 0.1).all())
    legs = body.part_mask(("legs",), size=64, padding_px=1)
    torso = body.part_mask(("torso",), size=64, padding_px=1)
    assert legs.any() and torso.any() and not (legs & torso).any()


def test_smpl_render_refusals(tiny_model):
    from davis_rig.scene.scene import SceneSpec, render_clip
    from davis_rig.scene.smpl import SmplBody

    path, _ = tiny_model
    no_uvs = SmplBody(path)
    motion = no_uvs.motion(*_walk_poses(30, 120.0), 120.0)
    with pytest.raises(ValueError, match="no UVs"):
        render_clip(SceneSpec(motion=motion, duration_s=0.01), model=no_uvs)
    with pytest.raises(ValueError, match="face_parts"):
        no_uvs.part_mask(("torso",))
    obj = tiny_model[0].parent / "uv.obj"
    obj.write_text("vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 3/2 5/3\nf 2/1 4/2 6/3\nf 9/1 11/2 13/3\n")
    body = SmplBody(path, uv_obj_path=obj)
    with pytest.raises(ValueError, match="part labels"):
        render_clip(SceneSpec(motion=motion, duration_s=0.01), model=body, part_labels=True)
    with pytest.raises(ValueError, match="walk cycle"):
        render_clip(SceneSpec(duration_s=0.01), model=body)
    with pytest.raises(ShapeError, match="face_parts"):
        SmplBody(path, face_parts=np.zeros(2))
    with pytest.raises(ValueError, match="PART_NAMES"):
        SmplBody(path, face_parts=np.full(3, 6))
