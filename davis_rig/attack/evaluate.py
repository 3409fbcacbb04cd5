"""The paper's digital evaluation protocol: AP and SeqASR of textures from events of the EXACT simulator.

Protocol (paper, Experiments; official code where the paper is silent):

- **Test scenes**: body shapes of the test split (:func:`davis_rig.attack.eot.split_shapes`, never used in
  training) and their walks (the gait generator's natural walk by default, ``walk``), or given test motions (e.g.
  the AMASS test split of :mod:`davis_rig.scene.mocap.splits`), several headings and start phases, each at the
  three camera scales
  (:data:`~davis_rig.scene.camera.TEST_SCALES_PX`: large / middle / small); the person walks across a blank
  grey background under the toolkit's default light. :meth:`EvalConfig.official` is the official renders' scene
  instead: blank white background (PyTorch3D's default), its light, the body walking in place. Every scene is
  rasterized once and re-composited per texture.
- **Events**: :func:`davis_rig.events.simulator.simulate_events` (quantized events with interpolated
  timestamps, the ideal sensor unless ``simulator`` says otherwise), then RVT's stacked histograms
  (:func:`davis_rig.events.histogram.stacked_histograms`) of ``seq_len`` (3) 50 ms windows; the detector runs the
  windows in order with its recurrent states (zero at the sequence start). ``events="official_relaxed"`` scores
  the official code's relaxed simulator instead (continuous counts scaled by 10/27, not events a camera could
  deliver; see :data:`EVENT_MODELS`), to compare with the paper's own numbers.
- **Labels**: the person's visible box at each window end (one label per window; the Prophesee size filter of
  :func:`davis_rig.metrics.ap.filter_boxes` applies to labels and detections alike).
- **Metrics per confidence threshold** (0.001, 0.01, 0.1, 0.25; NMS 0.45): COCO AP / AP50 / AP75 of the pedestrian
  class (:func:`davis_rig.metrics.ap.coco_ap`, one image per window) and SeqASR (:func:`davis_rig.metrics.seqasr`,
  ``"paper"`` mode: a sequence is detected when any pedestrian box passes the threshold in any window).
- **Tables**: :func:`~davis_rig.attack.report.table1` (white / black / random 60 x 60 baselines vs optimized
  textures of grid 60 ... 10) and :func:`~davis_rig.attack.report.table2` (the 7 body-part combinations at 10 x 10,
  threshold 0.25) as markdown plus plots; :func:`~davis_rig.attack.report.write_visualisations` draws event frames
  with the detector's boxes per texture and a GIF of the person walking in a texture.

This module holds the protocol (:class:`EvalConfig`, the test scenes, :func:`evaluate_textures`);
:mod:`davis_rig.attack.scoring` the events, detection and metrics (its names are importable from here too);
:mod:`davis_rig.attack.report` the tables and pictures.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Mapping, Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.attack.scoring import (
    EVENT_MODEL_NAMES,
    EVENT_MODELS,
    detect_histograms,
    detect_windows,
    score_detections,
    window_histograms,
)
from davis_rig.errors import ConfigError, ShapeError
from davis_rig.events.histogram import WINDOW_US
from davis_rig.events.simulator import SimulatorConfig
from davis_rig.scene.camera import PinholeCamera
from davis_rig.scene.scene import MIN_RENDER_RATE_HZ, WALKS, Motion, SceneSpec
from davis_rig.scene.shading import Light
from davis_rig.types import PAPER_THRESHOLDS

with optional_dependency("the attack evaluation"):
    import torch

__all__ = [
    "EVENT_MODELS",
    "EVENT_MODEL_NAMES",
    "PAPER_THRESHOLDS",
    "TABLE2_THRESHOLD",
    "EvalConfig",
    "EvalScene",
    "TextureSpec",
    "baseline_textures",
    "config_dict",
    "detect_histograms",
    "detect_windows",
    "evaluate_textures",
    "evaluation_scenes",
    "prepare_scenes",
    "score_detections",
    "texture_video",
    "window_histograms",
]

#: Table 2's threshold.
TABLE2_THRESHOLD = 0.25


@dataclass(frozen=True)
class EvalConfig:
    """Settings of the digital evaluation.

    Attributes:
        scales: camera scales (names of :data:`TEST_SCALES_PX` or person heights in px).
        thresholds: confidence thresholds.
        shapes: body shapes; ``None`` = the test split of :func:`~davis_rig.attack.eot.split_shapes`.
        headings_rad: person headings (0 = towards the camera, pi/2 = walking right).
        phases: start phases per shape and heading (times into the walk cycle / motion, s).
        seq_len: windows per sequence (paper: 3).
        window_us: window duration (µs).
        playback_speed: motion seconds per clip second (official code: 5/3,
            :data:`~davis_rig.scene.scene.OFFICIAL_PLAYBACK_SPEED`).
        warmup_windows: windows run before the scored ones (states warm-up; 0 = the paper's digital clips).
        nms_threshold: class-wise NMS IoU threshold.
        background: uniform background level (default 0.5 grey; the official renders are blank white, 1.0).
        light: the scene light (``None`` = the toolkit's default :class:`~davis_rig.scene.shading.Light`).
        walk_in_place: the walk stays in place (the official code drops the global translation); False =
            the person walks forward across the view.
        walk: the walk without test motions (:data:`~davis_rig.scene.scene.WALKS`): ``"natural"`` (default, the
            gait generator's 1.3 m/s) or ``"bundled"`` (the asset's cycle, the walk of the tables measured before).
        render_rate_hz, supersample: rendering.
        simulator: the exact simulator's settings (ideal sensor by default; its thresholds are θ of the relaxed
            model too).
        events: the event model (:data:`EVENT_MODELS`): ``"exact"`` (default) or ``"official_relaxed"``.
        seed: seeds the scenes' phases' jitter-free choices (kept for the record).
        camera: intrinsics.
    """

    scales: tuple = ("large", "middle", "small")
    thresholds: tuple[float, ...] = PAPER_THRESHOLDS
    shapes: tuple[int, ...] | None = None
    headings_rad: tuple[float, ...] = (math.pi / 2, -math.pi / 2, 0.0, math.pi)
    phases: tuple[float, ...] = (0.0, 0.5)
    seq_len: int = 3
    window_us: int = WINDOW_US
    playback_speed: float = 1.0
    warmup_windows: int = 0
    nms_threshold: float = 0.45
    background: float = 0.5
    light: Light | None = None
    walk_in_place: bool = False
    walk: str = "natural"
    render_rate_hz: float = MIN_RENDER_RATE_HZ
    supersample: int = 2
    simulator: SimulatorConfig = field(default_factory=SimulatorConfig)
    events: str = "exact"
    seed: int = 0
    camera: PinholeCamera = field(default_factory=PinholeCamera.rvt_crop)

    @classmethod
    def official(cls, **overrides) -> "EvalConfig":
        """The scene of the official code's renders: blank white background (PyTorch3D's default), its light
        (:meth:`Light.official`) and the body walking in place; ``overrides`` set any other field."""
        return cls(**{"background": 1.0, "light": Light.official(), "walk_in_place": True, **overrides})

    def __post_init__(self) -> None:
        from davis_rig.scene.camera import TEST_SCALES_PX

        def refuse(name: str, reason: str) -> None:
            raise ConfigError(name, f"{reason}, got {getattr(self, name)!r}")

        if int(self.seq_len) < 1:
            refuse("seq_len", "expected an integer >= 1")
        if int(self.warmup_windows) < 0:
            refuse("warmup_windows", "expected an integer >= 0")
        if not self.thresholds or any(not 0 <= t <= 1 for t in self.thresholds):
            refuse("thresholds", "expected one or more numbers in [0, 1]")
        if self.events not in EVENT_MODELS:
            refuse("events", f"expected one of {EVENT_MODELS}")
        if not self.scales or any(s not in TEST_SCALES_PX if isinstance(s, str) else not (math.isfinite(s) and s > 0)
                                  for s in self.scales):
            refuse("scales", f"expected names from {tuple(TEST_SCALES_PX)} or heights in px > 0")
        if not (math.isfinite(self.playback_speed) and self.playback_speed > 0):
            refuse("playback_speed", "expected a finite number > 0")
        if self.walk not in WALKS:
            refuse("walk", f"expected one of {WALKS}")

    @property
    def num_windows(self) -> int:
        """Windows rendered per scene (warm-up + scored)."""
        return int(self.warmup_windows) + int(self.seq_len)

    @property
    def duration_s(self) -> float:
        """Clip duration (s): all windows plus half a frame."""
        return self.num_windows * self.window_us / 1e6 + 0.5 / self.render_rate_hz


@dataclass(frozen=True)
class TextureSpec:
    """A texture to evaluate.

    Attributes:
        grid: float32 [n, n] of 0/1 (1 = white).
        parts: painted body parts (``None`` = whole body, no mask); white elsewhere.
    """

    grid: np.ndarray
    parts: tuple[str, ...] | None = ("torso", "arms", "legs")


@dataclass
class EvalScene:
    """A rasterized test scene.

    Attributes:
        spec: the scene; scale: its scale key; raster: the rasterized mesh; background: tensor [H, W];
        t_us: int64 [T]; window_end_us: int64 [W]; boxes: float32 [W, 4] person box at each window end.
    """

    spec: SceneSpec
    scale: object
    raster: object
    background: "torch.Tensor"
    t_us: np.ndarray
    window_end_us: np.ndarray
    boxes: np.ndarray


def evaluation_scenes(config: EvalConfig, num_shapes: int,
                      motions: Sequence[Motion] = ()) -> list[tuple[object, SceneSpec]]:
    """The test scenes: shapes x (walk cycle or test motions) x headings x phases x scales.

    Args:
        config: the evaluation settings.
        num_shapes: shapes of the body asset (for the default test split).
        motions: test motions (each replaces the walk cycle; the scene grid then runs over them too).

    Returns:
        list of ``(scale, SceneSpec)``.
    """
    from davis_rig.attack.eot import split_shapes

    shapes = config.shapes if config.shapes is not None else split_shapes(num_shapes)[1]
    sources: list[Motion | None] = list(motions) if motions else [None]
    out = []
    for scale in config.scales:
        for shape in shapes:
            for motion in sources:
                for heading in config.headings_rad:
                    for phase in config.phases:
                        out.append((scale, SceneSpec(
                            shape_index=int(shape), motion=motion, motion_start_s=float(phase),
                            playback_speed=float(config.playback_speed), advance=not config.walk_in_place,
                            walk=config.walk,
                            heading_rad=float(heading), scale=scale,
                            camera=config.camera, light=config.light, background=float(config.background),
                            render_rate_hz=config.render_rate_hz, duration_s=config.duration_s,
                            supersample=config.supersample, seed=config.seed)))
    return out


def prepare_scenes(specs: Sequence[tuple[object, SceneSpec]], model, config: EvalConfig, *,
                   progress: bool = False) -> list[EvalScene]:
    """Pose and rasterize the test scenes once (no autograd).

    Args:
        specs: ``(scale, SceneSpec)`` pairs (:func:`evaluation_scenes`).
        model: :class:`~davis_rig.scene.body.BodyModel`.
        config: the evaluation settings.
        progress: show a tqdm bar (stderr).

    Returns:
        list of :class:`EvalScene`.
    """
    import sys

    from tqdm import tqdm

    from davis_rig.scene.scene import render_clip

    scenes = []
    for scale, spec in tqdm(specs, disable=not progress, desc="preparing test scenes", unit="scene", file=sys.stderr):
        with torch.no_grad():
            clip = render_clip(spec, None, model=model)
        t_us = np.asarray(clip.t_us, dtype=np.int64)
        ends = int(t_us[0]) + int(config.window_us) * np.arange(1, config.num_windows + 1, dtype=np.int64)
        boxes = np.asarray(clip.boxes, dtype=np.float32)[np.searchsorted(t_us, ends)]
        scenes.append(EvalScene(spec=spec, scale=scale, raster=clip.raster,
                                background=torch.as_tensor(clip.background), t_us=t_us, window_end_us=ends,
                                boxes=boxes))
    return scenes


def texture_video(scene: EvalScene, texture: TextureSpec, mask_cache: dict | None = None) -> "torch.Tensor":
    """Render a scene in a texture (no grad): float tensor [T, H, W]."""
    from davis_rig.scene.masks import part_mask

    grid = torch.as_tensor(np.asarray(texture.grid, dtype=np.float32), device=scene.raster.coverage.device)
    if grid.ndim != 2 or grid.shape[0] != grid.shape[1]:
        raise ShapeError(f"texture grid must be [n, n], got {tuple(grid.shape)}")
    mask = None
    if texture.parts is not None:
        key = tuple(texture.parts)
        if mask_cache is not None and key in mask_cache:
            mask = mask_cache[key]
        else:
            mask = part_mask(key)
            if mask_cache is not None:
                mask_cache[key] = mask
    with torch.no_grad():
        lookup = scene.raster.lookup(size=1024, mode="nearest", grid_n=int(grid.shape[0]), mask=mask)
        return scene.raster.compose(lookup.sample(grid.to(scene.raster.shade.dtype), fill=1.0), scene.background)


def evaluate_textures(textures: Mapping[str, TextureSpec], detector, scenes: Sequence[EvalScene],
                      config: EvalConfig, *, progress: bool = False) -> list[dict]:
    """Score every texture on every scene: rows of AP and SeqASR per texture, scale (and ``"all"``) and threshold.

    Args:
        textures: name -> :class:`TextureSpec`.
        detector: RVT detector (eval mode).
        scenes: rasterized test scenes (:func:`prepare_scenes`).
        config: the evaluation settings.
        progress: show a tqdm bar.

    Returns:
        list of dicts ``{"texture", "scale", "threshold", "AP", "AP_50", "AP_75", "AP_S", "AP_M", "AP_L",
        "SeqASR", "num_sequences", "num_detected", "num_windows"}``.
    """
    from tqdm import tqdm

    detector = detector.eval()
    masks: dict = {}
    rows = []
    warm = int(config.warmup_windows)
    bar = tqdm(total=len(textures) * len(scenes), disable=not progress, desc="evaluate")
    for name, texture in textures.items():
        per_scene = []
        for scene in scenes:
            video = texture_video(scene, texture, masks)
            decoded, _ = detect_windows(detector, video, scene.t_us, scene.window_end_us, config.simulator,
                                         events=config.events, window_us=config.window_us)
            per_scene.append(decoded[warm:])
            bar.update(1)
        groups = {"all": list(range(len(scenes)))}
        for i, scene in enumerate(scenes):
            groups.setdefault(str(scene.scale), []).append(i)
        for group, idx in groups.items():
            res = score_detections([per_scene[i] for i in idx], [scenes[i].boxes[warm:] for i in idx],
                                   [scenes[i].window_end_us[warm:] for i in idx], config.thresholds,
                                   seq_len=config.seq_len, nms_threshold=config.nms_threshold)
            for thr, r in res.items():
                rows.append({"texture": name, "scale": group, "threshold": thr, **r})
    bar.close()
    return rows


def baseline_textures(parts: tuple[str, ...] | None = ("torso", "arms", "legs"),
                      seed: int = 0) -> dict[str, TextureSpec]:
    """The paper's baselines: white, black and a seeded random 60 x 60 pattern (on the given parts)."""
    from davis_rig.attack.texture import black_texture, random_texture, white_texture

    return {"white": TextureSpec(white_texture(1), parts), "black": TextureSpec(black_texture(1), parts),
            "random 60x60": TextureSpec(random_texture(60, seed=seed), parts)}


def config_dict(config: EvalConfig) -> dict:
    """JSON-ready dict of an :class:`EvalConfig`."""
    return json.loads(json.dumps(asdict(config), default=str))
