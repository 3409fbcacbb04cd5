"""The attack loop: optimise the texture generator against a frozen RVT over sequences of EoT clips.

One step (:func:`~davis_rig.attack.step.attack_loss` + Adam)::

    u = generator()                       (dropout seeded by (seed, step): identical on all ranks, exact resume)
    grid = binarize_ste(u, alpha(step))   (soft-to-hard schedule, straight-through gradient; the hard part
                                          u > 0.5, or u > t with per-cell draws t ~ U[0, 1) for binarize="sample")
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
default), each scored twice (:func:`~davis_rig.attack.validation.validate`): as trained (each clip's own sensor,
the forward of the step) and as tested (the evaluation's exact simulator events, or ``events``, from the ideal
sensor). The best texture is chosen on the first, the distribution the texture is trained on; every validation record
(and ``best.json``) carries both and their difference, the **transfer gap** (test minus training mean top score).
SeqASR at ``validation_threshold``. The refinement scores its flips as trained.

DDP: launch with ``torchrun --nproc_per_node N``; call :func:`optimize_texture` after
``torch.distributed.init_process_group`` (gloo on CPU, nccl on GPU; the CLI does it from the torchrun
environment). Each rank owns a share of the pool and draws ``clips_per_step / world_size`` clips per step; the
gradients are averaged, so the step equals a single process on the union of the clips. Rank 0 validates and
writes files.

The modules of the run: :mod:`~davis_rig.attack.config` (:class:`AttackConfig`), :mod:`~davis_rig.attack.step` (the
differentiable forward of a step), :mod:`~davis_rig.attack.validation` (validation clips, scores, the best-texture
rule), :mod:`~davis_rig.attack.checkpoint` (the run folder: checkpoint, log, outputs),
:mod:`~davis_rig.attack.detector` (the frozen detector); this module runs the loop.
Their public names are importable from here too.
"""

from __future__ import annotations

import functools
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.attack.checkpoint import (
    atomic_save,
    check_new_run,
    check_resume_config,
    clear_outputs,
    final_validation,
    read_attack_checkpoint,
    remove_unfinished,
    truncate_log,
    write_texture_png,
)
from davis_rig.attack.config import SELECTION_RULES, V2E_GRADIENTS, AttackConfig
from davis_rig.attack.detector import detector_fingerprint, load_attack_detector
from davis_rig.attack.eot import ClipPool, PoolClip
from davis_rig.attack.fixed_step import FixedShapeAttackLoss
from davis_rig.attack.lr_schedule import lr_at
from davis_rig.attack.step import attack_loss, binarization_threshold, clip_histograms, soft_grid
from davis_rig.stop import StopOnSignal, StopRequested, check_stop
from davis_rig.attack.texture import TextureGenerator, alpha_at, binarize_ste, hard_binarize
from davis_rig.attack.validation import REFINE_SEED_OFFSET, better, validate, validation_clips
from davis_rig.errors import CheckpointError

with optional_dependency("the attack"):
    import torch

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
    "validation_clips",
]


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


