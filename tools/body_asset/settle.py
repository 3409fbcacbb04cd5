"""The body asset's walk settled on the ground with davis_rig's own body model (no anny needed).

Per shape: steady planted-foot labels (hand-over chatter removed), the free foot lifted above the planted one by
knee + hip flexion, the root on the planted foot (no foot skating) and a foot on the floor in every frame; the
asset is rewritten in place with the contact figures in its metadata (``walk_contact``).
"""

from __future__ import annotations

import datetime
import json
import sys
from pathlib import Path

import numpy as np

#: The repository root (the tool runs in anny's virtual environment, where davis_rig is not installed).
REPO_ROOT = Path(__file__).resolve().parents[2]

SWING_CLEARANCE_M = 0.005  # the free foot's lowest point at least this far above the planted foot's
MIN_SUPPORT_FRAMES = 3  # shorter runs of one planted foot are hand-over chatter (flipped to the other foot)


def steady_planted_labels(planted_left: np.ndarray, min_run: int = MIN_SUPPORT_FRAMES) -> np.ndarray:
    """Planted-foot labels of a cycle without runs shorter than ``min_run`` steps (flipped, shortest first)."""
    left = np.asarray(planted_left, dtype=bool).copy()
    while True:
        change = np.flatnonzero(left != np.roll(left, 1))
        if len(change) < 2:
            return left
        lengths = np.diff(np.append(change, change[0] + len(left)))
        shortest = int(np.argmin(lengths))
        if lengths[shortest] >= min_run:
            return left
        run = (change[shortest] + np.arange(lengths[shortest])) % len(left)
        left[run] = ~left[run]


def lift_free_feet(motion, model, shape: int, planted_left: np.ndarray, iterations: int = 5):
    """Raise the free foot above the planted one wherever the walk has it lower, by knee + hip flexion.

    MPFB2's walk lets the free foot (toe-off, early swing) scuff lower than the planted foot for a few frames per
    hand-over, so grounding the lowest vertex would leave the planted foot hovering. In those frames the free leg
    gets extra knee flexion and hip flexion (rotations about the local X axes of lowerleg01 / upperleg01, the
    sagittal hinge of anny's rig; knee flexion only, never hyperextension), solved per frame by Gauss-Newton on
    finite differences so that the foot's lowest vertex is SWING_CLEARANCE_M above the planted foot's and its
    mean forward (Y) position is unchanged. Returns ``(motion, {side: angles_rad [T, 2]})``.
    """
    from davis_rig.scene.contact import foot_vertex_ids, posed_vertices
    from davis_rig.scene.motion import Motion, quat_from_rotvec, quat_multiply

    feet = foot_vertex_ids(model.asset)
    frames = motion.num_frames

    def rotated(base, side, angles):
        q = np.array(base.rotations_wxyz, dtype=np.float64)
        for k, bone in enumerate((f"lowerleg01.{side}", f"upperleg01.{side}")):
            rotvec = np.zeros((frames, 3))
            rotvec[:, 0] = angles[:, k]
            j = model.asset.bone_index(bone)
            q[:, j] = quat_multiply(q[:, j], quat_from_rotvec(rotvec))
        return Motion(q, base.root_translation_m, base.fps_hz, name=base.name, source=base.source,
                      cycle_advance_m=base.cycle_advance_m, bone_names=base.bone_names, metadata=base.metadata)

    def foot(m, side):
        v = posed_vertices(m, model, shape, feet[side])
        return v[:, :, 2].min(axis=1), v[:, :, 1].mean(axis=1)

    low = {side: foot(motion, side)[0] for side in "LR"}
    planted_low = np.where(planted_left, low["L"], low["R"])
    out, solved = motion, {}
    for side in "LR":
        free = planted_left != (side == "L")
        target = np.where(free, np.maximum(low[side], planted_low + SWING_CLEARANCE_M), low[side])
        need = target > low[side] + 1e-5
        angles = np.zeros((frames, 2))
        if need.any():
            _, y_start = foot(motion, side)
            eps = np.radians(1.0)
            for _ in range(iterations):
                z, y = foot(rotated(motion, side, angles), side)
                jac = np.empty((frames, 2, 2))
                for k in range(2):
                    probe = angles.copy()
                    probe[:, k] += eps
                    zk, yk = foot(rotated(motion, side, probe), side)
                    jac[:, 0, k], jac[:, 1, k] = (zk - z) / eps, (yk - y) / eps
                residual = np.stack([target - z, y_start - y], axis=1)
                step = np.linalg.solve(jac + 1e-9 * np.eye(2), residual[..., None])[..., 0]
                angles += np.clip(step, -0.3, 0.3) * need[:, None]
                angles[:, 0] = np.maximum(angles[:, 0], 0.0)
        solved[side] = angles
        out = rotated(out, side, angles)
    return out, solved


