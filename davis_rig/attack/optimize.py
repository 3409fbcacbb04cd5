"""The attack loop: optimise the texture generator against a frozen RVT over sequences of EoT clips.

One step (:func:`attack_loss` + Adam)::

    u = generator()                       (dropout seeded by (seed, step): identical on all ranks, exact resume)
    grid = binarize_ste(u, alpha(step))   (soft-to-hard schedule, straight-through gradient)
    for each clip drawn from the pool:    (pre-rasterized, no grad; see davis_rig.attack.eot)
        video = compose(lookup(grid))     [T, H, W]   grad -> grid
        hist  = V2E(video) + noise        [W, 20, H, W] ("dvs" counts with the clip's per-pixel thresholds;
                                          backward: relaxed-count surrogate or the paper's STE, clip_histograms)
    RVT over the W windows with recurrent states, batched over the clips (frozen, eval mode)
    L = lambda_1 mean(obj) + lambda_2 mean(p_ped) over all anchors of all windows (davis_rig.attack.loss;
        loss_anchors="person": only the anchors whose cell overlaps the person's box)
    backward; (DDP: gradients all-reduced and averaged over ranks); Adam step at lr(step)
                                          (cosine annealing with warm restarts, the official default, or constant;
                                          davis_rig.attack.lr_schedule)

Run state lives in ``out_dir``: ``checkpoints/last.pt`` (generator, optimizer, completed steps, pool generations,
best so far, config; written atomically every few minutes of work or every ``checkpoint_every`` steps, after the
last step of a call, and when SIGINT / SIGTERM asks the run to stop: the step in progress finishes, the checkpoint
is written and :class:`AttackInterrupted` is raised), ``log.jsonl`` (one JSON
object per step: loss, obj, cls, alpha, lr; validation records with SeqASR), ``snapshots/step_XXXXXX.png``
(the hard n x n texture), ``best_texture.npy/png`` + ``best.json`` (best validation SeqASR, ties broken by the
lower mean top pedestrian score; ``best_generator.pt`` is the generator of the best gradient-phase texture),
``texture.npy/png`` (final). With ``refine_passes > 0`` the run ends with greedy cell flips
(:mod:`davis_rig.attack.refine`): ``refined_texture.npy/png`` + ``refine.json``, and the refined texture becomes
the best when it validates better. Resume (``resume=True``) continues bit-identically:
every random choice of a step is derived from ``(seed, step)`` and the pool from its generations (bit-identical
as far as the kernels are: on CPU at any thread count, the texture lookup's backward summing in index order; on
CUDA, whose scatter-adds are atomic, with ``torch.use_deterministic_algorithms(True)``).

Validation: ``num_validation_clips`` clips drawn from the EoT distribution with their own seeds (training shapes,
the training motions and the training sensors as in the pool, half of them the evaluation's ideal sensor by
default), each scored twice (:func:`validate`): as trained (each clip's own sensor, the forward of the step) and
as tested (the evaluation's exact simulator events, or ``events``, from the ideal sensor). The best texture is
chosen on the first, the distribution the texture is trained on; every validation record (and ``best.json``)
carries both and their difference, the **transfer gap** (test minus training mean top score). SeqASR at
``validation_threshold``. The refinement scores its flips as trained.

DDP: launch with ``torchrun --nproc_per_node N``; call :func:`optimize_texture` after
``torch.distributed.init_process_group`` (gloo on CPU, nccl on GPU; the CLI does it from the torchrun
environment). Each rank owns a share of the pool and draws ``clips_per_step / world_size`` clips per step; the
gradients are averaged, so the step equals a single process on the union of the clips. Rank 0 validates and
writes files.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from davis_rig.attack.evaluate import EVENT_MODELS, score_detections
from davis_rig.attack.eot import ClipPool, EoTConfig, PoolClip, draw_scene, prepare_clip, slot_seed
from davis_rig.attack.lr_schedule import LR_SCHEDULES, OFFICIAL_LR_MIN, lr_at
from davis_rig.attack.loss import (
    DEFAULT_LAMBDA,
    LOSS_ANCHORS,
    LOSS_REDUCTIONS,
    AdversarialLoss,
    adversarial_loss,
    anchor_cells,
    anchors_on_boxes,
)
from davis_rig.attack.stop import StopOnSignal
from davis_rig.attack.texture import (
    ALPHA_SCHEDULES,
    MAX_CELLS,
    TextureGenerator,
    alpha_at,
    binarize_ste,
    hard_binarize,
)
from davis_rig.errors import CheckpointError, ConfigError, MissingDependencyError
from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS

try:
    import torch
except ImportError as exc:  # pragma: no cover - exercised only without torch
    raise MissingDependencyError("the attack needs torch: pip install 'davis_rig[torch]'") from exc

__all__ = [
    "AttackConfig",
    "AttackInterrupted",
    "AttackResult",
    "SELECTION_RULES",
    "V2E_GRADIENTS",
    "attack_loss",
    "clip_histograms",
    "load_attack_detector",
    "optimize_texture",
    "read_attack_checkpoint",
    "validate",
]

_VAL_SEED_OFFSET = 1_000_003
_REFINE_SEED_OFFSET = 2_000_003
#: Backward rules of the differentiable event counts (:func:`clip_histograms`).
V2E_GRADIENTS = ("relaxed", "ste")
#: How validation picks the best texture: SeqASR first, mean top score breaking ties (the paper's best-on-SeqASR),
#: or the mean top score alone (finer: with few validation clips one missed sequence is a coarse step).
SELECTION_RULES = ("seqasr", "score")


@dataclass(frozen=True)
class AttackConfig:
    """Settings of one texture optimisation (defaults: the paper).

    Attributes:
        grid_n: texture cells per side (paper 10 ... 60).
        parts: painted body parts (``None`` = whole body, no mask); white elsewhere.
        lambda_obj, lambda_cls: loss weights (paper 1e4 each).
        lr, betas, weight_decay: Adam (paper 1e-4, (0.9, 0.99), 1e-5).
        lr_schedule: :data:`~davis_rig.attack.lr_schedule.LR_SCHEDULES`: ``"cosine_restarts"`` (default, the
            official code's: cosine from ``lr`` to ``lr_min`` over ``lr_period`` steps, then a warm restart) or
            ``"constant"``.
        lr_min: floor of the cosine (official 1e-7).
        lr_period: steps of one cosine; ``None`` = ``iterations`` (the official 11,500-step run: one cosine
            over the whole run). Like alpha, it follows a changed ``iterations`` on resume.
        iterations: optimisation steps (paper 11,500).
        clips_per_step: EoT clips per step over all ranks (divisible by the world size).
        alpha_schedule: soft-to-hard schedule name (:data:`davis_rig.attack.texture.ALPHA_SCHEDULES`).
        hidden, dropout: generator (default ``2 n^2``, 0.5).
        pool_size: pre-rasterized clips in the pool; refresh_every / refresh_fraction: pool refresh.
        validate_every: validation period (steps; also after the last step); num_validation_clips: clips.
        validation_threshold: confidence threshold of the validation SeqASR.
        checkpoint_every: checkpoint period (steps); ``None`` (default): by wall time, every
            ``checkpoint_interval_s`` seconds of work (and always after the last step of a call and on a stop
            request). Both may change on resume.
        snapshot_every: period of the texture snapshots (steps).
        v2e_mode, v2e_binning: see :func:`davis_rig.events.v2e_torch.v2e_histograms` (``"official_relaxed"``
            and ``"floor"`` need a uniform threshold map, i.e. ``eot.threshold_sigma == 0``; checked here).
        v2e_gradient: backward of the event counts (:data:`V2E_GRADIENTS`, see :func:`clip_histograms`):
            ``"relaxed"`` (default) or ``"ste"`` (the paper's straight-through floor).
        events: the event model that scores validation and refinement
            (:data:`~davis_rig.attack.evaluate.EVENT_MODELS`; ``"exact"`` by default).
        box_margin_px: ``None`` = score all anchors (paper); else only anchors whose predicted centre lies within
            this margin of the person's box.
        loss_anchors: :data:`~davis_rig.attack.loss.LOSS_ANCHORS`: ``"all"`` (paper) or ``"person"``: only the
            anchors whose cell overlaps the person's box in that window (:func:`~davis_rig.attack.loss.anchors_on_boxes`).
        loss_reduction: ``"mean"`` over the scored anchors (paper) or ``"top"``: the highest-confidence scored
            anchor per window and clip (:func:`davis_rig.attack.loss.adversarial_loss`).
        precision: ``"fp32"`` or ``"bf16"`` (autocast of the detector's forward and backward; texture, V2E and
            loss stay fp32).
        refine_passes: after the last step, sweeps of greedy cell flips over the best texture (0 = none, the
            paper; :mod:`davis_rig.attack.refine`); refine_clips: EoT clips (training distribution, their own
            seeds) that score the flips.
        select_by: how validation (and the refinement) ranks textures (:data:`SELECTION_RULES`): ``"seqasr"``
            (default, paper: higher SeqASR, then lower mean top score) or ``"score"`` (lower mean top score).
        seed: seeds the generator init, dropout, pool and sampling.
        eot: the EoT distributions.
    """

    grid_n: int = 10
    parts: tuple[str, ...] | None = ("torso", "arms", "legs")
    lambda_obj: float = DEFAULT_LAMBDA
    lambda_cls: float = DEFAULT_LAMBDA
    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 1e-5
    lr_schedule: str = "cosine_restarts"
    lr_min: float = OFFICIAL_LR_MIN
    lr_period: int | None = None
    iterations: int = 11_500
    clips_per_step: int = 1
    alpha_schedule: str = "linear"
    hidden: int | None = None
    dropout: float = 0.5
    pool_size: int = 32
    refresh_every: int = 50
    refresh_fraction: float = 0.25
    validate_every: int = 1000
    num_validation_clips: int = 64
    validation_threshold: float = 0.25
    checkpoint_every: int | None = None
    checkpoint_interval_s: float = 300.0
    snapshot_every: int = 500
    v2e_mode: str = "dvs"
    v2e_binning: str = "interval"
    v2e_gradient: str = "relaxed"
    events: str = "exact"
    box_margin_px: float | None = None
    loss_anchors: str = "all"
    loss_reduction: str = "mean"
    precision: str = "fp32"
    refine_passes: int = 0
    refine_clips: int = 8
    select_by: str = "seqasr"
    seed: int = 0
    eot: EoTConfig = field(default_factory=EoTConfig)

    def __post_init__(self) -> None:
        def refuse(name: str, reason: str) -> None:
            raise ConfigError(name, f"{reason}, got {getattr(self, name)!r}")

        if isinstance(self.grid_n, bool) or int(self.grid_n) != self.grid_n or not 1 <= self.grid_n <= MAX_CELLS:
            refuse("grid_n", f"expected an integer in [1, {MAX_CELLS}]")
        for name in ("iterations", "clips_per_step", "pool_size", "refresh_every", "validate_every",
                     "snapshot_every", "num_validation_clips", "refine_clips"):
            if int(getattr(self, name)) < 1:
                refuse(name, "expected an integer >= 1")
        if self.checkpoint_every is not None and int(self.checkpoint_every) < 1:
            refuse("checkpoint_every", "expected an integer >= 1 or None")
        if self.refine_passes < 0:
            refuse("refine_passes", "expected an integer >= 0")
        for name in ("lr", "checkpoint_interval_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                refuse(name, "expected a finite number > 0")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            refuse("weight_decay", "expected a finite number >= 0")
        if self.box_margin_px is not None and not (math.isfinite(self.box_margin_px) and self.box_margin_px >= 0):
            refuse("box_margin_px", "expected a finite number >= 0 or None")
        if not 0 <= self.validation_threshold <= 1:
            refuse("validation_threshold", "expected a number in [0, 1]")
        if not (math.isfinite(self.lr_min) and 0 <= self.lr_min <= self.lr):
            refuse("lr_min", f"expected a number in [0, lr = {self.lr:g}]")
        if self.lr_period is not None and int(self.lr_period) < 1:
            refuse("lr_period", "expected an integer >= 1 or None")
        for name, allowed in (("alpha_schedule", tuple(ALPHA_SCHEDULES)), ("v2e_gradient", V2E_GRADIENTS),
                              ("lr_schedule", LR_SCHEDULES),
                              ("loss_reduction", LOSS_REDUCTIONS), ("loss_anchors", LOSS_ANCHORS),
                              ("precision", ("fp32", "bf16")),
                              ("select_by", SELECTION_RULES), ("events", EVENT_MODELS)):
            if getattr(self, name) not in allowed:
                refuse(name, f"expected one of {allowed}")
        if self.clips_per_step > self.pool_size:
            refuse("clips_per_step", f"expected at most pool_size ({self.pool_size}) clips per step")
        if self.v2e_mode != "dvs" and self.eot.threshold_sigma > 0:
            raise ConfigError("v2e_mode", f"{self.v2e_mode!r} needs one threshold per clip: set eot.threshold_sigma "
                                          f"to 0 (got {self.eot.threshold_sigma})")

    def to_dict(self) -> dict:
        """JSON-ready dict (nested dataclasses as dicts)."""
        return json.loads(json.dumps(asdict(self), default=str))


@dataclass
class AttackResult:
    """What :func:`optimize_texture` returns.

    Attributes:
        texture: float32 [n, n] final hard texture (1 = white).
        best_texture: float32 [n, n] best-on-validation texture (or the final one without validation).
        best_seq_asr: its validation SeqASR; best_step: its step (1-based count of completed steps).
        steps: completed steps; seconds_per_step: mean wall time of the steps of this call.
        out_dir: the run folder.
        final_validation: the validation record of the final texture (step ``iterations``: SeqASR and mean top
            score as tested and as trained, ``transfer_gap``); ``None`` before the run reaches its last step.
    """

    texture: np.ndarray
    best_texture: np.ndarray
    best_seq_asr: float
    best_step: int
    steps: int
    seconds_per_step: float
    out_dir: Path
    final_validation: dict | None = None


def load_attack_detector(path=None, device=None):
    """The frozen detector of the attack: a torch checkpoint, eval mode, no parameter gradients.

    Args:
        path: ``.ckpt``/``.pt``/``.pth``/``.safetensors`` (official RVT checkpoints included); ``None`` = the
            bundled default detector's weights (:func:`davis_rig.models.default_detector_weights_path`). An
            ``.onnx`` path is resolved to the ``.safetensors`` beside it
            (same stem, or ``model_fp16.safetensors`` of a training export).
        device: torch device.

    Returns:
        :class:`~davis_rig.models.rvt.detector.RVTDetector`.

    Raises:
        MissingDependencyError: no path and the bundled weights are not installed (the message names the file).
        CheckpointError: unreadable checkpoint, or an ONNX file without torch weights beside it.
    """
    from davis_rig.models.rvt.checkpoint import load_detector

    if path is None:
        from davis_rig.models import default_detector_weights_path

        path = default_detector_weights_path()
    path = Path(path)
    if path.suffix.lower() == ".onnx":
        candidates = [path.with_suffix(".safetensors"), path.parent / "model_fp16.safetensors"]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise CheckpointError(f"{path} is an ONNX graph; the attack needs torch weights (expected one of "
                                  f"{[str(c) for c in candidates]}); pass --detector CHECKPOINT")
        path = found
    detector = load_detector(path).float()
    if device is not None:
        detector = detector.to(device)
    detector.eval()
    for p in detector.parameters():
        p.requires_grad_(False)
    return detector


def clip_histograms(grid: "torch.Tensor", clip: PoolClip, mode: str = "dvs", binning: str = "interval",
                    gradient: str = "relaxed") -> "torch.Tensor":
    """Differentiable RVT input of one pool clip: float tensor [W, 20, H, W] (V2E counts + noise, clipped at 10).

    The forward value is always the event counts of ``mode`` plus the clip's noise events, clipped at
    ``COUNT_CUTOFF``. Counts (``"dvs"``, ``"floor"``) are taken in float64, the exact simulator's precision: with a
    uniform threshold map they are the simulator's events per pixel and window (float32 lin-log values move
    ~1 % of the events across a threshold; the bins still differ where events fall near a bin edge, see
    :func:`validate`). ``"official_relaxed"`` counts are the value itself (float32, their own gradient). The
    backward pass depends on ``gradient``:

    - ``"ste"`` (paper): the V2E's own gradient, straight through the floor of the counts; the clamp at 10 has
      zero gradient. Measured on the interim RVT-mini (2 clips, ``docs/attack.md``): a step along its negative
      gradient does not reliably lower the loss (the floor's surrogate ignores whether a threshold is crossed).
    - ``"relaxed"``: the gradient of the continuous counts ``relu(±(L_{k+1} - L_k) / theta)`` per frame pair
      (the official code's relaxed simulator in count units, clip-mean threshold theta) through the same binning,
      used as a straight-through surrogate of the exact counts (value: the exact counts; gradient: the
      surrogate's), no clamp. Along its negative gradient the exact-count loss falls monotonically for steps up to
      0.3 grid units.

    Args:
        grid: float tensor [n, n] texture grid (1 = white), gradients flow to it.
        clip: a :class:`~davis_rig.attack.eot.PoolClip`.
        mode, binning: V2E settings (:func:`davis_rig.events.v2e_torch.v2e_histograms`).
        gradient: ``"relaxed"`` or ``"ste"`` (:data:`V2E_GRADIENTS`).

    Raises:
        ValueError: unknown ``gradient``; a grid mode (``"floor"``, ``"official_relaxed"``) with a non-uniform
            threshold map.
    """
    from davis_rig.events.v2e_torch import OFFICIAL_RELAXED_SCALE, log_histograms, log_intensity

    if gradient not in V2E_GRADIENTS:
        raise ValueError(f"gradient must be one of {V2E_GRADIENTS}, got {gradient!r}")
    # events can only fire where the person is: the V2E runs on clip.active_box; the full-frame tensor is built
    # once (zeros, the crop's counts, the noise events, the clip at COUNT_CUTOFF), in place
    y0, y1, x0, x1 = clip.active_box
    video = clip.active_video(grid)
    log_video = log_intensity(video)
    uniform = clip.base_threshold is not None or bool((clip.threshold == clip.threshold.flatten()[0]).all())
    if mode != "dvs" and not uniform:  # the grid modes take one θ
        raise ValueError(f"v2e mode {mode!r} needs one threshold θ for all pixels; turn off the EoT's "
                         f"threshold mismatch")
    if uniform:  # one θ, as drawn (float64) when the clip knows it
        threshold = clip.base_threshold if clip.base_threshold is not None else float(clip.threshold.flatten()[0])
    else:
        threshold = clip.threshold[y0:y1, x0:x1]
    shape = (len(clip.window_end_us), 2 * NUM_BINS, *clip.threshold.shape)

    def full_frame(crop: "torch.Tensor") -> "torch.Tensor":
        hist = torch.zeros(shape, dtype=crop.dtype, device=crop.device)
        hist[..., y0:y1, x0:x1] = crop
        if clip.noise_cell.numel():
            hist.view(-1).index_add_(0, clip.noise_cell, clip.noise_count.to(hist.dtype))
        return torch.clamp(hist, max=float(COUNT_CUTOFF))

    def counts(log: "torch.Tensor", theta) -> "torch.Tensor":
        return log_histograms(log, clip.t_us, clip.window_end_us, mode=mode, binning=binning,
                              window_us=clip.window_us, count_cutoff=None, threshold_on=theta, threshold_off=theta)

    if mode == "official_relaxed":  # not counts: the relaxed value carries its own gradient
        return full_frame(counts(log_video, threshold))
    with torch.no_grad():  # the exact simulator's precision
        theta64 = threshold if uniform else threshold.double()
        exact = counts(log_intensity(video.detach().double()), theta64).to(log_video.dtype)
    if gradient == "ste":
        ste = counts(log_video, threshold)
        return full_frame(exact + (ste - ste.detach()))  # the value of the float64 counts, the floor's gradient
    theta = float(clip.threshold.mean())
    surrogate = log_histograms(log_video, clip.t_us, clip.window_end_us, mode="official_relaxed", binning=binning,
                               window_us=clip.window_us, count_cutoff=None, threshold_on=theta,
                               threshold_off=theta) / OFFICIAL_RELAXED_SCALE
    with torch.no_grad():
        hist = full_frame(exact)
    # the value stays the exact counts bit for bit (surrogate - surrogate == 0); the gradient is the surrogate's
    hist[..., y0:y1, x0:x1] += surrogate - surrogate.detach()
    return hist


def attack_loss(grid: "torch.Tensor", clips: Sequence[PoolClip], detector, config: AttackConfig) -> AdversarialLoss:
    """``L_adv`` of a texture grid over a batch of clips (over all windows and clips; ``config.loss_reduction``).

    Args:
        grid: float tensor [n, n] (after :func:`binarize_ste`).
        clips: pool clips of this rank (same number of windows).
        detector: frozen RVT detector in eval mode.
        config: the attack settings.

    Returns:
        :class:`~davis_rig.attack.loss.AdversarialLoss` (``total`` differentiable w.r.t. ``grid``).
    """
    from davis_rig.models.rvt.detector import pad_to_input

    device = next(detector.parameters()).device
    x = torch.stack([clip_histograms(grid, c, config.v2e_mode, config.v2e_binning, config.v2e_gradient)
                     for c in clips], dim=1)
    x = x.to(device)
    decoded, states = [], None
    amp = config.precision == "bf16"
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp):
        for w in range(x.shape[0]):
            out, states = detector(pad_to_input(x[w], detector.config.in_res_hw), states)
            decoded.append(out.float())
    boxes = torch.as_tensor(np.stack([c.boxes for c in clips], axis=1), device=device)  # [W, B, 4]
    on_person = None
    if config.loss_anchors == "person":
        cells = anchor_cells(detector.config.in_res_hw, detector.config.head_strides, device=device)
        on_person = anchors_on_boxes(cells, boxes)  # [W, B, A]
    return adversarial_loss(decoded, config.lambda_obj, config.lambda_cls,
                            boxes=boxes if config.box_margin_px is not None else None,
                            box_margin_px=config.box_margin_px or 0.0, reduction=config.loss_reduction,
                            anchor_mask=on_person)


def _step_seed(seed: int, step: int) -> int:
    state = np.random.SeedSequence([0xA77AC, int(seed), int(step)]).generate_state(1, dtype=np.uint64)
    return int(state[0] >> np.uint64(1))


def _soft_grid(generator: TextureGenerator, seed: int, step: int) -> "torch.Tensor":
    """The generator's output with dropout seeded by (seed, step) (global RNG state left untouched)."""
    device = next(generator.parameters()).device
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(_step_seed(seed, step))
        return generator()


def _dist():
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def _average_gradients(parameters, world_size: int) -> None:
    if world_size == 1:
        return
    for p in parameters:
        if p.grad is not None:
            torch.distributed.all_reduce(p.grad, op=torch.distributed.ReduceOp.SUM)
            p.grad /= world_size


def _write_png(path: Path, grid: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), (np.asarray(grid) > 0.5).astype(np.uint8) * 255)


def _validation_clips(config: AttackConfig, model, mask, num: int, seed_offset: int = _VAL_SEED_OFFSET,
                      motions: Sequence = (), on_clip: Callable[[], None] | None = None) -> list[PoolClip]:
    """``num`` clips of the training distribution (``motions`` included) with their own seeds (validation or
    refinement, by ``seed_offset``); ``on_clip`` is called after each prepared clip."""
    clips = []
    for i in range(num):
        seed = slot_seed(config.seed + seed_offset, i, 0)
        spec, sensor = draw_scene(config.eot, seed, model.num_shapes, motions)
        clips.append(prepare_clip(spec, sensor, model, config.grid_n, mask, config=config.eot, seed=seed))
        if on_clip is not None:
            on_clip()
    return clips


#: Clips per detector batch in :func:`validate`.
VALIDATION_BATCH = 8


def validate(grid: np.ndarray, clips: Sequence[PoolClip], detector, threshold: float,
             events: str = "exact", *, train_path: tuple[str, str] | None = None, test_path: bool = True,
             stop=None, batch: int = VALIDATION_BATCH) -> dict:
    """Validation SeqASR and top scores of a hard texture on pre-rasterized clips, as tested and as trained.

    The **test path** is the evaluation's: events of the exact simulator (or ``events``) from the ideal sensor
    (:class:`~davis_rig.events.simulator.SimulatorConfig`), simulated on the clip's active box only (the ideal
    sensor is per pixel and nothing changes outside the box: the same histograms as the whole frame). The **training path** (with ``train_path``) is what
    the optimisation sees: the forward of :func:`clip_histograms`, i.e. each clip's own sensor (its threshold,
    per-pixel mismatch and noise events). On a clip drawn with the test sensor both give the same counts. The
    detector runs on ``batch`` clips at once.

    Args:
        grid: float32 [n, n] hard texture.
        clips: validation clips (their lookups carry the part mask).
        detector: RVT detector.
        threshold: confidence threshold.
        events: the event model of the test path (:data:`davis_rig.attack.evaluate.EVENT_MODELS`).
        train_path: ``(v2e_mode, v2e_binning)`` of the training (``AttackConfig.v2e_mode``, ``v2e_binning``):
            also score the training path; ``None``: the test path only.
        test_path: score the test path (False needs ``train_path``: the training path alone, half the cost).
        stop: a :class:`~davis_rig.attack.stop.StopOnSignal` polled between clips (internal: a requested stop
            abandons the validation).
        batch: clips per detector call (>= 1).

    Returns:
        ``{"SeqASR", "num_sequences", "num_detected", "mean_top_score"}`` of the test path (top score: mean over
        windows of the highest obj * p_ped); with ``train_path`` also ``"train_SeqASR"``, ``"train_top_score"``
        and, with both paths, ``"transfer_gap"`` = ``mean_top_score - train_top_score`` (> 0: the test detects the
        texture more than training saw).

    Raises:
        ValueError: neither path requested.
    """
    if not test_path and train_path is None:
        raise ValueError("validate needs the test path, the training path or both")
    from davis_rig.attack.evaluate import detect_histograms, window_histograms

    g = torch.as_tensor(np.asarray(grid, dtype=np.float32), device=clips[0].threshold.device)
    paths = {name: ([], []) for name, wanted in (("test", test_path), ("train", train_path is not None)) if wanted}
    for first in range(0, len(clips), int(batch)):
        chunk = clips[first : first + int(batch)]
        hists = {name: [] for name in paths}
        for clip in chunk:
            _check_stop(stop)
            with torch.no_grad():
                if test_path:  # the ideal sensor is per pixel and the video is constant outside the active box
                    y0, y1, x0, x1 = clip.active_box
                    video = clip.active_video(g)
                    crop = torch.as_tensor(window_histograms(video, clip.t_us, clip.window_end_us, events=events,
                                                             device=video.device, window_us=clip.window_us))
                    hist = torch.zeros((*crop.shape[:2], *clip.threshold.shape), dtype=crop.dtype)
                    hist[..., y0:y1, x0:x1] = crop
                    hists["test"].append(hist)
                if train_path is not None:
                    hists["train"].append(clip_histograms(g, clip, train_path[0], train_path[1], gradient="ste"))
        for name, (decoded, tops) in paths.items():
            for dec in detect_histograms(detector, hists[name]):
                decoded.append(dec)
                tops += [float((d[:, 4] * d[:, 6]).max()) for d in dec]
    boxes = [clip.boxes for clip in clips]
    ends = [clip.window_end_us for clip in clips]
    scores = {name: score_detections(decoded, boxes, ends, (threshold,), seq_len=len(clips[0].window_end_us))
              [float(threshold)] for name, (decoded, _) in paths.items()}
    out = {}
    if test_path:
        test = scores["test"]
        out.update(SeqASR=test["SeqASR"], num_sequences=test["num_sequences"], num_detected=test["num_detected"],
                   mean_top_score=float(np.mean(paths["test"][1])))
    if train_path is not None:
        out.update(train_SeqASR=scores["train"]["SeqASR"], train_top_score=float(np.mean(paths["train"][1])))
    if test_path and train_path is not None:
        out["transfer_gap"] = out["mean_top_score"] - out["train_top_score"]
    return out


class AttackInterrupted(KeyboardInterrupt):
    """A stop request (SIGINT / SIGTERM) ended :func:`optimize_texture` after saving its state.

    A :class:`KeyboardInterrupt`, so callers that handle Ctrl-C handle it too.

    Attributes:
        step: completed steps saved in ``checkpoint`` (the number a resume continues from).
        iterations: the run's total steps.
        checkpoint: ``checkpoints/last.pt``, or ``None`` when the stop came before the run's first step (nothing
            was written).
        signal_name: ``"SIGINT"`` or ``"SIGTERM"``.
    """

    def __init__(self, step: int, iterations: int, checkpoint: Path | None, signal_name: str | None):
        self.step = int(step)
        self.iterations = int(iterations)
        self.checkpoint = checkpoint
        self.signal_name = signal_name
        where = (f"checkpoint {checkpoint} holds step {step} of {iterations}; continue with --resume"
                 if checkpoint is not None else "stopped while preparing clips, before the first step; nothing written")
        super().__init__(f"{signal_name or 'stop'}: {where}")


class _StopRequested(Exception):
    """Raised between clips of a preparation or validation when a stop was requested."""


def _check_stop(stop) -> None:
    if stop is not None and stop.requested:
        raise _StopRequested


def _atomic_save(obj, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


#: Keys of ``checkpoints/last.pt`` and their types (``pending_validation``, added later, is optional).
_CHECKPOINT_KEYS = {"generator": dict, "optimizer": dict, "step": int, "pool": dict, "best": str, "config": dict}


def read_attack_checkpoint(path: str | Path, map_location=None) -> dict:
    """Read an attack run's ``checkpoints/last.pt`` and check its layout.

    Args:
        path: the checkpoint.
        map_location: torch ``map_location`` of its tensors.

    Returns:
        The state dict: ``generator``, ``optimizer`` (state dicts), ``step`` (completed steps), ``pool``
        (``{"base_seed", "size", "generations"}``), ``best`` (JSON of the best validation record or ``""``),
        ``config`` (:meth:`AttackConfig.to_dict`), ``pending_validation`` (bool: the validation of ``step`` was
        interrupted and runs first on resume).

    Raises:
        CheckpointError: unreadable (truncated, corrupt) or not an attack checkpoint; the message names ``path``.
    """
    path = Path(path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... depending on the damage
        first = (str(exc).strip().splitlines() or [""])[0]  # torch's messages run over several lines
        raise CheckpointError(f"{path}: unreadable attack checkpoint ({type(exc).__name__}: {first})") from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: not an attack checkpoint (a {type(state).__name__}, not a dict)")
    wrong = sorted(k for k, kind in _CHECKPOINT_KEYS.items() if not isinstance(state.get(k), kind))
    if wrong:
        raise CheckpointError(f"{path}: not an attack checkpoint (missing or malformed: {', '.join(wrong)})")
    pool = state["pool"]
    if not isinstance(pool.get("generations"), list) or not isinstance(state["config"].get("eot"), dict):
        raise CheckpointError(f"{path}: not an attack checkpoint (malformed pool or config)")
    if state["step"] < 0:
        raise CheckpointError(f"{path}: negative step {state['step']}")
    try:
        json.loads(state["best"]) if state["best"] else None
    except ValueError as exc:
        raise CheckpointError(f"{path}: malformed best record ({exc})") from exc
    state.setdefault("pending_validation", False)
    return state


#: Settings that may change when a run is resumed (the others must match the checkpoint's).
_FREE_ON_RESUME = ("iterations", "refine_passes", "refine_clips", "checkpoint_every", "checkpoint_interval_s")
#: Fields whose default changed after runs were written without them: the value such a run used. A checkpoint
#: that lacks another field counts it as its (unchanged) default.
_LEGACY_VALUES = {"lr_schedule": "constant"}
#: The same for the fields of ``eot``.
_LEGACY_EOT_VALUES = {"test_sensor_probability": 0.0, "walk": "bundled"}


def _check_resume_config(state: dict, config: AttackConfig, path: Path) -> None:
    """Refuse a checkpoint written with other settings (naming the fields that differ).

    A field added after the checkpoint was written (top level or in ``eot``) counts as its default value, or as
    the value runs used before it existed (:data:`_LEGACY_VALUES`).
    """
    current = config.to_dict()
    defaults = json.loads(json.dumps({f.name: f.default for f in fields(AttackConfig) if f.default is not MISSING},
                                     default=str))
    saved = {**defaults, **_LEGACY_VALUES, **dict(state["config"])}
    saved["eot"] = {**json.loads(json.dumps(asdict(EoTConfig()), default=str)), **_LEGACY_EOT_VALUES,
                    **dict(saved["eot"])}
    for name in _FREE_ON_RESUME:
        saved.pop(name, None)
        current.pop(name, None)
    if saved != current:
        diff = sorted(k for k in current if saved.get(k) != current.get(k))
        raise CheckpointError(f"{path} was written with a different configuration (fields {diff})")


def _logged_steps(path: Path) -> int:
    """The last step recorded in a run's ``log.jsonl`` (0 when there is none)."""
    last = 0
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict) and isinstance(rec.get("step"), int):
                last = max(last, rec["step"])
    return last


def _truncate_log(path: Path, last_step: int) -> None:
    """Drop log records after ``last_step`` (written after the checkpoint a resume starts from)."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if int(rec.get("validation", rec).get("step", 0)) <= last_step:
            kept.append(line)
    path.write_text("".join(k + "\n" for k in kept))


#: Outputs of a run (besides ``checkpoints/``): removed when a run starts from step 0 (:func:`_clear_outputs`).
_RUN_OUTPUTS = ("log.jsonl", "best_texture.npy", "best_texture.png", "best.json", "best_generator.pt", "refine.json",
                "refined_texture.npy", "refined_texture.png", "texture.npy", "texture.png")


def _check_new_run(out: Path, resume: bool) -> None:
    """Refuse a new run (``resume=False``) in a folder that holds one (``checkpoints/last.pt`` or ``log.jsonl``),
    and a resume of a run that logged steps but left no checkpoint (it would silently restart at step 1).

    Raises:
        CheckpointError: the message names the folder and what to do.
    """
    ckpt = out / "checkpoints" / "last.pt"
    held = [p for p in (ckpt, out / "log.jsonl") if p.is_file()]
    if held and not resume:
        raise CheckpointError(f"{out} already holds a run ({held[0]}); continue it with --resume (resume=True) or "
                              f"write the new run to another --out folder")
    logged = _logged_steps(out / "log.jsonl")
    if resume and not ckpt.is_file() and logged:
        raise CheckpointError(f"{out}/log.jsonl records {logged} steps but there is no {ckpt} to continue from (the "
                              f"run ended before its first checkpoint); remove {out} or start again in another --out "
                              f"folder")


def _clear_outputs(out: Path) -> None:
    """Remove the outputs of an earlier run that left no checkpoint (:data:`_RUN_OUTPUTS`, ``snapshots/step_*.png``),
    so a run starting from step 0 neither appends to its log nor finds its best, refined or final texture."""
    for name in _RUN_OUTPUTS:
        (out / name).unlink(missing_ok=True)
    for snapshot in (out / "snapshots").glob("step_*.png"):
        snapshot.unlink()


def _remove_unfinished(out: Path, created: bool) -> None:
    """Undo a new run that failed before its first checkpoint: its outputs, and the folders it created."""
    _clear_outputs(out)
    for folder in (out / "snapshots", out / "checkpoints"):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    if created and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def _selection_scores(record: dict) -> tuple[float, float]:
    """``(SeqASR, mean top score)`` a validation record is ranked by: the training path's when it has one (the
    validation clips' own sensors, the distribution the texture is trained on), else the test path's."""
    if "train_top_score" in record:
        return record["train_SeqASR"], record["train_top_score"]
    return record["SeqASR"], record["mean_top_score"]


def _better(candidate: dict, best: dict | None, select_by: str = "seqasr") -> bool:
    """Whether a validation record beats the best so far under ``select_by`` (:data:`SELECTION_RULES`), on
    :func:`_selection_scores`."""
    if best is None:
        return True
    (a, a_top), (b, b_top) = _selection_scores(candidate), _selection_scores(best)
    if select_by == "score":
        return a_top < b_top
    a = -1.0 if not np.isfinite(a) else a
    b = -1.0 if not np.isfinite(b) else b
    return a > b or (a == b and a_top < b_top)


def _refine_best(config: AttackConfig, detector, body_model, mask, out: Path, best: dict | None,
                 val_clips: Sequence[PoolClip], start_grid: np.ndarray, motions: Sequence = ()) -> dict | None:
    """Greedy cell flips after the gradient phase (:mod:`davis_rig.attack.refine`); returns the new best record.

    Writes ``refined_texture.npy/png`` and ``refine.json`` and logs a ``{"refine": ...}`` record; the refined
    texture replaces ``best_texture`` when it validates better (``config.select_by``).
    """
    from davis_rig.attack.refine import refine_texture

    clips = _validation_clips(config, body_model, mask, config.refine_clips, _REFINE_SEED_OFFSET, motions)

    def score(grid: np.ndarray) -> float:
        return validate(grid, clips, detector, config.validation_threshold, config.events, test_path=False,
                        train_path=(config.v2e_mode, config.v2e_binning))["train_top_score"]

    t0 = time.perf_counter()
    found = refine_texture(start_grid, clips, score, config.refine_passes, config.seed)
    res = validate(found["texture"], val_clips, detector, config.validation_threshold, config.events,
                   train_path=(config.v2e_mode, config.v2e_binning))
    res.update(step=config.iterations, refined=True)
    summary = {key: value for key, value in found.items() if key != "texture"}
    summary.update(passes=config.refine_passes, clips=config.refine_clips, validation=res,
                   seconds=time.perf_counter() - t0, replaced_best=_better(res, best, config.select_by))
    np.save(out / "refined_texture.npy", found["texture"])
    _write_png(out / "refined_texture.png", found["texture"])
    with open(out / "log.jsonl", "a") as log:
        log.write(json.dumps({"refine": summary}) + "\n")
    (out / "refine.json").write_text(json.dumps(summary, indent=1))
    if not summary["replaced_best"]:
        return best
    np.save(out / "best_texture.npy", found["texture"])
    _write_png(out / "best_texture.png", found["texture"])
    (out / "best.json").write_text(json.dumps(res, indent=1))
    return res


def optimize_texture(
    config: AttackConfig,
    detector,
    out_dir: str | Path,
    *,
    resume: bool = False,
    body_model=None,
    motions: Sequence = (),
    device=None,
    progress: bool = True,
    max_steps: int | None = None,
    handle_signals: bool = True,
) -> AttackResult:
    """Optimise an adversarial texture (see the module docstring).

    Args:
        config: the attack settings.
        detector: frozen RVT detector (:func:`load_attack_detector`); put in eval mode, parameters frozen here.
        out_dir: run folder (created once the clips are prepared).
        resume: continue from ``out_dir/checkpoints/last.pt`` exactly where it stopped; without a checkpoint (and
            without logged steps) a new run. With ``resume=False`` ``out_dir`` must not hold a run.
            ``iterations`` may change on resume (as may ``refine_passes``, ``refine_clips`` and the checkpoint
            period); the alpha schedule then runs over the new total, so extending a finished run lowers alpha
            again (e.g. 300 -> 11,500 steps: from 1 back to about 0.03 at step 300).
        body_model: :class:`~davis_rig.scene.body.BodyModel` (default: bundled asset on ``device``).
        motions: training motions for the EoT, validation and refinement clips (default: the shapes' walk cycles).
        device: torch device of the generator and clips (default: the detector's).
        progress: tqdm bars on rank 0 (stderr): clip preparation, then the steps.
        max_steps: stop after this many steps in this call (the run can be resumed); ``None`` = to the end.
        handle_signals: from the main thread, SIGINT / SIGTERM finish the current step, write the checkpoint and
            raise :class:`AttackInterrupted` (a second signal interrupts at once); False: they act as usual.

    Returns:
        :class:`AttackResult`.

    Raises:
        CheckpointError: the checkpoint belongs to a different configuration or is unreadable; ``resume=False``
            and ``out_dir`` already holds a run; ``resume=True`` and the run logged steps but has no checkpoint.
        AttackInterrupted: a stop was requested (the checkpoint holds the completed steps).
    """
    from tqdm import tqdm

    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    rank, world = _dist()
    if config.clips_per_step % world:
        raise ValueError(f"clips_per_step {config.clips_per_step} must be divisible by the world size {world}")
    out = Path(out_dir)
    _check_new_run(out, resume)
    ckpt_path = out / "checkpoints" / "last.pt"
    device = torch.device(device) if device is not None else next(detector.parameters()).device
    state = None
    if resume and ckpt_path.is_file():
        state = read_attack_checkpoint(ckpt_path, map_location=device)
        _check_resume_config(state, config, ckpt_path)
    detector.eval()
    for p in detector.parameters():
        p.requires_grad_(False)
    body_model = body_model or BodyModel(device=device)
    mask = part_mask(config.parts) if config.parts is not None else None

    torch.manual_seed(config.seed)
    generator = TextureGenerator(config.grid_n, hidden=config.hidden, dropout=config.dropout).to(device)
    optimizer = torch.optim.Adam(generator.parameters(), lr=config.lr, betas=tuple(config.betas),
                                 weight_decay=config.weight_decay)
    start, best, generations, saved_pool, pending = 0, None, None, None, False
    if state is not None:
        try:
            generator.load_state_dict(state["generator"])
            optimizer.load_state_dict(state["optimizer"])
        except (RuntimeError, ValueError, KeyError) as exc:
            raise CheckpointError(f"{ckpt_path}: the generator or optimizer state does not fit this run ({exc})") \
                from exc
        start = int(state["step"])
        saved_pool = dict(state["pool"])
        generations = saved_pool["generations"]
        if len(generations) != config.pool_size:
            raise CheckpointError(f"{ckpt_path}: pool of {len(generations)} slots, the run has {config.pool_size}")
        best = json.loads(state["best"]) if state["best"] else None
        pending = bool(state["pending_validation"])

    per_rank = config.clips_per_step // world
    end = config.iterations if max_steps is None else min(config.iterations, start + int(max_steps))
    created = not out.exists()
    pool, val_clips = None, []
    wrote_checkpoint = state is not None

    def checkpoint(next_step: int, pending_validation: bool = False) -> None:
        nonlocal wrote_checkpoint, last_checkpoint_s
        # a finished run that is only refined builds no pool: its generations are the loaded ones
        pool_state = pool.state_dict() if pool is not None else saved_pool
        _atomic_save({"generator": generator.state_dict(), "optimizer": optimizer.state_dict(), "step": next_step,
                      "pool": pool_state, "best": json.dumps(best) if best else "", "config": config.to_dict(),
                      "pending_validation": bool(pending_validation)}, ckpt_path)
        wrote_checkpoint, last_checkpoint_s = True, time.monotonic()

    def checkpoint_due(done: int) -> bool:
        if done == end:
            return True
        if config.checkpoint_every is not None:
            return done % config.checkpoint_every == 0
        return time.monotonic() - last_checkpoint_s >= config.checkpoint_interval_s

    def hard_texture() -> np.ndarray:
        generator.eval()
        with torch.no_grad():
            grid = hard_binarize(generator())
        generator.train()
        return grid

    def run_validation(done: int, stop) -> None:
        nonlocal best
        tex = hard_texture()
        res = validate(tex, val_clips, detector, config.validation_threshold, config.events, stop=stop,
                       train_path=(config.v2e_mode, config.v2e_binning))
        res.update(step=done)
        log.write(json.dumps({"validation": res}) + "\n")
        if _better(res, best, config.select_by):
            best = res
            np.save(out / "best_texture.npy", tex)
            _write_png(out / "best_texture.png", tex)
            torch.save(generator.state_dict(), out / "best_generator.pt")
            (out / "best.json").write_text(json.dumps(best, indent=1))

    log, bar = None, None
    steps_done = 0
    with StopOnSignal(enabled=handle_signals) as stop:
        try:
            if end > start or pending:  # a finished run is only re-read: no clip is rendered
                owned = len(range(rank, config.pool_size, world))
                num_val = config.num_validation_clips if rank == 0 else 0
                prep = tqdm(total=owned + num_val, disable=not progress or rank != 0, desc="preparing clips",
                            unit="clip", file=sys.stderr)

                def prepared() -> None:
                    prep.update(1)
                    _check_stop(stop)

                try:
                    _check_stop(stop)
                    if end > start:
                        pool = ClipPool(config.eot, body_model, config.grid_n, mask, size=config.pool_size,
                                        base_seed=config.seed, motions=motions, rank=rank, world_size=world,
                                        generations=generations, on_clip=prepared)
                    else:
                        prep.total = num_val
                    if rank == 0:
                        val_clips = _validation_clips(config, body_model, mask, config.num_validation_clips,
                                                      motions=motions, on_clip=prepared)
                finally:
                    prep.close()
        except _StopRequested:
            raise AttackInterrupted(start, config.iterations, ckpt_path if state is not None else None,
                                    stop.signal_name) from None
        if rank == 0:
            out.mkdir(parents=True, exist_ok=True)
        if world > 1:  # every rank has read the folder before rank 0 changes it
            torch.distributed.barrier()
        if rank == 0 and start > 0:
            _truncate_log(out / "log.jsonl", start)
        elif rank == 0:
            _clear_outputs(out)
        t_start = time.perf_counter()
        last_checkpoint_s = time.monotonic()  # the period counts the steps' work, not the clip preparation
        try:
            log = open(out / "log.jsonl", "a") if rank == 0 else None
            bar = tqdm(total=config.iterations, initial=start, disable=not progress or rank != 0,
                       desc=f"attack {config.grid_n}x{config.grid_n}", unit="step", file=sys.stderr)
            generator.train()
            if pending and rank == 0:  # the validation of step `start` was interrupted: it runs first
                bar.set_postfix_str(f"validating {len(val_clips)} clips")
                try:
                    run_validation(start, stop)
                except _StopRequested:
                    raise AttackInterrupted(start, config.iterations, ckpt_path, stop.signal_name) from None
                log.flush()
                checkpoint(start)
            for step in range(start, end):
                if step > 0 and step % config.refresh_every == 0:
                    pool.refresh(step, config.refresh_fraction)
                alpha = alpha_at(config.alpha_schedule, step, config.iterations)
                for group in optimizer.param_groups:
                    group["lr"] = lr_at(config.lr_schedule, step, config.lr, config.lr_period or config.iterations,
                                        config.lr_min)
                grid = binarize_ste(_soft_grid(generator, config.seed, step), alpha)
                loss = attack_loss(grid, pool.sample(step, per_rank), detector, config)
                optimizer.zero_grad(set_to_none=True)
                loss.total.backward()
                _average_gradients(generator.parameters(), world)
                optimizer.step()
                values = torch.stack([loss.total.detach(), loss.obj.detach(), loss.cls.detach()]).float()
                if world > 1:
                    torch.distributed.all_reduce(values)
                    values /= world
                done = step + 1
                steps_done += 1
                stopped = False
                if rank == 0:
                    record = {"step": done, "loss": float(values[0]), "obj": float(values[1]),
                              "cls": float(values[2]), "alpha": alpha, "lr": optimizer.param_groups[0]["lr"]}
                    log.write(json.dumps(record) + "\n")
                    bar.set_postfix(loss=f"{record['loss']:.2f}", alpha=f"{alpha:.2f}")
                    bar.update(1)
                    if done % config.snapshot_every == 0 or done == config.iterations:
                        _write_png(out / "snapshots" / f"step_{done:06d}.png", hard_texture())
                    if done % config.validate_every == 0 or done == config.iterations:
                        bar.set_postfix_str(f"validating {len(val_clips)} clips")
                        try:
                            run_validation(done, stop)
                        except _StopRequested:
                            log.flush()
                            checkpoint(done, pending_validation=True)
                            stopped = True
                    log.flush()
                    if not stopped and (stop.requested or checkpoint_due(done)):
                        checkpoint(done)
                if _any_rank(stop.requested or stopped, world, device):
                    raise AttackInterrupted(done, config.iterations, ckpt_path, stop.signal_name)
        except BaseException as exc:
            if rank == 0 and not wrote_checkpoint and not isinstance(exc, AttackInterrupted):
                if log is not None:
                    log.close()
                    log = None
                _remove_unfinished(out, created)  # a new run that cannot be resumed leaves nothing behind
            raise
        finally:
            if bar is not None:
                bar.close()
            if log is not None:
                log.close()
    elapsed = time.perf_counter() - t_start
    texture = hard_texture()
    if rank == 0:
        np.save(out / "texture.npy", texture)
        _write_png(out / "texture.png", texture)
        if config.refine_passes > 0 and end == config.iterations and not (out / "refine.json").is_file():
            if not val_clips:
                val_clips = _validation_clips(config, body_model, mask, config.num_validation_clips,
                                              motions=motions)
            start_grid = np.load(out / "best_texture.npy") if (out / "best_texture.npy").is_file() else texture
            best = _refine_best(config, detector, body_model, mask, out, best, val_clips, start_grid, motions)
            checkpoint(end)  # its best now agrees with best_texture.npy / best.json
    best_tex = np.load(out / "best_texture.npy") if (out / "best_texture.npy").is_file() else texture
    return AttackResult(texture=texture, best_texture=best_tex,
                        best_seq_asr=float(best["SeqASR"]) if best else math.nan,
                        best_step=int(best["step"]) if best else end, steps=end - start,
                        seconds_per_step=elapsed / steps_done if steps_done else math.nan, out_dir=out,
                        final_validation=_final_validation(out / "log.jsonl", config.iterations) if rank == 0 else None)


def _final_validation(log_path: Path, iterations: int) -> dict | None:
    """The last gradient-phase validation record of step ``iterations`` in a run's log (``None`` if none)."""
    found = None
    if log_path.is_file():
        for line in log_path.read_text().splitlines():
            rec = json.loads(line).get("validation")
            if rec is not None and rec.get("step") == iterations and not rec.get("refined"):
                found = rec
    return found


def _any_rank(flag: bool, world: int, device) -> bool:
    """Whether ``flag`` is set on any rank (all ranks agree on when to stop)."""
    if world == 1:
        return bool(flag)
    value = torch.tensor([1.0 if flag else 0.0], device=device)
    torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX)
    return bool(value.item() > 0)
