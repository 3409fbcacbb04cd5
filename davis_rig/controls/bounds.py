"""Controls run on a victim before any attack: its baseline fingerprint and the free-appearance bound.

**Fingerprint** (:func:`fingerprint_textures` scored with :func:`davis_rig.attack.evaluate.evaluate_textures`):
AP and SeqASR of white, black, the paper's random 60 x 60, a random n x n and an n x n checkerboard on the
digital evaluation protocol. The paper's victim detects white best (AP 50.5 against black 43.8 and random 45.2
at 0.25); a victim with the opposite ordering keys on something else than the paper's does.

**Free-appearance bound** (:func:`free_appearance_bound`): on each test scene the person's appearance is optimised
freely for that scene alone, in four forms, from the least constrained to a print:

- ``"per-pixel"``: a free albedo in [0, 1] for every covered sample of every frame (the rendered intensity is
  still ``albedo * shade`` composited over the background: any appearance change, frame by frame);
- ``"per-frame texture"``: a free grey n x n grid on the painted parts, a different one in every frame;
- ``"static texture"``: a free grey n x n grid on the painted parts, the same in every frame (a wearable print
  with grey levels, fitted to this one scene: at least as strong as the attack's black/white grid there);
- ``"static per-texel"``: a free grey albedo for every texel of the 1024 x 1024 texture on the painted parts,
  the same in every frame (the finest static print there is).

The two static forms separate what a wearable texture could do from what only a changing appearance can: a
victim blinded by the per-frame forms but not the static ones cannot be blinded by any print on that scene.

Each is scored like the evaluation (exact simulator, the detector over the windows with its states): the share of
scenes whose optimised appearance leaves no detection at the threshold in any window is the best SeqASR any
appearance change can reach on those scenes, the bound an optimized texture is measured against.

Optimisation: Adam on logits (albedo = sigmoid), the event counts' forward value exact (the ideal sensor's
quantized counts) and their gradient the relaxed counts' ``relu(±ΔL / θ)`` (as ``davis-attack``'s default
``--v2e-gradient relaxed``), loss :func:`hinge_loss`. With ``events="official_relaxed"`` (the official code's
event model, :class:`~davis_rig.attack.evaluate.EvalConfig` ``events``) the relaxed counts are both the value and
the gradient, and the scoring runs on them too.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ShapeError

with optional_dependency("the controls"):
    import torch

__all__ = [
    "BOUND_KINDS",
    "BoundConfig",
    "bound_rows",
    "check_event_model",
    "fingerprint_textures",
    "free_appearance_bound",
    "hinge_loss",
    "optimise_appearance",
    "optimise_shared_texture",
    "relaxed_event_histograms",
]

#: The free appearances of :func:`free_appearance_bound`, least constrained first.
BOUND_KINDS = ("per-pixel", "per-frame texture", "static texture", "static per-texel")


@dataclass(frozen=True)
class BoundConfig:
    """Settings of the free-appearance optimisation (per scene).

    Attributes:
        steps: Adam steps per scene and kind.
        lr: Adam learning rate on the logits.
        threshold: confidence threshold the hinge aims below (and that scores the result).
        grid_n: cells per side of the per-frame texture.
        parts: painted parts of the per-frame texture (``None`` = whole body); the per-pixel kind paints the
            whole visible body.
        theta: contrast threshold of the relaxed counts' gradient (log units; the evaluation's ideal sensor: 0.2).
        kinds: the free appearances to optimise (a subset of :data:`BOUND_KINDS`, in that order).
        events: the event model optimised and scored (:data:`~davis_rig.attack.scoring.EVENT_MODELS`): ``"exact"``
            (default: exact counts, relaxed gradient) or ``"official_relaxed"`` (the official code's continuous
            counts, value and gradient); it must be the evaluation config's.
    """

    steps: int = 100
    lr: float = 0.1
    threshold: float = 0.25
    grid_n: int = 10
    parts: tuple[str, ...] | None = ("torso", "arms", "legs")
    theta: float = 0.2
    kinds: tuple[str, ...] = BOUND_KINDS
    events: str = "exact"

    def __post_init__(self) -> None:
        from davis_rig.attack.scoring import EVENT_MODELS

        if int(self.steps) < 0 or not self.lr > 0 or not 0 < self.threshold < 1 or int(self.grid_n) < 1:
            raise ValueError(f"need steps >= 0, lr > 0, 0 < threshold < 1, grid_n >= 1; got {self}")
        if not self.theta > 0:
            raise ValueError(f"theta must be > 0, got {self.theta}")
        unknown = [k for k in self.kinds if k not in BOUND_KINDS]
        if unknown or len(set(self.kinds)) != len(self.kinds):
            raise ValueError(f"kinds must be distinct names from {BOUND_KINDS}, got {self.kinds}")
        if self.events not in EVENT_MODELS:
            raise ValueError(f"events must be one of {EVENT_MODELS}, got {self.events!r}")


def fingerprint_textures(grid_n: int = 10, parts: tuple[str, ...] | None = ("torso", "arms", "legs"),
                         seed: int = 0) -> dict:
    """The fingerprint's textures: the paper's baselines (white, black, random 60 x 60) plus a random and a
    checkerboard n x n grid, on ``parts``: name -> :class:`~davis_rig.attack.evaluate.TextureSpec`."""
    from davis_rig.attack.evaluate import TextureSpec, baseline_textures
    from davis_rig.attack.texture import random_texture
    from davis_rig.controls.planted import checker_grid

    out = dict(baseline_textures(parts, seed))
    out[f"random {grid_n}x{grid_n}"] = TextureSpec(random_texture(grid_n, seed=seed), parts)
    out[f"checker {grid_n}x{grid_n}"] = TextureSpec(checker_grid(grid_n), parts)
    return out


def hinge_loss(decoded: Sequence[torch.Tensor], threshold: float, class_id: int | None = None) -> torch.Tensor:
    """``sum over windows and anchors of relu(obj * p_class - threshold / 2)``: every anchor a detection could
    come from is pushed below half the threshold, and nothing else counts.

    Args:
        decoded: per window, float tensor [B, A, 5 + nc] (cx, cy, w, h, obj, class probabilities).
        threshold: confidence threshold.
        class_id: attacked class (default the pedestrian class).

    Returns:
        0-dim tensor, differentiable w.r.t. ``decoded``; 0 when no anchor scores above ``threshold / 2``.
    """
    from davis_rig.types import PEDESTRIAN_CLASS_ID

    class_id = PEDESTRIAN_CLASS_ID if class_id is None else int(class_id)
    total = None
    for out in decoded:
        if out.ndim != 3 or out.shape[-1] < 6 + class_id:
            raise ShapeError(f"decoded windows must be [B, A, >= {6 + class_id}], got {tuple(out.shape)}")
        term = torch.relu(out[..., 4] * out[..., 5 + class_id] - threshold / 2).sum()
        total = term if total is None else total + term
    if total is None:
        raise ShapeError("decoded holds no window")
    return total


def relaxed_event_histograms(video: torch.Tensor, t_us, window_end_us, theta: float = 0.2,
                             window_us: int | None = None) -> torch.Tensor:
    """RVT input of a video with the exact counts as value and the relaxed counts' gradient: float [W, 20, H, W].

    The value is the ideal sensor's quantized event counts (the exact simulator's events per window, polarity and
    pixel; binned by frame interval, so an event may sit one bin from the simulator's interpolated timestamp),
    clipped at the histogram cutoff;
    the gradient is that of ``relu(±ΔL / θ)`` through the same binning, without the cutoff (the surrogate of
    :func:`davis_rig.attack.optimize.clip_histograms`).

    Args:
        video: float tensor [T, H, W], linear intensity in [0, 1].
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs).
        theta: contrast threshold (log units).
        window_us: window duration (µs; default RVT's 50 ms).
    """
    from davis_rig.events.histogram import COUNT_CUTOFF, WINDOW_US
    from davis_rig.events.v2e_torch import OFFICIAL_RELAXED_SCALE, log_histograms, log_intensity

    window_us = WINDOW_US if window_us is None else int(window_us)
    log_video = log_intensity(video)
    with torch.no_grad():
        exact = log_histograms(log_video.double(), t_us, window_end_us, mode="dvs", window_us=window_us,
                               count_cutoff=None, threshold_on=theta, threshold_off=theta)
        exact = torch.clamp(exact, max=float(COUNT_CUTOFF)).to(video.dtype)
    surrogate = log_histograms(log_video, t_us, window_end_us, mode="official_relaxed", window_us=window_us,
                               count_cutoff=None, threshold_on=theta, threshold_off=theta) / OFFICIAL_RELAXED_SCALE
    return exact + (surrogate - surrogate.detach())


def _appearance(scene, kind: str, config: BoundConfig, mask):
    """``(logits, render)``: the free parameters and a function logits -> video [T, H, W] (differentiable)."""
    raster = scene.raster
    background = scene.background.to(raster.shade.dtype)
    if kind == "per-pixel":
        logits = torch.zeros(raster.shade.shape[0], dtype=raster.shade.dtype, requires_grad=True)
        return logits, lambda z: raster.compose(torch.sigmoid(z), background)
    if kind not in BOUND_KINDS:
        raise ValueError(f"kind must be one of {BOUND_KINDS}, got {kind!r}")
    grid_n = None if kind == "static per-texel" else int(config.grid_n)
    lookup = raster.lookup(size=1024, mode="nearest", grid_n=grid_n, mask=mask)
    rows, cols = lookup.texture_hw
    if kind != "per-frame texture":
        logits = torch.zeros(rows, cols, dtype=raster.shade.dtype, requires_grad=True)
        return logits, lambda z: raster.compose(lookup.sample(torch.sigmoid(z), fill=1.0), background)
    h, w = raster.hw
    frame = (raster.sample_pixel // (h * w)).view(1, -1)
    logits = torch.zeros(raster.num_frames, rows, cols, dtype=raster.shade.dtype, requires_grad=True)

    def render(z):
        values = lookup.sample(torch.sigmoid(z), fill=1.0).gather(0, frame).view(-1)  # each sample its frame's grid
        return raster.compose(values, background)

    return logits, render


def check_event_model(config: BoundConfig, eval_config) -> None:
    """Refuse a bound that would optimise other counts than ``eval_config`` scores.

    Raises:
        ValueError: ``config.events`` differs from ``eval_config.events``, or with ``"official_relaxed"`` the
            bound's θ differs from the simulator's thresholds.
    """
    if config.events != eval_config.events:
        raise ValueError(f"the bound optimises {config.events!r} events and the evaluation scores "
                         f"{eval_config.events!r}: give both the same event model")
    if config.events == "official_relaxed" and not (
            config.theta == eval_config.simulator.threshold_on == eval_config.simulator.threshold_off):
        raise ValueError(f"official_relaxed events need the bound's theta ({config.theta}) equal to the simulator's "
                         f"thresholds ({eval_config.simulator.threshold_on}, {eval_config.simulator.threshold_off})")


def _scene_hinge(video: torch.Tensor, scene, detector, config: BoundConfig, eval_config=None) -> torch.Tensor:
    """:func:`hinge_loss` of a scene's video [T, H, W]: its windows' counts through the detector with its recurrent
    states. ``config.events``: exact value and relaxed gradient, or the official relaxed counts exactly as the
    evaluation scores them (:func:`~davis_rig.attack.scoring.relaxed_window_histograms`). The counts follow
    ``eval_config``'s simulator and window (default: the ideal sensor at ``config.theta``, RVT's 50 ms)."""
    from davis_rig.attack.scoring import relaxed_window_histograms
    from davis_rig.events.histogram import WINDOW_US
    from davis_rig.events.simulator import SimulatorConfig
    from davis_rig.models.rvt.detector import pad_to_input

    window_us = WINDOW_US if eval_config is None else int(eval_config.window_us)
    if config.events == "official_relaxed":
        simulator = (SimulatorConfig(threshold_on=config.theta, threshold_off=config.theta) if eval_config is None
                     else eval_config.simulator)
        hist = relaxed_window_histograms(video.to(torch.float32), scene.t_us, scene.window_end_us, simulator,
                                         window_us=window_us)
    else:
        hist = relaxed_event_histograms(video, scene.t_us, scene.window_end_us, config.theta, window_us=window_us)
    decoded, states = [], None
    for k in range(hist.shape[0]):
        out, states = detector(pad_to_input(hist[k : k + 1], detector.config.in_res_hw), states)
        decoded.append(out)
    return hinge_loss(decoded, config.threshold)


def optimise_appearance(scene, detector, kind: str, config: BoundConfig, mask=None, *,
                        eval_config=None) -> torch.Tensor:
    """The free appearance of one scene after ``config.steps`` Adam steps: its video, float tensor [T, H, W].

    Args:
        scene: :class:`~davis_rig.attack.evaluate.EvalScene`.
        detector: frozen RVT detector (eval mode, no parameter gradients).
        kind: one of :data:`BOUND_KINDS`.
        config: the settings.
        mask: bool [1024, 1024] paintable texels of the textures (``None``: whole body).
        eval_config: the :class:`~davis_rig.attack.evaluate.EvalConfig` that scores the result: the counts follow
            its simulator and window (default: the ideal sensor at ``config.theta``, 50 ms windows).

    Returns:
        The video of the appearance with the lowest loss seen (no grad).
    """
    if eval_config is not None:
        check_event_model(config, eval_config)
    logits, render = _appearance(scene, kind, config, mask)
    optimizer = torch.optim.Adam([logits], lr=config.lr)
    best, best_loss = None, float("inf")
    for _ in range(int(config.steps) + 1):
        video = render(logits)
        loss = _scene_hinge(video, scene, detector, config, eval_config)
        value = float(loss.detach())
        if value < best_loss:
            best_loss, best = value, video.detach()
        if best_loss == 0.0:
            break
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return best


def optimise_shared_texture(scenes: Sequence, detector, config: BoundConfig, mask=None, *,
                            binary: bool = False, eval_config=None) -> np.ndarray:
    """One free grey ``config.grid_n`` x ``config.grid_n`` texture for all ``scenes`` at once (a print must fit
    every scene it is worn in): Adam on its logits, the sum over scenes of :func:`hinge_loss`, the bound's
    exact-value / relaxed-gradient counts.

    Between the per-scene ``"static texture"`` bound and the attack: what remains of the bound when one texture
    must serve several scenes (still fitted on the scenes it is scored on, and grey; binarize it with
    :func:`davis_rig.attack.texture.hard_binarize` to see what the black/white constraint costs).

    Args:
        scenes: :class:`~davis_rig.attack.evaluate.EvalScene` list.
        detector: frozen RVT detector (eval mode, no parameter gradients).
        config: the settings (``steps``, ``lr``, ``threshold``, ``grid_n``, ``theta``).
        mask: bool [1024, 1024] paintable texels (``None``: whole body).
        binary: optimise the black/white texture itself (``[sigmoid(z) > 0.5]`` forward, the straight-through
            gradient of :func:`~davis_rig.attack.texture.binarize_ste` backward), as the paper's texture must be.
        eval_config: the evaluation config whose simulator and window the counts follow (as
            :func:`optimise_appearance`).

    Returns:
        float32 [n, n] (1 = white): in (0, 1), or of 0/1 with ``binary``; the texture of the lowest total loss seen.
    """
    from davis_rig.attack.texture import binarize_ste

    if not scenes:
        raise ValueError("need at least one scene")
    if eval_config is not None:
        check_event_model(config, eval_config)
    lookups = [scene.raster.lookup(size=1024, mode="nearest", grid_n=int(config.grid_n), mask=mask)
               for scene in scenes]
    logits = torch.zeros(config.grid_n, config.grid_n, dtype=scenes[0].raster.shade.dtype, requires_grad=True)
    if binary:  # start from a fair coin per cell (all-zero logits would all round to black)
        with torch.no_grad():
            logits.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(0))
    texture_of = (lambda z: binarize_ste(torch.sigmoid(z), 1.0)) if binary else torch.sigmoid
    optimizer = torch.optim.Adam([logits], lr=config.lr)
    best, best_loss = None, float("inf")
    for _ in range(int(config.steps) + 1):
        optimizer.zero_grad(set_to_none=True)
        total = 0.0
        for scene, lookup in zip(scenes, lookups):  # one scene's graph at a time: memory of one scene
            background = scene.background.to(scene.raster.shade.dtype)
            video = scene.raster.compose(lookup.sample(texture_of(logits), fill=1.0), background)
            loss = _scene_hinge(video, scene, detector, config, eval_config)
            total += float(loss.detach())
            loss.backward()
        if total < best_loss:
            best_loss, best = total, texture_of(logits.detach()).clone()
        if best_loss == 0.0:
            break
        optimizer.step()
    return best.float().cpu().numpy()


def free_appearance_bound(scenes: Sequence, detector, eval_config, config: BoundConfig | None = None, *,
                          baselines: dict | None = None, progress=None) -> dict:
    """The free-appearance bound on a set of test scenes (see the module docstring).

    Args:
        scenes: :class:`~davis_rig.attack.evaluate.EvalScene` list (:func:`~davis_rig.attack.evaluate.prepare_scenes`).
        detector: frozen RVT detector.
        eval_config: the :class:`~davis_rig.attack.evaluate.EvalConfig` the scenes were made with (simulator,
            NMS, sequence length).
        config: the optimisation settings (default :class:`BoundConfig`).
        baselines: name -> :class:`~davis_rig.attack.evaluate.TextureSpec` scored on the same scenes for
            comparison (default white and black; ``{}`` for none).
        progress: optional callable ``(message: str) -> None`` called after each scene.

    Returns:
        ``{"threshold", "scenes", "rows": [{"appearance", "AP", "SeqASR", "num_sequences", "num_detected",
        "mean_top_score"}], "per_scene": [...], "decoded": {appearance: per scene, per window float32 [A, 5 + nc]},
        "seconds"}`` (AP and SeqASR at ``config.threshold``).
    """
    from davis_rig.attack.evaluate import TextureSpec, detect_windows, texture_video
    from davis_rig.attack.texture import black_texture, white_texture
    from davis_rig.scene.masks import part_mask

    config = config or BoundConfig()
    if int(eval_config.warmup_windows) != 0:
        raise ValueError("the free-appearance bound scores scenes without warm-up windows (warmup_windows = 0)")
    check_event_model(config, eval_config)
    baselines = baselines if baselines is not None else {"white": TextureSpec(white_texture(1), config.parts),
                              "black": TextureSpec(black_texture(1), config.parts)}
    detector = detector.eval()
    for p in detector.parameters():
        p.requires_grad_(False)
    mask = part_mask(config.parts) if config.parts is not None else None
    names = list(baselines) + list(config.kinds)
    decoded = {name: [] for name in names}
    per_scene = []
    t0 = time.perf_counter()
    masks: dict = {}
    for index, scene in enumerate(scenes):
        record = {"scene": index, "scale": str(scene.scale), "shape": int(scene.spec.shape_index),
                  "heading_rad": float(scene.spec.heading_rad)}
        for name in names:
            if name in baselines:
                with torch.no_grad():
                    video = texture_video(scene, baselines[name], masks)
            else:
                video = optimise_appearance(scene, detector, name, config, mask, eval_config=eval_config)
            dec, _ = detect_windows(detector, video, scene.t_us, scene.window_end_us, eval_config.simulator,
                                    events=eval_config.events, window_us=eval_config.window_us)
            decoded[name].append(dec)
            record[name] = round(float(np.mean([(d[:, 4] * d[:, 6]).max() for d in dec])), 4)
        per_scene.append(record)
        if progress is not None:
            progress(f"scene {index + 1}/{len(scenes)}: " + ", ".join(f"{n} {record[n]:.3f}" for n in names))
    rows = bound_rows(decoded, scenes, per_scene, config.threshold, eval_config)
    return {"threshold": config.threshold, "scenes": len(scenes), "rows": rows, "per_scene": per_scene,
            "decoded": decoded, "seconds": time.perf_counter() - t0}


def bound_rows(decoded: dict, scenes: Sequence, per_scene: Sequence[dict], threshold: float, eval_config) -> list[dict]:
    """AP and SeqASR at ``threshold`` per appearance of ``decoded`` (name -> per scene, per window detections),
    with the mean over ``per_scene`` of each appearance's top score: the bound's rows."""
    from davis_rig.attack.evaluate import score_detections

    rows = []
    for name, per_window in decoded.items():
        res = score_detections(per_window, [s.boxes for s in scenes], [s.window_end_us for s in scenes],
                               (threshold,), seq_len=eval_config.seq_len,
                               nms_threshold=eval_config.nms_threshold)[float(threshold)]
        rows.append({"appearance": name, "AP": res["AP"], "SeqASR": res["SeqASR"],
                     "num_sequences": res["num_sequences"], "num_detected": res["num_detected"],
                     "mean_top_score": float(np.mean([r[name] for r in per_scene]))})
    return rows
