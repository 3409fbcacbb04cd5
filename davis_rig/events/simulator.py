"""Exact DVS event simulator: a video of linear intensity → a sorted (t µs, x, y, p) event stream (torch).

Model (noise-free, the default), per pixel, evaluated for every pair of consecutive frames ``k → k+1``:

* log intensity ``L = lin_log(intensity_scale · I)`` with v2e's lin-log mapping
  (:func:`davis_rig.events.intensity.lin_log`; ``intensity_scale = 255`` turns the renderer's linear intensity in
  [0, 1] into 8-bit-like units): linear below 20, ``ln(x)`` above; v2e's rounding of ``L`` to 1e-8 is not applied.
  RGB video is reduced to luma first (:func:`~davis_rig.events.intensity.rgb_to_luma`).
* a per-pixel reference ``L_ref`` (initialised to the first frame's ``L``); between two frames ``L`` is linear in
  time (linear interpolation **in log space**), so within one interval it moves monotonically and each crossing of
  ``L_ref + j · θ_on`` (j = 1, 2, ...) fires one ON event, each crossing of ``L_ref − j · θ_off`` one OFF event;
  after the interval the reference moves by whole thresholds: ``L_ref += n_on · θ_on − n_off · θ_off`` (v2e /
  the DVS pixel: the reference is not set to ``L``, so the remainder carries over). Several events per interval
  when the change crosses several thresholds.
* This is the DVS's hysteresis: after rising, a pixel needs a full ``θ_off`` drop below its reference before an OFF
  event. (The paper's formula ``S = ⌊(L − L_0)/θ⌋`` counts crossings of a fixed level grid instead; both agree on
  monotonic signals, see :mod:`davis_rig.events.v2e_torch`.)
* event times: ``t = t_k + ⌈f · (t_{k+1} − t_k)⌉`` µs with ``f ∈ (0, 1]`` the fraction of the interval at which
  the log level crosses (never stamped before the crossing; always in ``(t_k, t_{k+1}]``), or, with
  ``timestamps="frame_end"``, every event of the interval at ``t_{k+1}`` (what a frame-based simulator and the
  differentiable V2E in its ``"rvt_frame_end"`` binning see).
* polarity ``1`` = ON (increase), ``0`` = OFF; output :data:`EVENT_DTYPE` sorted by ``t`` (equal times: row-major
  pixel order, then OFF before ON, then crossing order).

Optional v2e-style non-idealities (all off by default, seeded by ``seed``): per-pixel threshold mismatch
(``threshold_sigma``, absolute std of θ in log units, θ clipped at ``min_threshold``), a refractory period
(events of a pixel closer than ``refractory_us`` to its previous event are dropped; the reference still moves, as in
v2e), shot noise (``shot_noise_rate_hz``: Poisson ON+OFF noise events per pixel, rate lower for bright pixels as in
v2e; they leave the reference alone, so the rate is exactly the one asked for), leak (``leak_rate_hz``: the
reference sinks by ``leak_rate_hz · θ_on`` per second from a random per-pixel phase, which fires spontaneous ON
events), hot pixels (``hot_pixel_fraction`` of the pixels, a fixed random set, fire noise at ``hot_pixel_rate_hz``
whatever the light, as on an ATIS / Gen1 sensor) and a first-order low-pass of ``L`` whose cutoff ``cutoff_hz``
scales with intensity (v2e's photoreceptor bandwidth model: ``ε = dt · 2π · cutoff_hz · (255 I + 20) / 275``,
clipped at 1).

All arithmetic is vectorised over pixels; Python loops run over frames (and, only with a refractory period, over
the crossing rank within one interval). torch is imported lazily; the simulator runs on any torch device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import ConfigError, FormatError, ShapeError
from davis_rig.events.intensity import DEFAULT_THRESHOLD, INTENSITY_SCALE, LIN_LOG_THRESHOLD, lin_log, rgb_to_luma
from davis_rig.types import EVENT_DTYPE

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = ["EventSimulator", "SimulatorConfig", "simulate_events"]

#: v2e's shot-noise intensity factor: the noise rate at full intensity is this fraction of the dark rate.
SHOT_NOISE_INTENSITY_FACTOR = 0.25


def _torch():
    return optional_import("torch", "the event simulator")


@dataclass(frozen=True)
class SimulatorConfig:
    """Settings of :class:`EventSimulator` (the defaults are the ideal, noise-free sensor of the paper).

    Attributes:
        threshold_on: ON contrast threshold θ_on, log units.
        threshold_off: OFF contrast threshold θ_off, log units.
        intensity_scale: input intensity multiplied by this before :func:`lin_log` (255: [0, 1] → 8-bit DN).
        lin_log_threshold: lin-log knee in scaled units.
        timestamps: ``"interpolate"`` (crossing time by linear interpolation of ``L`` between frames) or
            ``"frame_end"`` (all events of an interval at its end frame's time).
        threshold_sigma: per-pixel threshold mismatch, std of θ in log units (v2e ``sigma_thres``), 0 = off.
        min_threshold: lower clip of mismatched thresholds, log units.
        refractory_us: refractory period, µs (0 = off).
        shot_noise_rate_hz: shot-noise event rate per pixel (ON + OFF), Hz, at zero intensity (0 = off).
        leak_rate_hz: leak event rate per pixel, Hz (0 = off).
        hot_pixel_fraction: fraction of the pixels that are hot (a fixed random set drawn from ``seed``), 0 = none.
        hot_pixel_rate_hz: extra noise event rate (ON + OFF) of each hot pixel, Hz, whatever the intensity (an ATIS
            / Gen1 sensor's hot pixels fire tens of events per second).
        cutoff_hz: low-pass 3 dB cutoff at full intensity, Hz (0 = no low-pass).
        seed: seed of the noise generator (threshold mismatch, shot noise, leak phases).
        dtype: torch dtype name of the computation, ``"float64"`` (default, exact comparisons) or ``"float32"``.

    Raises:
        ConfigError: a value out of its range (its ``field`` names the attribute).
    """

    threshold_on: float = DEFAULT_THRESHOLD
    threshold_off: float = DEFAULT_THRESHOLD
    intensity_scale: float = INTENSITY_SCALE
    lin_log_threshold: float = LIN_LOG_THRESHOLD
    timestamps: str = "interpolate"
    threshold_sigma: float = 0.0
    min_threshold: float = 0.01
    refractory_us: int = 0
    shot_noise_rate_hz: float = 0.0
    leak_rate_hz: float = 0.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate_hz: float = 0.0
    cutoff_hz: float = 0.0
    seed: int = 0
    dtype: str = "float64"

    def __post_init__(self) -> None:
        for name in ("threshold_on", "threshold_off", "intensity_scale", "lin_log_threshold", "min_threshold"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"must be > 0, got {getattr(self, name)}")
        if self.timestamps not in ("interpolate", "frame_end"):
            raise ConfigError("timestamps", f"expected 'interpolate' or 'frame_end', got {self.timestamps!r}")
        for name in ("threshold_sigma", "refractory_us", "shot_noise_rate_hz", "leak_rate_hz", "hot_pixel_rate_hz",
                     "cutoff_hz"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.hot_pixel_fraction <= 1.0:
            raise ConfigError("hot_pixel_fraction", f"must be in [0, 1], got {self.hot_pixel_fraction}")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError("dtype", f"expected 'float32' or 'float64', got {self.dtype!r}")

    @property
    def ideal(self) -> bool:
        """True when no non-ideality is enabled (the noise-free sensor)."""
        return not (self.threshold_sigma or self.refractory_us or self.shot_noise_rate_hz or self.leak_rate_hz
                    or self.cutoff_hz or self.hot_pixels)

    @property
    def hot_pixels(self) -> bool:
        """True when some pixels are hot (a fraction and a rate above 0)."""
        return self.hot_pixel_fraction > 0 and self.hot_pixel_rate_hz > 0


def _as_video(video, device, dtype):
    torch = _torch()
    if isinstance(video, np.ndarray):
        video = torch.from_numpy(np.ascontiguousarray(video))
    elif not isinstance(video, torch.Tensor):
        video = torch.as_tensor(np.asarray(video))
    if video.ndim == 4:
        if video.shape[1] != 3:
            raise ShapeError(f"video: expected [T, H, W] or RGB [T, 3, H, W], got {tuple(video.shape)}")
        video = rgb_to_luma(video.to(dtype))
    if video.ndim != 3:
        raise ShapeError(f"video: expected [T, H, W] or RGB [T, 3, H, W], got {tuple(video.shape)}")
    if not video.dtype.is_floating_point:
        raise FormatError(f"video: expected a float tensor of linear intensity in [0, 1], got {video.dtype}")
    return video.detach().to(device=device or video.device, dtype=dtype)


def _as_times(t_us, n: int) -> np.ndarray:
    t = np.asarray(t_us.detach().cpu().numpy() if hasattr(t_us, "detach") else t_us)
    if t.ndim != 1 or t.shape[0] != n:
        raise ShapeError(f"t_us: expected shape ({n},) like the video's T, got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise FormatError(f"t_us: expected integer µs, got dtype {t.dtype}")
    t = t.astype(np.int64)
    if n > 1 and bool(np.any(np.diff(t) <= 0)):
        raise FormatError("t_us: expected strictly increasing frame times")
    return t


class EventSimulator:
    """Stateful DVS simulator over a stream of frames (feed a long video piecewise; see the module docstring).

    Args:
        height: frame height H, px.
        width: frame width W, px.
        config: :class:`SimulatorConfig` (default: ideal sensor, θ = 0.2).
        device: torch device of the computation (default: the first video's device, CPU for numpy input).

    Example:
        >>> import numpy as np
        >>> sim = EventSimulator(1, 1)
        >>> ev = sim.feed(np.array([[[0.5]], [[0.5 * np.exp(0.45)]]]), np.array([0, 1000]))
        >>> ev["t"].tolist(), ev["p"].tolist()  # two ON crossings at 0.2/0.45 and 0.4/0.45 of the interval
        ([445, 889], [1, 1])
    """

    def __init__(self, height: int, width: int, config: SimulatorConfig | None = None, *, device=None):
        self.height = int(height)
        self.width = int(width)
        self.config = config or SimulatorConfig()
        self.device = device
        self._state: dict | None = None

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the reference and the previous frame (the next frame initialises them)."""
        self._state = None

    @property
    def reference(self) -> "torch.Tensor | None":
        """The per-pixel log reference ``L_ref`` [H, W] (a copy), or None before the first frame."""
        return None if self._state is None else self._state["ref"].clone()

    def _init_state(self, frame, t_us: int) -> None:
        torch = _torch()
        cfg = self.config
        generator = torch.Generator(device=frame.device)
        generator.manual_seed(int(cfg.seed))
        shape = (self.height, self.width)
        theta_on = torch.full(shape, cfg.threshold_on, dtype=frame.dtype, device=frame.device)
        theta_off = torch.full(shape, cfg.threshold_off, dtype=frame.dtype, device=frame.device)
        if cfg.threshold_sigma > 0:
            noise = torch.randn((2, *shape), generator=generator, dtype=frame.dtype, device=frame.device)
            theta_on = torch.clamp(theta_on + cfg.threshold_sigma * noise[0], min=cfg.min_threshold)
            theta_off = torch.clamp(theta_off + cfg.threshold_sigma * noise[1], min=cfg.min_threshold)
        log_frame = lin_log(frame * cfg.intensity_scale, cfg.lin_log_threshold)
        ref = log_frame.clone()
        if cfg.leak_rate_hz > 0:  # random leak phase per pixel, so that leak events are not synchronous
            ref -= torch.rand(shape, generator=generator, dtype=frame.dtype, device=frame.device) * theta_on
        hot_rate_hz = None
        if cfg.hot_pixels:  # drawn after the other per-pixel draws: a sensor without hot pixels is unchanged
            draw = torch.rand(shape, generator=generator, dtype=frame.dtype, device=frame.device)
            hot = draw < cfg.hot_pixel_fraction
            hot_rate_hz = hot.to(frame.dtype) * cfg.hot_pixel_rate_hz
        self._state = {
            "generator": generator,
            "theta_on": theta_on,
            "theta_off": theta_off,
            "log": log_frame,  # (filtered) log intensity at the last frame
            "ref": ref,
            "hot_rate_hz": hot_rate_hz,  # [H, W] extra noise rate (ON + OFF), or None
            "t_us": int(t_us),
            "last_event_us": torch.full(shape, np.iinfo(np.int64).min // 2, dtype=torch.int64, device=frame.device),
        }

    # ------------------------------------------------------------------ stepping
    def feed(self, video, t_us) -> np.ndarray:
        """Simulate the events of a piece of video (continuing from the previous call).

        Args:
            video: linear intensity in [0, 1] (values above 1 allowed), float array/tensor [T, H, W] (or RGB
                [T, 3, H, W], converted to luma Y = 0.299 R + 0.587 G + 0.114 B).
            t_us: frame times, integer µs, shape [T], strictly increasing (and after the previous call's).

        Returns:
            Events, :data:`EVENT_DTYPE` [N], sorted by ``t`` (µs), ``x``/``y`` in the ``W x H`` frame.

        Raises:
            ShapeError: wrong video shape or frame size, ``t_us`` length mismatch.
            FormatError: non-float video, non-integer or non-increasing times.
        """
        torch = _torch()
        dtype = getattr(torch, self.config.dtype)
        video = _as_video(video, self.device, dtype)
        if tuple(video.shape[1:]) != (self.height, self.width):
            raise ShapeError(f"video: expected frames of (H, W) = {(self.height, self.width)}, got {tuple(video.shape[1:])}")
        times = _as_times(t_us, video.shape[0])
        if video.shape[0] == 0:
            return np.zeros(0, dtype=EVENT_DTYPE)
        start = 0
        if self._state is None:
            self._init_state(video[0], int(times[0]))
            start = 1
        elif int(times[0]) <= self._state["t_us"]:
            raise FormatError(f"t_us: first frame at {int(times[0])} µs is not after the previous one "
                              f"({self._state['t_us']} µs)")
        pieces = [self._step(video[k], int(times[k])) for k in range(start, video.shape[0])]
        pieces = [p for p in pieces if p.shape[0]]
        return np.concatenate(pieces) if pieces else np.zeros(0, dtype=EVENT_DTYPE)

    def _step(self, frame, t1_us: int) -> np.ndarray:
        """One interval ``(t_prev, t1_us]``: counts, reference update, event times; returns sorted events."""
        torch = _torch()
        cfg = self.config
        st = self._state
        t0_us = st["t_us"]
        dt_us = t1_us - t0_us
        dt_s = dt_us * 1e-6
        log_prev = st["log"]
        log_new = lin_log(frame * cfg.intensity_scale, cfg.lin_log_threshold)
        if cfg.cutoff_hz > 0:
            inten01 = (frame * 255.0 + 20.0) / 275.0
            eps = torch.clamp(dt_s * 2.0 * math.pi * cfg.cutoff_hz * inten01, max=1.0)
            log_new = (1.0 - eps) * log_prev + eps * log_new
        ref = st["ref"]
        if cfg.leak_rate_hz > 0:
            ref = ref - dt_s * cfg.leak_rate_hz * st["theta_on"]
        theta_on, theta_off = st["theta_on"], st["theta_off"]
        diff = log_new - ref
        n_on = torch.clamp(torch.floor(diff / theta_on), min=0)
        n_off = torch.clamp(torch.floor(-diff / theta_off), min=0)
        new_ref = ref + n_on * theta_on - n_off * theta_off

        pieces = []
        for polarity, counts, step in ((0, n_off, -theta_off), (1, n_on, theta_on)):
            idx = torch.nonzero(counts.reshape(-1) > 0).reshape(-1)
            if idx.numel() == 0:
                continue
            reps = counts.reshape(-1)[idx].to(torch.int64)
            pix = torch.repeat_interleave(idx, reps)
            # crossing rank j = 1..n within each pixel
            offsets = torch.cumsum(reps, 0) - reps
            rank = torch.arange(pix.numel(), device=pix.device) - torch.repeat_interleave(offsets, reps) + 1
            if cfg.timestamps == "frame_end":
                t_ev = torch.full_like(pix, t1_us)
            else:
                level = ref.reshape(-1)[pix] + rank.to(ref.dtype) * step.reshape(-1)[pix]
                lp, ln = log_prev.reshape(-1)[pix], log_new.reshape(-1)[pix]
                change = ln - lp
                # no change of L (a crossing caused by the leak moving the reference): stamp at the interval end
                safe = torch.where(change != 0, change, torch.ones_like(change))
                frac = torch.where(change != 0, (level - lp) / safe, torch.ones_like(change))
                frac = torch.clamp(frac, min=0.0, max=1.0)
                t_ev = t0_us + torch.clamp(torch.ceil(frac * dt_us).to(torch.int64), min=1, max=dt_us)
            pieces.append((pix, t_ev, polarity, rank))

        if cfg.refractory_us > 0 and pieces:
            pieces = self._refractory(pieces)
        if cfg.shot_noise_rate_hz > 0 or cfg.hot_pixels:
            noise, new_ref = self._shot_noise(frame, new_ref, t0_us, dt_us)
            pieces.extend(noise)

        st["ref"] = new_ref
        st["log"] = log_new
        st["t_us"] = t1_us
        if not pieces:
            return np.zeros(0, dtype=EVENT_DTYPE)
        pix = torch.cat([p[0] for p in pieces])
        t_ev = torch.cat([p[1] for p in pieces])
        pol = torch.cat([torch.full_like(p[0], p[2]) for p in pieces])
        # order: time, then pixel (row-major), polarity, crossing rank — via one stable sort on time of the
        # events pre-sorted by (pixel, polarity, rank).
        rank = torch.cat([p[3] for p in pieces])
        key = (pix * 2 + pol) * (int(rank.max()) + 1) + rank
        pre = torch.argsort(key, stable=True)
        order = pre[torch.argsort(t_ev[pre], stable=True)]
        pix, t_ev, pol = pix[order].cpu().numpy(), t_ev[order].cpu().numpy(), pol[order].cpu().numpy()
        events = np.empty(pix.shape[0], dtype=EVENT_DTYPE)
        events["t"] = t_ev
        events["x"] = pix % self.width
        events["y"] = pix // self.width
        events["p"] = pol
        return events

    def _refractory(self, pieces):
        """Drop events closer than ``refractory_us`` to the pixel's previous kept event (loop over crossing rank)."""
        torch = _torch()
        last = self._state["last_event_us"].reshape(-1)
        refr = int(self.config.refractory_us)
        pix = torch.cat([p[0] for p in pieces])
        t_ev = torch.cat([p[1] for p in pieces])
        pol = torch.cat([torch.full_like(p[0], p[2]) for p in pieces])
        rank = torch.cat([p[3] for p in pieces])
        keep = torch.zeros_like(pix, dtype=torch.bool)
        # at most one polarity per pixel per interval without noise: rank orders each pixel's events in time
        for j in range(1, int(rank.max()) + 1):
            sel = torch.nonzero(rank == j).reshape(-1)
            ok = t_ev[sel] - last[pix[sel]] >= refr
            keep[sel[ok]] = True
            last[pix[sel[ok]]] = t_ev[sel[ok]]
        return [
            (pix[keep & (pol == v)], t_ev[keep & (pol == v)], v, rank[keep & (pol == v)])
            for v in (0, 1)
            if bool((keep & (pol == v)).any())
        ]

    def _shot_noise(self, frame, ref, t0_us: int, dt_us: int):
        """Poisson shot-noise events (v2e's rate model) plus the hot pixels' rate: probability per pixel and
        polarity, uniform time in the interval. They do not move the reference (moving it would make a static pixel
        answer every noise event with an opposite "signal" event, doubling the rate)."""
        torch = _torch()
        cfg = self.config
        st = self._state
        gen = st["generator"]
        inten01 = torch.clamp(frame, 0.0, 1.0)
        rate_hz = 0.5 * cfg.shot_noise_rate_hz * ((SHOT_NOISE_INTENSITY_FACTOR - 1.0) * inten01 + 1.0)
        if st["hot_rate_hz"] is not None:
            rate_hz = rate_hz + 0.5 * st["hot_rate_hz"]
        prob = torch.clamp(rate_hz * dt_us * 1e-6, max=1.0)
        u = torch.rand((2, *prob.shape), generator=gen, dtype=prob.dtype, device=prob.device)
        out = []
        for polarity, fired in ((0, u[0] < prob), (1, u[1] < prob)):
            idx = torch.nonzero(fired.reshape(-1)).reshape(-1)
            if idx.numel() == 0:
                continue
            t_ev = t0_us + 1 + torch.floor(
                torch.rand(idx.shape, generator=gen, dtype=prob.dtype, device=prob.device) * dt_us
            ).to(torch.int64)
            t_ev = torch.clamp(t_ev, max=t0_us + dt_us)
            out.append((idx, t_ev, polarity, torch.zeros_like(idx)))
        return out, ref


def simulate_events(video, t_us, config: SimulatorConfig | None = None, *, device=None, **overrides) -> np.ndarray:
    """Simulate the DVS events of a whole video (see :class:`EventSimulator`).

    Args:
        video: linear intensity in [0, 1], float array/tensor [T, H, W] (or RGB [T, 3, H, W]).
        t_us: frame times, integer µs, shape [T], strictly increasing.
        config: :class:`SimulatorConfig`; keyword ``overrides`` replace its fields (e.g. ``timestamps="frame_end"``).
        device: torch device of the computation.

    Returns:
        Events, :data:`EVENT_DTYPE` [N], sorted by ``t`` (µs); no event at the first frame's time.

    Raises:
        ShapeError, FormatError: see :meth:`EventSimulator.feed`.

    Example:
        >>> import numpy as np
        >>> video = np.array([[[0.5]], [[0.5 * np.exp(0.5)]], [[0.5 * np.exp(-0.1)]]])
        >>> ev = simulate_events(video, np.array([0, 5000, 10000]))
        >>> ev["p"].tolist()  # up 0.5 = 2.5 θ: 2 ON (reference +0.4); down 0.6 to 0.5 below it: 2 OFF
        [1, 1, 0, 0]
    """
    import dataclasses

    config = dataclasses.replace(config or SimulatorConfig(), **overrides) if overrides else (config or SimulatorConfig())
    shape = tuple(video.shape) if hasattr(video, "shape") else tuple(np.shape(video))
    if len(shape) not in (3, 4):
        raise ShapeError(f"video: expected [T, H, W] or RGB [T, 3, H, W], got {shape}")
    height, width = shape[-2], shape[-1]
    return EventSimulator(height, width, config, device=device).feed(video, t_us)
