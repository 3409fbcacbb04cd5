"""The paper's differentiable video-to-event (V2E) conversion, straight into RVT's stacked-histogram layout (torch).

From a luminance video ``I`` [T, H, W] (linear intensity in [0, 1]; RGB [T, 3, H, W] is reduced to
``Y = 0.299 R + 0.587 G + 0.114 B``) and frame times ``t_us`` [T], every frame pair ``k → k+1`` gets per-pixel ON
and OFF event counts ``N⁺_k, N⁻_k`` [T-1, H, W], which are summed into RVT's input ``[windows, 2·B, H, W]`` (channel
``p·B + b``, B = 10 bins per 50 ms window, counts clipped at 10). Log intensity is v2e's lin-log of ``255 · I``
(:func:`davis_rig.events.intensity.lin_log`), exactly as in the exact simulator.

Count modes (``mode``):

* ``"dvs"`` (default) — the exact simulator's per-pixel reference with hysteresis, unrolled over the frames:
  ``N⁺ = h(⌊(L_{k+1} − L_ref)/θ_on⌋)``, ``N⁻ = h(⌊(L_ref − L_{k+1})/θ_off⌋)``, ``L_ref += N⁺θ_on − N⁻θ_off``.
  Forward counts are **identical** to :class:`~davis_rig.events.simulator.EventSimulator` (noise-free, same
  dtype): same formulas, same operations.
* ``"floor"`` — the paper's appendix literally: ``Ŝ_k = (L_k − L_0)/θ``, ``S_k = ⌊Ŝ_k⌋ + r_k``, ``D = S_{k+1} − S_k``,
  ``N⁺ = h(D)``, ``N⁻ = h(−D)``. It counts crossings of a fixed level grid ``L_0 + nθ`` without hysteresis, and
  ``⌊·⌋`` makes it asymmetric: ON levels are ``L_0 + θ, L_0 + 2θ, ...`` (as the DVS) but OFF levels are
  ``L_0, L_0 − θ, ...`` — a pixel darkening by less than θ already fires one OFF. So it equals the DVS model for
  brightening pixels, gives one extra OFF per darkening pixel, and one extra event per direction reversal
  (e.g. up 1.5 θ then down 1.0 θ: grid 1 ON + 1 OFF, DVS 1 ON + 0 OFF). Tests quantify both.
* ``"official_relaxed"`` — the paper's official code (for comparison only): no floor (``S = Ŝ``), continuous
  counts ``h(±D)`` scaled by ``10/27`` (``10 / ⌊ln 255 / 0.2⌋``). Its per-bin ±1 "sign-correction residual" is not
  reproduced. Not events: do not use it to score attacks.

Gradients: ``⌊·⌋`` is the straight-through surrogate of the paper (``S = ⌊Ŝ⌋ + r`` with the residual
``r = Ŝ − ⌊Ŝ⌋`` treated as a constant, i.e. forward floor, backward identity); ``h`` is ``relu``, so gradient
flows where a count is positive (pixels that fire), as in the paper. In ``"dvs"`` mode the reference update uses
the surrogate counts, so ``∂N⁺_k/∂L ≈ (δ_{k+1} − δ_k)/θ`` like the paper's ``D``.

Binning frame pairs into windows (``binning``) — the boundary rules, and how they relate to real event windows:

* ``"rvt_frame_end"`` — a pair is stamped at its end frame ``t_{k+1}``; a window ``[e − w, e]`` takes the pairs with
  ``e − w ≤ t_{k+1} ≤ e`` (both ends inclusive like RVT), and bins follow RVT's rule exactly (float32,
  ``t0``/``t1`` = first/last pair in the window **that fired**, i.e. the first/last event time). The result
  equals ``stacked_histograms(simulate_events(..., timestamps="frame_end"), ends)`` exactly (tests prove it), up to
  RVT's uint8 wrap at 256 events per cell (not reproduced). Caveat: a pair ending exactly at ``e − w`` counts in
  both windows (RVT does the same for events on the boundary), and at 200 fps pair ``(e−50, e−45] ms`` lands in
  bin 1, not 0.
* ``"interval"`` (default) — a window takes the pairs with ``e − w < t_{k+1} ≤ e`` (the changes observed during the
  window, no double counting) and each pair goes to the fixed-grid bin of its midpoint,
  ``⌊(t_mid − (e − w)) / w · B⌋``. With interpolated event times (the realistic simulator) the per-pixel totals of a
  window are identical; when the frame times lie on the bin grid (200 fps × n) each bin holds exactly the events
  of its half-open-left time slice; RVT's own bins (from the first/last event) can differ from it at bin edges
  by the events of one pair.

Use in the digital attack (one window per RVT step; the windows' ends on the frame grid)::

    clip = render_clip(spec, texture)                                  # clip.video [T, 240, 304], grad to texture
    ends = clip.t_us[0] + 50_000 * np.arange(1, n_windows + 1)
    hist = v2e_histograms(clip.video, clip.t_us, ends)                 # [n_windows, 20, 240, 304]
    x = pad_to_input(hist)                                             # davis_rig.models.rvt.detector

Several count modes of one video (the attack's exact counts and relaxed surrogate) share one lin-log video:
``log = log_intensity(video)``, then ``log_histograms(log, t_us, ends, mode=...)`` per mode (equal to
:func:`v2e_histograms`, bit for bit).

Test time (quantized events, what a camera would deliver): ``stacked_histograms(simulate_events(video, t_us), ends)``.

Measured (``benchmarks/v2e.py``, 304 × 240, 11 frames at 200 fps, fp32, 2-core shared CPU under load): ``"dvs"``
forward ≈ 7–11 ms and forward + backward ≈ 14–30 ms per 50 ms window (2 / 1 threads), i.e. 6–7 % of RVT-B's
forward + backward (243 / 436 ms). The attack's per-window cost (rendering + V2E as the optimiser runs them vs
RVT-B): ``benchmarks/digital_cost.py``.

torch is imported lazily (MissingDependencyError names the extra).
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import FormatError, ShapeError
from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS, WINDOW_US
from davis_rig.events.intensity import DEFAULT_THRESHOLD, INTENSITY_SCALE, LIN_LOG_THRESHOLD, lin_log, rgb_to_luma

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = [
    "MODES",
    "BINNINGS",
    "OFFICIAL_RELAXED_SCALE",
    "DifferentiableV2E",
    "floor_ste",
    "log_histograms",
    "log_intensity",
    "pair_bins",
    "v2e_counts",
    "v2e_histograms",
]

#: The official code's histogram scaling, 10 / floor(ln 255 / 0.2) = 10 / 27.
OFFICIAL_RELAXED_SCALE = 10.0 / 27.0
MODES = ("dvs", "floor", "official_relaxed")
BINNINGS = ("interval", "rvt_frame_end")


def _torch():
    return optional_import("torch", "the differentiable V2E")


# The autograd Functions are classes over torch: each is built once, on first use (torch is imported lazily).
@functools.cache
def _floor_ste_fn():
    torch = _torch()

    class FloorSTE(torch.autograd.Function):
        """Forward ``floor`` (exact), backward identity (straight-through estimator)."""

        @staticmethod
        def forward(ctx, x):
            return torch.floor(x)

        @staticmethod
        def backward(ctx, grad):
            return grad

    return FloorSTE


@functools.cache
def _lin_log_fn():
    """``lin_log(scale · x)`` as one autograd Function: the simulator's exact forward, a 4-kernel backward."""
    torch = _torch()

    class ScaledLinLog(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x, scale, threshold):
            scaled = x * scale
            ctx.save_for_backward(x)
            ctx.scale, ctx.threshold = scale, threshold
            return lin_log(scaled, threshold)

        @staticmethod
        def backward(ctx, grad):
            (x,) = ctx.saved_tensors
            slope = math.log(ctx.threshold) / ctx.threshold
            # d/dx: scale · ln(thr)/thr below the knee, d ln(scale x)/dx = 1/x above it
            dydx = torch.where(x * ctx.scale <= ctx.threshold, ctx.scale * slope, torch.reciprocal(x))
            return grad * dydx, None, None

    return ScaledLinLog


