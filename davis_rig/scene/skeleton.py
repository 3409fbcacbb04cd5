"""Rest geometry of one body shape's rig and numpy forward kinematics of its soles (no torch).

Shared by the gait generator (:mod:`davis_rig.scene.gait`: foot contact, swing clearance) and the mocap
importers (:mod:`davis_rig.scene.mocap.retarget`: foot locking, ground offsets), which need the feet's lowest
points for many frames without building a :class:`~davis_rig.scene.body.BodyModel`.

Axes and pose model are those of :mod:`davis_rig.scene.body` (Z up, m). A pose is given as per-bone *world*
rotations relative to the rest pose, ``G_c`` float [T, J, 3, 3] (``W_c = G_c R_c``, see
:func:`~davis_rig.scene.motion.motion_from_world_rotations`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from davis_rig.errors import ShapeError

__all__ = ["SOLE_BAND_M", "Rig", "depth_levels", "descendants", "sole_points"]

#: Height band above a foot's lowest rest vertex whose vertices count as its sole (m).
SOLE_BAND_M = 0.015


@dataclass(frozen=True, eq=False)
class Rig:
    """Bone names, hierarchy and rest geometry of one shape of a body asset.

    Build it with :meth:`from_asset`.

    Attributes:
        names: bone names, J.
        parents: int64 [J], parent bone index (the root, bone 0, has none; parents precede children).
        rest: float64 [J, 4, 4], rest bone poses (world, m).
        index: bone name -> index.
        ground_z: lowest rest-pose vertex height (m).
        hip_height_m: rest height of the left hip joint above ``ground_z`` (m).
        soles: ``"L"``/``"R"`` -> ``(points float64 [P, 3] rest positions (m), bones int64 [P])``: the
            vertices within :data:`SOLE_BAND_M` of the foot's lowest vertex, each attached rigidly to its
            dominant skinning bone.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    rest: np.ndarray
    index: dict[str, int]
    ground_z: float
    hip_height_m: float
    soles: dict[str, tuple[np.ndarray, np.ndarray]]

    @classmethod
    def from_asset(cls, asset, shape_index: int = 0) -> Rig:
        """The rig of shape ``shape_index`` of a :class:`~davis_rig.scene.body.BodyAsset`."""
        names = tuple(asset.bone_names)
        parents = np.asarray(asset.bone_parents, dtype=np.int64)
        rest = np.asarray(asset.rest_bone_poses[shape_index], dtype=np.float64)
        index = {n: i for i, n in enumerate(names)}
        verts = np.asarray(asset.rest_vertices_m[shape_index], dtype=np.float64)
        ground_z = float(verts[:, 2].min())
        hip_height_m = float(rest[index["upperleg01.L"], 2, 3] - ground_z)
        dominant = asset.skin_indices[np.arange(len(verts)), np.argmax(asset.skin_weights, axis=1)].astype(np.int64)
        soles = {}
        for side in ("L", "R"):
            in_foot = np.isin(dominant, descendants(parents, index[f"foot.{side}"]))
            low = in_foot & (verts[:, 2] < verts[in_foot, 2].min() + SOLE_BAND_M)
            soles[side] = (verts[low], dominant[low])
        return cls(names, parents, rest, index, ground_z, hip_height_m, soles)

    @property
    def heads(self) -> np.ndarray:
        """Rest bone head positions, float64 [J, 3] (m)."""
        return self.rest[:, :3, 3]

    def bone(self, name: str) -> int:
        """Index of the bone ``name`` (KeyError if the rig has none)."""
        return self.index[name]

    def direction(self, a: str, b: str) -> np.ndarray:
        """Unit vector from bone ``a``'s rest head to bone ``b``'s, float64 [3]."""
        d = self.heads[self.bone(b)] - self.heads[self.bone(a)]
        return d / np.linalg.norm(d)


def descendants(parents: np.ndarray, bone: int) -> np.ndarray:
    """Indices of ``bone`` and every bone below it, int64 [K] ascending (parents must precede children)."""
    keep = np.zeros(len(parents), dtype=bool)
    keep[bone] = True
    for c in range(bone + 1, len(parents)):
        keep[c] = keep[parents[c]]
    return np.flatnonzero(keep)


def sole_points(rig: Rig, world_rotations: np.ndarray, side: str) -> np.ndarray:
    """World positions of one foot's sole points for root translation 0 (numpy FK), float64 [T, P, 3] (m).

    Args:
        rig: the rig.
        world_rotations: float [T, J, 3, 3], per-bone world rotations relative to rest ``G_c``.
        side: ``"L"`` or ``"R"``.

    Raises:
        ShapeError: ``world_rotations`` is not [T, J, 3, 3] for the rig's J bones.
        KeyError: ``side`` is not ``"L"`` or ``"R"``.
    """
    g = np.asarray(world_rotations, dtype=np.float64)
    if g.ndim != 4 or g.shape[1:] != (len(rig.names), 3, 3):
        raise ShapeError(f"world_rotations must be [T, {len(rig.names)}, 3, 3], got {g.shape}")
    rest_heads = rig.heads
    heads = np.empty((g.shape[0], len(rig.names), 3))
    heads[:, 0] = rest_heads[0]
    for c in range(1, len(rig.names)):
        p = rig.parents[c]
        heads[:, c] = heads[:, p] + g[:, p] @ (rest_heads[c] - rest_heads[p])
    pts, bones = rig.soles[side]
    return heads[:, bones] + np.einsum("tpij,pj->tpi", g[:, bones], pts - rest_heads[bones])


def depth_levels(parents: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Bones grouped by depth in the tree, for forward kinematics one level at a time.

    Args:
        parents: int [J] parent of each bone (-1 for the root, bone 0); parents precede their children.

    Returns:
        Per level, ``(bone indices int64 [K], position of each bone's parent in the previous level's indices)``.
    """
    parents = np.asarray(parents, dtype=np.int64)
    depth = np.zeros(len(parents), dtype=np.int64)
    for bone in range(1, len(parents)):  # parents precede children (validated at load)
        depth[bone] = depth[parents[bone]] + 1
    levels = []
    previous = np.array([0])
    for level in range(depth.max() + 1):
        bones = np.flatnonzero(depth == level)
        if level == 0:
            parent_pos = np.zeros(1, dtype=np.int64)
        else:
            lookup = {bone: i for i, bone in enumerate(previous)}
            parent_pos = np.array([lookup[p] for p in parents[bones]], dtype=np.int64)
        levels.append((bones, parent_pos))
        previous = bones
    return levels
