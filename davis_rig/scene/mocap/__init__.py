"""Motion-capture importers onto the asset's anny rig: AMASS (SMPL-H ``.npz``), CMU BVH, train/test splits.

- :mod:`.amass`: :func:`~davis_rig.scene.mocap.amass.load_amass` (user-supplied AMASS trial files).
- :mod:`.bvh`: :func:`~davis_rig.scene.mocap.bvh.load_bvh` (CMU BVH, or any BVH with a joint map).
- :mod:`.splits`: the paper's train/test split by trial (47/13) as a deterministic rule over a folder.
- :mod:`.retarget`: the shared segment mapping and rest-pose alignment.

All numpy. Not re-exported: the function ``retarget`` (the submodule of that name would shadow it; use
``from davis_rig.scene.mocap.retarget import retarget``).
"""

from __future__ import annotations

from davis_rig.scene.mocap.amass import (
    SMPL_REST_DIRECTIONS,
    SMPLH_BODY_JOINTS,
    SMPLH_PARENTS,
    SMPLH_SEGMENT_JOINT,
    AmassTrial,
    load_amass,
    read_amass,
    retarget_smplh,
    smplh_global_rotations,
)
from davis_rig.scene.mocap.bvh import (
    CMU_JOINT_MAP,
    CMU_UNITS_TO_M,
    BvhSkeleton,
    bvh_global_rotations,
    load_bvh,
    read_bvh,
)
from davis_rig.scene.mocap.retarget import (
    ANNY_BONE_SEGMENT,
    ANNY_SEGMENT_ENDS,
    LIMB_SEGMENTS,
    SEGMENTS,
    Y_UP_TO_Z_UP,
    anny_segments,
    foot_locked_root,
    ground_offsets,
    put_on_ground,
    rest_offsets,
)
from davis_rig.scene.mocap.splits import (
    PAPER_TEST_TRIALS,
    PAPER_TRAIN_TRIALS,
    TrialSplit,
    find_trials,
    split_trials,
    trial_id,
)

__all__ = [
    "SMPL_REST_DIRECTIONS", "SMPLH_BODY_JOINTS", "SMPLH_PARENTS", "SMPLH_SEGMENT_JOINT", "AmassTrial", "load_amass",
    "read_amass", "retarget_smplh", "smplh_global_rotations",
    "CMU_JOINT_MAP", "CMU_UNITS_TO_M", "BvhSkeleton", "bvh_global_rotations", "load_bvh", "read_bvh",
    "ANNY_BONE_SEGMENT", "ANNY_SEGMENT_ENDS", "LIMB_SEGMENTS", "SEGMENTS", "Y_UP_TO_Z_UP", "anny_segments",
    "foot_locked_root", "ground_offsets", "put_on_ground", "rest_offsets",
    "PAPER_TEST_TRIALS", "PAPER_TRAIN_TRIALS", "TrialSplit", "find_trials", "split_trials", "trial_id",
]  # fmt: skip
