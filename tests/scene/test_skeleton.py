"""davis_rig.scene.skeleton: rig rest geometry and the numpy sole forward kinematics."""

import numpy as np
import pytest

from davis_rig.errors import ShapeError
from davis_rig.scene.motion import rotation_about_z
from davis_rig.scene.skeleton import SOLE_BAND_M, Rig, descendants, sole_points


def test_descendants_of_a_hand_made_tree():
    parents = np.array([-1, 0, 1, 0, 3, 4, 1])  # 0 -> (1 -> (2, 6), 3 -> 4 -> 5)
    assert descendants(parents, 0).tolist() == [0, 1, 2, 3, 4, 5, 6]
    assert descendants(parents, 1).tolist() == [1, 2, 6]
    assert descendants(parents, 3).tolist() == [3, 4, 5]
    assert descendants(parents, 5).tolist() == [5]


def test_rig_from_asset(asset):
    rig = Rig.from_asset(asset, 3)
    assert rig.names == tuple(asset.bone_names)
    assert rig.bone("foot.L") == list(asset.bone_names).index("foot.L")
    np.testing.assert_array_equal(rig.heads, np.asarray(asset.rest_bone_poses[3])[:, :3, 3])
    assert 0.6 < rig.hip_height_m < 1.2  # adult hip height (m)
    np.testing.assert_allclose(np.linalg.norm(rig.direction("upperleg01.L", "lowerleg01.L")), 1.0)
    for side in ("L", "R"):
        points, bones = rig.soles[side]
        assert points.shape == (len(bones), 3) and len(bones) > 0
        assert set(bones.tolist()) <= set(descendants(rig.parents, rig.bone(f"foot.{side}")).tolist())
        assert np.ptp(points[:, 2]) < SOLE_BAND_M
    assert min(rig.soles["L"][0][:, 2].min(), rig.soles["R"][0][:, 2].min()) == pytest.approx(rig.ground_z)


def test_sole_points_rest_pose_and_rigid_rotation(asset):
    rig = Rig.from_asset(asset, 0)
    joints = len(rig.names)
    identity = np.broadcast_to(np.eye(3), (2, joints, 3, 3))
    rest_points = rig.soles["L"][0]
    np.testing.assert_allclose(sole_points(rig, identity, "L"), np.broadcast_to(rest_points, (2,) + rest_points.shape),
                               atol=1e-12)
    # every bone turned by the same R: the body turns rigidly about the root head
    r = rotation_about_z(0.7)
    turned = sole_points(rig, np.broadcast_to(r, (1, joints, 3, 3)), "R")
    root = rig.heads[0]
    np.testing.assert_allclose(turned[0], root + (rig.soles["R"][0] - root) @ r.T, atol=1e-12)


def test_sole_points_rejects_bad_input(asset):
    rig = Rig.from_asset(asset, 0)
    with pytest.raises(ShapeError, match=r"\[T, \d+, 3, 3\]"):
        sole_points(rig, np.zeros((2, 3, 3, 3)), "L")
    with pytest.raises(KeyError):
        sole_points(rig, np.broadcast_to(np.eye(3), (1, len(rig.names), 3, 3)), "middle")
