"""The DVS pixel's view of intensity, shared by the exact simulator and the differentiable V2E (torch, lazy).

- :func:`rgb_to_luma`: RGB frames → luma with the ITU-R BT.601 weights :data:`LUMA_WEIGHTS` (as the paper's
  official code);
- :func:`lin_log`: v2e's lin-log mapping of ``INTENSITY_SCALE · I`` (linear intensity in [0, 1] → 8-bit-like DN):
  linear ``x · ln(20) / 20`` for ``x ≤ 20`` (dark pixels: a pure log would make sensor-noise-sized changes of dark
  pixels fire storms of events) and ``ln(x)`` above, continuous at the knee :data:`LIN_LOG_THRESHOLD`;
- :data:`DEFAULT_THRESHOLD`: the paper's contrast threshold θ in these log units.

:mod:`davis_rig.events.simulator` and :mod:`davis_rig.events.v2e_torch` both take their log intensity from here,
so their forward values are the same numbers.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = ["DEFAULT_THRESHOLD", "INTENSITY_SCALE", "LIN_LOG_THRESHOLD", "LUMA_WEIGHTS", "lin_log", "rgb_to_luma"]

#: The paper's contrast threshold θ (log units), both polarities.
DEFAULT_THRESHOLD = 0.2
#: Linear intensity in [0, 1] is multiplied by this before :func:`lin_log` (8-bit-like DN).
INTENSITY_SCALE = 255.0
#: v2e's lin-log knee, in ``INTENSITY_SCALE`` units (8-bit-like DN): linear below, ln above.
LIN_LOG_THRESHOLD = 20.0
#: ITU-R BT.601 luma weights (R, G, B), as in the paper's official code.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)


def lin_log(x: "torch.Tensor", threshold: float = LIN_LOG_THRESHOLD) -> "torch.Tensor":
    """v2e's lin-log mapping: ``x · ln(threshold)/threshold`` for ``x ≤ threshold``, else ``ln(x)`` (differentiable).

    Args:
        x: non-negative intensities in ``intensity_scale`` units (e.g. 0..255), float tensor of any shape.
        threshold: the knee, same units as ``x``.

    Returns:
        Float tensor shaped like ``x``, log units; continuous at the knee (both sides give ``ln(threshold)``).

    Example:
        >>> import torch
        >>> lin_log(torch.tensor([0.0, 20.0, 255.0])).tolist()  # doctest: +ELLIPSIS
        [0.0, 2.99..., 5.54...]
    """
    torch = optional_import("torch", "the lin-log mapping")
    slope = math.log(threshold) / threshold
    # clamp inside the log so that the unused branch never produces -inf/NaN gradients.
    return torch.where(x <= threshold, x * slope, torch.log(torch.clamp(x, min=threshold)))


def rgb_to_luma(rgb: "torch.Tensor") -> "torch.Tensor":
    """Luma ``Y = 0.299 R + 0.587 G + 0.114 B`` of RGB frames (differentiable).

    Args:
        rgb: float tensor [..., 3, H, W] (channel axis third from last).

    Returns:
        Float tensor [..., H, W].

    Raises:
        ShapeError: the channel axis does not have 3 entries.
    """
    if rgb.ndim < 3 or rgb.shape[-3] != 3:
        raise ShapeError(f"rgb: expected [..., 3, H, W], got {tuple(rgb.shape)}")
    r, g, b = rgb.unbind(-3)
    return LUMA_WEIGHTS[0] * r + LUMA_WEIGHTS[1] * g + LUMA_WEIGHTS[2] * b
