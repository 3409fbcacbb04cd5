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
- **Tables**: :func:`table1` (white / black / random 60 x 60 baselines vs optimized textures of grid 60 ... 10) and
  :func:`table2` (the 7 body-part combinations at 10 x 10, threshold 0.25) as markdown plus plots;
  :func:`write_visualisations` draws event frames with the detector's boxes per texture and a GIF of the
  person walking in a texture.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from davis_rig.errors import ConfigError, MissingDependencyError, ShapeError
from davis_rig.events.histogram import WINDOW_US, stacked_histograms
from davis_rig.events.simulator import SimulatorConfig, simulate_events
from davis_rig.scene.camera import PinholeCamera
from davis_rig.scene.scene import MIN_RENDER_RATE_HZ, WALKS, Motion, SceneSpec
from davis_rig.scene.shading import Light
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID

try:
    import torch
except ImportError as exc:  # pragma: no cover - exercised only without torch
    raise MissingDependencyError("the attack evaluation needs torch: pip install 'davis_rig[torch]'") from exc

__all__ = [
    "PAPER_THRESHOLDS",
    "EvalConfig",
    "EvalScene",
    "TextureSpec",
    "EVENT_MODELS",
    "EVENT_MODEL_NAMES",
    "detect_histograms",
    "detect_windows",
    "evaluate_textures",
    "prepare_scenes",
    "results_markdown",
    "score_detections",
    "table1",
    "table2",
    "evaluation_scenes",
    "window_histograms",
    "write_table",
    "write_visualisations",
]

#: The paper's confidence thresholds.
PAPER_THRESHOLDS = (0.001, 0.01, 0.1, 0.25)
#: Table 2's threshold.
TABLE2_THRESHOLD = 0.25
#: Event models of the evaluation: ``"exact"`` (quantized events of the exact simulator, what a camera delivers;
#: the default) and ``"official_relaxed"`` (the official code's continuous counts scaled by 10/27, the input its
#: evaluation scored; not events, for comparison with the paper's numbers only).
EVENT_MODELS = ("exact", "official_relaxed")
#: How tables name the event models.
EVENT_MODEL_NAMES = {"exact": "exact simulator", "official_relaxed": "official code's relaxed counts, not events"}


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


def window_histograms(video, t_us, window_end_us, simulator: SimulatorConfig | None = None, events: str = "exact",
                      device=None, window_us: int = WINDOW_US) -> np.ndarray:
    """RVT's stacked histograms [W, 20, H, W] of a video under an event model (:data:`EVENT_MODELS`).

    Args:
        video: float tensor/array [T, H, W], linear intensity in [0, 1].
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs); window k is ``[window_end_us[k] - window_us, window_end_us[k]]``.
        simulator: simulator settings (default ideal sensor); ``"official_relaxed"`` uses its θ_on (= θ_off).
        events: ``"exact"``: quantized events of :func:`~davis_rig.events.simulator.simulate_events`, uint8
            counts; ``"official_relaxed"``: the official code's continuous counts
            (:func:`~davis_rig.events.v2e_torch.v2e_histograms`, mode ``"official_relaxed"``), float32.
        device: where the simulator runs.
        window_us: window duration (µs; RVT: 50 ms).

    Raises:
        ValueError: unknown ``events``, or unequal thresholds with ``"official_relaxed"``.
    """
    from davis_rig.events.v2e_torch import v2e_histograms

    simulator = simulator or SimulatorConfig()
    video = video.detach() if isinstance(video, torch.Tensor) else torch.as_tensor(np.asarray(video))
    if events == "exact":
        stream = simulate_events(video, t_us, simulator, device=device)
        h, w = video.shape[-2:]
        return stacked_histograms(stream, window_end_us, window_us=int(window_us), height=int(h), width=int(w))
    if events != "official_relaxed":
        raise ValueError(f"events must be one of {EVENT_MODELS}, got {events!r}")
    with torch.no_grad():
        hist = v2e_histograms(video.to(device=device, dtype=torch.float32), t_us, window_end_us,
                              mode="official_relaxed", window_us=int(window_us),
                              threshold_on=float(simulator.threshold_on),
                              threshold_off=float(simulator.threshold_off),
                              intensity_scale=simulator.intensity_scale,
                              lin_log_threshold=simulator.lin_log_threshold)
    return hist.cpu().numpy()