def contact_measures(motion, model, shape: int, planted_left: np.ndarray | None = None):
    """Planted-foot slip speed [T] (m/s), lowest vertex height [T] (m) and how far the planted foot's lowest point
    rises above the lowest vertex at most (m) of a walk (``planted_left`` default: the foot that moves less)."""
    from davis_rig.scene.contact import contact_slip, foot_vertex_ids, lowest_vertex_z, posed_vertices

    slip, left = contact_slip(motion, model, shape, planted_left=planted_left)
    speed = np.linalg.norm(slip, axis=1) * motion.fps_hz
    low = lowest_vertex_z(motion, model, shape)
    feet = foot_vertex_ids(model.asset)
    planted = np.where(left, *(posed_vertices(motion, model, shape, feet[side])[:, :, 2].min(axis=1)
                               for side in "LR"))
    return speed, low, float((planted - low).max())


def _record_contact(stats: dict, measures) -> None:
    """Append one shape's :func:`contact_measures` to ``stats`` (slip median/max, floor gap, hover)."""
    slip, low, hover = measures
    stats["slip_median"].append(float(np.median(slip)))
    stats["slip_max"].append(float(slip.max()))
    stats["gap_max"].append(float(low.max() - low.min()))
    stats["hover"].append(hover)


def settle_shape(walk, model, shape: int):
    """One shape's walk settled: steady planted-foot labels, the free foot lifted (:func:`lift_free_feet`), the root
    on the planted foot (``lock_stance_foot``) and a foot on the floor in every frame (``ground_contact``).

    Returns:
        ``(settled motion, planted_left bool [T], largest added free-leg flexion (deg))``.
    """
    from davis_rig.scene.contact import contact_slip, ground_contact, lock_stance_foot

    _, guessed = contact_slip(lock_stance_foot(walk, model, shape), model, shape)
    planted_left = steady_planted_labels(guessed)
    locked = lock_stance_foot(walk, model, shape, planted_left=planted_left)
    lifted, angles = lift_free_feet(locked, model, shape, planted_left)
    settled = ground_contact(lock_stance_foot(lifted, model, shape, planted_left=planted_left), model, shape,
                             mode="frame")
    return settled, planted_left, float(np.degrees(np.abs(np.concatenate(list(angles.values())))).max())


