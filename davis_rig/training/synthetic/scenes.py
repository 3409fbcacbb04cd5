"""Synthetic scene descriptions and their samplers: people, distractors, cars, camera, sensor noise, splits.

A :class:`SyntheticScene` holds everything that defines one sequence with all randomness resolved (JSON-able with
:meth:`SyntheticScene.to_dict`); :func:`sample_scene` draws a training / validation scene from the ranges of a
:class:`SyntheticSceneConfig`, :func:`held_out_scene` one of the held-out test subsets.

Splits are disjoint in body shapes (:data:`SPLIT_SHAPES`: 0-17 train, 18-20 val, 21-23 test), in the seeds of
gaits, clothing, backgrounds, distractors and noise (each split draws them from its own range,
:data:`SPLIT_SEED_OFFSETS`) and in gait speed bands (:data:`SPLIT_SPEEDS_M_S`). The held-out test set
(:func:`held_out_scene`) has one subset per clothing kind in :data:`TEST_CLOTHING` (white, black, random 60 x 60
pattern) x each paper scale in :data:`~davis_rig.scene.camera.TEST_SCALES_PX` (large, middle, small): one
person walking across a static camera at the distance where a 1.75 m person spans that height.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from davis_rig.errors import ConfigError
from davis_rig.events.simulator import SimulatorConfig
from davis_rig.scene.camera import (
    DEFAULT_PERSON_HEIGHT_M,
    TEST_SCALES_PX,
    EgoMotion,
    PinholeCamera,
    distance_for_height,
)
from davis_rig.scene.shading import Light

__all__ = [
    "CLOTHING_KINDS",
    "GEN1_LIKE_SCENES",
    "PAINT_PATTERNS",
    "SCENE_RECIPES",
    "DISTRACTOR_KINDS",
    "SEED_RANGE",
    "SPLIT_SEED_OFFSETS",
    "SPLIT_SHAPES",
    "SPLIT_SPEEDS_M_S",
    "TEST_CLOTHING",
    "TEST_SUBSETS",
    "DistractorSpec",
    "PersonSpec",
    "SyntheticScene",
    "SyntheticSceneConfig",
    "VehicleSpec",
    "check_split",
    "held_out_scene",
    "sample_distractor",
    "sample_scene",
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
#: Paints of distractors and car bodies (see :class:`DistractorSpec`).
PAINT_PATTERNS = ("flat", "stripes", "checks")


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
        hot_pixel_fraction, hot_pixel_rate_hz: ranges of the fraction of hot pixels and of their noise rate (Hz);
            drawn only when the rate's upper end is above 0 (the default draws nothing, so older datasets stay as
            they were).
        simulator_dtype: ``"float64"`` (exact) or ``"float32"`` (faster, for big runs).
        clothing_kinds: the kinds :func:`sample_scene` draws clothing from (uniformly; default all of
            :data:`CLOTHING_KINDS`). E.g. without ``"grid"`` and ``"pattern60"`` the detector never sees
            black/white cell textures (an attack victim that, like the paper's Gen1 RVT, was not trained on them).
            The held-out test subsets keep their fixed clothing.
        vehicle_counts: (min, max) labelled cars per train/val scene (:class:`VehicleSpec`, Gen1 class 0); the
            default ``(0, 0)`` is the single-class bundled recipe. With cars the detector's class score must
            tell a person from a car, as Gen1's two-class RVT does. The held-out test scenes have none.
        vehicle_contrast, vehicle_patterns: range of the contrast of a car's body paint around its level, and the
            patterns it is drawn from (as :class:`DistractorSpec`'s).

    :data:`SCENE_RECIPES` names the two recipes: ``"bundled"`` (these defaults) and ``"gen1like"``
    (:data:`GEN1_LIKE_SCENES`).
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
    hot_pixel_fraction: tuple[float, float] = (0.0, 0.0)
    hot_pixel_rate_hz: tuple[float, float] = (0.0, 0.0)
    simulator_dtype: str = "float64"
    clothing_kinds: tuple[str, ...] = CLOTHING_KINDS
    vehicle_counts: tuple[int, int] = (0, 0)
    vehicle_contrast: tuple[float, float] = (0.0, 0.45)
    vehicle_patterns: tuple[str, ...] = PAINT_PATTERNS

    def __post_init__(self) -> None:
        if not 0 <= self.vehicle_counts[0] <= self.vehicle_counts[1]:
            raise ConfigError("vehicle_counts", f"expected 0 <= min <= max, got {tuple(self.vehicle_counts)}")
        unknown = sorted(set(self.clothing_kinds) - set(CLOTHING_KINDS))
        if not self.clothing_kinds or unknown:
            raise ConfigError("clothing_kinds", f"expected a non-empty subset of {CLOTHING_KINDS}, got "
                             f"{tuple(self.clothing_kinds)}")
        if not self.vehicle_patterns or set(self.vehicle_patterns) - set(PAINT_PATTERNS):
            raise ConfigError("vehicle_patterns", f"expected a non-empty subset of {PAINT_PATTERNS}, got "
                             f"{tuple(self.vehicle_patterns)}")
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


#: A recipe closer to the paper's victim, RVT trained on Prophesee Gen1 (car-mounted ATIS, 304 x 240): small
#: people (most Gen1 pedestrians are 20-120 px tall), an ATIS-like sensor (higher and mismatched thresholds, a
#: refractory period, limited bandwidth, leak, shot noise and hot pixels), a mostly moving camera, plain grey
#: clothing, and 1-3 cars with high-contrast painted bodies in every scene, so that dense events inside an object
#: speak for "car", not "pedestrian" (the direction the paper's L_cls exploits). The test subsets are unchanged.
GEN1_LIKE_SCENES = SyntheticSceneConfig(
    person_height_px=(25.0, 180.0), test_scale_probability=0.1, ego_motion_probability=0.8,
    threshold=(0.25, 0.45), threshold_sigma=(0.02, 0.06), refractory_probability=1.0, refractory_us=(500.0, 2000.0),
    shot_noise_rate_hz=(0.1, 2.0), leak_rate_hz=(0.1, 1.0), cutoff_probability=1.0, cutoff_hz=(50.0, 300.0),
    hot_pixel_fraction=(1e-4, 1e-3), hot_pixel_rate_hz=(20.0, 100.0), clothing_kinds=("parts_grey",),
    vehicle_counts=(1, 3), vehicle_contrast=(0.5, 0.95), vehicle_patterns=("stripes", "checks"),
)
#: The named scene recipes of ``davis-make-dataset --recipe``.
SCENE_RECIPES = {"bundled": SyntheticSceneConfig(), "gen1like": GEN1_LIKE_SCENES}


def check_split(split: str) -> None:
    """Raise :class:`~davis_rig.errors.ConfigError` (field ``split``) unless ``split`` is ``"train"``, ``"val"`` or
    ``"test"``."""
    if split not in SPLIT_SHAPES:
        raise ConfigError("split", f"expected one of {tuple(SPLIT_SHAPES)}, got {split!r}")


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


def sample_distractor(rng, split: str, hw: tuple[int, int], duration_s: float,
                      front_probability: float) -> DistractorSpec:
    """Draw one distractor of a ``hw`` frame that crosses the view around mid-clip (``duration_s``, s); it is in
    front of the people with probability ``front_probability``."""
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
        pattern=str(rng.choice(PAINT_PATTERNS)), period_px=float(rng.uniform(4, 30)),
        front=bool(rng.random() < front_probability),
    )


def _vehicle(rng, hw: tuple[int, int], duration_s: float, config: SyntheticSceneConfig) -> VehicleSpec:
    h, w = hw
    length = float(rng.uniform(50, 220))
    speed = float(rng.uniform(40, 300)) * float(rng.choice([1.0, -1.0]))
    velocity = (speed, float(rng.uniform(-0.05, 0.05)) * abs(speed))
    # mid-clip centre: anywhere across a slightly enlarged frame, on the lower part of the image (the road)
    mid = (float(rng.uniform(-0.1, 1.1) * w), float(rng.uniform(0.45, 0.95) * h))
    start = (mid[0] - velocity[0] * duration_s / 2, mid[1] - velocity[1] * duration_s / 2)
    return VehicleSpec(
        length_px=length, start_xy_px=start, velocity_px_s=velocity, level=float(rng.uniform(0.05, 0.95)),
        contrast=float(rng.uniform(*config.vehicle_contrast)), pattern=str(rng.choice(config.vehicle_patterns)),
        period_px=float(rng.uniform(4, 30)), window_level=float(rng.uniform(0.02, 0.3)),
    )


def _simulator(rng, split: str, config: SyntheticSceneConfig) -> SimulatorConfig:
    theta = float(rng.uniform(*config.threshold))
    asym = float(rng.uniform(-config.threshold_asymmetry, config.threshold_asymmetry))
    hot = {}
    if config.hot_pixel_rate_hz[1] > 0:  # drawn only with hot pixels: other recipes draw what they drew before
        hot = {"hot_pixel_fraction": float(rng.uniform(*config.hot_pixel_fraction)),
               "hot_pixel_rate_hz": float(rng.uniform(*config.hot_pixel_rate_hz))}
    return SimulatorConfig(
        threshold_on=theta * (1 + asym), threshold_off=theta * (1 - asym),
        threshold_sigma=float(rng.uniform(*config.threshold_sigma)),
        refractory_us=int(rng.uniform(*config.refractory_us)) if rng.random() < config.refractory_probability else 0,
        shot_noise_rate_hz=float(rng.uniform(*config.shot_noise_rate_hz)),
        leak_rate_hz=float(rng.uniform(*config.leak_rate_hz)),
        cutoff_hz=float(rng.uniform(*config.cutoff_hz)) if rng.random() < config.cutoff_probability else 0.0,
        seed=_seed(rng, split) % (1 << 62), dtype=config.simulator_dtype, **hot,
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
        ConfigError: unknown split (field ``split``).
    """
    check_split(split)
    config = config or SyntheticSceneConfig()
    camera = PinholeCamera.rvt_crop()
    scene_seed = _seed(rng, split)
    count = int(rng.choice(4, p=np.asarray(config.people_probabilities)))
    people = tuple(_person(rng, split, config, config.duration_s, camera) for _ in range(count))
    n_distractors = int(rng.integers(config.distractor_counts[0], config.distractor_counts[1] + 1))
    distractors = tuple(
        sample_distractor(rng, split, camera.hw, config.duration_s, config.front_distractor_probability)
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
    return dataclasses.replace(scene, vehicles=tuple(_vehicle(rng, camera.hw, config.duration_s, config)
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
        ConfigError: unknown clothing or scale (field ``clothing`` or ``scale``).
    """
    if clothing not in CLOTHING_KINDS:
        raise ConfigError("clothing", f"expected one of {CLOTHING_KINDS}, got {clothing!r}")
    if scale not in TEST_SCALES_PX:
        raise ConfigError("scale", f"expected one of {tuple(TEST_SCALES_PX)}, got {scale!r}")
    config = config or SyntheticSceneConfig()
    camera = PinholeCamera.rvt_crop()
    scene_seed = _seed(rng, "test")
    heading = float(rng.choice([1.0, -1.0]) * math.pi / 2 + rng.uniform(-0.35, 0.35))
    person = _person(rng, "test", config, config.duration_s, camera, clothing=clothing,
                     height_px=TEST_SCALES_PX[scale], heading_rad=heading, x_mid_m=0.0)
    person = dataclasses.replace(
        person, x_mid_m=float(rng.uniform(-0.3, 0.3) * _half_width_m(person.depth_mid_m, camera)))
    n_distractors = int(rng.integers(0, 2))
    distractors = tuple(sample_distractor(rng, "test", camera.hw, config.duration_s, 0.0)
                        for _ in range(n_distractors))
    return SyntheticScene(
        split="test", seed=scene_seed, duration_s=config.duration_s, render_rate_hz=config.render_rate_hz,
        people=(person,), distractors=distractors, background_seed=_seed(rng, "test"),
        camera_height_m=DEFAULT_PERSON_HEIGHT_M / 2, ego_motion=None,
        background_depth_m=float(person.depth_mid_m + rng.uniform(3.0, 20.0)), light=Light.random(rng),
        simulator=_simulator(rng, "test", config), subset=f"{clothing}/{scale}",
    )