def detect_windows(detector, video, t_us, window_end_us, simulator: SimulatorConfig | None = None,
                   device=None, events: str = "exact",
                   window_us: int = WINDOW_US) -> tuple[list[np.ndarray], np.ndarray]:
    """Events of a video -> stacked histograms -> the detector over the windows with states.

    Args:
        detector: :class:`~davis_rig.models.rvt.detector.RVTDetector` (eval mode).
        video: float tensor/array [T, H, W], linear intensity.
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs).
        simulator: exact simulator settings (default ideal sensor).
        device: torch device of the detector (default: its parameters').
        events: the event model (:func:`window_histograms`; default the exact simulator).
        window_us: window duration (µs).

    Returns:
        ``(decoded, hist)``: one float32 [A, 5 + nc] array per window (the head's decoded output) and the
        histograms [W, 20, H, W] (uint8 counts; float32 with ``"official_relaxed"``).
    """
    from davis_rig.models.rvt.detector import pad_to_input

    device = next(detector.parameters()).device if device is None else torch.device(device)
    # the simulator runs where the detector is
    hist = window_histograms(video, t_us, window_end_us, simulator, events, device=device, window_us=window_us)
    decoded, states = [], None
    with torch.no_grad():
        for k in range(hist.shape[0]):
            x = pad_to_input(torch.from_numpy(hist[k : k + 1]).to(device), detector.config.in_res_hw)
            out, states = detector(x, states)
            decoded.append(out[0].float().cpu().numpy())
    return decoded, hist


def detect_histograms(detector, hists: Sequence["torch.Tensor"], device=None) -> list[list[np.ndarray]]:
    """The detector over the windows of several sequences at once, recurrent states per sequence.

    Args:
        detector: :class:`~davis_rig.models.rvt.detector.RVTDetector` (eval mode).
        hists: per sequence a tensor [W, 20, H, W] of counts (all the same shape).
        device: torch device of the detector (default: its parameters').

    Returns:
        per sequence, per window: the head's decoded float32 [A, 5 + nc] array.
    """
    from davis_rig.models.rvt.detector import pad_to_input

    device = next(detector.parameters()).device if device is None else torch.device(device)
    batch = torch.stack([torch.as_tensor(h) for h in hists], dim=1).to(device=device, dtype=torch.float32)
    decoded, states = [[] for _ in hists], None
    with torch.no_grad():
        for k in range(batch.shape[0]):
            out, states = detector(pad_to_input(batch[k], detector.config.in_res_hw), states)
            out = out.float().cpu().numpy()
            for i in range(len(hists)):
                decoded[i].append(out[i])
    return decoded


def _label_boxes(box: np.ndarray, t_us: int) -> np.ndarray:
    out = np.zeros(0 if not np.isfinite(box).all() else 1, dtype=BBOX_DTYPE)
    if out.size:
        out["t"] = t_us
        out["x"], out["y"] = box[0], box[1]
        out["w"], out["h"] = box[2] - box[0], box[3] - box[1]
        out["class_id"] = PEDESTRIAN_CLASS_ID
        out["class_confidence"] = 1.0
    return out


