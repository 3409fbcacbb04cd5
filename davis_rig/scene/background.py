"""Static textured backgrounds (linear intensity in [0, 1]): procedural patterns and image files.

All generators return a new float32 array [H, W]; they take an explicit ``numpy.random.Generator`` where
random. Nothing is downloaded: image backgrounds come from files the user supplies. :func:`warp_background`
renders a background as a plane seen by a moving camera (ego-motion).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError

__all__ = [
    "KINDS",
    "checker",
    "from_image",
    "gradient",
    "noise",
    "random_background",
    "rectangles",
    "stripes",
    "uniform",
    "warp_background",
]

KINDS = ("uniform", "noise", "stripes", "checker", "gradient", "rectangles")


def _check_hw(hw) -> tuple[int, int]:
    h, w = int(hw[0]), int(hw[1])
    if h < 1 or w < 1:
        raise ValueError(f"background size must be positive, got {hw}")
    return h, w


def _range(image: np.ndarray, low: float, high: float) -> np.ndarray:
    return (low + (high - low) * image).astype(np.float32)


def uniform(hw, level: float = 0.5) -> np.ndarray:
    """A constant background of intensity ``level`` (float32 [H, W])."""
    h, w = _check_hw(hw)
    return np.full((h, w), level, dtype=np.float32)


def noise(hw, rng: np.random.Generator, scale_px: float = 24.0, octaves: int = 3, low=0.15, high=0.85) -> np.ndarray:
    """Smooth multi-octave value noise (bicubic-upsampled random lattices), float32 [H, W] in [low, high]."""
    import cv2

    h, w = _check_hw(hw)
    total = np.zeros((h, w), dtype=np.float64)
    amplitude, norm = 1.0, 0.0
    for octave in range(int(octaves)):
        cell = max(2.0, scale_px / (2**octave))
        gh, gw = int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2
        lattice = rng.random((gh, gw)).astype(np.float32)
        up = cv2.resize(lattice, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
        total += amplitude * up[:h, :w]
        norm += amplitude
        amplitude *= 0.5
    total /= norm
    total = (total - total.min()) / max(total.max() - total.min(), 1e-9)
    return _range(total, low, high)


def stripes(hw, period_px: float = 20.0, angle_rad: float = 0.0, low=0.2, high=0.8, soft: bool = True) -> np.ndarray:
    """Parallel stripes of ``period_px`` at ``angle_rad`` (0 = vertical stripes), float32 [H, W]."""
    h, w = _check_hw(hw)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    phase = (xx * np.cos(angle_rad) + yy * np.sin(angle_rad)) / period_px
    wave = 0.5 + 0.5 * np.sin(2 * np.pi * phase) if soft else (np.floor(2 * phase) % 2)
    return _range(wave, low, high)


def checker(hw, cell_px: int = 16, low=0.2, high=0.8) -> np.ndarray:
    """A checkerboard of ``cell_px`` squares (top-left cell = low), float32 [H, W]."""
    h, w = _check_hw(hw)
    yy, xx = np.mgrid[0:h, 0:w]
    return _range(((yy // cell_px + xx // cell_px) % 2).astype(np.float64), low, high)


def gradient(hw, angle_rad: float = np.pi / 2, low=0.2, high=0.8) -> np.ndarray:
    """A linear ramp from ``low`` to ``high`` along ``angle_rad`` (pi/2 = top to bottom), float32 [H, W]."""
    h, w = _check_hw(hw)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    ramp = xx * np.cos(angle_rad) + yy * np.sin(angle_rad)
    ramp = (ramp - ramp.min()) / max(ramp.max() - ramp.min(), 1e-9)
    return _range(ramp, low, high)


def rectangles(hw, rng: np.random.Generator, count: int = 30, low=0.1, high=0.9) -> np.ndarray:
    """Random axis-aligned rectangles of random intensity on a random base (like buildings / posters)."""
    h, w = _check_hw(hw)
    image = np.full((h, w), rng.uniform(low, high), dtype=np.float32)
    x0 = rng.integers(0, w, count)
    y0 = rng.integers(0, h, count)
    rw = rng.integers(max(2, w // 40), max(3, w // 4), count)
    rh = rng.integers(max(2, h // 40), max(3, h // 3), count)
    levels = rng.uniform(low, high, count)
    for i in range(int(count)):  # a few dozen rectangles, not a per-pixel loop
        image[y0[i] : y0[i] + rh[i], x0[i] : x0[i] + rw[i]] = levels[i]
    return image


def from_image(path: str | Path, hw, srgb: bool = True) -> np.ndarray:
    """A background from an image file: grayscale, scaled to cover ``hw`` and centre-cropped.

    Args:
        path: any image OpenCV reads (PNG, JPEG, ...).
        hw: output (height, width), px.
        srgb: undo the sRGB transfer curve (the renderer works in linear intensity).

    Returns:
        float32 [H, W] in [0, 1].

    Raises:
        FileNotFoundError: no such file. FormatError: OpenCV cannot decode it.
    """
    import cv2

    h, w = _check_hw(hw)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"background image not found: {path}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(f"{path}: not an image OpenCV can read")
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    peak = np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer) else 1.0
    image = image.astype(np.float32) / peak
    scale = max(h / image.shape[0], w / image.shape[1])
    size = (max(w, int(round(image.shape[1] * scale))), max(h, int(round(image.shape[0] * scale))))
    image = cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    top = (image.shape[0] - h) // 2
    left = (image.shape[1] - w) // 2
    image = np.clip(image[top : top + h, left : left + w], 0.0, 1.0)
    if srgb:
        image = np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4)
    return np.ascontiguousarray(image, dtype=np.float32)


def random_background(hw, rng: np.random.Generator, kinds=KINDS) -> np.ndarray:
    """A random procedural background of one of ``kinds`` with random parameters, float32 [H, W]."""
    kind = kinds[int(rng.integers(len(kinds)))]
    low = float(rng.uniform(0.05, 0.4))
    high = float(rng.uniform(low + 0.2, 0.95))
    if kind == "uniform":
        return uniform(hw, float(rng.uniform(0.1, 0.9)))
    if kind == "noise":
        return noise(hw, rng, scale_px=float(rng.uniform(8, 64)), low=low, high=high)
    if kind == "stripes":
        return stripes(hw, float(rng.uniform(6, 60)), float(rng.uniform(0, np.pi)), low, high, bool(rng.random() < 0.5))
    if kind == "checker":
        return checker(hw, int(rng.integers(6, 48)), low, high)
    if kind == "gradient":
        return gradient(hw, float(rng.uniform(0, 2 * np.pi)), low, high)
    if kind == "rectangles":
        return rectangles(hw, rng, int(rng.integers(10, 60)), low, high)
    raise ValueError(f"unknown background kind {kind!r}; expected one of {KINDS}")


def warp_background(background: np.ndarray, camera, rotation, translation, depth_m: float,
                    reference: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Per-frame views of a background as a plane ``depth_m`` in front of a reference camera, float32 [T, H, W].

    The image ``background`` is what the reference camera sees of the plane; every frame gets the plane-induced
    homography ``K (R_rel + t_rel n^T / depth_m) K^-1`` from the reference camera to its own (``n`` = the
    reference optical axis), applied with bilinear interpolation and reflected borders.

    Args:
        background: float32 [H, W], linear intensity, the view of the reference camera.
        camera: the intrinsics (:class:`~davis_rig.scene.camera.PinholeCamera`; output size ``camera.hw``).
        rotation, translation: world -> camera extrinsics per frame, [T, 3, 3] and [T, 3] (m).
        depth_m: distance of the plane from the reference camera along its optical axis (m).
        reference: ``(rotation [3, 3], translation [3])`` of the reference camera (default: the first frame's).

    Returns:
        float32 [T, H, W].
    """
    import cv2

    k = camera.matrix.copy()
    k[0, 2] -= 0.5  # OpenCV puts pixel centres at integers
    k[1, 2] -= 0.5
    k_inv = np.linalg.inv(k)
    normal = np.array([0.0, 0.0, 1.0])
    h, w = camera.hw
    r0, t0 = (rotation[0], translation[0]) if reference is None else reference
    frames = []
    for r_k, t_k in zip(rotation, translation):  # one homography per frame (a warp is an image op)
        r_rel = r_k @ r0.T
        t_rel = t_k - r_rel @ t0
        homography = k @ (r_rel + np.outer(t_rel, normal) / depth_m) @ k_inv
        frames.append(cv2.warpPerspective(background, homography, (w, h), flags=cv2.INTER_LINEAR,
                                          borderMode=cv2.BORDER_REFLECT))
    return np.stack(frames).astype(np.float32)
