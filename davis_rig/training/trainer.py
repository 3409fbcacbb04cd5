"""Train an RVT detector from scratch with truncated BPTT, the YOLOX losses and RVT's Gen1 recipe.

Recipe (RVT ``config/general.yaml`` + ``config/experiment/gen1/default.yaml``, ``modules/detection.py``):
AdamW (lr 2e-4, weight decay 0), OneCycleLR (pct_start 0.005, div_factor 20, final lr = max lr / 10000,
linear annealing, no momentum cycling, stepped every batch), gradient-norm clipping 1.0, batch 8 of chunks of
L = 21 windows with ``mixed`` sampling (half the batch: streaming lanes whose states are carried from batch to
batch and reset at sequence starts, augmented with one flip/zoom-out draw per sequence; half: random-access
chunks ending at a labelled window, states reset per chunk), loss on every labelled window of the chunk
(backbone features of all labelled windows go through the FPN + head in one batch), mixed precision on GPU
(RVT: fp16 AMP; here bf16 where supported, else fp16 with a gradient scaler), YOLOX head biases initialised to
the 0.01 prior. Differences to RVT: optional EMA of the weights; validation AP computed with
:mod:`davis_rig.metrics.ap` on the streamed validation split.

Everything a run needs to continue bit-identically on CPU is in its checkpoint: model, optimizer, scheduler,
gradient scaler, EMA, the data position (epoch, batch), the augmentation generator and the torch RNG.
"""

from __future__ import annotations

import copy
import json
import math
import sys
import time
import warnings
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import CheckpointError, ConfigError, FormatError
from davis_rig.models.rvt.checkpoint import TRAIN_CHECKPOINT_FORMAT
from davis_rig.models.rvt.config import RVTConfig
from davis_rig.models.rvt.detector import RVTDetector, pad_to_input
from davis_rig.training.augment import AugmentParams, apply_augment, sample_params
from davis_rig.training.batches import (
    ChunkBatch,
    RandomChunkDataset,
    ResumableBatchSampler,
    StreamingTrainLanes,
    collate_chunks,
)
from davis_rig.training.losses import AnchorGrid, init_head_biases, yolox_loss, yolox_targets
from davis_rig.training.train_config import TrainConfig
from davis_rig.training.validation import reset_states, validate_detector
from davis_rig.types import RVT_HW

with optional_dependency("training"):
    import torch
    from torch import nn

__all__ = ["TrainConfig", "Trainer", "CHECKPOINT_FORMAT", "read_train_checkpoint"]

#: ``format`` of ``checkpoints/last.pt`` (one string with the weights reader: ``models.rvt.checkpoint``).
CHECKPOINT_FORMAT = TRAIN_CHECKPOINT_FORMAT


