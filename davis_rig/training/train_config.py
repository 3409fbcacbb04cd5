"""Hyper-parameters of a training run (:class:`TrainConfig`, defaults: RVT's Gen1 recipe), checked on creation.

Every invalid field raises :class:`~davis_rig.errors.ConfigError` naming the field. :meth:`TrainConfig.to_dict` /
:meth:`TrainConfig.from_dict` are the JSON form stored in checkpoints and model cards.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, Mapping

from davis_rig.errors import ConfigError
from davis_rig.models.rvt.config import RVTConfig
from davis_rig.training.augment import AugmentConfig

__all__ = ["TrainConfig"]


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (defaults: RVT Gen1 recipe).

    Attributes:
        model: a :meth:`RVTConfig.presets` name: ``"tiny"``, ``"small"``, ``"base"``, ``"mini"`` or ``"nano"``.
        steps: total optimizer steps (the one-cycle schedule spans them).
        batch_size: chunks per batch. seq_len: windows per chunk (TBPTT length L).
        lr, weight_decay, pct_start, div_factor, final_div_factor: AdamW + OneCycleLR (final lr = lr /
            final_div_factor, RVT's convention).
        grad_clip: max gradient L2 norm (0 = off).
        precision: ``"auto"`` (bf16 on CUDA if supported, else fp16; fp32 on CPU), ``"fp32"``, ``"bf16"``, ``"fp16"``.
        ema_decay: EMA of the weights (e.g. 0.9998) used for validation and export; ``None`` = off.
        val_every, ckpt_every, log_every: intervals in steps (0 = never; a checkpoint is always written at the
            end, and a finished run is always validated at its last step).
        val_batch_size, val_seq_len: streaming lanes and chunk length for validation.
        val_conf_threshold: postprocess threshold for AP (RVT's reported evaluation: 0.001).
        val_skip_first_us: labels and detections within this time from a sequence's start are ignored (RVT 0.5 s).
        val_max_sequences: evaluate only the first N validation sequences (``None`` = all).
        min_box_side_px: training labels with a side ≤ this (after clipping to the frame) are dropped.
        sampling: ``"mixed"`` (RVT: half streaming lanes, half random chunks; needs batch ≥ 2) or ``"random"``.
        augment: :class:`AugmentConfig` of the random-access chunks (RVT ``data_augmentation.random``).
        stream_augment: :class:`AugmentConfig` of the streaming lanes, drawn once per sequence (RVT ``stream``).
        seed: seeds the model initialisation, the data order and the augmentation.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:1"``...
        num_workers: DataLoader workers reading histograms (0 = main process).
        use_l1: add YOLOX's L1 loss (RVT: off).
        progress: show a tqdm progress bar on stderr.
    """

    model: str = "tiny"
    steps: int = 400_000
    batch_size: int = 8
    seq_len: int = 21
    lr: float = 2e-4
    weight_decay: float = 0.0
    pct_start: float = 0.005
    div_factor: float = 20.0
    final_div_factor: float = 10_000.0
    grad_clip: float = 1.0
    precision: str = "auto"
    ema_decay: float | None = None
    val_every: int = 5_000
    ckpt_every: int = 1_000
    log_every: int = 50
    val_batch_size: int = 8
    val_seq_len: int = 21
    val_conf_threshold: float = 0.001
    val_skip_first_us: int = 500_000
    val_max_sequences: int | None = None
    min_box_side_px: float = 0.0
    sampling: str = "mixed"
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    stream_augment: AugmentConfig = field(default_factory=AugmentConfig.rvt_stream)
    seed: int = 0
    device: str = "auto"
    num_workers: int = 0
    use_l1: bool = False
    progress: bool = False

    def __post_init__(self):
        if self.model not in RVTConfig.presets():
            raise ConfigError("model", f"expected one of {sorted(RVTConfig.presets())}, got {self.model!r}")
        if self.precision not in ("auto", "fp32", "bf16", "fp16"):
            raise ConfigError("precision", f"expected auto, fp32, bf16 or fp16, got {self.precision!r}")
        for name in ("steps", "batch_size", "seq_len", "val_batch_size", "val_seq_len"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(name, f"expected ≥ 1, got {getattr(self, name)}")
        if self.sampling not in ("mixed", "random"):
            raise ConfigError("sampling", f"expected 'mixed' or 'random', got {self.sampling!r}")
        if self.sampling == "mixed" and self.batch_size < 2:
            raise ConfigError("batch_size", "sampling 'mixed' needs ≥ 2 (half streaming, half random); use 'random'")
        if self.ema_decay is not None and not 0 < self.ema_decay < 1:
            raise ConfigError("ema_decay", f"expected in (0, 1), got {self.ema_decay}")
        if not float(self.lr) > 0:  # also rejects NaN
            raise ConfigError("lr", f"expected > 0, got {self.lr}")
        for name in ("val_every", "ckpt_every", "log_every", "num_workers", "val_skip_first_us"):
            if int(getattr(self, name)) < 0:
                raise ConfigError(name, f"expected ≥ 0, got {getattr(self, name)}")
        for name in ("weight_decay", "grad_clip", "min_box_side_px"):
            if not float(getattr(self, name)) >= 0:
                raise ConfigError(name, f"expected ≥ 0, got {getattr(self, name)}")
        if self.val_max_sequences is not None and int(self.val_max_sequences) < 1:
            raise ConfigError("val_max_sequences", f"expected ≥ 1 or None, got {self.val_max_sequences}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (``from_dict`` reads it back)."""
        out = asdict(self)
        out["augment"] = asdict(self.augment)
        out["stream_augment"] = asdict(self.stream_augment)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        kwargs = {k: v for k, v in d.items() if k in names}
        for name in ("augment", "stream_augment"):
            if isinstance(kwargs.get(name), Mapping):
                aug = dict(kwargs[name])
                for key in ("zoom_in_range", "zoom_out_range"):
                    if key in aug:
                        aug[key] = tuple(aug[key])
                kwargs[name] = AugmentConfig(**aug)
        return cls(**kwargs)