def score_detections(decoded: Sequence[Sequence[np.ndarray]], boxes: Sequence[np.ndarray], window_end_us,
                     thresholds: Sequence[float], *, seq_len: int, nms_threshold: float = 0.45,
                     ap_backend: str = "faster_coco_eval") -> dict[float, dict]:
    """AP and SeqASR per threshold of the scored windows of several sequences.

    Args:
        decoded: per sequence, per scored window: the detector's decoded float [A, 5 + nc].
        boxes: per sequence: float32 [W, 4] label box per scored window (NaN: no person).
        window_end_us: per sequence: int64 [W] window ends (label and detection times).
        thresholds: confidence thresholds.
        seq_len: windows per sequence.
        nms_threshold: NMS IoU threshold.
        ap_backend: COCO backend of :func:`davis_rig.metrics.ap.coco_ap`.

    Returns:
        ``{threshold: {"AP", "AP_50", "AP_75", ..., "SeqASR", "num_sequences", "num_detected", "num_windows"}}``.
    """
    from davis_rig.metrics.ap import coco_ap, detections_to_boxes, filter_boxes
    from davis_rig.metrics.seqasr import label_sequences, seq_asr, windows_detected
    from davis_rig.models.rvt.postprocess import postprocess

    if not (len(decoded) == len(boxes) == len(window_end_us)):
        raise ShapeError(f"decoded, boxes and window_end_us must have one entry per sequence, got "
                         f"{len(decoded)}, {len(boxes)}, {len(window_end_us)}")
    results = {}
    for thr in thresholds:
        gts, dts, detected_all, seqs_all = [], [], [], []
        offset = 0
        for seq_decoded, seq_boxes, ends in zip(decoded, boxes, window_end_us):
            dets = postprocess(np.stack(seq_decoded), float(thr), nms_threshold)
            labelled = np.isfinite(np.asarray(seq_boxes)).all(axis=1)
            detected_all.append(windows_detected(dets, mode="paper"))
            seqs_all.append(label_sequences(labelled, seq_len) + offset)
            offset += len(dets)
            for k, det in enumerate(dets):
                t = int(ends[k])
                gts.append(filter_boxes(_label_boxes(np.asarray(seq_boxes[k]), t)))
                dt = detections_to_boxes(det, t)
                dts.append(filter_boxes(dt[dt["class_id"] == PEDESTRIAN_CLASS_ID]))
        ap = coco_ap(gts, dts, backend=ap_backend)
        sa = seq_asr(np.concatenate(detected_all), np.concatenate(seqs_all, axis=0))
        results[float(thr)] = {**ap, "SeqASR": sa.seq_asr, "num_sequences": sa.num_sequences,
                               "num_detected": sa.num_detected, "num_windows": offset}
    return results


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


def _fmt(value: float) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{100.0 * value:.1f}"