@functools.cache
def _dvs_fn():
    """The ``"dvs"`` recursion as one autograd Function (forward under no_grad, analytic STE backward).

    Gradients are exactly those of the unrolled graph ``on = relu(floor_ste(d/θ_on))``,
    ``off = relu(floor_ste(−d/θ_off))``, ``d = L_{k+1} − ref``, ``ref += θ_on on − θ_off off`` (see
    :func:`_dvs_counts_unrolled`, which the tests compare it with), with fewer kernels and saved tensors.
    """
    torch = _torch()

    class DvsCounts(torch.autograd.Function):
        @staticmethod
        def forward(ctx, log_video, theta_on, theta_off):
            # the same operations as the exact simulator, written into preallocated outputs and buffers (the
            # recurrence through ref keeps the loop over frames)
            on = torch.empty_like(log_video[1:])
            off = torch.empty_like(on)
            step_on, step_off = torch.empty_like(log_video[0]), torch.empty_like(log_video[0])
            ref = log_video[0]
            for k in range(on.shape[0]):
                diff = log_video[k + 1] - ref
                torch.div(diff, theta_on, out=on[k]).floor_().clamp_(min=0)
                torch.div(diff.neg_(), theta_off, out=off[k]).floor_().clamp_(min=0)
                ref = ref + torch.mul(on[k], theta_on, out=step_on)
                ref -= torch.mul(off[k], theta_off, out=step_off)
            ctx.save_for_backward(on, off, theta_on, theta_off)
            return on, off

        @staticmethod
        def backward(ctx, grad_on, grad_off):
            on, off, theta_on, theta_off = ctx.saved_tensors
            m_on = (on > 0).to(on.dtype)
            m_off = (off > 0).to(off.dtype)
            if grad_on is None:
                grad_on = torch.zeros_like(on)
            if grad_off is None:
                grad_off = torch.zeros_like(off)
            # gd_k = ∂loss/∂d_k = A_k + g_ref · M_k with A = g_on m_on/θ_on − g_off m_off/θ_off, M = m_on + m_off;
            # the reference carries g_ref ← g_ref − gd_k = g_ref (1 − M_k) − A_k back to the previous pair.
            a = grad_on * m_on / theta_on - grad_off * m_off / theta_off
            m = m_on + m_off
            keep = 1.0 - m
            neg_a = -a
            grad_video = torch.empty((on.shape[0] + 1, *on.shape[1:]), dtype=on.dtype, device=on.device)
            g_ref = torch.zeros_like(on[0])
            for k in range(on.shape[0] - 1, -1, -1):
                torch.addcmul(a[k], g_ref, m[k], out=grad_video[k + 1])
                g_ref = torch.addcmul(neg_a[k], g_ref, keep[k])
            grad_video[0] = g_ref
            return grad_video, None, None

    return DvsCounts


