"""RVT-style spatial augmentation of histogram chunks and their boxes (one draw per chunk, applied to all windows).

Follows RVT's ``data/utils/augmentor.py`` with the Gen1 defaults of ``config/dataset/base.yaml``: horizontal
flip with p = 0.5; with p = 0.8 a zoom, zoom-in (weight 8, factor U[1, 1.5]) or zoom-out (weight 2, factor
U[1, 1.2]); rotation is off (prob 0) in RVT and not implemented. Zoom-in crops a window of
``(int(H/f), int(W/f))`` that contains the centre of a random box of the chunk's latest labelled window and
rescales it to the full frame (``nearest-exact``, as RVT); zoom-out shrinks the frame to that size and pastes it
at a random position on a zero canvas. Boxes follow the same maps, are clipped to the frame and dropped when a
side falls to ``min_side_px`` or less.

Box format: float [K, 5] ``(class, x, y, w, h)`` in frame px (top-left corner), ``None`` = unlabelled window.
Kernels return new tensors and never modify their inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ConfigError, ShapeError

with optional_dependency("training"):
    import torch
    import torch.nn.functional as F

__all__ = ["AugmentConfig", "AugmentParams", "sample_params", "apply_augment", "hflip", "zoom_in", "zoom_out"]


@dataclass(frozen=True)
class AugmentConfig:
    """Augmentation probabilities and ranges (defaults: RVT ``data_augmentation.random``).

    Raises:
        ConfigError: a value out of its range (its ``field`` names the attribute).
    """

    prob_hflip: float = 0.5
    zoom_prob: float = 0.8
    zoom_in_weight: float = 8.0
    zoom_in_range: tuple[float, float] = (1.0, 1.5)
    zoom_out_weight: float = 2.0
    zoom_out_range: tuple[float, float] = (1.0, 1.2)
    min_side_px: float = 1.0

    @classmethod
    def rvt_stream(cls) -> "AugmentConfig":
        """RVT ``data_augmentation.stream``: flip p 0.5, zoom-out only (p 0.5, factor U[1, 1.2])."""
        return cls(prob_hflip=0.5, zoom_prob=0.5, zoom_in_weight=0.0, zoom_out_weight=1.0)

    @classmethod
    def off(cls) -> "AugmentConfig":
        """No augmentation."""
        return cls(prob_hflip=0.0, zoom_prob=0.0)

    def __post_init__(self):
        for name in ("prob_hflip", "zoom_prob"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(name, f"expected a probability in [0, 1], got {getattr(self, name)}")
        for name in ("zoom_in_weight", "zoom_out_weight"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"expected ≥ 0, got {getattr(self, name)}")
        if self.zoom_in_weight + self.zoom_out_weight <= 0:
            raise ConfigError("zoom_in_weight", "the zoom weights must have a positive sum, got 0 and 0")
        for name in ("zoom_in_range", "zoom_out_range"):
            lo, hi = getattr(self, name)
            if not 1 <= lo <= hi:
                raise ConfigError(name, f"zoom factors must satisfy 1 ≤ min ≤ max, got {(lo, hi)}")


@dataclass(frozen=True)
class AugmentParams:
    """One draw: flip, then at most one of zoom-in / zoom-out (factor 1 = off) with its window origin (px)."""

    hflip: bool = False
    zoom_in: float = 1.0
    zoom_out: float = 1.0
    x0: int = 0
    y0: int = 0


def _uniform(generator: torch.Generator, lo: float, hi: float) -> float:
    return float(lo + (hi - lo) * torch.rand((), generator=generator).item())


def sample_params(config: AugmentConfig, generator: torch.Generator, frame_hw: tuple[int, int],
                  latest_boxes: torch.Tensor | None) -> AugmentParams:
    """Draw the augmentation of one chunk.

    Args:
        config: probabilities and ranges.
        generator: CPU torch generator (its state is saved with training checkpoints).
        frame_hw: (height, width) of the histograms, px.
        latest_boxes: float [K, 5] boxes of the chunk's latest labelled window (zoom-in keeps one in view),
            or ``None``/empty (zoom-in is then skipped, as RVT does).

    Returns:
        The parameters.
    """
    height, width = frame_hw
    hflip = bool(torch.rand((), generator=generator).item() < config.prob_hflip)
    do_zoom = bool(torch.rand((), generator=generator).item() < config.zoom_prob)
    total = config.zoom_in_weight + config.zoom_out_weight
    zoom_in_chosen = bool(torch.rand((), generator=generator).item() * total < config.zoom_in_weight)
    if not do_zoom:
        return AugmentParams(hflip=hflip)
    if zoom_in_chosen:
        factor = _uniform(generator, *config.zoom_in_range)
        if factor == 1.0 or latest_boxes is None or latest_boxes.shape[0] == 0:
            return AugmentParams(hflip=hflip)
        win_h, win_w = int(height / factor), int(width / factor)
        pick = int(torch.randint(latest_boxes.shape[0], (), generator=generator).item())
        box = latest_boxes[pick].tolist()
        x_c = box[1] + box[3] / 2
        y_c = box[2] + box[4] / 2
        if hflip:
            x_c = width - x_c
        x_lo, x_hi = max(0, int(x_c) - win_w + 1), min(width - win_w, int(x_c))
        y_lo, y_hi = max(0, int(y_c) - win_h + 1), min(height - win_h, int(y_c))
        x_lo, y_lo = min(x_lo, x_hi), min(y_lo, y_hi)
        x0 = int(torch.randint(x_lo, x_hi + 1, (), generator=generator).item())
        y0 = int(torch.randint(y_lo, y_hi + 1, (), generator=generator).item())
        return AugmentParams(hflip=hflip, zoom_in=factor, x0=x0, y0=y0)
    factor = _uniform(generator, *config.zoom_out_range)
    win_h, win_w = int(height / factor), int(width / factor)
    x0 = int(_uniform(generator, 0, width - win_w))
    y0 = int(_uniform(generator, 0, height - win_h))
    return AugmentParams(hflip=hflip, zoom_out=factor, x0=x0, y0=y0)


def _clip_boxes(boxes: torch.Tensor, frame_hw: tuple[int, int], min_side_px: float) -> torch.Tensor:
    height, width = frame_hw
    x1 = boxes[:, 1].clamp(0, width)
    y1 = boxes[:, 2].clamp(0, height)
    x2 = (boxes[:, 1] + boxes[:, 3]).clamp(0, width)
    y2 = (boxes[:, 2] + boxes[:, 4]).clamp(0, height)
    out = torch.stack([boxes[:, 0], x1, y1, x2 - x1, y2 - y1], dim=1)
    return out[(out[:, 3] > min_side_px) & (out[:, 4] > min_side_px)]


def hflip(hist: torch.Tensor, boxes: list[torch.Tensor | None]) -> tuple[torch.Tensor, list[torch.Tensor | None]]:
    """Mirror the chunk left-right: ``x' = W − x − w``.

    Args:
        hist: [L, C, H, W] histograms (any dtype).
        boxes: L entries of float [K, 5] or ``None``.

    Returns:
        (flipped histograms, flipped boxes), new tensors.
    """
    width = hist.shape[-1]
    out = []
    for b in boxes:
        if b is None:
            out.append(None)
            continue
        b = b.clone()
        b[:, 1] = width - b[:, 1] - b[:, 3]
        out.append(b)
    return torch.flip(hist, dims=[-1]), out


def _zoom_window(name: str, hw: tuple[int, int], factor: float, x0: int, y0: int) -> tuple[int, int]:
    """The zoom window ``(int(H/f), int(W/f))`` (px); ShapeError naming ``name`` if at (x0, y0) it leaves the frame."""
    height, width = hw
    win_h, win_w = int(height / factor), int(width / factor)
    if not (0 <= x0 <= width - win_w and 0 <= y0 <= height - win_h):
        raise ShapeError(f"{name}: window {win_w}×{win_h} at ({x0}, {y0}) leaves the {width}×{height} frame")
    return win_h, win_w


def _scale_boxes(boxes: list[torch.Tensor | None], x_of, y_of, sx: float, sy: float, hw: tuple[int, int],
                 min_side_px: float) -> list[torch.Tensor | None]:
    """Boxes ``(class, x, y, w, h)`` mapped to ``(class, x_of(x), y_of(y), w sx, h sy)`` and clipped to the frame
    (:func:`_clip_boxes`); ``None`` entries stay ``None``."""
    return [None if b is None else
            _clip_boxes(torch.stack([b[:, 0], x_of(b[:, 1]), y_of(b[:, 2]), b[:, 3] * sx, b[:, 4] * sy], 1), hw,
                        min_side_px)
            for b in boxes]


def zoom_in(hist: torch.Tensor, boxes: list[torch.Tensor | None], factor: float, x0: int, y0: int,
            min_side_px: float = 1.0) -> tuple[torch.Tensor, list[torch.Tensor | None]]:
    """Crop the window ``[y0, y0 + int(H/f)) × [x0, x0 + int(W/f))`` and rescale it to H × W (nearest-exact).

    Args:
        hist: float [L, C, H, W]. boxes: L entries of float [K, 5] or ``None``.
        factor: zoom factor f ≥ 1. x0, y0: window origin, px.
        min_side_px: drop boxes whose clipped side is ≤ this.

    Returns:
        (zoomed histograms, transformed boxes).

    Raises:
        ShapeError: the window leaves the frame.
    """
    height, width = hist.shape[-2:]
    win_h, win_w = _zoom_window("zoom_in", (height, width), factor, x0, y0)
    crop = hist[..., y0:y0 + win_h, x0:x0 + win_w]
    out = F.interpolate(crop, size=(height, width), mode="nearest-exact")
    sx, sy = width / win_w, height / win_h
    return out, _scale_boxes(boxes, lambda x: (x - x0) * sx, lambda y: (y - y0) * sy, sx, sy, (height, width),
                             min_side_px)


def zoom_out(hist: torch.Tensor, boxes: list[torch.Tensor | None], factor: float, x0: int, y0: int,
             min_side_px: float = 1.0) -> tuple[torch.Tensor, list[torch.Tensor | None]]:
    """Shrink the frame to ``(int(H/f), int(W/f))`` (nearest-exact) and paste it at (x0, y0) on zeros.

    Args and Returns: as :func:`zoom_in`.
    """
    height, width = hist.shape[-2:]
    win_h, win_w = _zoom_window("zoom_out", (height, width), factor, x0, y0)
    small = F.interpolate(hist, size=(win_h, win_w), mode="nearest-exact")
    out = torch.zeros_like(hist)
    out[..., y0:y0 + win_h, x0:x0 + win_w] = small
    sx, sy = win_w / width, win_h / height
    return out, _scale_boxes(boxes, lambda x: x * sx + x0, lambda y: y * sy + y0, sx, sy, (height, width),
                             min_side_px)


def apply_augment(hist: torch.Tensor, boxes: list[torch.Tensor | None], params: AugmentParams,
                  min_side_px: float = 1.0) -> tuple[torch.Tensor, list[torch.Tensor | None]]:
    """Apply one draw to a chunk: flip, then zoom-in or zoom-out.

    Args:
        hist: float [L, C, H, W] histograms of one chunk (one sample of the batch).
        boxes: L entries of float [K, 5] ``(class, x, y, w, h)`` or ``None``.
        params: from :func:`sample_params`.
        min_side_px: drop boxes whose clipped side is ≤ this after a zoom.

    Returns:
        (augmented histograms [L, C, H, W], boxes), new tensors; the inputs are unchanged.

    Raises:
        ShapeError: ``hist`` is not 4-D or ``boxes`` has not L entries.
    """
    if hist.ndim != 4 or len(boxes) != hist.shape[0]:
        raise ShapeError(f"apply_augment: expected hist [L, C, H, W] and L box entries, got {tuple(hist.shape)} "
                         f"and {len(boxes)}")
    if params.hflip:
        hist, boxes = hflip(hist, boxes)
    if params.zoom_in > 1.0:
        hist, boxes = zoom_in(hist, boxes, params.zoom_in, params.x0, params.y0, min_side_px)
    elif params.zoom_out > 1.0:
        hist, boxes = zoom_out(hist, boxes, params.zoom_out, params.x0, params.y0, min_side_px)
    return hist, boxes
