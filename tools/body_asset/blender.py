"""MPFB2's walk cycle from its Blender action, resolved into per-bone local rotations + root translation.

The action (a JSON export of Blender F-curves, with IK helper bones) is evaluated at the integer frames: Bezier
F-curve segments, Blender bone-space Euler rotations, bone rest bases from head/tail/roll, analytic two-bone IK
with the knee/elbow helpers as pole targets, feet and hands copying their IK helpers' rotations. numpy only.
"""

from __future__ import annotations

import math

import numpy as np


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
