"""DAVIS346 pinhole camera, look-at extrinsics, the paper's test scales, EoT jitter and camera ego-motion.

Conventions
-----------
- World: the body asset's frame (metres, **Z up**, the body faces -Y; see :mod:`davis_rig.scene.body`).
- Camera: OpenCV convention, **x right, y down, z forward** (depth = z > 0 in front of the camera).
  Extrinsics map world to camera: ``X_cam = R @ X_world + t`` (``R`` [3, 3] world->camera rotation).
- Image: continuous pixel coordinates, pixel ``(row i, col j)`` covers ``[j, j+1) x [i, i+1)``, its centre
  is ``(j + 0.5, i + 0.5)``; the image origin is the upper-left corner, rows grow downwards (as events'
  ``y``). Projection: ``x_px = fx * X/Z + cx``, ``y_px = fy * Y/Z + cy``.

Intrinsics
----------
DAVIS346: 346 x 260 pixels of 18.5 um behind a 12 mm lens: ``f = 12 mm / 18.5 um = 648.65 px``, principal
point at the sensor centre ``(173, 130)``, no distortion. The RVT frame (304 x 240) is the centred crop
(origin x=21, y=10, as :func:`davis_rig.events.crop.center_crop_origin`), i.e. the same camera with the
principal point at ``(152, 120)`` (:meth:`PinholeCamera.rvt_crop`).

Test scales
-----------
The official code renders at camera distances 1.5 / 1.75 / 2.0 (PyTorch3D units; large / middle / small)
and trains at 1.75. The projected height of a person is proportional to 1/distance, so the three scales are
defined here as **heights of a 1.75 m person in pixels of the 240-row RVT frame**, in the ratios
``1/1.5 : 1/1.75 : 1/2.0``. The middle scale is 150 px (62.5 % of the 240 rows: the whole walking body incl.
arm swing stays clearly inside the frame with room for the EoT distance jitter, which enlarges it by at most
``1.75/1.5``); hence large = 150 * 1.75/1.5 = 175 px and small = 150 * 1.75/2.0 = 131.25 px. With f = 648.65
px these are camera distances of 6.49 m / 7.57 m / 8.65 m from the person (:func:`distance_for_height`).

EoT jitter (official code): with p = 0.4 the camera rotation is perturbed (the official code adds +-0.1 to
the rotation matrix entries, which leaves SO(3); here a random rotation vector with components uniform in
+-0.1 rad is applied instead), and with p = 0.4 the distance changes by +-0.25 at 1.75, i.e. by a relative
factor uniform in ``1 +- 0.25/1.75``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from davis_rig.errors import ShapeError
from davis_rig.types import DAVIS346_HW, RVT_HW

__all__ = [
    "DAVIS346_FOCAL_PX",
    "DAVIS346_LENS_MM",
    "DAVIS346_PIXEL_UM",
    "DEFAULT_PERSON_HEIGHT_M",
    "EoTJitter",
    "EgoMotion",
    "PinholeCamera",
    "TEST_SCALES_PX",
    "TRAIN_SCALE",
    "distance_for_height",
    "look_at",
    "rotation_from_vector",
]

#: DAVIS346 pixel pitch, micrometres.
DAVIS346_PIXEL_UM = 18.5
#: Lens focal length used in the paper's rig, millimetres.
DAVIS346_LENS_MM = 12.0
#: Focal length in pixels, ``12 mm / 18.5 um`` = 648.65 px.
DAVIS346_FOCAL_PX = DAVIS346_LENS_MM * 1000.0 / DAVIS346_PIXEL_UM
#: Reference person height of the scale definition, metres.
DEFAULT_PERSON_HEIGHT_M = 1.75
_MIDDLE_PX = 150.0
#: Height of a 1.75 m person in pixels of the 240-row frame, per test scale (ratios 1/1.5 : 1/1.75 : 1/2).
TEST_SCALES_PX: dict[str, float] = {
    "large": _MIDDLE_PX * 1.75 / 1.5,
    "middle": _MIDDLE_PX,
    "small": _MIDDLE_PX * 1.75 / 2.0,
}
#: The training scale (official code trains at the middle distance).
TRAIN_SCALE = "middle"


@dataclass(frozen=True)
class PinholeCamera:
    """Distortion-free pinhole intrinsics.

    Attributes:
        width_px, height_px: image size (pixels).
        fx_px, fy_px: focal lengths (pixels).
        cx_px, cy_px: principal point in continuous pixel coordinates (image centre = ``(W/2, H/2)``).
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float

    def __post_init__(self) -> None:
        if int(self.width_px) < 1 or int(self.height_px) < 1:
            raise ShapeError(f"camera size must be >= 1 px, got {self.width_px} x {self.height_px}")
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise ValueError(f"focal lengths must be > 0 px, got fx={self.fx_px}, fy={self.fy_px}")

    @classmethod
    def davis346(cls, lens_mm: float = DAVIS346_LENS_MM) -> "PinholeCamera":
        """The full DAVIS346 sensor (346 x 260 px, 18.5 um pixels) behind a ``lens_mm`` lens."""
        f = lens_mm * 1000.0 / DAVIS346_PIXEL_UM
        h, w = DAVIS346_HW
        return cls(width_px=w, height_px=h, fx_px=f, fy_px=f, cx_px=w / 2.0, cy_px=h / 2.0)

    @classmethod
    def rvt_crop(cls, lens_mm: float = DAVIS346_LENS_MM) -> "PinholeCamera":
        """The centred 304 x 240 RVT crop of the DAVIS346 (origin x=21, y=10) as a camera."""
        h, w = RVT_HW
        full = cls.davis346(lens_mm)
        return full.crop((full.width_px - w) // 2, (full.height_px - h) // 2, w, h)

    @property
    def hw(self) -> tuple[int, int]:
        """Image (height, width) in pixels."""
        return (int(self.height_px), int(self.width_px))

    @property
    def matrix(self) -> np.ndarray:
        """Intrinsic matrix K, float64 [3, 3] (continuous pixel coordinates)."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def crop(self, x0_px: int, y0_px: int, width_px: int, height_px: int) -> "PinholeCamera":
        """The camera seeing the window ``[x0, x0+w) x [y0, y0+h)`` of this image.

        Raises:
            ShapeError: the window does not fit the image.
        """
        if x0_px < 0 or y0_px < 0 or x0_px + width_px > self.width_px or y0_px + height_px > self.height_px:
            raise ShapeError(
                f"crop x0={x0_px} y0={y0_px} {width_px}x{height_px} does not fit {self.width_px}x{self.height_px}"
            )
        return replace(
            self, width_px=int(width_px), height_px=int(height_px), cx_px=self.cx_px - x0_px, cy_px=self.cy_px - y0_px
        )

    def scaled(self, factor: int) -> "PinholeCamera":
        """The same view at ``factor`` x the resolution (used for supersampling)."""
        return PinholeCamera(
            width_px=self.width_px * factor,
            height_px=self.height_px * factor,
            fx_px=self.fx_px * factor,
            fy_px=self.fy_px * factor,
            cx_px=self.cx_px * factor,
            cy_px=self.cy_px * factor,
        )

    def project(self, points_world, rotation_w2c, translation_w2c):
        """Project world points (torch, batched over frames).

        Args:
            points_world: float tensor [T, N, 3] (m).
            rotation_w2c: float tensor [T, 3, 3] or [3, 3].
            translation_w2c: float tensor [T, 3] or [3] (m).

        Returns:
            float tensor [T, N, 3]: ``(x_px, y_px, depth_m)``; points behind the camera get meaningless
            ``x, y`` and depth <= 0 (the rasterizer discards faces with a vertex at depth <= near).

        Raises:
            ShapeError: points are not [T, N, 3].
        """
        import torch

        if points_world.ndim != 3 or points_world.shape[-1] != 3:
            raise ShapeError(f"points_world must be [T, N, 3], got {tuple(points_world.shape)}")
        r = torch.as_tensor(rotation_w2c, dtype=points_world.dtype, device=points_world.device)
        t = torch.as_tensor(translation_w2c, dtype=points_world.dtype, device=points_world.device)
        if r.ndim == 2:
            r = r[None]
        if t.ndim == 1:
            t = t[None]
        cam = points_world @ r.transpose(1, 2) + t[:, None, :]
        z = cam[..., 2]
        safe = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
        x = self.fx_px * cam[..., 0] / safe + self.cx_px
        y = self.fy_px * cam[..., 1] / safe + self.cy_px
        return torch.stack([x, y, z], dim=-1)


def distance_for_height(
    height_px: float, camera: PinholeCamera | None = None, person_height_m: float = DEFAULT_PERSON_HEIGHT_M
) -> float:
    """Camera distance (m) at which a fronto-parallel person of ``person_height_m`` spans ``height_px`` rows.

    Args:
        height_px: projected height (pixels) or a scale name from :data:`TEST_SCALES_PX`.
        camera: intrinsics (default DAVIS346 / RVT crop: same focal length).
        person_height_m: person height (m).

    Returns:
        Distance along the optical axis, m (``fy * person_height_m / height_px``).
    """
    if isinstance(height_px, str):
        if height_px not in TEST_SCALES_PX:
            raise ValueError(f"unknown scale {height_px!r}; expected one of {tuple(TEST_SCALES_PX)}")
        height_px = TEST_SCALES_PX[height_px]
    if not height_px > 0:
        raise ValueError(f"height_px must be > 0, got {height_px}")
    fy = (camera or PinholeCamera.rvt_crop()).fy_px
    return float(fy * person_height_m / height_px)


def look_at(eye_m, target_m, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World->camera extrinsics of a camera at ``eye`` looking at ``target`` (OpenCV axes).

    Args:
        eye_m: camera centre, [3] or [T, 3] (m).
        target_m: point on the optical axis, [3] or [T, 3] (m).
        up: world up direction [3] (image rows grow against it).

    Returns:
        ``(R [.., 3, 3], t [.., 3])`` float64 with ``X_cam = R X_world + t``.

    Raises:
        ValueError: eye == target, or the view direction is parallel to ``up``.
    """
    eye = np.asarray(eye_m, dtype=np.float64)
    target = np.asarray(target_m, dtype=np.float64)
    up = np.broadcast_to(np.asarray(up, dtype=np.float64), np.broadcast(eye, target).shape)
    forward = target - eye
    norm = np.linalg.norm(forward, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise ValueError("look_at: eye and target coincide")
    forward = forward / norm
    right = np.cross(forward, up)
    rnorm = np.linalg.norm(right, axis=-1, keepdims=True)
    if np.any(rnorm < 1e-9):
        raise ValueError("look_at: view direction parallel to up")
    right = right / rnorm
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward], axis=-2)  # rows = camera axes in world coordinates
    translation = -np.einsum("...ij,...j->...i", rotation, eye)
    return rotation, translation


