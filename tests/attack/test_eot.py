"""davis_rig.attack.eot motion loading: one side of the CMU trial split from a folder of tiny synthetic BVH files."""

import numpy as np
import pytest
from tests.helpers.mocap_files import write_bvh

pytest.importorskip("torch")


def _bvh_folder(root, num_trials=5):
    """``<root>/07/07_<k>.bvh``: 3 frames at 120 fps, a knee flexion that differs per trial."""
    (root / "07").mkdir(parents=True)
    for k in range(1, num_trials + 1):
        frames = [{"LeftLeg": (0.0, 0.0, 5.0 * k * f)} for f in range(3)]
        write_bvh(root / "07" / f"07_{k:02d}.bvh", frames)
    return root


def test_bvh_motions_follow_the_trial_split(tmp_path):
    from davis_rig.attack.eot import bvh_motions
    from davis_rig.scene.body import BodyAsset
    from davis_rig.scene.mocap.splits import find_trials, split_trials

    root = _bvh_folder(tmp_path / "cmu")
    split = split_trials(find_trials(root, pattern="*.bvh"))
    assert (len(split.train), len(split.test)) == (4, 1)  # round(5 * 13 / 60) = 1 test trial
    train, test = bvh_motions(root, "train"), bvh_motions(root, "test")
    assert [m.name for m in train] == [t.split("/")[1] for t in split.train]
    assert [m.name for m in test] == [t.split("/")[1] for t in split.test]
    bones = BodyAsset.load().num_bones
    for motion in train + test:
        assert (motion.num_frames, motion.num_bones, motion.fps_hz) == (3, bones, pytest.approx(120.0))
        assert np.isfinite(motion.rotations_wxyz).all() and motion.metadata["translation"] == "foot_locked"
    assert [m.name for m in bvh_motions(root, "train", max_trials=2)] == [m.name for m in train[:2]]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"no BVH trials \(\*\.bvh\)"):
        bvh_motions(tmp_path / "empty")
    with pytest.raises(ValueError, match="split"):
        bvh_motions(root, "val")
    with pytest.raises(FileNotFoundError):
        bvh_motions(tmp_path / "missing")


def test_test_scene_config_is_the_evaluations_scene_and_ideal_sensor():
    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.scene.body import BodyModel

    config = EoTConfig.test_scene(scale="small", supersample=1)
    assert config.scale == "small" and config.shapes is None  # placement, shapes and headings are still drawn
    clip = next(iter(ClipPool(config, BodyModel(), 4, size=1, base_seed=2).clips.values()))
    assert clip.base_threshold == pytest.approx(0.2)  # one theta, no mismatch
    assert clip.noise_cell.numel() == 0  # no noise events
    assert np.unique(clip.background.numpy()).tolist() == [0.5]  # uniform grey