@dataclass
class _Run:
    """One call of :func:`optimize_texture` on one rank: what its steps share.

    Attributes:
        config, detector, out: the call's arguments (``out`` the run folder).
        generator, optimizer: the texture generator and its Adam.
        rank, world, device: this process's rank, the world size, the torch device.
        start, end: the steps of this call: ``range(start, end)`` (``start`` = completed steps of the checkpoint).
        best: the best validation record so far (``None`` before the first validation).
        generations, saved_pool: the pool state of the checkpoint (``None`` for a new run).
        pending: the validation of step ``start`` was interrupted and runs first.
        pool, val_clips: the EoT pool of this rank and the validation clips (rank 0).
        wrote_checkpoint: a checkpoint exists (the run can be resumed).
        last_checkpoint_s: ``time.monotonic()`` of the last checkpoint (the wall-time period).
        log: ``log.jsonl`` open for appending (rank 0, while the steps run).
        step_loss: ``(grid, clips) -> AdversarialLoss`` of a step: :func:`~davis_rig.attack.step.attack_loss` or,
            with ``config.detector_step`` other than ``"eager"``, a
            :class:`~davis_rig.attack.fixed_step.FixedShapeAttackLoss` built once for the run.
        steps_done: steps completed in this call.
        detector_fingerprint: :func:`~davis_rig.attack.detector.detector_fingerprint` of ``detector`` (kept in the
            checkpoint; a resume with other weights is refused).
    """

    config: AttackConfig
    detector: object
    out: Path
    generator: TextureGenerator
    optimizer: "torch.optim.Optimizer"
    rank: int
    world: int
    device: "torch.device"
    start: int = 0
    end: int = 0
    best: dict | None = None
    generations: list | None = None
    saved_pool: dict | None = None
    pending: bool = False
    pool: ClipPool | None = None
    val_clips: list = field(default_factory=list)
    wrote_checkpoint: bool = False
    last_checkpoint_s: float = 0.0
    log: object = None
    steps_done: int = 0
    detector_fingerprint: str = ""
    step_loss: object = None

    @property
    def ckpt_path(self) -> Path:
        """``out/checkpoints/last.pt``."""
        return self.out / "checkpoints" / "last.pt"

    def checkpoint(self, next_step: int, pending_validation: bool = False) -> None:
        """Write ``checkpoints/last.pt`` holding ``next_step`` completed steps."""
        # a finished run that is only refined builds no pool: its generations are the loaded ones
        pool_state = self.pool.state_dict() if self.pool is not None else self.saved_pool
        atomic_save({"generator": self.generator.state_dict(), "optimizer": self.optimizer.state_dict(),
                     "step": next_step, "pool": pool_state, "best": json.dumps(self.best) if self.best else "",
                     "config": self.config.to_dict(), "pending_validation": bool(pending_validation),
                     "detector": self.detector_fingerprint},
                    self.ckpt_path)
        self.wrote_checkpoint, self.last_checkpoint_s = True, time.monotonic()

    def checkpoint_due(self, done: int) -> bool:
        """Whether a checkpoint is due after ``done`` steps (the call's last step, the step or the time period)."""
        if done == self.end:
            return True
        if self.config.checkpoint_every is not None:
            return done % self.config.checkpoint_every == 0
        return time.monotonic() - self.last_checkpoint_s >= self.config.checkpoint_interval_s

    def hard_texture(self) -> np.ndarray:
        """The generator's hard texture without dropout: float32 [n, n] of 0/1."""
        self.generator.eval()
        with torch.no_grad():
            grid = hard_binarize(self.generator())
        self.generator.train()
        return grid

    def run_validation(self, done: int, stop: StopOnSignal) -> None:
        """Validate the hard texture after ``done`` steps, log the record, keep it when it is the best so far."""
        config = self.config
        tex = self.hard_texture()
        res = validate(tex, self.val_clips, self.detector, config.validation_threshold, config.events, stop=stop,
                       train_path=(config.v2e_mode, config.v2e_binning))
        res.update(step=done)
        self.log.write(json.dumps({"validation": res}) + "\n")
        if better(res, self.best, config.select_by):
            self.best = res
            np.save(self.out / "best_texture.npy", tex)
            write_texture_png(self.out / "best_texture.png", tex)
            torch.save(self.generator.state_dict(), self.out / "best_generator.pt")
            (self.out / "best.json").write_text(json.dumps(self.best, indent=1))


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
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    rank, world = _dist()
    if config.clips_per_step % world:
        raise ValueError(f"clips_per_step {config.clips_per_step} must be divisible by the world size {world}")
    out = Path(out_dir)
    check_new_run(out, resume)
    device = torch.device(device) if device is not None else next(detector.parameters()).device
    fingerprint = detector_fingerprint(detector)
    state = _read_state(out / "checkpoints" / "last.pt", resume, config, device, fingerprint)
    detector.eval()
    for p in detector.parameters():
        p.requires_grad_(False)
    body_model = body_model or BodyModel(device=device)
    mask = part_mask(config.parts) if config.parts is not None else None
    run = _new_run(config, detector, out, rank, world, device, state, max_steps)
    run.detector_fingerprint = fingerprint
    created = not out.exists()
    with StopOnSignal(enabled=handle_signals) as stop:
        _prepare_clips(run, body_model, mask, motions, progress, stop)
        _open_run_folder(run)
        t_start = time.perf_counter()
        run.last_checkpoint_s = time.monotonic()  # the period counts the steps' work, not the clip preparation
        _train(run, stop, progress, created)
    elapsed = time.perf_counter() - t_start
    return _finish(run, body_model, mask, motions, elapsed)