def results_markdown(rows: Sequence[dict], thresholds: Sequence[float], *, scale: str = "all",
                     label: str = "Texture") -> str:
    """A markdown table: one row per texture, AP and SeqASR (%) per threshold, for one scale group."""
    names = list(dict.fromkeys(r["texture"] for r in rows))
    head = f"| {label} | " + " | ".join(f"AP@{t:g} | SeqASR@{t:g}" for t in thresholds) + " |"
    sep = "|---|" + "---|---|" * len(thresholds)
    lines = [head, sep]
    for name in names:
        cells = []
        for t in thresholds:
            r = next((r for r in rows if r["texture"] == name and r["scale"] == scale and
                      math.isclose(r["threshold"], t)), None)
            cells += [_fmt(r["AP"]) if r else "n/a", _fmt(r["SeqASR"]) if r else "n/a"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plot(rows: Sequence[dict], thresholds: Sequence[float], path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["texture"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name in names:
        sel = [next(r for r in rows if r["texture"] == name and r["scale"] == "all" and math.isclose(r["threshold"], t))
               for t in thresholds]
        for ax, key in zip(axes, ("AP", "SeqASR")):
            ax.plot(range(len(thresholds)), [100 * s[key] for s in sel], marker="o", label=name)
    for ax, key in zip(axes, ("AP (%)", "SeqASR (%)")):
        ax.set_xticks(range(len(thresholds)), [f"{t:g}" for t in thresholds])
        ax.set_xlabel("confidence threshold")
        ax.set_ylabel(key)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_table(rows: Sequence[dict], thresholds: Sequence[float], out_dir: str | Path, stem: str, title: str, *,
                command: str | None = None, label: str = "Texture") -> dict:
    """Write ``<stem>.md`` (all scales + per scale), ``<stem>.json`` (rows + command) and ``<stem>.png`` (plots).

    Returns:
        ``{"markdown", "json", "plot": paths, "rows": rows}``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    text = [f"# {title}\n"]
    if command:
        text.append(f"Command: `{command}`\n")
    text.append("All scales:\n")
    text.append(results_markdown(rows, thresholds, label=label))
    for scale in dict.fromkeys(r["scale"] for r in rows):
        if scale != "all":
            text.append(f"\nScale {scale}:\n")
            text.append(results_markdown(rows, thresholds, scale=scale, label=label))
    md = out_dir / f"{stem}.md"
    md.write_text("\n".join(text))
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps({"rows": rows, "command": command}, indent=1, default=float))
    png = _plot(rows, thresholds, out_dir / f"{stem}.png", title)
    return {"markdown": md, "json": js, "plot": png, "rows": rows}


def table1(optimized: Mapping[int, np.ndarray], detector, out_dir: str | Path, *, config: EvalConfig | None = None,
           model=None, parts=("torso", "arms", "legs"), command: str | None = None, motions: Sequence[Motion] = (),
           progress: bool = False) -> dict:
    """Table 1: white / black / random 60 x 60 baselines vs optimized textures (grid 60 ... 10), all thresholds.

    Args:
        optimized: grid size n -> float [n, n] optimized texture (e.g. from ``optimize`` runs' ``best_texture.npy``).
        detector: RVT detector.
        out_dir: writes ``table1.md``, ``table1.json``, ``table1.png``.
        config: evaluation settings (default :class:`EvalConfig`).
        model: :class:`~davis_rig.scene.body.BodyModel` (default: bundled asset).
        parts: painted parts of all textures (paper Table 1: the full body).
        command: the command line recorded in the markdown.
        motions: test motions (default: the test shapes' walk cycles).
        progress: progress bar.

    Returns:
        ``{"markdown", "json", "plot": paths, "rows": list}``.
    """
    from davis_rig.scene.body import BodyModel

    config = config or EvalConfig()
    model = model or BodyModel()
    textures = baseline_textures(tuple(parts) if parts else None, seed=config.seed)
    for n in sorted(optimized, reverse=True):
        grid = np.asarray(optimized[n], dtype=np.float32)
        textures[f"ours {n}x{n}"] = TextureSpec(grid, tuple(parts) if parts else None)
    scenes = prepare_scenes(evaluation_scenes(config, model.num_shapes, motions), model, config, progress=progress)
    rows = evaluate_textures(textures, detector, scenes, config, progress=progress)
    return write_table(rows, config.thresholds, out_dir, "table1",
                       f"Table 1: baselines vs optimized textures (digital, {EVENT_MODEL_NAMES[config.events]})",
                       command=command)


def table2(optimized: Mapping[str, np.ndarray], detector, out_dir: str | Path, *, config: EvalConfig | None = None,
           model=None, command: str | None = None, motions: Sequence[Motion] = (), progress: bool = False) -> dict:
    """Table 2: the 7 body-part combinations at 10 x 10 (threshold 0.25 by default).

    Args:
        optimized: combination key (``"torso"``, ``"torso+arms"``, ... as
            :func:`davis_rig.scene.masks.combination_masks`) -> float [n, n] texture optimized on those parts.
        detector, out_dir, model, command, motions, progress: see :func:`table1`.
        config: evaluation settings (default: :class:`EvalConfig` with thresholds ``(0.25,)``).

    Returns:
        ``{"markdown", "json", "plot", "rows"}`` (files ``table2.*``).
    """
    from davis_rig.scene.body import BodyModel

    config = config or EvalConfig(thresholds=(TABLE2_THRESHOLD,))
    model = model or BodyModel()
    textures = {key: TextureSpec(np.asarray(grid, dtype=np.float32), tuple(key.split("+")))
                for key, grid in optimized.items()}
    scenes = prepare_scenes(evaluation_scenes(config, model.num_shapes, motions), model, config, progress=progress)
    rows = evaluate_textures(textures, detector, scenes, config, progress=progress)
    return write_table(rows, config.thresholds, out_dir, "table2",
                       f"Table 2: body-part combinations (10x10, {EVENT_MODEL_NAMES[config.events]})",
                       command=command, label="Parts")


def _event_image(hist: np.ndarray) -> np.ndarray:
    """RGB uint8 [H, W, 3] of one window's histogram [20, H, W]: white background, ON blue, OFF red."""
    on = hist[10:].sum(0).astype(np.float32)
    off = hist[:10].sum(0).astype(np.float32)
    img = np.full(on.shape + (3,), 255, dtype=np.uint8)
    img[off > 0] = (220, 40, 40)
    img[on > 0] = (40, 60, 220)
    img[(on > 0) & (off > 0)] = (120, 0, 120)
    return img


def write_visualisations(textures: Mapping[str, TextureSpec], detector, out_dir: str | Path, *,
                         config: EvalConfig | None = None, model=None, scene_spec: SceneSpec | None = None,
                         threshold: float = TABLE2_THRESHOLD, gif_texture: str | None = None) -> dict:
    """Event frames with the detector's boxes for each texture, and a GIF of the person walking in one texture.

    Args:
        textures: name -> :class:`TextureSpec`.
        detector: RVT detector.
        out_dir: writes ``events_<name>.png`` (one row of the windows per texture) and ``walk_<name>.gif``.
        config: evaluation settings.
        model: body model (default bundled).
        scene_spec: the scene (default: the first test shape, walking right, middle scale).
        threshold: confidence threshold of the drawn boxes.
        gif_texture: texture of the GIF (default: the last one).

    Returns:
        ``{"frames": [paths], "gif": path}``.
    """
    import cv2
    from PIL import Image

    from davis_rig.models.rvt.postprocess import postprocess
    from davis_rig.scene.body import BodyModel

    config = config or EvalConfig()
    model = model or BodyModel()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if scene_spec is None:
        scene_spec = evaluation_scenes(EvalConfig(**{**_config_kwargs(config), "scales": ("middle",),
                                               "headings_rad": (math.pi / 2,), "phases": (0.0,)}),
                                 model.num_shapes)[0][1]
    scene = prepare_scenes([("middle", scene_spec)], model, config)[0]
    frames, masks = [], {}
    for name, texture in textures.items():
        video = texture_video(scene, texture, masks)
        decoded, hist = detect_windows(detector, video, scene.t_us, scene.window_end_us, config.simulator,
                                       events=config.events, window_us=config.window_us)
        dets = postprocess(np.stack(decoded), float(threshold), config.nms_threshold)
        tiles = []
        for k in range(hist.shape[0]):
            img = np.ascontiguousarray(_event_image(hist[k]))
            if np.isfinite(scene.boxes[k]).all():
                x0, y0, x1, y1 = scene.boxes[k].astype(int)
                cv2.rectangle(img, (int(x0), int(y0)), (int(x1), int(y1)), (0, 160, 0), 1)
            for det in (dets[k] if dets[k] is not None else []):
                if int(det[6]) == PEDESTRIAN_CLASS_ID:
                    cv2.rectangle(img, (int(det[0]), int(det[1])), (int(det[2]), int(det[3])), (255, 140, 0), 2)
            tiles.append(img)
        strip = np.concatenate(tiles, axis=1)
        safe = "".join(c if c.isalnum() else "_" for c in name)
        path = out / f"events_{safe}.png"
        cv2.imwrite(str(path), strip[..., ::-1])
        frames.append(path)
    gif_name = gif_texture or list(textures)[-1]
    video = texture_video(scene, textures[gif_name], masks).clamp(0, 1).cpu().numpy()
    images = [Image.fromarray((np.power(f, 1 / 2.2) * 255).astype(np.uint8)) for f in video]
    gif = out / f"walk_{''.join(c if c.isalnum() else '_' for c in gif_name)}.gif"
    images[0].save(gif, save_all=True, append_images=images[1:], duration=int(1000 / 25), loop=0)
    return {"frames": frames, "gif": gif}


def _config_kwargs(config: EvalConfig) -> dict:
    return {f: getattr(config, f) for f in config.__dataclass_fields__}


def config_dict(config: EvalConfig) -> dict:
    """JSON-ready dict of an :class:`EvalConfig`."""
    return json.loads(json.dumps(asdict(config), default=str))