def _dvs_counts_unrolled(log_video, threshold_on, threshold_off):
    """Reference implementation of the ``"dvs"`` counts as a plain autograd graph (tests compare the fused one)."""
    torch = _torch()
    frames = log_video.unbind(0)
    ref = frames[0]
    ons, offs = [], []
    for frame in frames[1:]:
        diff = frame - ref
        on = torch.relu(floor_ste(diff / threshold_on))
        off = torch.relu(floor_ste(-diff / threshold_off))
        ref = ref + on * threshold_on - off * threshold_off
        ons.append(on)
        offs.append(off)
    return torch.stack(ons), torch.stack(offs)


def floor_ste(x: "torch.Tensor") -> "torch.Tensor":
    """``⌊x⌋`` in the forward pass (bit-exact), identity gradient in the backward pass (the paper's ``⌊Ŝ⌋ + r``).

    Args:
        x: float tensor of any shape.

    Returns:
        Float tensor shaped like ``x``.
    """
    return _floor_ste_fn().apply(x)


def log_intensity(
    video,
    *,
    intensity_scale: float = INTENSITY_SCALE,
    lin_log_threshold: float = LIN_LOG_THRESHOLD,
) -> "torch.Tensor":
    """The log video the counts are taken from: v2e's lin-log of ``intensity_scale · Y`` (differentiable).

    Compute it once and pass it to :func:`log_histograms` when several count modes of one video are needed
    (the attack's exact counts and their relaxed surrogate): :func:`v2e_histograms` equals
    ``log_histograms(log_intensity(video), ...)``.

    Args:
        video: linear intensity, float tensor [T, H, W] or RGB [T, 3, H, W], T ≥ 2 (gradients flow to it).
        intensity_scale: the video is multiplied by this before the lin-log (255: [0, 1] → 8-bit DN).
        lin_log_threshold: lin-log knee in scaled units.

    Returns:
        Float tensor [T, H, W], log units, the video's dtype and device (the simulator's exact values).

    Raises:
        ShapeError: bad video shape. FormatError: non-float video.
    """
    torch = _torch()
    if not isinstance(video, torch.Tensor):
        video = torch.as_tensor(np.asarray(video))
    if video.ndim == 4:
        video = rgb_to_luma(video)
    _check_frames(video, "video", "[T, H, W] or RGB [T, 3, H, W]")
    if video.requires_grad:
        return _lin_log_fn().apply(video, float(intensity_scale), float(lin_log_threshold))
    return lin_log(video * intensity_scale, lin_log_threshold)


