"""davis_rig.scene.mocap.retarget: putting a motion on the ground (shared by the AMASS and BVH importers)."""

import numpy as np
import pytest

from davis_rig.scene.mocap.retarget import ground_offsets, put_on_ground
from davis_rig.scene.motion import Motion


@pytest.fixture()
def hopping(asset):
    """The walk cycle's first frames as a clip whose root bobs 0, 5, 10 cm above the cycle's height + 0.3 m."""
    walk = Motion.from_walk_cycle(asset, 0, advance=False)
    root = walk.root_translation_m[:3].astype(np.float64) + [[0, 0, 0.30], [0, 0, 0.35], [0, 0, 0.40]]
    return Motion(walk.rotations_wxyz[:3], root, walk.fps_hz, bone_names=walk.bone_names)


def test_clip_mode_shifts_once_frame_mode_per_frame(asset, hopping):
    before = ground_offsets(hopping, asset, 0)
    clip = put_on_ground(hopping, asset, 0, "clip")
    np.testing.assert_allclose(ground_offsets(clip, asset, 0), before - before.min(), atol=1e-6)
    assert ground_offsets(clip, asset, 0).min() == pytest.approx(0.0, abs=1e-6)
    frame = put_on_ground(hopping, asset, 0, "frame")
    np.testing.assert_allclose(ground_offsets(frame, asset, 0), 0.0, atol=1e-6)
    np.testing.assert_allclose(frame.root_translation_m[:, :2], hopping.root_translation_m[:, :2])  # heights only
    assert (clip.metadata["ground"], frame.metadata["ground"]) == ("clip", "frame")


def test_none_keeps_the_motion_and_other_modes_are_refused(asset, hopping):
    assert put_on_ground(hopping, asset, 0, None) is hopping
    with pytest.raises(ValueError, match="ground must be 'clip', 'frame' or None, got 'floor'"):
        put_on_ground(hopping, asset, 0, "floor")
