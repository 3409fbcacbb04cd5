"""Training of the bundled RVT detector: synthetic data, dataset format, augmentation, YOLOX losses, TBPTT trainer.

Modules: ``dataset`` (RVT preprocessed layout: :class:`~davis_rig.training.dataset.DatasetWriter`,
:class:`~davis_rig.training.dataset.SequenceData`; numpy + h5py), ``batches`` (chunk datasets and samplers of
truncated BPTT, torch imported lazily), ``augment`` (flip / zoom of histogram chunks and boxes), ``losses``
(SimOTA + YOLOX losses), ``trainer`` (:class:`~davis_rig.training.trainer.Trainer`,
:func:`~davis_rig.training.trainer.train`), ``cards`` (dataset and model card templates), ``synthetic`` (the
synthetic dataset generator), ``recording`` (a rendered scene → a DAVIS346 session.h5, through the capture
path). Importing this package imports nothing heavy.
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports

_LAZY = {
    "davis_rig.training.dataset": ("DatasetWriter", "SequenceData", "list_sequences"),
    "davis_rig.training.batches": ("RandomChunkDataset", "StreamingBatches"),
    "davis_rig.training.augment": ("AugmentConfig",),
    "davis_rig.training.losses": ("yolox_loss", "simota_assign"),
    "davis_rig.training.train_config": ("TrainConfig",),
    "davis_rig.training.trainer": ("Trainer", "train"),
    "davis_rig.training.cards": ("write_model_card",),
    "davis_rig.training.recording": (
        "SYNTHETIC_LABELER", "SyntheticRecording", "embed_in_sensor", "labels_to_crop", "simulate_recording",
        "write_clip_session", "write_synthetic_session",
    ),
}  # fmt: skip

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = [name for names in _LAZY.values() for name in names]