def _read_state(ckpt_path: Path, resume: bool, config: AttackConfig, device, fingerprint: str) -> dict | None:
    """The checkpoint a resume continues from (``None``: a new run), checked against ``config`` and the detector's
    ``fingerprint`` (a checkpoint written before fingerprints were kept has none to check)."""
    if not (resume and ckpt_path.is_file()):
        return None
    state = read_attack_checkpoint(ckpt_path, map_location=device)
    check_resume_config(state, config, ckpt_path)
    saved = state.get("detector")
    if saved and saved != fingerprint:
        raise CheckpointError(f"{ckpt_path} was written against another detector (weights {saved}, the given one "
                              f"{fingerprint}): resume with the run's --detector, or start the new one in another "
                              "--out folder")
    return state


def _new_run(config: AttackConfig, detector, out: Path, rank: int, world: int, device, state: dict | None,
             max_steps: int | None) -> _Run:
    """The generator (seeded by ``config.seed``) and its optimizer, restored from ``state`` when resuming."""
    torch.manual_seed(config.seed)
    generator = TextureGenerator(config.grid_n, hidden=config.hidden, dropout=config.dropout)
    generator = generator.start_from(config.start, config.start_grid).to(device)
    optimizer = torch.optim.Adam(generator.parameters(), lr=config.lr, betas=tuple(config.betas),
                                 weight_decay=config.weight_decay)
    if config.detector_step == "eager":
        step_loss = functools.partial(attack_loss, detector=detector, config=config)
    else:
        step_loss = FixedShapeAttackLoss(detector, config, mode=config.detector_step)
    run = _Run(config=config, detector=detector, out=out, generator=generator, optimizer=optimizer, rank=rank,
               world=world, device=device, wrote_checkpoint=state is not None, step_loss=step_loss)
    if state is not None:
        try:
            generator.load_state_dict(state["generator"])
            optimizer.load_state_dict(state["optimizer"])
        except (RuntimeError, ValueError, KeyError) as exc:
            raise CheckpointError(f"{run.ckpt_path}: the generator or optimizer state does not fit this run "
                                  f"({exc})") from exc
        run.start = int(state["step"])
        run.saved_pool = dict(state["pool"])
        run.generations = run.saved_pool["generations"]
        if len(run.generations) != config.pool_size:
            raise CheckpointError(f"{run.ckpt_path}: pool of {len(run.generations)} slots, the run has "
                                  f"{config.pool_size}")
        run.best = json.loads(state["best"]) if state["best"] else None
        run.pending = bool(state["pending_validation"])
    else:  # a plain start is a candidate itself: validated at step 0, the run never returns worse on validation
        run.pending = config.start != "random"
    run.end = config.iterations if max_steps is None else min(config.iterations, run.start + int(max_steps))
    return run


def _prepare_clips(run: _Run, body_model, mask, motions: Sequence, progress: bool, stop: StopOnSignal) -> None:
    """Build this rank's pool (when steps remain) and rank 0's validation clips; a finished run that is only
    re-read renders nothing. A stop request raises :class:`AttackInterrupted`."""
    from tqdm import tqdm

    config = run.config
    if not (run.end > run.start or run.pending):
        return
    owned = len(range(run.rank, config.pool_size, run.world))
    num_val = config.num_validation_clips if run.rank == 0 else 0
    prep = tqdm(total=owned + num_val, disable=not progress or run.rank != 0, desc="preparing clips", unit="clip",
                file=sys.stderr)

    def prepared() -> None:
        prep.update(1)
        check_stop(stop)

    try:
        check_stop(stop)
        if run.end > run.start:
            run.pool = ClipPool(config.eot, body_model, config.grid_n, mask, size=config.pool_size,
                                base_seed=config.seed, motions=motions, rank=run.rank, world_size=run.world,
                                generations=run.generations, on_clip=prepared)
        else:
            prep.total = num_val
        if run.rank == 0:
            run.val_clips = validation_clips(config, body_model, mask, config.num_validation_clips, motions=motions,
                                             on_clip=prepared)
    except StopRequested:
        raise AttackInterrupted(run.start, config.iterations, run.ckpt_path if run.wrote_checkpoint else None,
                                stop.signal_name) from None
    finally:
        prep.close()


