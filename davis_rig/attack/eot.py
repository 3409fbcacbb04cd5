"""Expectation over transformation (EoT) for the digital attack: seeded scene distributions and a clip pool.

Only the texture changes between optimisation steps, so the expensive, texture-independent part of a training
sample is prepared once: body shape, motion, heading, placement, camera distance/angle jitter, light,
background and sensor parameters are drawn from one integer seed (:func:`draw_scene`), the clip is posed and
rasterized once without autograd (:func:`prepare_clip`), and a step only does the differentiable part
(texture lookup -> compose -> V2E -> RVT, see :mod:`davis_rig.attack.optimize`).

:class:`ClipPool` holds ``size`` such clips. Slot ``i`` in generation ``g`` is built from the seed
``slot_seed(base_seed, i, g)``; every ``refresh_every`` steps a seeded random ``refresh_fraction`` of the slots
moves to its next generation and is rebuilt. The pool is therefore a pure function of ``(base_seed,
generations)``: a checkpoint stores the generation array and a resumed run rebuilds exactly the same clips.
Under torchrun each rank builds only the slots it owns (``i % world_size == rank``).

Beyond the paper (whose official code renders a walking-in-place SMPL body on a blank background with camera
jitter only), every clip draws:

- body shape from the **training** shapes (:func:`split_shapes`; the test shapes are never used for training),
  motion: the shape's walk (``walk``: the gait generator's natural walk by default, or the asset's bundled
  cycle; walking forward or in place) or one of the given training motions
  (e.g. the AMASS train split of :mod:`davis_rig.scene.mocap.splits`), start time, heading;
- camera: the training scale (middle) with the official jitter (:class:`~davis_rig.scene.camera.EoTJitter`,
  p = 0.4 rotation +-0.1 rad, p = 0.4 distance +-0.25/1.75), a lateral/depth placement offset;
- light (:meth:`~davis_rig.scene.shading.Light.random`) and background (procedural, or a uniform grey);
  :meth:`EoTConfig.official` is the official code's distribution instead (white background, its light, walking
  in place, camera jitter only, ideal sensor);
- sensor non-idealities for the differentiable V2E: the clip's contrast threshold (uniform range), per-pixel
  threshold mismatch (Gaussian, v2e's ``sigma_thres``) and shot-noise events (Poisson, added to the histogram as
  constants: they carry no gradient, like real noise); with ``test_sensor_probability`` (default 1/2) the clip
  has the evaluation's ideal sensor instead, so the test sensor is inside the distribution that trains and
  validates the texture.

All randomness comes from ``numpy.random.default_rng`` seeded with integers; no global RNG is touched.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ConfigError, ShapeError
from davis_rig.events.histogram import NUM_BINS, WINDOW_US
from davis_rig.events.simulator import DEFAULT_THRESHOLD
from davis_rig.scene.camera import TRAIN_SCALE, EoTJitter, PinholeCamera
from davis_rig.scene.scene import MIN_RENDER_RATE_HZ, WALKS, Motion, SceneSpec
from davis_rig.scene.shading import Light

with optional_dependency("the attack"):
    import torch

__all__ = [
    "ClipPool",
    "amass_motions",
    "bvh_motions",
    "EoTConfig",
    "PoolClip",
    "draw_scene",
    "prepare_clip",
    "slot_seed",
    "split_shapes",
]

_SEED_SALT = 0x5EED_A77C
#: The evaluation's contrast threshold (:class:`~davis_rig.events.simulator.SimulatorConfig`, ON = OFF).
TEST_THRESHOLD = DEFAULT_THRESHOLD


def split_shapes(num_shapes: int, test_every: int = 4) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Deterministic train/test split of the body shapes: every ``test_every``-th shape (1, 5, 9, ...) is a test shape.

    The bundled asset has 24 adult shapes: 18 for training, 6 (1, 5, 9, 13, 17, 21) unseen in training and used
    by the digital evaluation (:mod:`davis_rig.attack.evaluate`).

    Args:
        num_shapes: shapes in the asset (>= 2).
        test_every: one test shape per this many shapes (>= 2).

    Returns:
        ``(train_indices, test_indices)``, disjoint, sorted.

    Raises:
        ValueError: num_shapes < 2 or test_every < 2.
    """
    if int(num_shapes) < 2 or int(test_every) < 2:
        raise ValueError(f"need num_shapes >= 2 and test_every >= 2, got {num_shapes}, {test_every}")
    test = tuple(i for i in range(int(num_shapes)) if i % int(test_every) == 1)
    train = tuple(i for i in range(int(num_shapes)) if i % int(test_every) != 1)
    return train, test