def rotation_from_vector(rotvec) -> np.ndarray:
    """Rotation matrices of rotation vectors (axis * angle, rad), float64 [..., 3] -> [..., 3, 3] (Rodrigues)."""
    v = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)[..., None]
    axis = v / np.maximum(angle[..., 0], 1e-12)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(v.shape[:-1] + (3, 3))
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class EoTJitter:
    """Random camera perturbation for training (expectation over transformation), as the official code.

    Attributes:
        rotation_probability: chance of a rotation perturbation (official: 0.4).
        rotation_rad: each rotation-vector component uniform in +-rotation_rad (rad, camera axes).
        distance_probability: chance of a distance change (official: 0.4).
        distance_relative: distance factor uniform in ``1 +- distance_relative`` (official +-0.25 at 1.75).
    """

    rotation_probability: float = 0.4
    rotation_rad: float = 0.1
    distance_probability: float = 0.4
    distance_relative: float = 0.25 / 1.75

    def sample(self, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        """Draw one perturbation (constant over a clip).

        Returns:
            ``(rotation [3, 3] float64 applied in camera axes, distance factor)``.
        """
        rotation = np.eye(3)
        factor = 1.0
        if rng.random() < self.rotation_probability:
            rotation = rotation_from_vector(rng.uniform(-self.rotation_rad, self.rotation_rad, size=3))
        if rng.random() < self.distance_probability:
            factor = float(rng.uniform(1.0 - self.distance_relative, 1.0 + self.distance_relative))
        return rotation, factor


@dataclass(frozen=True)
class EgoMotion:
    """Smooth camera ego-motion over a clip: a sinusoidal pan/tilt plus a constant-velocity translation.

    Attributes:
        pan_amplitude_rad: yaw amplitude about the camera's y (down) axis (rad).
        tilt_amplitude_rad: pitch amplitude about the camera's x axis (rad).
        period_s: period of the pan/tilt oscillation (s).
        phase_rad: phase of the oscillation (rad).
        velocity_m_s: camera-centre velocity in world axes, [3] (m/s).
    """

    pan_amplitude_rad: float = 0.0
    tilt_amplitude_rad: float = 0.0
    period_s: float = 2.0
    phase_rad: float = 0.0
    velocity_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def random(cls, rng: np.random.Generator, max_pan_rad: float = 0.05, max_speed_m_s: float = 0.3) -> "EgoMotion":
        """A random gentle ego-motion (hand-held camera drift)."""
        direction = rng.normal(size=3)
        direction[2] *= 0.3
        direction /= np.linalg.norm(direction) + 1e-12
        return cls(
            pan_amplitude_rad=float(rng.uniform(0, max_pan_rad)),
            tilt_amplitude_rad=float(rng.uniform(0, max_pan_rad / 2)),
            period_s=float(rng.uniform(1.0, 4.0)),
            phase_rad=float(rng.uniform(0, 2 * math.pi)),
            velocity_m_s=tuple(float(v) for v in direction * rng.uniform(0, max_speed_m_s)),
        )

    def apply(self, rotation_w2c: np.ndarray, translation_w2c: np.ndarray, t_s: np.ndarray):
        """Per-frame extrinsics of the moving camera.

        Args:
            rotation_w2c: float64 [3, 3], the extrinsics at rest; translation_w2c: [3] (m).
            t_s: frame times relative to the clip start, [T] (s).

        Returns:
            ``(R [T, 3, 3], t [T, 3])`` float64.
        """
        t_s = np.asarray(t_s, dtype=np.float64)
        omega = 2 * math.pi / self.period_s
        angle = omega * t_s + self.phase_rad
        pan = self.pan_amplitude_rad * (np.sin(angle) - math.sin(self.phase_rad))
        tilt = self.tilt_amplitude_rad * (np.sin(2 * angle) - math.sin(2 * self.phase_rad))
        rotvec = np.stack([tilt, pan, np.zeros_like(pan)], axis=-1)
        delta = rotation_from_vector(rotvec)  # camera-axes rotation per frame
        rotation = delta @ rotation_w2c[None]
        centre = -rotation_w2c.T @ translation_w2c  # camera centre in world (m)
        centres = centre[None] + t_s[:, None] * np.asarray(self.velocity_m_s, dtype=np.float64)[None]
        translation = -np.einsum("tij,tj->ti", rotation, centres)
        return rotation, translation
