"""Ground contact of a motion on a body: the lowest vertex on z = 0, foot slip, the stance foot locked in place.

These kernels pose the mesh (a :class:`~davis_rig.scene.body.BodyModel`, torch, no grad, in batches of frames):

- :func:`ground_contact`: shift the root vertically so that the lowest mesh vertex touches z = 0, per frame
  (walking: a foot is always on the ground), per cycle or per clip (running: keeps flight phases);
- :func:`lowest_vertex_z`, :func:`posed_vertices`, :func:`foot_vertex_ids`: what the mesh does in a motion;
- :func:`contact_slip`: how far the planted foot slides; :func:`lock_stance_foot`: the root moved so that the planted
  foot stays still.

All return new motions or arrays; none mutates its input.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from davis_rig.errors import ShapeError
from davis_rig.scene.motion import Motion

if TYPE_CHECKING:  # pragma: no cover
    from davis_rig.scene.body import BodyModel

__all__ = ["contact_slip", "foot_vertex_ids", "ground_contact", "lock_stance_foot", "lowest_vertex_z",
           "posed_vertices"]


def _pose_batches(motion: Motion, model: "BodyModel", shape_index: int, batch_frames: int = 64):
    """Posed vertices batch by batch (no grad): yields ``(start, stop, vertices tensor [stop - start, V, 3])``."""
    import torch

    motion.check_rig(model.asset.bone_names)
    with torch.no_grad():
        for start in range(0, motion.num_frames, batch_frames):
            stop = min(start + batch_frames, motion.num_frames)
            rot = torch.as_tensor(motion.rotations_wxyz[start:stop].copy(), device=model.device)
            root = torch.as_tensor(motion.root_translation_m[start:stop].copy(), device=model.device)
            yield start, stop, model.pose(shape_index, rot, root)


def lowest_vertex_z(motion: Motion, model: "BodyModel", shape_index: int = 0, batch_frames: int = 64) -> np.ndarray:
    """Height of the lowest skinned vertex per frame, float64 [T] (m), computed with ``model`` (FK + LBS)."""
    out = np.empty(motion.num_frames)
    for start, stop, verts in _pose_batches(motion, model, shape_index, batch_frames):
        out[start:stop] = verts[..., 2].amin(dim=1).double().cpu().numpy()
    return out


def ground_contact(
    motion: Motion,
    model: "BodyModel",
    shape_index: int = 0,
    *,
    mode: str = "frame",
    cycle_frames: int | None = None,
    ground_z_m: float = 0.0,
) -> Motion:
    """Shift the root vertically so that the body stands on the ground plane ``z = ground_z_m``.

    Modes (the lowest skinned mesh vertex is measured with ``model``):

    - ``"frame"``: per frame, the lowest vertex is put exactly on the ground. Right for walking (one foot is
      always on the ground); it removes flight phases, so do not use it for running.
    - ``"cycle"``: one offset per block of ``cycle_frames`` frames (default: the whole motion when it is a
      cycle): the lowest vertex *of the cycle* touches the ground; vertical bob and flight are kept.
    - ``"clip"``: one offset for the whole motion.

    Args:
        motion: the motion (bone order of ``model``'s asset).
        model: :class:`~davis_rig.scene.body.BodyModel` (any device).
        shape_index: body shape to measure.
        mode: ``"frame"``, ``"cycle"`` or ``"clip"``.
        cycle_frames: block length for ``"cycle"``.
        ground_z_m: ground height (m).

    Returns:
        The motion with corrected root heights (metadata ``ground_contact`` records the mode).

    Raises:
        ValueError: unknown mode, or ``"cycle"`` without a cycle length. ShapeError: rig mismatch.
    """
    low = lowest_vertex_z(motion, model, shape_index)
    if mode == "frame":
        offset = ground_z_m - low
    elif mode == "clip":
        offset = np.full_like(low, ground_z_m - low.min())
    elif mode == "cycle":
        n = cycle_frames if cycle_frames is not None else (motion.num_frames if motion.is_cycle else None)
        if n is None or n < 1:
            raise ValueError("mode='cycle' needs cycle_frames (or a cyclic motion)")
        block = np.arange(motion.num_frames) // n
        block_min = np.minimum.reduceat(low, np.arange(0, motion.num_frames, n))
        offset = ground_z_m - block_min[block]
    else:
        raise ValueError(f"unknown ground contact mode {mode!r}; expected 'frame', 'cycle' or 'clip'")
    root = motion.root_translation_m.astype(np.float64).copy()
    root[:, 2] += offset
    return replace(motion, root_translation_m=root, metadata={**motion.metadata, "ground_contact": mode})


def foot_vertex_ids(asset) -> dict[str, np.ndarray]:
    """Mesh vertices of each foot, ``{"L": int64 [K], "R": int64 [K]}`` (the ``feet`` part, split by rest X sign)."""
    feet = np.unique(asset.faces[asset.face_part_mask(["feet"])])
    x = asset.rest_vertices_m[0, feet, 0]
    return {"L": feet[x > 0], "R": feet[x < 0]}


def posed_vertices(motion: Motion, model: "BodyModel", shape_index: int, ids: np.ndarray) -> np.ndarray:
    """Posed positions of some mesh vertices in every frame of a motion (posed in batches of frames, no grad).

    Args:
        motion: the motion (over the model's rig).
        model: :class:`~davis_rig.scene.body.BodyModel`.
        shape_index: body shape.
        ids: int [K] vertex indices (e.g. :func:`foot_vertex_ids`).

    Returns:
        float64 [T, K, 3] (m, Z up).
    """
    out = np.empty((motion.num_frames, len(ids), 3))
    for start, stop, verts in _pose_batches(motion, model, shape_index):
        out[start:stop] = verts[:, ids].double().cpu().numpy()
    return out


def contact_slip(
    motion: Motion,
    model: "BodyModel",
    shape_index: int = 0,
    foot_vertices: dict[str, np.ndarray] | None = None,
    planted_left: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal slip of the planted foot per frame step.

    At each step ``t -> t + 1`` the planted foot is the one whose lowest vertex moves least in X/Y (the
    other one swings forward); its slip is how far that lowest vertex moves in X/Y. A cyclic motion has
    ``S = T`` steps (the last one wraps to frame 0 of the next period, shifted by ``cycle_advance_m``), a clip
    ``S = T - 1``. The motion must already advance roughly (an in-place cycle has no planted foot: give it
    an estimated ``cycle_advance_m`` first).

    Args:
        motion: the motion (bone order of ``model``'s asset).
        model: :class:`~davis_rig.scene.body.BodyModel`.
        shape_index: body shape.
        foot_vertices: vertex ids per foot (default :func:`foot_vertex_ids` of the model's asset).
        planted_left: bool [S], which foot is planted at each step (default: the one that moves less).

    Returns:
        ``(slip float64 [S, 2] in m per step — multiply by fps_hz for m/s, planted_left bool [S])``.
    """
    feet = foot_vertices if foot_vertices is not None else foot_vertex_ids(model.asset)
    steps = motion.num_frames if motion.is_cycle else motion.num_frames - 1
    both = posed_vertices(motion, model, shape_index, np.concatenate([feet["L"], feet["R"]]))  # pose once
    if motion.is_cycle:
        both = np.concatenate([both, both[:1] + motion.cycle_advance_m])
    t = np.arange(steps)
    moves = []
    for v in np.split(both, [len(feet["L"])], axis=1):
        low = np.argmin(v[:steps, :, 2], axis=1)
        moves.append(v[t + 1, low, :2] - v[t, low, :2])
    if planted_left is None:
        left = np.linalg.norm(moves[0], axis=1) <= np.linalg.norm(moves[1], axis=1)
    else:
        left = np.asarray(planted_left, dtype=bool)
        if left.shape != (steps,):
            raise ShapeError(f"planted_left must be [{steps}], got {left.shape}")
    return np.where(left[:, None], moves[0], moves[1]), left


def lock_stance_foot(
    motion: Motion,
    model: "BodyModel",
    shape_index: int = 0,
    foot_vertices: dict[str, np.ndarray] | None = None,
    planted_left: np.ndarray | None = None,
) -> Motion:
    """Move the root horizontally so that the ground contact does not slide (no foot skating).

    The root's X/Y path is rebuilt from :func:`contact_slip`: each step's root displacement loses the slip
    of the planted foot, so its lowest vertex stays put from one frame to the next (a rolling contact:
    heel, then ball, then toe). Heights, rotations and frame 0 are unchanged; for a cycle,
    ``cycle_advance_m`` becomes the distance the body then covers per period. Meant for walks (one foot always
    down); flight phases of a run are not contacts. ``planted_left`` (bool [S]) fixes which foot is planted at
    each step instead of :func:`contact_slip`'s guess.

    Returns:
        The corrected motion (metadata ``stance_locked`` is True).
    """
    slip, _ = contact_slip(motion, model, shape_index, foot_vertices, planted_left)
    root = motion.root_translation_m.astype(np.float64).copy()
    steps = np.diff(root[:, :2], axis=0) - slip[: motion.num_frames - 1]
    root[1:, :2] = root[0, :2] + np.cumsum(steps, axis=0)
    advance = None
    if motion.is_cycle:
        advance = np.array(motion.cycle_advance_m, dtype=np.float64)
        advance[:2] -= slip.sum(axis=0)
    return replace(motion, root_translation_m=root, cycle_advance_m=advance,
                   metadata={**motion.metadata, "stance_locked": True})
