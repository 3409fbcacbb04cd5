"""Optional SMPL / SMPL-H body (the paper's body model) through the ``smplx`` package, for users who own the model files.

SMPL, SMPL-H and their UV layouts are licensed by the Max Planck Institute and are **not** shipped or
downloaded: pass the paths of your own files (``SMPL_NEUTRAL.pkl``, ``SMPLH_MALE.pkl``, ...; the SMPL
``.pkl`` layout: ``v_template`` [V, 3], ``shapedirs`` [V, 3, B], ``posedirs`` [V, 3, 9 (J-1)], ``J_regressor``
[J, V], ``weights`` [V, J], ``kintree_table`` [2, J], ``f`` [F, 3]). ``smplx`` is imported lazily
(``pip install 'davis_rig[smpl]'``).

:class:`SmplBody` adapts the model to the interfaces of :class:`~davis_rig.scene.body.BodyModel` where they
carry over: ``faces`` (int64 [F, 3]), ``face_uvs`` (float [F, 3, 2], u right / v up, when a UV ``.obj`` is
given), ``num_vertices``, ``device``/``dtype``, and :meth:`SmplBody.pose` returning posed vertices
[T, V, 3] (m). SMPL's pose is its own (axis-angle per SMPL joint, e.g. AMASS ``poses``), not the anny rig's
local rotations; vertices come out in the frame of the poses (AMASS: Z-up world, heading from the root
orientation; SMPL's canonical frame is Y up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import FormatError, ShapeError

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
        uv_obj_path: optional UV ``.obj`` of the same topology (gives :attr:`face_uvs`).
        device, dtype: torch device / dtype.

    Raises:
        MissingDependencyError: smplx (or torch) not installed.
        FileNotFoundError: a file is missing. FormatError: smplx cannot read the model.
    """

    def __init__(self, model_path, *, model_type: str = "smpl", num_betas: int = 10, uv_obj_path=None,
                 device="cpu", dtype=None):
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
            betas: float [B'] shape coefficients (first ``num_betas`` used) or None (mean shape).

        Returns:
            ``(vertices [T, V, 3], joints [T, J, 3])`` in metres (the skeleton joints; smplx's extra
            landmark joints are not added).

        Raises:
            ShapeError: wrong pose / translation shapes.
        """
        torch = _torch()
        kw = dict(device=self.device, dtype=self.dtype)
        poses = torch.as_tensor(np.asarray(poses) if not isinstance(poses, torch.Tensor) else poses).to(**kw)
        if poses.ndim != 2:
            raise ShapeError(f"poses must be [T, {self.pose_size}], got {tuple(poses.shape)}")
        t = poses.shape[0]
        if poses.shape[1] < self.pose_size and poses.shape[1] >= 66:
            poses = torch.cat([poses, torch.zeros(t, self.pose_size - poses.shape[1], **kw)], dim=1)
        elif poses.shape[1] > self.pose_size:
            poses = poses[:, : self.pose_size]
        if poses.shape[1] != self.pose_size:
            raise ShapeError(f"poses must be [T, {self.pose_size}] (or [T, >= 66]), got {tuple(poses.shape)}")
        trans = torch.zeros(t, 3, **kw) if root_translation_m is None else torch.as_tensor(root_translation_m).to(**kw)
        if tuple(trans.shape) != (t, 3):
            raise ShapeError(f"root_translation_m must be [{t}, 3], got {tuple(trans.shape)}")
        shape = torch.zeros(self.num_betas, **kw)
        if betas is not None:
            b = torch.as_tensor(np.asarray(betas)).to(**kw).reshape(-1)[: self.num_betas]
            shape[: len(b)] = b
        args = dict(betas=shape.expand(t, -1), global_orient=poses[:, :3], transl=trans, return_verts=True)
        if self.model_type == "smpl":
            args["body_pose"] = poses[:, 3:72]
        else:
            args.update(body_pose=poses[:, 3:66], left_hand_pose=poses[:, 66:111], right_hand_pose=poses[:, 111:156])
        out = self.model(**args)
        return out.vertices, out.joints

    def pose(self, poses, root_translation_m=None, betas=None):
        """Posed vertices [T, V, 3] (m); see :meth:`forward`."""
        return self.forward(poses, root_translation_m, betas)[0]

    def pose_amass(self, path, start_frame: int = 0, stop_frame: int | None = None):
        """Vertices [T, V, 3] of an AMASS trial (its poses, trans and betas), frames ``[start, stop)``."""
        from davis_rig.scene.mocap.amass import read_amass

        trial = read_amass(path)
        sl = slice(start_frame, stop_frame)
        return self.pose(trial.poses[sl], trial.trans[sl], trial.betas)
