"""Procedural painting of synthetic scenes: clothing textures and the 2-D distractor and car layers.

- :func:`clothing_texture`: random grey/colour per body part, stripes, checks, black/white grids of 10..60 cells,
  plain white, plain black, the paper's random 60 x 60 pattern (a texture of the body's UV map);
- :func:`distractor_layers`: textured 2-D boxes, discs and bars (:class:`~.scenes.DistractorSpec`) behind or in
  front of the people, as alpha and premultiplied intensity per frame;
- :func:`vehicle_layers`: side-view cars (:class:`~.scenes.VehicleSpec`), one layer per car.

Objects are supersampled (``supersample`` samples per pixel side) and box-filtered to pixels. numpy only.
"""

from __future__ import annotations

import math

import numpy as np

from davis_rig.training.synthetic.scenes import CLOTHING_KINDS

__all__ = ["clothing_texture", "distractor_layers", "vehicle_layers"]

#: Skin grey level range (linear intensity) for head and hands.
_SKIN = (0.15, 0.6)
#: Texture resolution of part-based / procedural clothing (grid of the 1024 UV map).
_CLOTHING_TEXELS = 256


def clothing_texture(kind: str, seed: int, label_map: np.ndarray | None = None) -> np.ndarray:
    """A clothing texture: an ``n x n`` grid of linear reflectances, nearest-upsampled onto the body's UV map.

    Clothing covers torso, arms and legs; head and hands get one skin grey level, feet one shoe level
    (every kind, also white/black/pattern: the test subsets dress the body, not the skin).

    Args:
        kind: ``"parts_grey"`` (a random grey per part), ``"parts_colour"`` (a random RGB colour per part, as
            the DVS sees it: luma), ``"stripes"`` (random period, angle, two levels), ``"checks"`` (random
            cell, two levels), ``"grid"`` (a random black/white grid of 10..60 cells per side), ``"white"``
            (1.0), ``"black"`` (0.0), ``"pattern60"`` (the paper's random black/white 60 x 60 grid).
        seed: seed of the random parameters.
        label_map: uint8 [S, S] part labels of the UV map (:func:`~davis_rig.scene.masks.part_label_map`);
            default: the bundled body's at 256 texels.

    Returns:
        float32 [n, n] in [0, 1], ``n`` = the label map size (grids are nearest-upsampled to it, so skin and
        shoe parts can be set per texel).

    Raises:
        ValueError: unknown kind.
    """
    from davis_rig.scene.body import PART_NAMES
    from davis_rig.scene.masks import part_label_map

    if kind not in CLOTHING_KINDS:
        raise ValueError(f"kind: expected one of {CLOTHING_KINDS}, got {kind!r}")
    labels = part_label_map(_CLOTHING_TEXELS) if label_map is None else np.asarray(label_map)
    n = labels.shape[0]
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64) + 0.5
    levels = np.sort(rng.uniform(0.0, 1.0, 2))
    if kind == "parts_grey":
        per_part = rng.uniform(0.02, 1.0, len(PART_NAMES) + 1)
        cloth = per_part[np.minimum(labels, len(PART_NAMES))]
    elif kind == "parts_colour":
        rgb = rng.uniform(0.0, 1.0, (len(PART_NAMES) + 1, 3)) ** 2.2  # sRGB-ish colours to linear
        per_part = rgb @ np.array([0.2126, 0.7152, 0.0722])
        cloth = per_part[np.minimum(labels, len(PART_NAMES))]
    elif kind == "stripes":
        period = rng.uniform(0.02, 0.2) * n
        angle = rng.uniform(0, math.pi)
        phase = (cols * math.cos(angle) + rows * math.sin(angle)) / period
        cloth = np.where(np.floor(2 * phase) % 2 == 0, levels[0], levels[1])
    elif kind == "checks":
        cell = rng.uniform(0.015, 0.12) * n
        cloth = np.where((np.floor(rows / cell) + np.floor(cols / cell)) % 2 == 0, levels[0], levels[1])
    elif kind in ("grid", "pattern60"):
        cells = 60 if kind == "pattern60" else int(rng.integers(10, 61))
        grid = rng.integers(0, 2, (cells, cells)).astype(np.float64)
        index = (np.arange(n) * cells) // n
        cloth = grid[index][:, index]
    elif kind == "white":
        cloth = np.ones((n, n))
    else:  # black
        cloth = np.zeros((n, n))
    skin = rng.uniform(*_SKIN)
    shoes = rng.uniform(0.02, 0.5)
    out = np.array(cloth, dtype=np.float64)
    out[(labels == PART_NAMES.index("head")) | (labels == PART_NAMES.index("hands"))] = skin
    out[labels == PART_NAMES.index("feet")] = shoes
    return out.astype(np.float32)

def _local_coordinates(cx: np.ndarray, cy: np.ndarray, angle: np.ndarray, reach: float, hw: tuple[int, int],
                       supersample: int):
    """Object-local coordinates of the supersamples an object centred at ``(cx, cy)`` [T] may touch.

    Returns:
        ``(u, v, (y0, y1, x0, x1))``: u, v float64 [T, (y1-y0) s, (x1-x0) s] along and across the object (px)
        over the pixel box ``[y0, y1) x [x0, x1)``; ``None`` when the object misses the frame.
    """
    h, w = hw
    s = supersample
    x0, x1 = max(0, int(cx.min() - reach)), min(w, int(math.ceil(cx.max() + reach)))
    y0, y1 = max(0, int(cy.min() - reach)), min(h, int(math.ceil(cy.max() + reach)))
    if x1 <= x0 or y1 <= y0:
        return None
    dx = (np.arange(x0 * s, x1 * s) + 0.5)[None, None, :] / s - cx[:, None, None]  # [T, 1, w s]
    dy = (np.arange(y0 * s, y1 * s) + 0.5)[None, :, None] / s - cy[:, None, None]  # [T, h s, 1]
    c, sn = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    return c * dx + sn * dy, -sn * dx + c * dy, (y0, y1, x0, x1)


