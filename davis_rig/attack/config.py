"""The settings of one texture optimisation: :class:`AttackConfig` and its validation.

The defaults are the paper's; every field is checked when the config is built (a
:class:`~davis_rig.errors.ConfigError` names the field). :func:`~davis_rig.attack.optimize.optimize_texture` runs a
config; its checkpoints record :meth:`AttackConfig.to_dict` (:mod:`davis_rig.attack.checkpoint`).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from davis_rig.attack.eot import EoTConfig
from davis_rig.attack.loss import DEFAULT_LAMBDA, LOSS_ANCHORS, LOSS_REDUCTIONS
from davis_rig.attack.lr_schedule import LR_SCHEDULES, OFFICIAL_LR_MIN
from davis_rig.attack.scoring import EVENT_MODELS
from davis_rig.attack.texture import ALPHA_SCHEDULES, BINARIZERS, MAX_CELLS, TEXTURE_STARTS
from davis_rig.errors import ConfigError

#: How the detector part of an attack step runs (:class:`~davis_rig.attack.fixed_step.FixedShapeAttackLoss`).
DETECTOR_STEPS = ("eager", "cuda_graph", "compile")

__all__ = ["AttackConfig", "DETECTOR_STEPS", "SELECTION_RULES", "V2E_GRADIENTS"]

#: Backward rules of the differentiable event counts (:func:`~davis_rig.attack.step.clip_histograms`).
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
        binarize: the hard part of the binarization (:data:`davis_rig.attack.texture.BINARIZERS`): ``"threshold"``
            (default, the paper: white where u > 0.5) or ``"sample"`` (each cell white with probability u, drawn
            afresh every step from ``(seed, step)``; validation, export and the final texture still round u).
        hidden, dropout: generator (default ``2 n^2``, 0.5).
        start: the generator's starting texture (:data:`~davis_rig.attack.texture.TEXTURE_STARTS`): ``"random"``
            (default, the official code's initialisation) or plain ``"white"`` / ``"black"``
            (:meth:`~davis_rig.attack.texture.TextureGenerator.start_from`), or ``"grid"``: the black/white
            ``start_grid`` (e.g. a control started near a planted trigger); a start other than random is validated
            at step 0, so the chosen texture is never worse on validation than it.
        start_grid: [n][n] of 0/1 (1 = white) for ``start="grid"``, else ``None``.
        pool_size: pre-rasterized clips in the pool; refresh_every / refresh_fraction: pool refresh.
        validate_every: validation period (steps; also after the last step); num_validation_clips: clips.
        validation_threshold: confidence threshold of the validation SeqASR.
        checkpoint_every: checkpoint period (steps); ``None`` (default): by wall time, every
            ``checkpoint_interval_s`` seconds of work (and always after the last step of a call and on a stop
            request). Both may change on resume.
        snapshot_every: period of the texture snapshots (steps).
        v2e_mode, v2e_binning: see :func:`davis_rig.events.v2e_torch.v2e_histograms` (``"official_relaxed"``
            and ``"floor"`` need a uniform threshold map, i.e. ``eot.threshold_sigma == 0``; checked here).
        v2e_gradient: backward of the event counts (:data:`V2E_GRADIENTS`, see
            :func:`~davis_rig.attack.step.clip_histograms`):
            ``"relaxed"`` (default) or ``"ste"`` (the paper's straight-through floor).
        events: the event model that scores validation and refinement
            (:data:`~davis_rig.attack.scoring.EVENT_MODELS`; ``"exact"`` by default).
        box_margin_px: ``None`` = score all anchors (paper); else only anchors whose predicted centre lies within
            this margin of the person's box.
        loss_anchors: :data:`~davis_rig.attack.loss.LOSS_ANCHORS`: ``"all"`` (paper) or ``"person"``: only the
            anchors whose cell overlaps the person's box in that window (:func:`~davis_rig.attack.loss.anchors_on_boxes`).
        loss_reduction: ``"mean"`` over the scored anchors (paper) or ``"top"``: the highest-confidence scored
            anchor per window and clip (:func:`davis_rig.attack.loss.adversarial_loss`).
        precision: ``"fp32"`` or ``"bf16"`` (autocast of the detector's forward and backward; texture, V2E and
            loss stay fp32).
        detector_step: how the detector part of a step runs (:data:`DETECTOR_STEPS`, see
            :mod:`davis_rig.attack.fixed_step`): ``"eager"`` (default), ``"cuda_graph"`` (recorded once, replayed;
            CUDA only; RVT-B step 103 → 22 ms on an H200) or ``"compile"``.
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
    binarize: str = "threshold"
    hidden: int | None = None
    dropout: float = 0.5
    start: str = "random"
    start_grid: tuple[tuple[float, ...], ...] | None = None
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
    detector_step: str = "eager"
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
        for name, allowed in (("alpha_schedule", tuple(ALPHA_SCHEDULES)), ("binarize", BINARIZERS),
                              ("start", TEXTURE_STARTS),
                              ("v2e_gradient", V2E_GRADIENTS),
                              ("lr_schedule", LR_SCHEDULES),
                              ("loss_reduction", LOSS_REDUCTIONS), ("loss_anchors", LOSS_ANCHORS),
                              ("precision", ("fp32", "bf16")), ("detector_step", DETECTOR_STEPS),
                              ("select_by", SELECTION_RULES), ("events", EVENT_MODELS)):
            if getattr(self, name) not in allowed:
                refuse(name, f"expected one of {allowed}")
        if (self.start == "grid") != (self.start_grid is not None):
            refuse("start_grid", "expected an n x n grid exactly when start is 'grid'")
        if self.start_grid is not None:
            grid = np.asarray(self.start_grid, dtype=np.float64)
            if grid.shape != (self.grid_n, self.grid_n) or not np.isin(grid, (0.0, 1.0)).all():
                refuse("start_grid", f"expected a {self.grid_n} x {self.grid_n} grid of 0 and 1, got shape "
                                     f"{list(grid.shape)}")
        if self.clips_per_step > self.pool_size:
            refuse("clips_per_step", f"expected at most pool_size ({self.pool_size}) clips per step")
        if self.v2e_mode != "dvs" and self.eot.threshold_sigma > 0:
            raise ConfigError("v2e_mode", f"{self.v2e_mode!r} needs one threshold per clip: set eot.threshold_sigma "
                                          f"to 0 (got {self.eot.threshold_sigma})")

    def to_dict(self) -> dict:
        """JSON-ready dict (nested dataclasses as dicts)."""
        return json.loads(json.dumps(asdict(self), default=str))