def _check_frames(frames, name: str, expected: str) -> None:
    """Raise unless ``frames`` is a float tensor [T, H, W] with T ≥ 2."""
    if frames.ndim != 3:
        raise ShapeError(f"{name}: expected {expected}, got {tuple(frames.shape)}")
    if not frames.dtype.is_floating_point:
        raise FormatError(f"{name}: expected a float tensor, got {frames.dtype}")
    if frames.shape[0] < 2:
        raise ShapeError(f"{name}: expected at least 2 frames, got {frames.shape[0]}")


def _log_counts(log_video, mode: str, threshold_on, threshold_off):
    """ON / OFF counts [T-1, H, W] of a log video [T, H, W] in ``mode`` (see :func:`v2e_counts`)."""
    torch = _torch()
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if mode == "dvs":
        theta_on = torch.as_tensor(threshold_on, dtype=log_video.dtype, device=log_video.device)
        theta_off = torch.as_tensor(threshold_off, dtype=log_video.dtype, device=log_video.device)
        return _dvs_fn().apply(log_video, theta_on, theta_off)
    if not (isinstance(threshold_on, (int, float)) and isinstance(threshold_off, (int, float))
            and threshold_on == threshold_off):
        raise ValueError(f"mode {mode!r} uses one threshold θ: expected equal float thresholds, "
                         f"got on={threshold_on!r}, off={threshold_off!r}")
    s_hat = (log_video - log_video[0]) / threshold_on
    s = floor_ste(s_hat) if mode == "floor" else s_hat
    d = s[1:] - s[:-1]
    on, off = torch.relu(d), torch.relu(-d)
    if mode == "official_relaxed":
        on, off = on * OFFICIAL_RELAXED_SCALE, off * OFFICIAL_RELAXED_SCALE
    return on, off


