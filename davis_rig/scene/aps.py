"""Synthetic DAVIS346 APS (grey-level) frames from a rendered linear-intensity video (numpy).

Global-shutter timing per frame ``i`` (all integer µs): start of frame ``SOF = t_first_us + i · frame_interval_us``,
reset read-out, exposure ``[SOE, EOE]`` with ``SOE = SOF + reset_readout_us`` and ``EOE = SOE + exposure_us``,
signal read-out, end of frame ``EOF = EOE + signal_readout_us``. The default 25 fps / 4 ms exposure matches the
paper's rig; frames must not overlap (``EOF < next SOF``).

Pixel model: the exposure integrates the video — the mean of the video frames whose time lies inside
``[SOE, EOE]`` (the frame nearest to the exposure midpoint when none does) — into photo-electrons
``e = I · full_well_e · exposure_us / saturation_exposure_us`` (``I = 1`` fills the well at the reference
exposure), Poisson shot noise on ``e``, clip at the full well, then the 10-bit ADC:
``DN = round(gain · 1023 · e / full_well_e + offset_dn + N(0, read_noise_dn))`` clipped to 0..1023, stored on
libcaer's 16-bit scale ``DN << 6`` (what the decoder delivers and session.h5 stores). Noise is seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from davis_rig.errors import ConfigError, FormatError, ShapeError
from davis_rig.protocol.frames import ApsFrame

__all__ = ["ApsConfig", "aps_frame_times", "synthesize_aps_frames", "to_adc"]

ADC_MAX_DN = 1023
ADC_SHIFT = 6


@dataclass(frozen=True)
class ApsConfig:
    """APS synthesis settings.

    Attributes:
        frame_rate_hz: frame rate, Hz (the frame interval is ``round(1e6 / frame_rate_hz)`` µs).
        exposure_us: exposure time, µs.
        reset_readout_us: start of frame → start of exposure (reset read), µs.
        signal_readout_us: end of exposure → end of frame (signal read), µs.
        full_well_e: full-well capacity, electrons (sets the shot-noise level).
        saturation_exposure_us: exposure at which intensity 1.0 fills the well, µs (None: ``exposure_us``).
        gain: ADC gain (1.0: a full well reads 1023 DN before the offset).
        offset_dn: black level, DN.
        read_noise_dn: read-noise standard deviation, DN.
        shot_noise: apply Poisson shot noise.
        seed: seed of the noise generator.

    Raises:
        ConfigError: a value out of its range (its ``field`` names the attribute).
    """

    frame_rate_hz: float = 25.0
    exposure_us: int = 4000
    reset_readout_us: int = 1000
    signal_readout_us: int = 1000
    full_well_e: float = 10_000.0
    saturation_exposure_us: int | None = None
    gain: float = 0.9
    offset_dn: float = 20.0
    read_noise_dn: float = 1.5
    shot_noise: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("frame_rate_hz", "full_well_e"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"expected > 0, got {getattr(self, name)}")
        if not self.exposure_us >= 1:
            raise ConfigError("exposure_us", f"expected >= 1, got {self.exposure_us}")
        for name in ("reset_readout_us", "signal_readout_us", "read_noise_dn"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"expected >= 0, got {getattr(self, name)}")
        if self.reset_readout_us + self.exposure_us + self.signal_readout_us >= self.frame_interval_us:
            raise ConfigError(
                "exposure_us",
                f"frame does not fit its interval: reset {self.reset_readout_us} + exposure {self.exposure_us} + "
                f"signal {self.signal_readout_us} µs >= interval {self.frame_interval_us} µs"
            )

    @property
    def frame_interval_us(self) -> int:
        """Frame interval, µs."""
        return int(round(1e6 / self.frame_rate_hz))


def aps_frame_times(t_first_us: int, t_last_us: int, config: ApsConfig = ApsConfig()) -> np.ndarray:
    """The four timestamps of every frame whose exposure fits in ``[t_first_us, t_last_us]``.

    Args:
        t_first_us: start of the first frame, µs.
        t_last_us: latest allowed end of exposure, µs (the video's last frame time).
        config: timing settings.

    Returns:
        int64 [F, 4]: ``SOF, SOE, EOE, EOF`` per frame, µs.
    """
    interval = config.frame_interval_us
    eoe_offset = config.reset_readout_us + config.exposure_us
    n = max(0, (int(t_last_us) - int(t_first_us) - eoe_offset) // interval + 1)
    sof = int(t_first_us) + interval * np.arange(n, dtype=np.int64)
    soe = sof + config.reset_readout_us
    eoe = soe + config.exposure_us
    eof = eoe + config.signal_readout_us
    return np.stack([sof, soe, eoe, eof], axis=1)


def to_adc(intensity: np.ndarray, config: ApsConfig = ApsConfig(), rng: np.random.Generator | None = None) -> np.ndarray:
    """Convert the exposure-mean linear intensity of one frame into libcaer 16-bit pixel values.

    Args:
        intensity: float [H, W], linear intensity (1.0 = full well at the saturation exposure).
        config: pixel / ADC settings.
        rng: noise generator (default: seeded from ``config.seed``).

    Returns:
        uint16 [H, W], ``DN << 6`` with DN in 0..1023.
    """
    rng = rng if rng is not None else np.random.default_rng(config.seed)
    saturation_us = config.saturation_exposure_us or config.exposure_us
    electrons = np.clip(np.asarray(intensity, dtype=np.float64), 0.0, None) * (
        config.full_well_e * config.exposure_us / saturation_us
    )
    if config.shot_noise:
        electrons = rng.poisson(np.minimum(electrons, 1e9)).astype(np.float64)
    electrons = np.minimum(electrons, config.full_well_e)
    dn = config.gain * ADC_MAX_DN * electrons / config.full_well_e + config.offset_dn
    if config.read_noise_dn > 0:
        dn = dn + rng.normal(0.0, config.read_noise_dn, size=dn.shape)
    dn = np.clip(np.rint(dn), 0, ADC_MAX_DN).astype(np.uint16)
    return dn << ADC_SHIFT


def synthesize_aps_frames(
    video,
    t_us,
    config: ApsConfig = ApsConfig(),
    *,
    t_first_us: int | None = None,
    position_xy: tuple[int, int] = (0, 0),
) -> list[ApsFrame]:
    """Synthesize the APS frames a DAVIS346 would read out while watching a video.

    Args:
        video: linear intensity, float array/tensor [T, H, W] (detached; torch tensors are moved to CPU).
        t_us: video frame times, integer µs, shape [T], strictly increasing.
        config: :class:`ApsConfig` (frame rate, exposure, read-out, pixel/ADC model, seed).
        t_first_us: start of the first APS frame, µs (default: the first video frame's time).
        position_xy: ``(position_x, position_y)`` of the frames' ROI on the sensor, px (the pixels are the
            whole video frame).

    Returns:
        One :class:`~davis_rig.protocol.frames.ApsFrame` per frame interval whose exposure ends by the last video
        frame: ``pixels`` uint16 [H, W] (DN << 6) and the four timestamps (µs).

    Raises:
        ShapeError: video not [T, H, W] or ``t_us`` of another length. FormatError: non-integer or unsorted times.
    """
    if hasattr(video, "detach"):
        video = video.detach().cpu().numpy()
    video = np.asarray(video)
    if video.ndim != 3:
        raise ShapeError(f"video: expected [T, H, W], got shape {video.shape}")
    t = np.asarray(t_us)
    if t.shape != (video.shape[0],):
        raise ShapeError(f"t_us: expected shape ({video.shape[0]},), got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise FormatError(f"t_us: expected integer µs, got dtype {t.dtype}")
    t = t.astype(np.int64)
    if t.size > 1 and bool(np.any(np.diff(t) <= 0)):
        raise FormatError("t_us: expected strictly increasing frame times")
    if t.size == 0:
        return []
    times = aps_frame_times(int(t[0]) if t_first_us is None else int(t_first_us), int(t[-1]), config)
    rng = np.random.default_rng(config.seed)
    frames = []
    for sof, soe, eoe, eof in times.tolist():
        lo, hi = np.searchsorted(t, soe, "left"), np.searchsorted(t, eoe, "right")
        if hi > lo:
            mean = video[lo:hi].mean(axis=0, dtype=np.float64)
        else:
            mid = soe + (eoe - soe) // 2
            mean = video[int(np.argmin(np.abs(t - mid)))].astype(np.float64)
        frames.append(
            ApsFrame(
                pixels=to_adc(mean, config, rng),
                position_x=int(position_xy[0]),
                position_y=int(position_xy[1]),
                t_start_of_frame_us=sof,
                t_start_exposure_us=soe,
                t_end_exposure_us=eoe,
                t_end_of_frame_us=eof,
            )
        )
    return frames