def slot_seed(base_seed: int, slot: int, generation: int) -> int:
    """The seed of pool slot ``slot`` in generation ``generation`` (a 63-bit integer, stable across platforms)."""
    ss = np.random.SeedSequence([_SEED_SALT, int(base_seed), int(slot), int(generation)])
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


@dataclass(frozen=True)
class EoTConfig:
    """Distributions of the training clips (every field has a paper-compatible or documented default).

    Attributes:
        shapes: body shapes to draw from; ``None`` = the training split of :func:`split_shapes`.
        heading_range_rad: heading uniform in this range (0 = towards the camera, pi/2 = walking right).
        across_view_probability: chance that a clip walks across the view instead: its heading uniform within
            ``across_view_spread_rad`` of +pi/2 or -pi/2 (either side, equally likely), the direction of the
            paper's physical test and of the evaluation's default headings; 0 (default) = ``heading_range_rad``
            alone.
        across_view_spread_rad: half-width of the across-view headings around +-pi/2 (rad).
        advance_probability: chance that the walk moves forward (else walks in place, as the official code).
        walk: the walk of the clips without a training motion (:data:`~davis_rig.scene.scene.WALKS`):
            ``"natural"`` (default, the gait generator's 1.3 m/s) or ``"bundled"`` (the asset's cycle).
        scale: camera scale name or person height in px (:data:`~davis_rig.scene.camera.TEST_SCALES_PX`).
        jitter: camera EoT jitter (official p = 0.4 / p = 0.4); ``None`` = none.
        offset_x_m: lateral placement uniform in +-offset_x_m (m).
        offset_depth_m: depth placement uniform in +-offset_depth_m (m).
        random_light_probability: chance of a random light (else ``light``).
        light: the light of the other clips (``None`` = the toolkit's default light).
        random_background_probability: chance of a procedural background (else uniform grey).
        background_level_range: grey level of a uniform background, uniform in this range.
        threshold_range: clip contrast threshold theta (log units), uniform in this range (paper: 0.2).
        threshold_sigma: per-pixel threshold mismatch std (log units), 0 = off.
        min_threshold: lower clip of the per-pixel thresholds.
        shot_noise_rate_hz: per-pixel noise event rate (ON + OFF), uniform in this range (Hz).
        test_sensor_probability: chance that a clip's sensor is the evaluation's instead of the ranges above:
            the ideal sensor of :class:`~davis_rig.events.simulator.SimulatorConfig` (theta = 0.2 ON and OFF,
            no mismatch, no noise), so the test sensor lies inside the training (and validation) distribution.
        seq_len: windows per sequence (paper: 3).
        window_us: window duration (RVT: 50 ms).
        playback_speed: motion seconds per clip second (official code: 5/3,
            :data:`~davis_rig.scene.scene.OFFICIAL_PLAYBACK_SPEED`).
        render_rate_hz: frames per second (>= 200).
        supersample: samples per pixel side of the rasterizer.
        camera: intrinsics (default: RVT 304 x 240 crop of the DAVIS346).
    """

    shapes: tuple[int, ...] | None = None
    heading_range_rad: tuple[float, float] = (0.0, 2.0 * math.pi)
    across_view_probability: float = 0.0
    across_view_spread_rad: float = math.pi / 6
    advance_probability: float = 0.5
    walk: str = "natural"
    scale: str | float = TRAIN_SCALE
    jitter: EoTJitter | None = field(default_factory=EoTJitter)
    offset_x_m: float = 0.4
    offset_depth_m: float = 0.5
    random_light_probability: float = 0.8
    light: Light | None = None
    random_background_probability: float = 0.7
    background_level_range: tuple[float, float] = (0.2, 0.8)
    threshold_range: tuple[float, float] = (0.17, 0.23)
    threshold_sigma: float = 0.02
    min_threshold: float = 0.05
    shot_noise_rate_hz: tuple[float, float] = (0.0, 1.0)
    test_sensor_probability: float = 0.5
    seq_len: int = 3
    window_us: int = WINDOW_US
    playback_speed: float = 1.0
    render_rate_hz: float = MIN_RENDER_RATE_HZ
    supersample: int = 2
    camera: PinholeCamera = field(default_factory=PinholeCamera.rvt_crop)

    @classmethod
    def official(cls, **overrides) -> "EoTConfig":
        """The official code's training distribution: its scene (blank white background, its light
        (:meth:`Light.official`), the body walking in place at the centre) with the camera jitter as the only
        EoT, and the ideal sensor (theta = 0.2, no mismatch, no noise). Body shapes and headings are still drawn
        (the official code's come from its AMASS clips). ``overrides`` set any other field."""
        return cls(**{"advance_probability": 0.0, "offset_x_m": 0.0, "offset_depth_m": 0.0,
                      "random_light_probability": 0.0, "light": Light.official(),
                      "random_background_probability": 0.0, "background_level_range": (1.0, 1.0),
                      "threshold_range": (0.2, 0.2), "threshold_sigma": 0.0, "shot_noise_rate_hz": (0.0, 0.0),
                      **overrides})

    @classmethod
    def test_scene(cls, **overrides) -> "EoTConfig":
        """The evaluation's scene and sensor: a uniform grey background (level 0.5), the default light and the
        ideal sensor (theta = 0.2, no mismatch, no noise); body shapes, headings, placement and camera jitter are
        still drawn. ``overrides`` set any other field (e.g. ``scale``)."""
        return cls(**{"random_light_probability": 0.0, "random_background_probability": 0.0,
                      "background_level_range": (0.5, 0.5), "threshold_range": (0.2, 0.2), "threshold_sigma": 0.0,
                      "shot_noise_rate_hz": (0.0, 0.0), **overrides})

    def __post_init__(self) -> None:
        def refuse(name: str, reason: str) -> None:
            raise ConfigError(name, f"{reason}, got {getattr(self, name)!r}")

        if int(self.seq_len) < 1:
            refuse("seq_len", "expected an integer >= 1")
        for name in ("advance_probability", "random_light_probability", "random_background_probability",
                     "test_sensor_probability", "across_view_probability"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                refuse(name, "expected a number in [0, 1]")
        lo, hi = self.threshold_range
        if not 0 < lo <= hi:
            refuse("threshold_range", "expected 0 < low <= high")
        low_rate, high_rate = self.shot_noise_rate_hz
        if not 0 <= low_rate <= high_rate:
            refuse("shot_noise_rate_hz", "expected a range of rates 0 <= low <= high")
        if not self.threshold_sigma >= 0:
            refuse("threshold_sigma", "expected a number >= 0")
        if int(self.window_us) <= 0:
            refuse("window_us", "expected an integer > 0")
        if not 0.0 <= self.across_view_spread_rad <= math.pi / 2:
            refuse("across_view_spread_rad", "expected a half-width in [0, pi/2] rad")
        if self.walk not in WALKS:
            refuse("walk", f"expected one of {WALKS}")
        if not (math.isfinite(self.playback_speed) and self.playback_speed > 0):
            refuse("playback_speed", "expected a finite number > 0")

    @property
    def duration_s(self) -> float:
        """Clip duration: ``seq_len`` windows plus one frame (the first frame only sets the reference), s."""
        return self.seq_len * self.window_us / 1e6 + 0.5 / self.render_rate_hz

    def window_end_us(self, t0_us: int = 0) -> np.ndarray:
        """Window ends of a clip starting at ``t0_us``: int64 [seq_len] (µs)."""
        return t0_us + int(self.window_us) * np.arange(1, int(self.seq_len) + 1, dtype=np.int64)


@dataclass
class PoolClip:
    """One pre-rasterized EoT clip (everything except the texture).

    Attributes:
        seed: the seed it was drawn from.
        spec: the :class:`~davis_rig.scene.scene.SceneSpec`.
        raster: :class:`~davis_rig.scene.renderer.RasterizedMesh` (no grad) without its ``uv``, ``face``,
            ``sample_index``, ``sample_pixel`` and ``coverage`` (a step needs only :meth:`~RasterizedMesh.person`
            with ``active_pixel``; use ``lookup`` for the texels, ``active_backdrop`` for the background).
        lookup: :class:`~davis_rig.scene.texture.TexelLookup` of the grid (mask applied: white outside).
        background: float32 tensor [H, W]; outside :attr:`active_box` every frame is this background.
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs).
        boxes: float32 [W, 4] person box ``(x0, y0, x1, y1)`` at each window end (px; NaN: not visible).
        threshold: float32 tensor [H, W], per-pixel contrast threshold (log units), ON = OFF.
        noise_cell: int64 tensor [K], distinct flat indices into the [W, 2 * B, H, W] histogram where noise fired.
        noise_count: float32 tensor [K], noise events in each of those cells.
        active_box: ``(y0, y1, x0, x1)`` (px, end exclusive), the rows and columns of every pixel the person covers
            in any frame. Outside it the video is the constant background, so no event can fire there and the
            V2E runs on this crop only (:meth:`active_video`); at least one pixel even when the person is unseen.
        active_backdrop: float32 tensor [T, y1 - y0, x1 - x0], the visible background ``background * (1 -
            coverage)`` inside the active box (computed once; outside the box the coverage is 0).
        active_pixel: int64 tensor [N], each covered sample's flat pixel index ``t*h*w + row*w + col`` in the box.
        window_us: window duration (µs): each window is ``[end - window_us, end]``.
        base_threshold: the clip's contrast threshold as drawn (float64) when every pixel has it (no mismatch),
            else ``None``.
    """

    seed: int
    spec: SceneSpec
    raster: object
    lookup: object
    background: "torch.Tensor"
    t_us: np.ndarray
    window_end_us: np.ndarray
    boxes: np.ndarray
    threshold: "torch.Tensor"
    noise_cell: "torch.Tensor"
    noise_count: "torch.Tensor"
    active_box: tuple[int, int, int, int]
    active_backdrop: "torch.Tensor"
    active_pixel: "torch.Tensor"
    window_us: int = WINDOW_US
    base_threshold: float | None = None

    def video(self, grid: "torch.Tensor") -> "torch.Tensor":
        """Render the clip with an n x n grid (differentiable w.r.t. ``grid``): float tensor [T, H, W].

        Equals ``raster.compose(lookup.sample(grid), background)`` of the full raster (bit for bit with a float32
        grid): the background everywhere, :meth:`active_video` inside the active box.
        """
        active = self.active_video(grid)
        y0, y1, x0, x1 = self.active_box
        frames = torch.broadcast_to(self.background.to(active.dtype), (active.shape[0], *self.background.shape))
        video = frames.clone()
        video[:, y0:y1, x0:x1] = active
        return video

    def active_video(self, grid: "torch.Tensor") -> "torch.Tensor":
        """:meth:`video` inside :attr:`active_box`: float tensor [T, y1 - y0, x1 - x0] (the same bits, computed
        on the box only: the person's samples are all inside it)."""
        person = self.raster.person(self.lookup.sample(grid, fill=1.0), pixels=self.active_pixel,
                                    hw=tuple(self.active_backdrop.shape[1:]))
        return self.active_backdrop.to(person.dtype) + person

    def add_noise(self, hist: "torch.Tensor") -> "torch.Tensor":
        """``hist`` plus the clip's noise events (constants: the gradient passes through unchanged).

        Args:
            hist: float tensor [W, 2 * B, H, W] of event counts.

        Returns:
            Float tensor [W, 2 * B, H, W]; ``hist`` itself when the clip has no noise.
        """
        if not self.noise_cell.numel():
            return hist
        return hist.reshape(-1).index_add(0, self.noise_cell, self.noise_count.to(hist.dtype)).view_as(hist)


def draw_scene(config: EoTConfig, seed: int, num_shapes: int, motions: Sequence[Motion] = ()) -> tuple[SceneSpec, dict]:
    """Draw one training scene and its sensor parameters from a seed.

    Args:
        config: the distributions.
        seed: integer seed (the same seed gives the same scene).
        num_shapes: shapes in the body asset (for the default training split).
        motions: optional training motions; when given, a clip uses one of them with probability 1/2.

    Returns:
        ``(spec, sensor)``: the scene (``seed`` resolves jitter, light and background inside
        :func:`~davis_rig.scene.scene.render_clip`) and ``{"threshold", "threshold_sigma", "noise_rate_hz",
        "sensor_seed", "test_sensor"}`` (``test_sensor``: the evaluation's ideal sensor was drawn).
    """
    rng = np.random.default_rng([_SEED_SALT, int(seed)])
    shapes = config.shapes if config.shapes is not None else split_shapes(num_shapes)[0]
    shape = int(shapes[int(rng.integers(len(shapes)))])
    motion = None
    start_s = float(rng.uniform(0.0, 2.0))
    if motions and rng.random() < 0.5:
        motion = motions[int(rng.integers(len(motions)))]
        length_s = motion.rotations_wxyz.shape[0] / motion.fps_hz
        start_s = float(rng.uniform(0.0, max(0.0, length_s - config.playback_speed * config.duration_s)))
    advance = bool(rng.random() < config.advance_probability)
    heading = _draw_heading(config, rng)
    offset = (float(rng.uniform(-config.offset_x_m, config.offset_x_m)),
              float(rng.uniform(-config.offset_depth_m, config.offset_depth_m)))
    light = "random" if rng.random() < config.random_light_probability else config.light
    if rng.random() < config.random_background_probability:
        background: object = "random"
    else:
        background = float(rng.uniform(*config.background_level_range))
    spec = SceneSpec(
        shape_index=shape, motion=motion, motion_start_s=start_s, playback_speed=config.playback_speed,
        advance=advance, walk=config.walk, heading_rad=heading, scale=config.scale, offset_m=offset,
        camera=config.camera,
        jitter=config.jitter, light=light,
        background=background, render_rate_hz=config.render_rate_hz, duration_s=config.duration_s,
        supersample=config.supersample, seed=int(rng.integers(2**62)),
    )
    sensor = {
        "threshold": float(rng.uniform(*config.threshold_range)),
        "threshold_sigma": float(config.threshold_sigma),
        "noise_rate_hz": float(rng.uniform(*config.shot_noise_rate_hz)),
        "sensor_seed": int(rng.integers(2**62)),
        "test_sensor": False,
    }
    # drawn last: the draws above (scene and sensor) are the same whatever the probability
    if config.test_sensor_probability > 0 and rng.random() < config.test_sensor_probability:
        sensor.update(threshold=TEST_THRESHOLD, threshold_sigma=0.0, noise_rate_hz=0.0, test_sensor=True)
    return spec, sensor


def _draw_heading(config: EoTConfig, rng: np.random.Generator) -> float:
    """A clip's heading (rad): across the view with ``config.across_view_probability`` (uniform within the spread
    around +-pi/2), else uniform in ``config.heading_range_rad``. With the probability 0 it draws exactly one
    number from ``rng``, as before the option existed, so earlier seeds give the same clips."""
    if config.across_view_probability > 0.0 and rng.random() < config.across_view_probability:
        side = 1.0 if rng.random() < 0.5 else -1.0
        spread = config.across_view_spread_rad
        return float(side * math.pi / 2 + rng.uniform(-spread, spread))
    return float(rng.uniform(*config.heading_range_rad))


def prepare_clip(
    spec: SceneSpec,
    sensor: dict,
    model,
    grid_n: int,
    mask=None,
    *,
    config: EoTConfig | None = None,
    seed: int = 0,
    texture_size: int = 1024,
) -> PoolClip:
    """Pose and rasterize a scene once (no autograd) and prepare its texel lookup and sensor parameters.

    Args:
        spec: the scene (:func:`draw_scene`).
        sensor: the sensor parameters of :func:`draw_scene`.
        model: :class:`~davis_rig.scene.body.BodyModel` (its device is the clip's device).
        grid_n: texture grid cells per side.
        mask: bool [texture_size, texture_size] paintable texels (``None``: whole body).
        config: the EoT config (window length, sequence length); default :class:`EoTConfig`.
        seed: recorded in the clip.
        texture_size: UV map resolution (paper 1024).

    Returns:
        :class:`PoolClip` on the model's device.
    """
    from davis_rig.scene.scene import render_clip

    config = config or EoTConfig()
    with torch.no_grad():
        clip = render_clip(spec, None, model=model)
    lookup = clip.raster.lookup(size=texture_size, mode="nearest", grid_n=int(grid_n), mask=mask)
    t_us = np.asarray(clip.t_us, dtype=np.int64)
    ends = config.window_end_us(int(t_us[0]))
    if ends[-1] > t_us[-1]:
        raise ShapeError(f"clip ends at {t_us[-1]} µs before the last window end {ends[-1]} µs")
    frame = np.searchsorted(t_us, ends)
    boxes = np.asarray(clip.boxes, dtype=np.float32)[frame]
    h, w = clip.raster.hw
    rng = np.random.default_rng(sensor["sensor_seed"])
    theta = np.full((h, w), sensor["threshold"], dtype=np.float32)
    if sensor["threshold_sigma"] > 0:
        theta = theta + rng.normal(0.0, sensor["threshold_sigma"], size=(h, w)).astype(np.float32)
        theta = np.maximum(theta, np.float32(config.min_threshold))
    n_windows = len(ends)
    mean_events = sensor["noise_rate_hz"] * h * w * n_windows * config.window_us / 1e6
    k = int(rng.poisson(mean_events)) if mean_events > 0 else 0
    # each noise event: window, polarity, bin, pixel uniformly (a pixel fires ON and OFF noise alike)
    noise_index = rng.integers(0, n_windows * 2 * NUM_BINS * h * w, size=k, dtype=np.int64)
    noise_cell, noise_count = np.unique(noise_index, return_counts=True)
    device = clip.raster.coverage.device
    active_box = _active_box(clip.raster.coverage)
    background = torch.as_tensor(clip.background, device=device)
    backdrop = clip.raster.backdrop(background)  # [T, H, W]: only its active box is kept
    y0, y1, x0, x1 = active_box
    frame_px = h * w
    pixel = clip.raster.sample_pixel
    frame, row, col = pixel // frame_px, pixel % frame_px // w, pixel % w
    active_pixel = (frame * (y1 - y0) + row - y0) * (x1 - x0) + col - x0
    # a step needs only the shade (RasterizedMesh.person into the active box) once the texel lookup, the backdrop
    # and the active pixels are built: drop the per-sample UVs, faces, sample indices and full-frame pixels and the
    # coverage (with the full-frame backdrop, ~60 % of a clip's memory: 24 -> 10 MB at 10 x 10, middle scale)
    raster = dataclasses.replace(clip.raster, face=None, uv=None, sample_index=None, coverage=None, sample_pixel=None)
    return PoolClip(
        seed=int(seed), spec=spec, raster=raster, lookup=lookup, background=background,
        t_us=t_us, window_end_us=ends, boxes=boxes, threshold=torch.as_tensor(theta, device=device),
        noise_cell=torch.as_tensor(noise_cell, device=device),
        noise_count=torch.as_tensor(noise_count.astype(np.float32), device=device), active_box=active_box,
        active_backdrop=backdrop[:, y0:y1, x0:x1].contiguous(), active_pixel=active_pixel,
        window_us=int(config.window_us),
        base_threshold=None if sensor["threshold_sigma"] > 0 else float(sensor["threshold"]),
    )


def _active_box(coverage: "torch.Tensor") -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` bounding the pixels with coverage > 0 in any frame of [T, H, W]; (0, 1, 0, 1) if none."""
    seen = (coverage > 0).any(dim=0)
    rows = torch.nonzero(seen.any(dim=1)).flatten()
    cols = torch.nonzero(seen.any(dim=0)).flatten()
    if rows.numel() == 0:
        return 0, 1, 0, 1
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


class ClipPool:
    """A pool of pre-rasterized EoT clips, refreshed piecewise, reproducible from ``(base_seed, generations)``.

    Args:
        config: the EoT distributions.
        model: :class:`~davis_rig.scene.body.BodyModel` (device of the clips).
        grid_n: texture grid cells per side.
        mask: bool [1024, 1024] paintable texels or ``None``.
        size: number of slots.
        base_seed: seed of the whole pool.
        motions: optional training motions (see :func:`draw_scene`).
        rank, world_size: this process owns the slots ``i`` with ``i % world_size == rank`` (DDP).
        generations: int [size] generation of each slot (a checkpoint's ``state_dict()["generations"]``);
            default zeros.
        on_clip: called after each clip built here (progress; an exception it raises stops the building).

    Raises:
        ValueError: size < world_size or bad rank.
    """

    def __init__(self, config: EoTConfig, model, grid_n: int, mask=None, *, size: int = 32, base_seed: int = 0,
                 motions: Sequence[Motion] = (), rank: int = 0, world_size: int = 1, generations=None,
                 on_clip: Callable[[], None] | None = None):
        if int(world_size) < 1 or not 0 <= int(rank) < int(world_size):
            raise ValueError(f"need 0 <= rank < world_size, got rank={rank}, world_size={world_size}")
        if int(size) < int(world_size):
            raise ValueError(f"pool size {size} must be >= world_size {world_size} (every rank needs a slot)")
        self.config = config
        self.model = model
        self.grid_n = int(grid_n)
        self.mask = mask
        self.size = int(size)
        self.base_seed = int(base_seed)
        self.motions = tuple(motions)
        self.rank = int(rank)
        self.world_size = int(world_size)
        gens = np.zeros(self.size, dtype=np.int64) if generations is None else np.asarray(generations, dtype=np.int64)
        if gens.shape != (self.size,):
            raise ShapeError(f"generations must be [{self.size}], got {gens.shape}")
        self.generations = gens.copy()
        self.owned = np.arange(self.rank, self.size, self.world_size, dtype=np.int64)
        self.clips: dict[int, PoolClip] = {}
        for slot in self.owned.tolist():
            self._build(slot)
            if on_clip is not None:
                on_clip()

    def _build(self, slot: int) -> None:
        seed = slot_seed(self.base_seed, slot, int(self.generations[slot]))
        spec, sensor = draw_scene(self.config, seed, self.model.num_shapes, self.motions)
        self.clips[slot] = prepare_clip(spec, sensor, self.model, self.grid_n, self.mask, config=self.config,
                                        seed=seed)

    def refresh(self, step: int, fraction: float) -> list[int]:
        """Move a seeded random ``fraction`` of all slots to their next generation and rebuild the owned ones.

        Args:
            step: the optimisation step (seeds the choice, so every rank picks the same slots).
            fraction: share of the slots to replace, in [0, 1].

        Returns:
            The refreshed slot indices (all ranks), sorted.
        """
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"fraction must be in [0, 1], got {fraction}")
        count = int(round(fraction * self.size))
        if count == 0:
            return []
        rng = np.random.default_rng([_SEED_SALT, self.base_seed, int(step), 1])
        slots = np.sort(rng.choice(self.size, size=count, replace=False))
        self.generations[slots] += 1
        for slot in slots.tolist():
            if slot % self.world_size == self.rank:
                self._build(slot)
        return slots.tolist()

    def sample(self, step: int, per_rank: int) -> list[PoolClip]:
        """The clips this rank uses at ``step``: ``per_rank`` owned slots drawn without replacement (seeded).

        Args:
            step: optimisation step.
            per_rank: clips per rank and step (<= owned slots).

        Returns:
            list of :class:`PoolClip`.
        """
        if not 1 <= int(per_rank) <= len(self.owned):
            raise ValueError(f"per_rank must be in [1, {len(self.owned)}] (owned slots), got {per_rank}")
        rng = np.random.default_rng([_SEED_SALT, self.base_seed, int(step), 2, self.rank])
        picks = rng.choice(len(self.owned), size=int(per_rank), replace=False)
        return [self.clips[int(self.owned[i])] for i in picks]

    def state_dict(self) -> dict:
        """What rebuilds the pool: ``{"base_seed", "size", "generations"}``."""
        return {"base_seed": self.base_seed, "size": self.size, "generations": self.generations.tolist()}

    def __len__(self) -> int:
        return len(self.owned)

    def __repr__(self) -> str:
        return (f"ClipPool(size={self.size}, owned={len(self.owned)}, grid_n={self.grid_n}, "
                f"base_seed={self.base_seed}, rank={self.rank}/{self.world_size})")



def amass_motions(root, split: str = "train", *, asset=None, shape_index: int = 0, max_trials: int | None = None,
                  translation: str = "foot_locked") -> list:
    """Motions of one side of the paper's AMASS/CMU trial split (47 train / 13 test of 60), retargeted onto the rig.

    Training uses ``split="train"``, the evaluation ``split="test"`` (motions unseen in training), from the
    deterministic rule of :func:`davis_rig.scene.mocap.splits.split_trials`.

    Args:
        root: the user's AMASS CMU folder (``<root>/<subject>/*_poses.npz``; never downloaded).
        split: ``"train"`` or ``"test"``.
        asset: body asset (``None`` = bundled).
        shape_index: shape whose rig the motions are retargeted to.
        max_trials: keep the first N trials of the side (sorted by id).
        translation: root translation mode of :func:`davis_rig.scene.mocap.amass.load_amass`.

    Returns:
        list of :class:`davis_rig.scene.motion.Motion`.

    Raises:
        FileNotFoundError: root is not a folder. ValueError: bad split or no trial found.
    """
    from davis_rig.scene.mocap.amass import load_amass

    paths = _split_trial_paths(root, "*_poses.npz", "AMASS", split, max_trials)
    return [load_amass(p, asset, shape_index, translation=translation) for p in paths]


def bvh_motions(root, split: str = "train", *, asset=None, shape_index: int = 0, max_trials: int | None = None,
                translation: str = "foot_locked") -> list:
    """Motions of one side of the CMU BVH trial split, retargeted onto the rig: :func:`amass_motions` for BVH files.

    Args:
        root: the user's CMU BVH folder (``<root>/<subject>/<subject>_<trial>.bvh``, e.g. ``07/07_01.bvh``; CMU
            joint names and units, see :func:`davis_rig.scene.mocap.bvh.load_bvh`).
        split, asset, shape_index, max_trials: as :func:`amass_motions` (the same split rule and trial ids).
        translation: root translation mode of :func:`davis_rig.scene.mocap.bvh.load_bvh`.

    Returns:
        list of :class:`davis_rig.scene.motion.Motion`.

    Raises:
        FileNotFoundError: root is not a folder. ValueError: bad split or no trial found. FormatError: a file
        is not a readable BVH.
    """
    from davis_rig.scene.mocap.bvh import load_bvh

    paths = _split_trial_paths(root, "*.bvh", "BVH", split, max_trials)
    return [load_bvh(p, asset, shape_index, translation=translation) for p in paths]


def _split_trial_paths(root, pattern: str, kind: str, split: str, max_trials: int | None) -> list:
    """Files of one side (``"train"`` / ``"test"``) of the trial split of ``<root>/<subject>/<pattern>``."""
    from davis_rig.scene.mocap.splits import find_trials, split_trials

    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    trials = find_trials(root, pattern=pattern)
    if not trials:
        raise ValueError(f"no {kind} trials ({pattern}) under {root}")
    parts = split_trials(trials)
    paths = parts.train_paths() if split == "train" else parts.test_paths()
    return paths if max_trials is None else paths[: int(max_trials)]