def v2e_counts(
    video,
    *,
    mode: str = "dvs",
    threshold_on=DEFAULT_THRESHOLD,
    threshold_off=DEFAULT_THRESHOLD,
    intensity_scale: float = INTENSITY_SCALE,
    lin_log_threshold: float = LIN_LOG_THRESHOLD,
) -> tuple["torch.Tensor", "torch.Tensor"]:
    """Per-frame-pair ON / OFF event counts of a video, differentiable w.r.t. the video (see module docstring).

    Args:
        video: linear intensity, float tensor [T, H, W] or RGB [T, 3, H, W], T ≥ 2 (gradients flow to it).
        mode: ``"dvs"``, ``"floor"`` (paper's formula) or ``"official_relaxed"`` (official code, not events).
        threshold_on: θ_on, log units, float or tensor broadcastable to [H, W] (per-pixel thresholds).
        threshold_off: θ_off, likewise (``"floor"`` and ``"official_relaxed"`` need ``θ_on == θ_off``).
        intensity_scale: the video is multiplied by this before the lin-log (255: [0, 1] → 8-bit DN).
        lin_log_threshold: lin-log knee in scaled units.

    Returns:
        ``(on, off)``: float tensors [T-1, H, W] in the video's dtype and device; integer-valued except in
        ``"official_relaxed"`` mode (scaled continuous values).

    Raises:
        ShapeError: bad video shape. FormatError: non-float video. ValueError: unknown mode, or unequal thresholds
        in a grid mode.

    Example:
        >>> import math, torch
        >>> video = torch.tensor([0.5, 0.5 * math.exp(0.5), 0.5 * math.exp(-0.1)]).reshape(3, 1, 1)
        >>> on, off = v2e_counts(video)
        >>> on.flatten().tolist(), off.flatten().tolist()
        ([2.0, 0.0], [0.0, 2.0])
    """
    log_video = log_intensity(video, intensity_scale=intensity_scale, lin_log_threshold=lin_log_threshold)
    return _log_counts(log_video, mode, threshold_on, threshold_off)


def _rvt_bins(t_us: np.ndarray, t0_us: int, t1_us: int, num_bins: int) -> np.ndarray:
    """RVT's float32 bin rule with given first/last times, clipped to ``0 .. num_bins - 1``."""
    span = np.float32(max(int(t1_us - t0_us), 1))
    norm = (t_us - t0_us).astype(np.float32) / span * np.float32(num_bins)
    return np.clip(np.floor(norm), 0, num_bins - 1).astype(np.int64)


