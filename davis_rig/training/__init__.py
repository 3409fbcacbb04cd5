"""Training of the bundled RVT detector: dataset format, augmentation, YOLOX losses, TBPTT trainer.

Modules: ``dataset`` (RVT preprocessed layout: :class:`~davis_rig.training.dataset.DatasetWriter`,
:class:`~davis_rig.training.dataset.SequenceData`, chunk datasets; numpy + h5py, torch only for the torch-facing
classes), ``augment`` (flip / zoom of histogram chunks and boxes), ``losses`` (SimOTA + YOLOX losses),
``trainer`` (:class:`~davis_rig.training.trainer.Trainer`, :func:`~davis_rig.training.trainer.train`),
``cards`` (dataset and model card templates). Importing this package imports nothing heavy.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "DatasetWriter": "davis_rig.training.dataset",
    "SequenceData": "davis_rig.training.dataset",
    "RandomChunkDataset": "davis_rig.training.dataset",
    "StreamingBatches": "davis_rig.training.dataset",
    "list_sequences": "davis_rig.training.dataset",
    "AugmentConfig": "davis_rig.training.augment",
    "yolox_loss": "davis_rig.training.losses",
    "simota_assign": "davis_rig.training.losses",
    "TrainConfig": "davis_rig.training.trainer",
    "Trainer": "davis_rig.training.trainer",
    "train": "davis_rig.training.trainer",
    "write_model_card": "davis_rig.training.cards",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__():
    return sorted(list(globals()) + list(_LAZY))


__all__ = list(_LAZY)
