"""Differentiable float version of RVT's stacked histogram (torch), for the digital optimizer.

Same layout and time binning as :func:`davis_rig.events.histogram.stacked_histogram` (channel
``p * num_bins + b``, bins from the first/last event time in float32) but the counts are float sums of
optional per-event weights, **without** the uint8 wrap and the count cutoff, so gradients flow from the
histogram back to the weights (e.g. the probability that a simulated event fires).

torch is imported lazily; importing this module without torch raises
:class:`davis_rig.errors.MissingDependencyError` only when a function is called.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from davis_rig._lazy import optional_import
from davis_rig.errors import FormatError, ShapeError
from davis_rig.events.histogram import NUM_BINS, WINDOW_US
from davis_rig.types import RVT_HW

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = ["StackedHistogramTorch", "stacked_histogram_torch", "stacked_histograms_torch", "time_bins_torch"]


def _torch():
    return optional_import("torch", "the differentiable histogram")


def time_bins_torch(t_us: "torch.Tensor", num_bins: int = NUM_BINS) -> "torch.Tensor":
    """Official time-bin index (int64 [N]) of the events of one window, computed like RVT in torch.

    Args:
        t_us: event timestamps, integer tensor (µs), shape [N], non-decreasing.
        num_bins: number of time bins B.

    Returns:
        int64 tensor [N] with values in ``0 .. num_bins - 1``.
    """
    torch = _torch()
    t_us = t_us.to(torch.int64)
    if t_us.numel() == 0:
        return torch.zeros(0, dtype=torch.int64, device=t_us.device)
    span_us = max(int(t_us[-1] - t_us[0]), 1)
    t_norm = (t_us - t_us[0]).to(torch.float32) / torch.tensor(float(span_us), dtype=torch.float32)
    t_norm = t_norm * torch.tensor(float(num_bins), dtype=torch.float32)
    return torch.clamp(torch.floor(t_norm), max=num_bins - 1).to(torch.int64)


def stacked_histogram_torch(
    x,
    y,
    t_us,
    p,
    weights: "torch.Tensor | None" = None,
    *,
    height: int = RVT_HW[0],
    width: int = RVT_HW[1],
    num_bins: int = NUM_BINS,
    dtype: "torch.dtype | None" = None,
) -> "torch.Tensor":
    """Float stacked histogram of one window, differentiable w.r.t. per-event weights.

    Args:
        x: columns, integer tensor/array [N], pixels, ``0 <= x < width``.
        y: rows, integer tensor/array [N], pixels, ``0 <= y < height``.
        t_us: timestamps, integer tensor/array [N], µs, non-decreasing.
        p: polarities in {0, 1}, integer tensor/array [N] (negative values map to 0).
        weights: optional float tensor [N] added per event instead of 1 (gradients flow to it).
        height: frame height H, pixels.
        width: frame width W, pixels.
        num_bins: time bins B per polarity.
        dtype: output dtype; default ``weights.dtype`` or float32.

    Returns:
        Float tensor [2 * num_bins, H, W] on the weights' (else ``t_us``') device. Without weights it
        equals the uint8 official histogram before the wrap and the clip.

    Raises:
        ShapeError: columns of different lengths, or coordinates outside the frame.
        FormatError: polarities above 1 or decreasing timestamps.

    Example:
        >>> import torch
        >>> w = torch.ones(2, requires_grad=True)
        >>> h = stacked_histogram_torch([0, 1], [0, 0], [0, 10], [1, 0], w, height=2, width=2, num_bins=2)
        >>> h.sum().backward(); w.grad.tolist()
        [1.0, 1.0]
    """
    torch = _torch()
    device = weights.device if weights is not None else None
    t_us = torch.as_tensor(t_us, device=device)
    device = t_us.device
    x = torch.as_tensor(x, device=device).to(torch.int64)
    y = torch.as_tensor(y, device=device).to(torch.int64)
    p = torch.clamp(torch.as_tensor(p, device=device).to(torch.int64), min=0)
    n = t_us.shape[0] if t_us.ndim == 1 else -1
    for name, column in (("t_us", t_us), ("x", x), ("y", y), ("p", p)):
        if column.ndim != 1 or column.shape[0] != n:
            raise ShapeError(f"{name}: expected shape ({n},), got {tuple(column.shape)}")
    if weights is not None and tuple(weights.shape) != (n,):
        raise ShapeError(f"weights: expected shape ({n},), got {tuple(weights.shape)}")
    out_dtype = dtype or (weights.dtype if weights is not None else torch.float32)
    size = 2 * num_bins * height * width
    if n == 0:
        hist = torch.zeros(size, dtype=out_dtype, device=device)
        if weights is not None:
            hist = hist + weights.sum().to(out_dtype)  # keeps the graph connected (adds 0)
        return hist.reshape(2 * num_bins, height, width)
    if int(x.min()) < 0 or int(x.max()) >= width or int(y.min()) < 0 or int(y.max()) >= height:
        raise ShapeError(
            f"event coordinates outside the frame: expected 0 <= x < {width} and 0 <= y < {height}, "
            f"got x in [{int(x.min())}, {int(x.max())}], y in [{int(y.min())}, {int(y.max())}]"
        )
    if int(p.max()) > 1:
        raise FormatError(f"polarity: expected values in {{0, 1}}, got max {int(p.max())}")
    if n > 1 and bool((t_us[1:] < t_us[:-1]).any()):
        raise FormatError("t_us: expected non-decreasing timestamps within a window")
    bins = time_bins_torch(t_us, num_bins)
    flat = x + width * y + (height * width) * bins + (num_bins * height * width) * p
    source = weights.to(out_dtype) if weights is not None else torch.ones(n, dtype=out_dtype, device=device)
    hist = torch.zeros(size, dtype=out_dtype, device=device).index_add(0, flat, source)
    return hist.reshape(2 * num_bins, height, width)


def stacked_histograms_torch(
    x,
    y,
    t_us,
    p,
    window_end_us,
    weights: "torch.Tensor | None" = None,
    *,
    window_us: int = WINDOW_US,
    height: int = RVT_HW[0],
    width: int = RVT_HW[1],
    num_bins: int = NUM_BINS,
    dtype: "torch.dtype | None" = None,
) -> "torch.Tensor":
    """Float stacked histograms of a time-sorted stream for several windows, differentiable w.r.t. weights.

    Window ``i`` holds the events with ``end_i - window_us <= t <= end_i`` (both inclusive, as the official
    pre-processing and :func:`davis_rig.events.window_indices`); each is binned by
    :func:`stacked_histogram_torch` (its own first/last event times).

    Args:
        x, y, t_us, p: event columns [N] (tensors or arrays), time-sorted over the whole stream.
        window_end_us: window ends, µs, sequence or tensor [T].
        weights: optional float tensor [N] (gradients flow to it).
        window_us: window duration, µs.
        height, width, num_bins, dtype: as :func:`stacked_histogram_torch`.

    Returns:
        Float tensor [T, 2 * num_bins, H, W].

    Raises:
        ShapeError, FormatError: as :func:`stacked_histogram_torch`.
    """
    torch = _torch()
    device = weights.device if weights is not None else None
    t_us = torch.as_tensor(t_us, device=device).to(torch.int64)
    x, y, p = (torch.as_tensor(column, device=t_us.device) for column in (x, y, p))
    ends = torch.as_tensor(window_end_us, dtype=torch.int64, device=t_us.device).reshape(-1)
    starts = torch.searchsorted(t_us, ends - int(window_us), right=False).tolist()
    stops = torch.searchsorted(t_us, ends, right=True).tolist()
    frames = [
        stacked_histogram_torch(
            x[start:stop],
            y[start:stop],
            t_us[start:stop],
            p[start:stop],
            None if weights is None else weights[start:stop],
            height=height,
            width=width,
            num_bins=num_bins,
            dtype=dtype,
        )
        for start, stop in zip(starts, stops)
    ]
    if not frames:
        out_dtype = dtype or (weights.dtype if weights is not None else torch.float32)
        return torch.zeros((0, 2 * num_bins, height, width), dtype=out_dtype, device=t_us.device)
    return torch.stack(frames)


class StackedHistogramTorch:
    """Callable transform holding the histogram geometry (frozen settings, no state).

    Args:
        height: frame height H, pixels.
        width: frame width W, pixels.
        num_bins: time bins B per polarity.
    """

    __slots__ = ("height", "width", "num_bins")

    def __init__(self, height: int = RVT_HW[0], width: int = RVT_HW[1], num_bins: int = NUM_BINS):
        self.height = height
        self.width = width
        self.num_bins = num_bins

    def __call__(self, x, y, t_us, p, weights=None):
        """See :func:`stacked_histogram_torch`; returns float [2 * num_bins, H, W]."""
        return stacked_histogram_torch(
            x, y, t_us, p, weights, height=self.height, width=self.width, num_bins=self.num_bins
        )

    def __repr__(self) -> str:
        return f"StackedHistogramTorch(height={self.height}, width={self.width}, num_bins={self.num_bins})"
