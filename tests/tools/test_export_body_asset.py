"""tools/export_body_asset.py: the walk-settling helpers that run without anny (``--settle-walk-only``), in
tools/body_asset/settle.py."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("body_asset_settle", ROOT / "tools" / "body_asset" / "settle.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_steady_planted_labels_flip_hand_over_chatter(tool):
    chatter = np.array([1, 1, 1, 0, 0, 1, 1, 1, 1, 1, 0, 1, 1, 0, 0, 0, 0, 0, 0, 0], dtype=bool)
    steady = tool.steady_planted_labels(chatter, min_run=3)
    np.testing.assert_array_equal(steady, [1] * 13 + [0] * 7)  # runs of 2 and 1 steps flipped
    # a cycle: the run that wraps around the end counts as one run; long runs are kept as they are
    wrapped = np.array([0, 1, 1, 1, 1, 1, 0, 0, 0, 0], dtype=bool)
    np.testing.assert_array_equal(tool.steady_planted_labels(wrapped, min_run=3), wrapped)
    np.testing.assert_array_equal(tool.steady_planted_labels(np.ones(6, dtype=bool)), np.ones(6, dtype=bool))


def test_lift_free_feet_raises_the_free_foot_above_the_planted_one(tool):
    pytest.importorskip("torch")
    from davis_rig.scene.body import BodyAsset, BodyModel
    from davis_rig.scene.contact import foot_vertex_ids, posed_vertices
    from davis_rig.scene.motion import Motion

    asset = BodyAsset.load()
    model = BodyModel(asset)
    walk = Motion.from_walk_cycle(asset, 0, advance=True)
    walk = Motion(walk.rotations_wxyz[::4], walk.root_translation_m[::4], walk.fps_hz / 4,
                  cycle_advance_m=walk.cycle_advance_m, bone_names=walk.bone_names)  # 10 frames: fast
    feet = foot_vertex_ids(asset)
    low = {s: posed_vertices(walk, model, 0, feet[s])[:, :, 2].min(axis=1) for s in "LR"}
    planted_left = low["L"] <= low["R"]
    planted_left[[2, 7]] = ~planted_left[[2, 7]]  # the lower foot swings there: it must be lifted
    lifted, angles = tool.lift_free_feet(walk, model, 0, planted_left)
    new = {s: posed_vertices(lifted, model, 0, feet[s])[:, :, 2].min(axis=1) for s in "LR"}
    planted = np.where(planted_left, new["L"], new["R"])
    free = np.where(planted_left, new["R"], new["L"])
    assert (free >= planted + tool.SWING_CLEARANCE_M - 1e-3).all()
    np.testing.assert_allclose(planted, np.where(planted_left, low["L"], low["R"]), atol=1e-6)  # untouched
    assert all((a[:, 0] >= 0).all() for a in angles.values())  # knee flexion only
    lifted_frames = np.flatnonzero(np.abs(np.concatenate([angles["L"], angles["R"]], axis=1)).max(axis=1) > 0)
    assert {2, 7} <= set(lifted_frames.tolist())
