"""RVT (Recurrent Vision Transformer, uzh-rpg/RVT) event-camera detector.

Importing this package does not import torch: :class:`RVTConfig` is pure Python and the torch-based names
(``RVTDetector``, ``pad_to_input``, ``load_detector``, ``read_state_dict``, ``save_safetensors``,
``export_step_onnx``) are loaded on first access (``MissingDependencyError`` naming the ``torch`` extra if torch
is absent). ``RVTOnnxRunner`` (onnxruntime) and ``postprocess.postprocess`` (numpy) work without torch.

Modules: ``config`` (RVTConfig), ``layers`` / ``backbone`` / ``fpn`` / ``head`` / ``detector`` (the PyTorch
model), ``checkpoint`` (safe checkpoint io), ``postprocess`` (NMS), ``onnx_export``, ``ort_runner``.
"""

from __future__ import annotations

import importlib

from davis_rig.models.rvt.config import RVTConfig

_LAZY = {
    "RVTDetector": "davis_rig.models.rvt.detector",
    "pad_to_input": "davis_rig.models.rvt.detector",
    "load_detector": "davis_rig.models.rvt.checkpoint",
    "read_state_dict": "davis_rig.models.rvt.checkpoint",
    "save_safetensors": "davis_rig.models.rvt.checkpoint",
    # not "postprocess": the submodule of that name would shadow the function after its first import;
    # use ``from davis_rig.models.rvt.postprocess import postprocess``
    "export_step_onnx": "davis_rig.models.rvt.onnx_export",
    "RVTOnnxRunner": "davis_rig.models.rvt.ort_runner",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__():
    return sorted(list(globals()) + list(_LAZY))


__all__ = ["RVTConfig", *_LAZY]
