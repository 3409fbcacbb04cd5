"""SMPL adapter through smplx on a tiny synthetic model file in the SMPL .pkl layout (no licensed data)."""

import pickle
import sys

import numpy as np
import pytest

from davis_rig.errors import FormatError, MissingDependencyError, ShapeError

torch = pytest.importorskip("torch")

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
LEFT_KNEE, LEFT_ANKLE = 4, 7


def _tiny_smpl(path, num_betas=10):
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
        "f": np.array([[0, 2, 4], [1, 3, 5], [8, 10, 12]], dtype=np.int64),
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
    out = body.pose(np.zeros((1, 72)), np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(out[0].numpy(), verts + [0, 0, 1.0], atol=1e-12)
    assert body.faces.dtype == torch.int64 and tuple(body.faces.shape) == (3, 3)


def test_knee_flexion_rotates_the_shank_about_the_knee(tiny_model):
    from davis_rig.scene.smpl import SmplBody

    path, verts = tiny_model
    body = SmplBody(path, dtype=torch.float64)
    poses = np.zeros((1, 66))  # an AMASS-style SMPL-H body pose is accepted and padded
    poses[0, 3 * LEFT_KNEE] = np.radians(30)  # flexion about +X
    out = body.pose(poses)[0].numpy()
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
        body.pose(np.zeros((2, 10)))
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