def _open_run_folder(run: _Run) -> None:
    """Create the run folder (rank 0) and drop what a resume does not continue: log records after the checkpoint,
    or an earlier run's outputs when starting from step 0."""
    if run.rank == 0:
        run.out.mkdir(parents=True, exist_ok=True)
    if run.world > 1:  # every rank has read the folder before rank 0 changes it
        torch.distributed.barrier()
    if run.rank == 0 and run.start > 0:
        truncate_log(run.out / "log.jsonl", run.start)
    elif run.rank == 0:
        clear_outputs(run.out)


def _train(run: _Run, stop: StopOnSignal, progress: bool, created: bool) -> None:
    """The steps of this call (first the interrupted validation of a resumed run); a new run that fails before its
    first checkpoint leaves nothing behind. A stop request raises :class:`AttackInterrupted` after the checkpoint."""
    from tqdm import tqdm

    config = run.config
    bar = None
    try:
        run.log = open(run.out / "log.jsonl", "a") if run.rank == 0 else None
        bar = tqdm(total=config.iterations, initial=run.start, disable=not progress or run.rank != 0,
                   desc=f"attack {config.grid_n}x{config.grid_n}", unit="step", file=sys.stderr)
        run.generator.train()
        if run.pending and run.rank == 0:  # an interrupted validation of step `start`, or a plain start: first
            bar.set_postfix_str(f"validating {len(run.val_clips)} clips")
            try:
                run.run_validation(run.start, stop)
            except StopRequested:
                raise AttackInterrupted(run.start, config.iterations, run.ckpt_path if run.wrote_checkpoint else None,
                                        stop.signal_name) from None
            run.log.flush()
            run.checkpoint(run.start)
        for step in range(run.start, run.end):
            values, alpha = _optimizer_step(run, step)
            done = step + 1
            run.steps_done += 1
            stopped = _record_step(run, done, values, alpha, bar, stop) if run.rank == 0 else False
            if _any_rank(stop.requested or stopped, run.world, run.device):
                raise AttackInterrupted(done, config.iterations, run.ckpt_path, stop.signal_name)
    except BaseException:
        if run.rank == 0 and not run.wrote_checkpoint:  # stopped or failed before a checkpoint: nothing to resume
            if run.log is not None:
                run.log.close()
                run.log = None
            remove_unfinished(run.out, created)  # a new run that cannot be resumed leaves nothing behind
        raise
    finally:
        if bar is not None:
            bar.close()
        if run.log is not None:
            run.log.close()
            run.log = None