def pair_bins(
    t_us,
    window_end_us,
    *,
    fired=None,
    window_us: int = WINDOW_US,
    num_bins: int = NUM_BINS,
    binning: str = "interval",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Assign frame pairs ``k → k+1`` to (window, time bin) by the chosen binning rule (module docstring).

    Args:
        t_us: frame times, integer µs, shape [T], strictly increasing.
        window_end_us: window ends ``e``, integer µs, scalar or [Wn].
        fired: bool [T-1], whether pair k produced any event (``"rvt_frame_end"`` takes the first/last *firing*
            pair of a window as RVT's ``t0``/``t1``); default all True.
        window_us: window duration w, µs.
        num_bins: bins B per window.
        binning: ``"interval"`` or ``"rvt_frame_end"``.

    Returns:
        ``(window_index, bin_index, pair_index)``: int64 arrays [M], one entry per (window, pair) membership.

    Raises:
        ValueError: unknown binning. ShapeError / FormatError: bad times.
    """
    if binning not in BINNINGS:
        raise ValueError(f"binning: expected one of {BINNINGS}, got {binning!r}")
    t = np.asarray(t_us)
    if t.ndim != 1 or t.shape[0] < 2:
        raise ShapeError(f"t_us: expected shape [T] with T >= 2, got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise FormatError(f"t_us: expected integer µs, got dtype {t.dtype}")
    t = t.astype(np.int64)
    if bool(np.any(np.diff(t) <= 0)):
        raise FormatError("t_us: expected strictly increasing frame times")
    ends = np.atleast_1d(np.asarray(window_end_us, dtype=np.int64))
    n_pairs = t.shape[0] - 1
    fired = np.ones(n_pairs, dtype=bool) if fired is None else np.asarray(fired, dtype=bool)
    if fired.shape != (n_pairs,):
        raise ShapeError(f"fired: expected shape ({n_pairs},), got {fired.shape}")
    t_end = t[1:]
    windows, bins, pairs = [], [], []
    for w, e in enumerate(ends.tolist()):
        if binning == "rvt_frame_end":
            lo, hi = np.searchsorted(t_end, e - window_us, "left"), np.searchsorted(t_end, e, "right")
            idx = np.arange(lo, hi)
            firing = idx[fired[lo:hi]]
            if firing.size:
                b = _rvt_bins(t_end[idx], int(t_end[firing[0]]), int(t_end[firing[-1]]), num_bins)
            else:
                b = np.zeros(idx.size, dtype=np.int64)
        else:
            lo, hi = np.searchsorted(t_end, e - window_us, "right"), np.searchsorted(t_end, e, "right")
            idx = np.arange(lo, hi)
            mid = (t[idx] + t_end[idx]) // 2 - (e - window_us)
            b = np.clip((mid * num_bins) // window_us, 0, num_bins - 1).astype(np.int64)
        windows.append(np.full(idx.size, w, dtype=np.int64))
        bins.append(b)
        pairs.append(idx.astype(np.int64))
    return np.concatenate(windows), np.concatenate(bins), np.concatenate(pairs)


def v2e_histograms(
    video,
    t_us,
    window_end_us,
    *,
    mode: str = "dvs",
    binning: str = "interval",
    window_us: int = WINDOW_US,
    num_bins: int = NUM_BINS,
    count_cutoff: float | None = COUNT_CUTOFF,
    threshold_on=DEFAULT_THRESHOLD,
    threshold_off=DEFAULT_THRESHOLD,
    intensity_scale: float = INTENSITY_SCALE,
    lin_log_threshold: float = LIN_LOG_THRESHOLD,
) -> "torch.Tensor":
    """Differentiable RVT input ``[windows, 2·B, H, W]`` of a video (V2E counts binned per window).

    Args:
        video: linear intensity, float tensor [T, H, W] or RGB [T, 3, H, W] (gradients flow to it).
        t_us: frame times, integer µs, shape [T], strictly increasing (≥ 200 fps for 10 bins of 5 ms).
        window_end_us: window ends, integer µs, scalar or [Wn]; window = ``[e − window_us, e]`` (see binning).
        mode: count mode, see :func:`v2e_counts`.
        binning: ``"interval"`` or ``"rvt_frame_end"`` (module docstring).
        window_us: window duration, µs.
        num_bins: time bins B per polarity.
        count_cutoff: counts clipped to ``[0, count_cutoff]`` like RVT (clamp: zero gradient above it); None = no clip.
        threshold_on, threshold_off, intensity_scale, lin_log_threshold: see :func:`v2e_counts`.

    Returns:
        Float tensor [Wn, 2·B, H, W] (channel ``p·B + b``; p = 0 OFF, 1 ON), video's dtype and device.

    Raises:
        ShapeError, FormatError, ValueError: see :func:`v2e_counts` and :func:`pair_bins`.
    """
    log_video = log_intensity(video, intensity_scale=intensity_scale, lin_log_threshold=lin_log_threshold)
    return log_histograms(log_video, t_us, window_end_us, mode=mode, binning=binning, window_us=window_us,
                          num_bins=num_bins, count_cutoff=count_cutoff, threshold_on=threshold_on,
                          threshold_off=threshold_off)


def log_histograms(
    log_video,
    t_us,
    window_end_us,
    *,
    mode: str = "dvs",
    binning: str = "interval",
    window_us: int = WINDOW_US,
    num_bins: int = NUM_BINS,
    count_cutoff: float | None = COUNT_CUTOFF,
    threshold_on=DEFAULT_THRESHOLD,
    threshold_off=DEFAULT_THRESHOLD,
) -> "torch.Tensor":
    """:func:`v2e_histograms` of a video already in log units (:func:`log_intensity`), differentiable w.r.t. it.

    Args:
        log_video: float tensor [T, H, W], log units, T ≥ 2.
        t_us, window_end_us, mode, binning, window_us, num_bins, count_cutoff, threshold_on, threshold_off: see
            :func:`v2e_histograms`.

    Returns:
        Float tensor [Wn, 2·B, H, W] (channel ``p·B + b``; p = 0 OFF, 1 ON), ``log_video``'s dtype and device.

    Raises:
        ShapeError, FormatError, ValueError: see :func:`v2e_counts` and :func:`pair_bins`.

    Example:
        >>> import torch
        >>> log_video = torch.tensor([0.0, 0.45, 0.0]).reshape(3, 1, 1)  # up 2 θ, then down 2 θ
        >>> hist = log_histograms(log_video, [0, 25_000, 50_000], 50_000)
        >>> off, on = hist[0, :, 0, 0].reshape(2, 10).tolist()  # channel p·B + b: OFF bins, then ON bins
        >>> on.index(2.0), off.index(2.0)  # 2 ON in pair 0-25 ms (bin 2), 2 OFF in pair 25-50 ms (bin 7)
        (2, 7)
    """
    torch = _torch()
    if not isinstance(log_video, torch.Tensor):
        raise FormatError(f"log_video: expected a torch tensor, got {type(log_video).__name__}")
    _check_frames(log_video, "log_video", "[T, H, W]")
    on, off = _log_counts(log_video, mode, threshold_on, threshold_off)
    t = np.asarray(t_us.detach().cpu().numpy() if hasattr(t_us, "detach") else t_us)
    if t.shape != (on.shape[0] + 1,):
        raise ShapeError(f"t_us: expected shape ({on.shape[0] + 1},) like the video's T, got {t.shape}")
    fired = None
    if binning == "rvt_frame_end":
        fired = ((on.detach() + off.detach()).flatten(1) > 0).any(1).cpu().numpy()
    w_idx, b_idx, p_idx = pair_bins(t, window_end_us, fired=fired, window_us=window_us, num_bins=num_bins,
                                    binning=binning)
    n_windows = int(np.atleast_1d(np.asarray(window_end_us)).shape[0])
    height, width = on.shape[1:]
    hist = torch.zeros((n_windows * 2 * num_bins, height, width), dtype=on.dtype, device=on.device)
    if p_idx.size:
        device = on.device
        channel_off = torch.as_tensor(w_idx * 2 * num_bins + b_idx, device=device)
        if not np.array_equal(p_idx, np.arange(on.shape[0])):  # else every pair once, in order: no gather
            pairs = torch.as_tensor(p_idx, device=device)
            on, off = on.index_select(0, pairs), off.index_select(0, pairs)
        hist.index_add_(0, channel_off, off).index_add_(0, channel_off + num_bins, on)
    hist = hist.reshape(n_windows, 2 * num_bins, height, width)
    if count_cutoff is not None:
        hist = torch.clamp(hist, max=float(count_cutoff))
    return hist


class DifferentiableV2E:
    """Callable holding the V2E settings: ``v2e(video, t_us, window_end_us) -> [Wn, 2·B, H, W]``.

    Args:
        mode, binning, window_us, num_bins, count_cutoff, threshold_on, threshold_off, intensity_scale,
            lin_log_threshold: see :func:`v2e_histograms`.
    """

    def __init__(self, *, mode: str = "dvs", binning: str = "interval", window_us: int = WINDOW_US,
                 num_bins: int = NUM_BINS, count_cutoff: float | None = COUNT_CUTOFF,
                 threshold_on=DEFAULT_THRESHOLD, threshold_off=DEFAULT_THRESHOLD,
                 intensity_scale: float = INTENSITY_SCALE, lin_log_threshold: float = LIN_LOG_THRESHOLD):
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
        if binning not in BINNINGS:
            raise ValueError(f"binning: expected one of {BINNINGS}, got {binning!r}")
        self.settings = dict(mode=mode, binning=binning, window_us=window_us, num_bins=num_bins,
                             count_cutoff=count_cutoff, threshold_on=threshold_on, threshold_off=threshold_off,
                             intensity_scale=intensity_scale, lin_log_threshold=lin_log_threshold)

    def __call__(self, video, t_us, window_end_us) -> "torch.Tensor":
        """See :func:`v2e_histograms`."""
        return v2e_histograms(video, t_us, window_end_us, **self.settings)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.settings.items())
        return f"DifferentiableV2E({args})"
