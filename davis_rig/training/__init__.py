"""Training of the bundled RVT detector: dataset format, augmentation, YOLOX losses, TBPTT trainer.

Modules: ``dataset`` (RVT preprocessed layout: :class:`~davis_rig.training.dataset.DatasetWriter`,
:class:`~davis_rig.training.dataset.SequenceData`, chunk datasets; numpy + h5py, torch only for the torch-facing
classes), ``augment`` (flip / zoom of histogram chunks and boxes), ``losses`` (SimOTA + YOLOX losses),
``trainer`` (:class:`~davis_rig.training.trainer.Trainer`, :func:`~davis_rig.training.trainer.train`),
``cards`` (dataset and model card templates). Importing this package imports nothing heavy.
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports

_LAZY = {
    "davis_rig.training.dataset": (
        "DatasetWriter", "SequenceData", "RandomChunkDataset", "StreamingBatches", "list_sequences",
    ),
    "davis_rig.training.augment": ("AugmentConfig",),
    "davis_rig.training.losses": ("yolox_loss", "simota_assign"),
    "davis_rig.training.trainer": ("TrainConfig", "Trainer", "train"),
    "davis_rig.training.cards": ("write_model_card",),
}  # fmt: skip

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = [name for names in _LAZY.values() for name in names]