def contact_summary(before: dict, after: dict, lift_max_deg: float, speed_all: np.ndarray) -> dict:
    """The ``walk_contact`` metadata entry: method, slip, floor gap and hover before and after, lift, speeds."""
    return {
        "method": "planted foot per step = the one that moves less, hand-over chatter (runs < "
                  f"{MIN_SUPPORT_FRAMES} frames) removed; the free foot lifted {SWING_CLEARANCE_M} m above the "
                  "planted one by knee + hip flexion where the walk had it lower (lift_free_feet); the root follows "
                  "the planted foot's lowest vertex (davis_rig.scene.contact.lock_stance_foot); per-frame ground "
                  "contact (ground_contact mode 'frame'); stored back as an in-place cycle + walk_speed_m_s; the "
                  "small lateral drift per cycle is dropped",
        "planted_foot_slip_m_s": {"before": {k: max(v) if k != "slip_median" else float(np.median(v))
                                             for k, v in before.items() if k.startswith("slip")},
                                  "after": {k: max(v) if k != "slip_median" else float(np.median(v))
                                            for k, v in after.items() if k.startswith("slip")}},
        "floor_gap_max_m": {"before": max(before["gap_max"]), "after": max(after["gap_max"])},
        "planted_foot_above_floor_max_m": {"before": max(before["hover"]), "after": max(after["hover"])},
        "free_leg_flexion_added_max_deg": round(lift_max_deg, 2),
        "lateral_drift_per_cycle_max_m": float(np.abs(after["lateral_drift_per_cycle_m"]).max()),
        "speed_m_s": [round(float(v), 4) for v in speed_all],
        "settled_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def settle_walk(path: Path) -> dict:
    """Rewrite the asset's walk so the planted foot never slides and a foot always touches the floor.

    Per shape, with davis_rig's own BodyModel: the in-place cycle advancing at the stored speed is given a
    no-slip root path (``lock_stance_foot``: the root follows the planted foot's lowest vertex), then the root
    is lowered/raised per frame so the lowest vertex is on z = 0 (``ground_contact(mode="frame")``). The
    result is stored again as an in-place cycle (the uniform forward progression removed) plus its new
    ``walk_speed_m_s``, so every consumer keeps the same semantics. Returns (and stores in the metadata under
    ``walk_contact``) the planted-foot slip and floor gap before and after.
    """
    import torch

    sys.path.insert(0, str(REPO_ROOT))
    from davis_rig.scene.body import BodyAsset, BodyModel
    from davis_rig.scene.motion import Motion

    torch.set_grad_enabled(False)
    asset = BodyAsset.load(path)
    model = BodyModel(asset, dtype=torch.float64)
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    metadata = json.loads(str(arrays.pop("metadata_json")))
    root_all = arrays["walk_root_translation_m"].astype(np.float64)
    rotations_all = arrays["walk_rotations_wxyz"].copy()
    planted_all, lift_max_deg = [], 0.0
    speed_all = arrays["walk_speed_m_s"].astype(np.float64)
    before = {"slip_median": [], "slip_max": [], "gap_max": [], "hover": []}
    after = {"slip_median": [], "slip_max": [], "gap_max": [], "hover": [], "lateral_drift_per_cycle_m": []}
    frames = asset.walk_rotations_wxyz.shape[1]
    for s in range(asset.num_shapes):
        walk = Motion.from_walk_cycle(asset, s, advance=True)
        _record_contact(before, contact_measures(walk, model, s))
        settled, planted_left, lift_deg = settle_shape(walk, model, s)
        rotations_all[s] = settled.rotations_wxyz
        lift_max_deg = max(lift_max_deg, lift_deg)
        planted_all.append(planted_left)
        advance = settled.cycle_advance_m
        ramp = np.arange(frames)[:, None] / frames
        root_all[s] = settled.root_translation_m - ramp * advance  # back to an in-place cycle
        speed_all[s] = -advance[1] / settled.duration_s
        after["lateral_drift_per_cycle_m"].append(float(advance[0]))
    arrays["walk_rotations_wxyz"] = rotations_all.astype(np.float32)
    arrays["walk_root_translation_m"] = root_all.astype(np.float32)
    arrays["walk_speed_m_s"] = speed_all.astype(np.float32)
    np.savez_compressed(path, metadata_json=np.array(json.dumps(metadata, sort_keys=True)), **arrays)
    asset = BodyAsset.load(path)  # measure what is stored (float32), as every consumer will read it
    model = BodyModel(asset, dtype=torch.float64)
    for s in range(asset.num_shapes):
        _record_contact(after, contact_measures(Motion.from_walk_cycle(asset, s, advance=True), model, s,
                                                planted_all[s]))
    summary = contact_summary(before, after, lift_max_deg, speed_all)
    metadata["walk_contact"] = summary
    metadata["walk_speed_from"] = "distance per cycle of the no-slip root path (walk_contact)"
    np.savez_compressed(path, metadata_json=np.array(json.dumps(metadata, sort_keys=True)), **arrays)
    return summary
