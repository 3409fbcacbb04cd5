"""RVT (Recurrent Vision Transformer, uzh-rpg/RVT) event-camera detector.

Importing this package does not import torch: :class:`RVTConfig` is pure Python and the torch-based names
(``RVTDetector``, ``pad_to_input``, ``load_detector``, ``read_state_dict``, ``save_safetensors``,
``export_step_onnx``) are loaded on first access (``MissingDependencyError`` naming the ``torch`` extra if torch
is absent). ``RVTOnnxRunner`` (onnxruntime) and ``postprocess.postprocess`` (numpy) work without torch.

Modules: ``config`` (RVTConfig), ``layers`` / ``backbone`` / ``fpn`` / ``head`` / ``detector`` (the PyTorch
model), ``checkpoint`` (safe checkpoint io), ``postprocess`` (NMS), ``onnx_export``, ``ort_runner``.
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports
from davis_rig.models.rvt.config import RVTConfig

# not "postprocess": the submodule of that name would shadow the function after its first import;
# use ``from davis_rig.models.rvt.postprocess import postprocess``
_LAZY = {
    "davis_rig.models.rvt.detector": ("RVTDetector", "pad_to_input"),
    "davis_rig.models.rvt.checkpoint": ("load_detector", "read_state_dict", "save_safetensors"),
    "davis_rig.models.rvt.onnx_export": ("export_step_onnx",),
    "davis_rig.models.rvt.ort_runner": ("RVTOnnxRunner",),
}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = ["RVTConfig", *(name for names in _LAZY.values() for name in names)]