class ModelEMA:
    """Exponential moving average of a model's parameters and buffers (YOLOX ramp: d · (1 − exp(−n / 2000)))."""

    def __init__(self, model: nn.Module, decay: float):
        self.decay = float(decay)
        self.updates = 0
        self.model = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / 2000))
        source = model.state_dict()
        for key, value in self.model.state_dict().items():
            if value.dtype.is_floating_point:
                value.mul_(d).add_(source[key].detach(), alpha=1 - d)
            else:
                value.copy_(source[key])

    def state_dict(self) -> dict[str, Any]:
        return {"decay": self.decay, "updates": self.updates, "model": self.model.state_dict()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.decay, self.updates = float(state["decay"]), int(state["updates"])
        self.model.load_state_dict(state["model"])


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise FormatError(f"device {name!r}: CUDA is not available")
    return device


def _amp_dtype(precision: str, device: torch.device):
    if device.type != "cuda" or precision == "fp32":
        return None
    if precision == "fp16":
        return torch.float16
    if precision == "bf16" or torch.cuda.is_bf16_supported():
        return torch.bfloat16
    return torch.float16


def _restore_scaler(scaler, state: Mapping[str, Any] | None) -> bool:
    """Load a saved gradient-scaler state only where it applies; return whether it was loaded.

    A CPU or bf16 run saves ``{}`` (disabled scaler); resuming it with fp16 on a GPU starts a fresh scaler, and an
    fp16 state resumed without fp16 is dropped (``--device`` may change on resume).
    """
    if not scaler.is_enabled() or not state:
        return False
    scaler.load_state_dict(state)
    return True


def read_train_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a :data:`CHECKPOINT_FORMAT` file (``checkpoints/last.pt``).

    Raises:
        CheckpointError: unreadable (truncated, corrupt) or not a training checkpoint; the message names ``path``.
    """
    path = Path(path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt files
        raise CheckpointError(f"{path}: unreadable training checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} file")
    return state


def _finite_mean(values) -> float:
    """Mean of the finite values; NaN when there are none (a log window whose steps all had no labelled lane)."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


class Trainer:
    """Train, validate, checkpoint and export an RVT detector.

    Args:
        data_dir: dataset folder in RVT's layout (``train/`` required, ``val/`` for validation AP).
        run_dir: output folder: ``log.jsonl``, ``checkpoints/last.pt``, ``checkpoints/best.safetensors``,
            ``export/`` (created).
        config: the hyper-parameters.
        model_config: override the architecture (default: the ``config.model`` preset).

    Raises:
        FormatError: no training data, or a bad configuration.
    """

    def __init__(self, data_dir: str | Path, run_dir: str | Path, config: TrainConfig,
                 model_config: RVTConfig | None = None):
        self.data_dir = Path(data_dir)
        self.run_dir = Path(run_dir)
        self.config = config
        self.device = _resolve_device(config.device)
        self.amp_dtype = _amp_dtype(config.precision, self.device)
        self.model_config = model_config or RVTConfig.presets()[config.model]
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "checkpoints").mkdir(exist_ok=True)

        torch.manual_seed(config.seed)
        self.model = RVTDetector(self.model_config).to(self.device)
        init_head_biases(self.model)
        self.model.train()
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.OneCycleLR(
            self.optimizer, max_lr=config.lr, total_steps=config.steps, pct_start=config.pct_start,
            div_factor=config.div_factor, final_div_factor=config.final_div_factor / config.div_factor,
            cycle_momentum=False, anneal_strategy="linear")
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp_dtype == torch.float16)
        self.ema = ModelEMA(self.model, config.ema_decay) if config.ema_decay else None
        self.anchors = AnchorGrid.build(self.model_config.in_res_hw, self.model_config.head_strides, self.device)
        self.init_source: str | None = None  # the weights the run started from (init_from), None = random

        self.train_set = RandomChunkDataset(self.data_dir, "train", config.seq_len, min_side_px=config.min_box_side_px)
        num_stream = config.batch_size // 2 if config.sampling == "mixed" else 0
        self.sampler = ResumableBatchSampler(len(self.train_set), config.batch_size - num_stream, seed=config.seed)
        self.stream = (StreamingTrainLanes(self.train_set.sequences, config.seq_len, num_stream, seed=config.seed,
                                           min_side_px=config.min_box_side_px) if num_stream else None)
        self.stream_params: list[AugmentParams | None] = [None] * num_stream
        self.aug_generator = torch.Generator().manual_seed(config.seed + 1)
        self.step = 0
        self.batches_done = 0
        self.best: dict[str, Any] = {"AP": None, "step": None}
        self.history_s = 0.0
        self._states = None

    # ------------------------------------------------------------------ data
    def _random_items(self) -> Iterator[list[dict[str, Any]]]:
        bpe = self.sampler.batches_per_epoch
        self.sampler.epoch, self.sampler.position = divmod(self.batches_done, bpe)
        if self.config.num_workers > 0:
            loader = torch.utils.data.DataLoader(
                self.train_set, batch_sampler=self.sampler, collate_fn=list,
                num_workers=self.config.num_workers, persistent_workers=False)
            yield from loader
        else:
            for indices in self.sampler:
                yield [self.train_set[i] for i in indices]

    def _batches(self) -> Iterator[ChunkBatch]:
        """Training batches: streaming lanes first (``mixed``), then the random-access chunks."""
        for items in self._random_items():
            stream_items = self.stream.next_items() if self.stream is not None else []
            yield collate_chunks(stream_items + items)

    def augment_batch(self, batch: ChunkBatch) -> tuple[torch.Tensor, list[list[torch.Tensor | None]]]:
        """Move a batch to the device as float and augment each chunk: the inputs :meth:`train_step` learns from.

        Random-access chunks get a fresh draw each; streaming lanes keep the draw of their current sequence (the
        draws advance the trainer's augmentation generator).

        Returns:
            ``(hist, labels)``: float tensor [L, B, 20, H, W] on the device, and ``labels[t][b]`` (the chunk's
            boxes at window ``t`` after the augmentation, or ``None`` for an unlabelled window).
        """
        hist = batch.histograms.to(self.device, non_blocking=True).float()
        labels = [[b for b in row] for row in batch.labels]
        length, size = hist.shape[0], hist.shape[1]
        out = torch.empty_like(hist)
        num_stream = len(self.stream_params)
        for b in range(size):
            chunk_labels = [labels[t][b] for t in range(length)]
            if b < num_stream:
                aug = self.config.stream_augment
                if bool(batch.is_first[b]) or self.stream_params[b] is None:
                    self.stream_params[b] = sample_params(aug, self.aug_generator, RVT_HW, None)
                params = self.stream_params[b]
            else:
                aug = self.config.augment
                latest = next((lab for lab in reversed(chunk_labels) if lab is not None and lab.shape[0]), None)
                params = sample_params(aug, self.aug_generator, RVT_HW, latest)
            chunk, chunk_labels = apply_augment(hist[:, b], chunk_labels, params, aug.min_side_px)
            out[:, b] = chunk
            for t in range(length):
                labels[t][b] = chunk_labels[t]
        return out, labels

    # ------------------------------------------------------------------ one step
    def train_step(self, batch: ChunkBatch) -> dict[str, float]:
        """One optimizer step of truncated BPTT over a batch of chunks.

        Args:
            batch: a :class:`ChunkBatch` (time-major, L windows × B chunks).

        Returns:
            Scalar floats: loss, iou_loss, conf_loss, cls_loss, l1_loss, num_fg, lr, grad_norm, labelled.
        """
        self.model.train()
        hist, labels = self.augment_batch(batch)
        states = reset_states(self._states, batch.is_first)
        autocast = torch.autocast(self.device.type, dtype=self.amp_dtype, enabled=self.amp_dtype is not None)
        lr = self.optimizer.param_groups[0]["lr"]
        selected: dict[int, list[torch.Tensor]] = {2: [], 3: [], 4: []}
        targets: list[torch.Tensor] = []
        with autocast:
            for t in range(hist.shape[0]):
                features, states = self.model.forward_backbone(pad_to_input(hist[t], self.model_config.in_res_hw),
                                                               states)
                lanes = [b for b, lab in enumerate(labels[t]) if lab is not None and bool(batch.valid[t, b])]
                if not lanes:
                    continue
                index = torch.tensor(lanes, device=self.device)
                for level in selected:
                    selected[level].append(features[level].index_select(0, index))
                targets.extend(yolox_targets(labels[t][b]).to(self.device) for b in lanes)
            if targets:
                raw = self.model.forward_raw_head({k: torch.cat(v) for k, v in selected.items()})
        self._states = [(h.detach(), c.detach()) for h, c in states]
        if not targets:
            self.step += 1
            self.batches_done += 1
            self.scheduler.step()
            return {"loss": float("nan"), "lr": lr, "labelled": 0}
        losses = yolox_loss(raw, targets, self.anchors, use_l1=self.config.use_l1)
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(losses["loss"]).backward()
        grad_norm = float("nan")
        if self.config.grad_clip > 0:
            self.scaler.unscale_(self.optimizer)
            grad_norm = float(nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip))
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        if self.ema is not None:
            self.ema.update(self.model)
        self.step += 1
        self.batches_done += 1
        out = {key: float(value.detach()) for key, value in losses.items()}
        out.update(lr=lr, grad_norm=grad_norm, labelled=len(targets))
        return out

    # ------------------------------------------------------------------ validation
    @property
    def eval_model(self) -> RVTDetector:
        """The weights used for validation and export (EMA if enabled)."""
        return self.ema.model if self.ema is not None else self.model

    def validate(self, split: str = "val") -> dict[str, Any]:
        """Stream the split through the eval model and compute COCO AP with the RVT protocol
        (:func:`~davis_rig.training.validation.validate_detector` with this run's settings).

        Returns:
            ``{"AP", "AP_50", "AP_75", "AP_S", "AP_M", "AP_L", "num_images", "num_labels", "num_detections",
            "sequences", "time_s"}``; an empty dict when the split does not exist.
        """
        cfg = self.config
        return validate_detector(self.eval_model, self.data_dir, split, seq_len=cfg.val_seq_len,
                                 batch_size=cfg.val_batch_size, conf_threshold=cfg.val_conf_threshold,
                                 skip_first_us=cfg.val_skip_first_us, max_sequences=cfg.val_max_sequences,
                                 amp_dtype=self.amp_dtype)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the run (tensors and plain Python values only)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "batches_done": self.batches_done,
            "train_config": self.config.to_dict(),
            "model_config": self.model_config.to_json(),
            "init_source": self.init_source,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict(),
            "ema": self.ema.state_dict() if self.ema is not None else None,
            "aug_generator": self.aug_generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            "states": self._states,
            "stream": self.stream.state_dict() if self.stream is not None else None,
            "stream_params": [asdict(p) if p is not None else None for p in self.stream_params],
            "best": dict(self.best),
            "history_s": self.history_s,
        }

    def init_from(self, detector: nn.Module, source: str) -> None:
        """Start from a trained detector's weights (fine-tuning): the model and its EMA take them; the optimizer and
        the schedule stay fresh. ``source`` (the file) goes into the checkpoints and the export metadata.

        Raises:
            CheckpointError: the detector's architecture is not this run's.
        """
        if getattr(detector, "config", None) != self.model_config:
            raise CheckpointError(f"{source}: the weights are {getattr(detector, 'config', None)}, this run is "
                                  f"{self.model_config.name}")
        self.model.load_state_dict(detector.state_dict())
        if self.ema is not None:
            self.ema = ModelEMA(self.model, self.config.ema_decay)
        self.init_source = str(source)

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        """Write the full training state (atomically: temp file + rename); default ``checkpoints/last.pt``."""
        path = Path(path) if path is not None else self.run_dir / "checkpoints" / "last.pt"
        tmp = path.with_suffix(path.suffix + ".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)
        return path

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore a state written by :meth:`save_checkpoint`.

        Raises:
            CheckpointError: unreadable, another format, or another architecture.
        """
        path = Path(path)
        state = read_train_checkpoint(path, map_location=self.device)
        saved_model = RVTConfig.from_dict(state["model_config"])
        if saved_model != self.model_config:
            raise CheckpointError(f"{path}: checkpoint is {saved_model.name} ({saved_model.to_json()}), this run "
                                  f"is {self.model_config.name}")
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        _restore_scaler(self.scaler, state.get("scaler"))
        if self.ema is not None and state.get("ema") is not None:
            self.ema.load_state_dict(state["ema"])
        self.aug_generator.set_state(state["aug_generator"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        if state.get("cuda_rng") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda_rng"]])
        self._states = state.get("states")
        self.init_source = state.get("init_source")
        if self.stream is not None and state.get("stream") is not None:
            self.stream.load_state_dict(state["stream"])
            self.stream_params = [AugmentParams(**p) if p is not None else None for p in state["stream_params"]]
        self.step = int(state["step"])
        self.batches_done = int(state["batches_done"])
        self.best = dict(state.get("best") or {"AP": None, "step": None})
        self.history_s = float(state.get("history_s", 0.0))

    # ------------------------------------------------------------------ loop
    def _log(self, record: Mapping[str, Any]) -> None:
        """Append one record to ``log.jsonl`` (strict JSON: NaN/inf become null)."""
        clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()}
        with open(self.run_dir / "log.jsonl", "a", encoding="utf-8") as handle:
            handle.write(json.dumps(clean, default=float, allow_nan=False) + "\n")

    def _validate_and_select(self) -> dict[str, Any]:
        from davis_rig.models.rvt.checkpoint import save_safetensors

        result = self.validate()
        if not result:
            return result
        self._log({"kind": "val", "step": self.step, **result})
        ap = result.get("AP")
        if ap is not None and not math.isnan(ap) and (self.best["AP"] is None or ap > self.best["AP"]):
            self.best = {"AP": ap, "AP_50": result.get("AP_50"), "step": self.step}
            save_safetensors(self.eval_model, self.run_dir / "checkpoints" / "best.safetensors",
                             metadata={"step": str(self.step), "val_AP": f"{ap:.6f}",
                                       "val_AP_50": f"{result.get('AP_50', float('nan')):.6f}"})
        return result

    def fit(self, max_steps: int | None = None, time_budget_s: float | None = None, stop=None) -> dict[str, Any]:
        """Train until ``config.steps`` (or for at most ``max_steps`` more steps / ``time_budget_s`` seconds).

        A checkpoint is written every ``ckpt_every`` steps and when the call returns, so a run can proceed in
        resumable chunks (``Trainer(...).load_checkpoint(last.pt)`` then ``fit`` again).

        Args:
            max_steps, time_budget_s: stop this call early.
            stop: a :class:`~davis_rig.stop.StopOnSignal` polled between steps: a requested stop (Ctrl-C) ends the
                call after the step in progress, with its checkpoint written (``None``: never).

        Returns:
            Summary: step, finished, last train losses, last validation result, best, seconds of this call, and
            ``stopped_by``: the signal that stopped it (``"SIGINT"``) or ``None``.
        """
        cfg = self.config
        start = time.perf_counter()
        target = cfg.steps if max_steps is None else min(cfg.steps, self.step + int(max_steps))
        bar = None
        if cfg.progress:
            from tqdm import tqdm

            bar = tqdm(total=cfg.steps, initial=self.step, desc="train", unit="step", file=sys.stderr)
        last_losses: dict[str, float] = {}
        last_val: dict[str, Any] = {}
        batches = self._batches()
        window: list[dict[str, float]] = []
        try:
            while self.step < target:
                if time_budget_s is not None and time.perf_counter() - start > time_budget_s:
                    break
                if stop is not None and stop.requested:
                    break
                batch = next(batches)
                last_losses = self.train_step(batch)
                window.append(last_losses)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{last_losses.get('loss', float('nan')):.3f}")
                if cfg.log_every and (self.step % cfg.log_every == 0 or self.step == target):
                    keys = [k for k in window[-1] if k not in ("lr",)]
                    mean = {k: _finite_mean([w.get(k, np.nan) for w in window]) for k in keys}
                    self._log({"kind": "train", "step": self.step, "lr": last_losses.get("lr"),
                               "elapsed_s": round(self.history_s + time.perf_counter() - start, 3), **mean})
                    window = []
                if cfg.val_every and self.step % cfg.val_every == 0:
                    last_val = self._validate_and_select()
                if cfg.ckpt_every and self.step % cfg.ckpt_every == 0:
                    self.save_checkpoint()
        finally:
            if bar is not None:
                bar.close()
            batches.close()
        finished = self.step >= cfg.steps
        stopped_by = stop.signal_name if stop is not None else None
        if finished and stopped_by is None and (not cfg.val_every or self.step % cfg.val_every != 0):  # val_every 0: only at the end
            last_val = self._validate_and_select()
        self.history_s += time.perf_counter() - start
        self.save_checkpoint()
        return {"step": self.step, "finished": finished, "train": last_losses, "val": last_val,
                "best": dict(self.best), "seconds": round(time.perf_counter() - start, 3),
                "total_seconds": round(self.history_s, 3), "stopped_by": stopped_by}

    # ------------------------------------------------------------------ export
    def export(self, out_dir: str | Path | None = None, *, use_best: bool = True, onnx: bool = True) -> dict[str, Path]:
        """Export the detector: fp16 safetensors (+ fp32 ONNX step graph).

        Args:
            out_dir: default ``run_dir/export``.
            use_best: export ``checkpoints/best.safetensors`` if this run recorded a best validation (``best["step"]``
                set), else the current eval weights (a stale file of an earlier run is never exported).
            onnx: also write ``model.onnx`` (one recurrent step, ``export_step_onnx``).

        Returns:
            ``{"safetensors": path, "onnx": path, "model_card": path}`` (ONNX only if written); the model card
            (``MODEL_CARD.md``) is filled from the run and the dataset card.
        """
        from davis_rig.models.rvt.checkpoint import load_detector, save_safetensors
        from davis_rig.models.rvt.onnx_export import export_step_onnx

        out_dir = Path(out_dir) if out_dir is not None else self.run_dir / "export"
        out_dir.mkdir(parents=True, exist_ok=True)
        best_path = self.run_dir / "checkpoints" / "best.safetensors"
        if use_best and self.best.get("step") is not None and best_path.is_file():
            model = load_detector(best_path)
            source = f"best (step {self.best.get('step')})"
        else:
            model = copy.deepcopy(self.eval_model).to("cpu").float().eval()
            source = f"step {self.step}"
        meta = {"trained_steps": str(self.step), "source": source, "init": str(self.init_source),
                "train_config": json.dumps(self.config.to_dict()),
                "best_val": json.dumps(self.best), "data": str(self.data_dir.name)}
        half = copy.deepcopy(model).half()
        paths = {"safetensors": save_safetensors(half, out_dir / "model_fp16.safetensors", metadata=meta)}
        if onnx:
            paths["onnx"] = export_step_onnx(model.float().eval(), out_dir / "model.onnx")
        from davis_rig.training.cards import write_model_card

        card_path = self.data_dir / "dataset_card.json"
        dataset_card = json.loads(card_path.read_text(encoding="utf-8")) if card_path.is_file() else None
        files = {p.name: ("fp16 weights + config (safetensors)" if k == "safetensors" else
                          "one recurrent step, fp32 (ONNX)") for k, p in paths.items()}
        paths["model_card"] = write_model_card(
            out_dir / "MODEL_CARD.md", model_name=f"davis_rig {self.model_config.name} ({self.data_dir.name})",
            model_config=self.model_config.to_dict(), train_config=self.config.to_dict(), dataset_card=dataset_card,
            validation=self.best if self.best.get("AP") is not None else None,
            compute={"device": str(self.device), "precision": str(self.amp_dtype or torch.float32),
                     "steps": self.step, "train_hours": round(self.history_s / 3600, 3),
                     **({"initial weights": self.init_source} if self.init_source else {})},
            files=files)
        return paths


def train(data_dir: str | Path, run_dir: str | Path, config: TrainConfig, *, resume: bool = False,
          max_steps: int | None = None, time_budget_s: float | None = None, export: bool = True,
          init_weights: str | Path | None = None, stop=None) -> dict[str, Any]:
    """Build a :class:`Trainer`, optionally resume from ``run_dir/checkpoints/last.pt``, fit, export when finished.

    Args:
        data_dir, run_dir, config: see :class:`Trainer`.
        resume: continue from the last checkpoint (its training config wins over ``config`` except
            ``device``, ``num_workers`` and ``progress``). Without it, an earlier run's ``last.pt`` is overwritten
            and its ``log.jsonl`` and ``best.safetensors`` are removed (with a warning).
        max_steps, time_budget_s: stop this call early (resumable chunks).
        export: export the final model when ``config.steps`` is reached.
        init_weights: a new run starts from these RVT weights (any file :func:`load_detector` reads: an official
            or davis_rig checkpoint, ``.safetensors``, a davis-train ``last.pt``), fine-tuning them; the
            architecture is theirs (``config.model`` is not used). Not with ``resume`` (the checkpoint has them).
        stop: see :meth:`Trainer.fit` (a stopped run is not exported).

    Returns:
        The :meth:`Trainer.fit` summary plus ``export`` paths (as strings) when exported.

    Raises:
        CheckpointError: ``resume`` without a checkpoint, or an unreadable, foreign or incompatible one.
    """
    from davis_rig.models.rvt.checkpoint import load_detector

    run_dir = Path(run_dir)
    last = run_dir / "checkpoints" / "last.pt"
    if resume and init_weights is not None:
        raise ConfigError("init_weights", "a resumed run continues its checkpoint: no initial weights")
    model_config = init = None
    if init_weights is not None:  # read before anything in RUN_DIR changes: a bad file leaves an earlier run intact
        init = load_detector(init_weights)
        model_config = init.config
    if resume:
        if not last.is_file():
            raise CheckpointError(f"{last}: no checkpoint to resume from")
        saved = read_train_checkpoint(last)
        try:
            saved_cfg = TrainConfig.from_dict(saved.get("train_config", {}))
        except (TypeError, ValueError, FormatError) as exc:
            raise CheckpointError(f"{last}: bad training settings in the checkpoint ({exc})") from exc
        config = replace(saved_cfg, device=config.device, num_workers=config.num_workers, progress=config.progress)
        if saved.get("model_config") is not None:  # the architecture of the run (of its initial weights, if any)
            model_config = RVTConfig.from_dict(saved["model_config"])
        del saved
    else:  # a fresh run: nothing of an earlier run in RUN_DIR may be mistaken for this one's
        stale = [p for p in (last, run_dir / "checkpoints" / "best.safetensors", run_dir / "log.jsonl") if p.is_file()]
        if stale:
            warnings.warn(f"{', '.join(map(str, stale))} of an earlier run will be overwritten or removed (pass "
                          "resume=True to continue it)", stacklevel=2)
    trainer = Trainer(data_dir, run_dir, config, model_config=model_config)
    if init is not None:
        trainer.init_from(init, str(init_weights))
    if not resume:  # removed only once the run could start (a bad DATA_DIR keeps the earlier run intact)
        (run_dir / "checkpoints" / "best.safetensors").unlink(missing_ok=True)
        (run_dir / "log.jsonl").unlink(missing_ok=True)
    if resume:
        trainer.load_checkpoint(last)
    summary = trainer.fit(max_steps=max_steps, time_budget_s=time_budget_s, stop=stop)
    if export and summary["finished"] and summary["stopped_by"] is None:
        summary["export"] = {k: str(v) for k, v in trainer.export().items()}
    return summary
