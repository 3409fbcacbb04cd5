"""Quaternion and rotation kernels of the scene's motions (float64 numpy, no input mutated).

Quaternions are arrays ``[..., 4]`` in ``(w, x, y, z)`` order (unit for rotations); matrices ``[..., 3, 3]`` act on
column vectors. :func:`quat_slerp` takes the shortest arc, as :func:`davis_rig.scene.motion.sample` needs.
:func:`quaternion_to_matrix` is the torch twin of :func:`quat_to_matrix` (torch imported when it is called), used by
the body model's forward kinematics.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = [
    "quat_conjugate",
    "quat_from_matrix",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_slerp",
    "quat_to_matrix",
    "quaternion_to_matrix",
    "rotation_about_z",
]


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


def quaternion_to_matrix(quaternions_wxyz: "torch.Tensor") -> "torch.Tensor":
    """Rotation matrices of (w, x, y, z) quaternions (normalised first), in torch (differentiable).

    Args:
        quaternions_wxyz: float tensor [..., 4].

    Returns:
        float tensor [..., 3, 3] (column-vector convention, ``R @ x``).

    Raises:
        ShapeError: the last dimension is not 4.
    """
    torch = optional_import("torch", "quaternion_to_matrix")
    if quaternions_wxyz.shape[-1] != 4:
        raise ShapeError(f"quaternions must have shape [..., 4], got {tuple(quaternions_wxyz.shape)}")
    q = quaternions_wxyz / torch.linalg.norm(quaternions_wxyz, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))