def _optimizer_step(run: _Run, step: int) -> tuple["torch.Tensor", float]:
    """One Adam step at ``step`` (0-based) on this rank's clips, gradients averaged over the ranks.

    Returns:
        ``(values, alpha)``: float tensor [3] of (loss, obj, cls) averaged over the ranks; the step's alpha.
    """
    config = run.config
    if step > 0 and step % config.refresh_every == 0:
        run.pool.refresh(step, config.refresh_fraction)
    alpha = alpha_at(config.alpha_schedule, step, config.iterations)
    for group in run.optimizer.param_groups:
        group["lr"] = lr_at(config.lr_schedule, step, config.lr, config.lr_period or config.iterations, config.lr_min)
    soft = soft_grid(run.generator, config.seed, step)
    grid = binarize_ste(soft, alpha, binarization_threshold(config.binarize, config.seed, step, soft))
    loss = run.step_loss(grid, run.pool.sample(step, config.clips_per_step // run.world))
    run.optimizer.zero_grad(set_to_none=True)
    loss.total.backward()
    _average_gradients(run.generator.parameters(), run.world)
    run.optimizer.step()
    values = torch.stack([loss.total.detach(), loss.obj.detach(), loss.cls.detach()]).float()
    if run.world > 1:
        torch.distributed.all_reduce(values)
        values /= run.world
    return values, alpha


def _record_step(run: _Run, done: int, values: "torch.Tensor", alpha: float, bar, stop: StopOnSignal) -> bool:
    """Rank 0 after a step: the log record, the snapshot, the validation and the checkpoint when due.

    Returns:
        True when a stop request abandoned the validation (the checkpoint then marks it pending).
    """
    config = run.config
    record = {"step": done, "loss": float(values[0]), "obj": float(values[1]), "cls": float(values[2]),
              "alpha": alpha, "lr": run.optimizer.param_groups[0]["lr"]}
    run.log.write(json.dumps(record) + "\n")
    bar.set_postfix(loss=f"{record['loss']:.2f}", alpha=f"{alpha:.2f}")
    bar.update(1)
    if done % config.snapshot_every == 0 or done == config.iterations:
        write_texture_png(run.out / "snapshots" / f"step_{done:06d}.png", run.hard_texture())
    stopped = False
    if done % config.validate_every == 0 or done == config.iterations:
        bar.set_postfix_str(f"validating {len(run.val_clips)} clips")
        try:
            run.run_validation(done, stop)
        except StopRequested:
            run.log.flush()
            run.checkpoint(done, pending_validation=True)
            stopped = True
    run.log.flush()
    if not stopped and (stop.requested or run.checkpoint_due(done)):
        run.checkpoint(done)
    return stopped


def _finish(run: _Run, body_model, mask, motions: Sequence, elapsed_s: float) -> AttackResult:
    """The final texture (and, once the run is complete, the refinement), then the call's result."""
    config, out = run.config, run.out
    texture = run.hard_texture()
    if run.rank == 0:
        np.save(out / "texture.npy", texture)
        write_texture_png(out / "texture.png", texture)
        if config.refine_passes > 0 and run.end == config.iterations and not (out / "refine.json").is_file():
            if not run.val_clips:
                run.val_clips = validation_clips(config, body_model, mask, config.num_validation_clips,
                                                 motions=motions)
            start_grid = np.load(out / "best_texture.npy") if (out / "best_texture.npy").is_file() else texture
            run.best = _refine_best(config, run.detector, body_model, mask, out, run.best, run.val_clips, start_grid,
                                    motions)
            run.checkpoint(run.end)  # its best now agrees with best_texture.npy / best.json
    best_tex = np.load(out / "best_texture.npy") if (out / "best_texture.npy").is_file() else texture
    best = run.best
    return AttackResult(texture=texture, best_texture=best_tex,
                        best_seq_asr=float(best["SeqASR"]) if best else math.nan,
                        best_step=int(best["step"]) if best else run.end, steps=run.end - run.start,
                        seconds_per_step=elapsed_s / run.steps_done if run.steps_done else math.nan, out_dir=out,
                        final_validation=final_validation(out / "log.jsonl", config.iterations) if run.rank == 0
                        else None)


def _refine_best(config: AttackConfig, detector, body_model, mask, out: Path, best: dict | None,
                 val_clips: Sequence[PoolClip], start_grid: np.ndarray, motions: Sequence = ()) -> dict | None:
    """Greedy cell flips after the gradient phase (:mod:`davis_rig.attack.refine`); returns the new best record.

    Writes ``refined_texture.npy/png`` and ``refine.json`` and logs a ``{"refine": ...}`` record; the refined
    texture replaces ``best_texture`` when it validates better (``config.select_by``).
    """
    from davis_rig.attack.refine import refine_texture

    clips = validation_clips(config, body_model, mask, config.refine_clips, REFINE_SEED_OFFSET, motions)

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
                   seconds=time.perf_counter() - t0, replaced_best=better(res, best, config.select_by))
    np.save(out / "refined_texture.npy", found["texture"])
    write_texture_png(out / "refined_texture.png", found["texture"])
    with open(out / "log.jsonl", "a") as log:
        log.write(json.dumps({"refine": summary}) + "\n")
    (out / "refine.json").write_text(json.dumps(summary, indent=1))
    if not summary["replaced_best"]:
        return best
    np.save(out / "best_texture.npy", found["texture"])
    write_texture_png(out / "best_texture.png", found["texture"])
    (out / "best.json").write_text(json.dumps(res, indent=1))
    return res


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


def _any_rank(flag: bool, world: int, device) -> bool:
    """Whether ``flag`` is set on any rank (all ranks agree on when to stop)."""
    if world == 1:
        return bool(flag)
    value = torch.tensor([1.0 if flag else 0.0], device=device)
    torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX)
    return bool(value.item() > 0)