def _paint(u: np.ndarray, v: np.ndarray, level: float, contrast: float, pattern: str, period_px: float):
    """Intensity of a ``"flat"``, ``"stripes"`` or ``"checks"`` paint at object-local ``(u, v)``, in [0, 1]."""
    if pattern == "stripes":
        sign = np.where(np.floor(2 * u / period_px) % 2 == 0, 1.0, -1.0)
    elif pattern == "checks":
        sign = np.where((np.floor(u / period_px) + np.floor(v / period_px)) % 2 == 0, 1.0, -1.0)
    else:
        sign = np.zeros_like(u)
    return np.clip(level + contrast * sign, 0.0, 1.0)


def _pixel_means(inside: np.ndarray, value: np.ndarray, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Box-filter supersamples [T, h s, w s] to pixels: coverage and premultiplied value, float32 [T, h, w]."""
    n, hs, ws = inside.shape
    s = supersample
    shape = (n, hs // s, s, ws // s, s)
    alpha = inside.reshape(shape).mean(axis=(2, 4)).astype(np.float32)
    return alpha, (inside * value).reshape(shape).mean(axis=(2, 4)).astype(np.float32)


def distractor_layers(distractors, t_s: np.ndarray, hw: tuple[int, int], supersample: int = 2):
    """Alpha and intensity of the distractors per frame, back and front layers.

    Returns:
        ``{"back": (alpha [T, H, W], value [T, H, W]), "front": (...)}`` float32 (value premultiplied).
    """
    n = len(t_s)
    out = {}
    for layer in ("back", "front"):
        alpha = np.zeros((n, *hw), dtype=np.float32)
        value = np.zeros((n, *hw), dtype=np.float32)
        for d in (d for d in distractors if d.front == (layer == "front")):  # <= 3 objects
            cx = d.start_xy_px[0] + d.velocity_px_s[0] * t_s  # [T]
            cy = d.start_xy_px[1] + d.velocity_px_s[1] * t_s
            reach = 0.5 * math.hypot(*d.size_px) + 1.0  # only the pixels the object can touch in this chunk
            local = _local_coordinates(cx, cy, d.angle_rad + d.spin_rad_s * t_s, reach, hw, supersample)
            if local is None:
                continue
            u, v, (y0, y1, x0, x1) = local
            half_w, half_h = d.size_px[0] / 2, d.size_px[1] / 2
            if d.kind == "disc":
                inside = u * u + v * v <= half_w * half_w
            else:
                inside = (np.abs(u) <= half_w) & (np.abs(v) <= half_h)
            a, val = _pixel_means(inside, _paint(u, v, d.level, d.contrast, d.pattern, d.period_px), supersample)
            region = (slice(None), slice(y0, y1), slice(x0, x1))
            value[region] = value[region] * (1 - a) + val  # later objects in front of earlier ones
            alpha[region] = alpha[region] * (1 - a) + a
        out[layer] = (alpha, value)
    return out


def vehicle_layers(vehicles, t_s: np.ndarray, hw: tuple[int, int], supersample: int = 2):
    """Per car (:class:`~.scenes.VehicleSpec`), its own coverage and premultiplied intensity per frame.

    Returns:
        list of ``(alpha [T, H, W], value [T, H, W])`` float32, in drawing order (later cars in front).
    """
    n = len(t_s)
    out = []
    for car in vehicles:
        alpha = np.zeros((n, *hw), dtype=np.float32)
        value = np.zeros((n, *hw), dtype=np.float32)
        length = car.length_px
        cx = car.start_xy_px[0] + car.velocity_px_s[0] * t_s
        cy = car.start_xy_px[1] + car.velocity_px_s[1] * t_s
        local = _local_coordinates(cx, cy, np.zeros_like(t_s), 0.6 * length + 1.0, hw, supersample)
        if local is not None:
            u, v, (y0, y1, x0, x1) = local
            cabin_u = u + math.copysign(0.06 * length, car.velocity_px_s[0] or 1.0)  # cabin towards the rear
            body = (np.abs(u) <= 0.5 * length) & (v >= -0.08 * length) & (v <= 0.18 * length)
            cabin = (np.abs(cabin_u) <= 0.25 * length) & (v >= -0.28 * length) & (v < -0.08 * length)
            windows = ((np.abs(cabin_u) <= 0.21 * length) & (np.abs(cabin_u) >= 0.015 * length)
                       & (v >= -0.25 * length) & (v <= -0.11 * length))
            wheels = (np.abs(u) - 0.3 * length) ** 2 + (v - 0.18 * length) ** 2 <= (0.11 * length) ** 2
            shade = np.where(wheels, 0.05, np.where(windows, car.window_level,
                                                    _paint(u, v, car.level, car.contrast, car.pattern,
                                                           car.period_px)))
            a, val = _pixel_means(body | cabin | wheels, shade, supersample)
            alpha[:, y0:y1, x0:x1] = a
            value[:, y0:y1, x0:x1] = val
        out.append((alpha, value))
    return out

