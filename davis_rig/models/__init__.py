"""Detectors used by the rig: ``davis_rig.models.rvt`` (RVT, recurrent event-camera detector).

The bundled default detector (trained on synthetic events only, see its ``MODEL_CARD.md``) lives in
``davis_rig/assets/detector/``: :func:`default_detector_path` (one recurrent RVT step as ONNX, for
``davis-eval`` and onnxruntime) and :func:`default_detector_weights_path` (the same weights as fp16 safetensors
with the architecture in the metadata ``config``, for ``davis_rig.models.rvt.load_detector`` and the attack).
"""

from pathlib import Path as _Path

#: Folder of the bundled synthetic-trained default detector inside the package.
DEFAULT_DETECTOR_DIR = _Path(__file__).resolve().parent.parent / "assets" / "detector"
#: One recurrent RVT step, fp32 ONNX (``export_step_onnx`` layout).
DEFAULT_DETECTOR_FILE = "rvt_default.onnx"
#: The same step with Conv and MatMul in int8 (``davis-quantize``, calibrated on synthetic training windows).
DEFAULT_INT8_FILE = "rvt_default_int8.onnx"
#: The same detector as fp16 safetensors with its ``RVTConfig`` JSON in the metadata key ``config``.
DEFAULT_WEIGHTS_FILE = "rvt_default.safetensors"


def _bundled(name: str, hint: str) -> _Path:
    path = DEFAULT_DETECTOR_DIR / name
    if not path.is_file():
        from davis_rig.errors import MissingDependencyError

        raise MissingDependencyError(
            f"the bundled default detector {path} is missing (the synthetic-trained model is not "
            f"installed with this copy of davis_rig); {hint}")
    return path


def default_detector_path(int8: bool = False) -> _Path:
    """Path of the bundled default RVT step ONNX (``davis_rig/assets/detector/rvt_default.onnx``).

    Args:
        int8: the int8 graph instead (``rvt_default_int8.onnx``, :mod:`davis_rig.models.rvt.quantize`): about
            1.5x faster on a CPU with 8-bit dot-product instructions, scores close to but not equal to fp32's
            (the model card gives both graphs' AP).

    Returns:
        The path of the bundled model (one recurrent step; input uint8/float histograms [1, 20, 240, 304]).

    Raises:
        MissingDependencyError: the file is absent; pass an RVT step ONNX explicitly (``davis-eval --detector
            rvt.onnx``, exported with ``davis_rig.models.rvt.onnx_export.export_step_onnx``).
    """
    return _bundled(DEFAULT_INT8_FILE if int8 else DEFAULT_DETECTOR_FILE,
                    "pass --detector RVT_STEP.onnx (davis_rig.models.rvt.onnx_export.export_step_onnx)")


def default_detector_weights_path() -> _Path:
    """Path of the bundled default detector's weights (``davis_rig/assets/detector/rvt_default.safetensors``).

    The file holds fp16 tensors and the architecture (``RVTConfig`` JSON, metadata key ``config``), so
    ``davis_rig.models.rvt.load_detector(default_detector_weights_path())`` rebuilds the model (fp32, eval mode).

    Returns:
        The path of the bundled weights.

    Raises:
        MissingDependencyError: the file is absent; pass an RVT checkpoint explicitly (``.ckpt``, ``.pt`` or
            ``.safetensors``, e.g. ``davis-attack optimize --detector rvt-t.ckpt``).
    """
    return _bundled(DEFAULT_WEIGHTS_FILE, "pass an RVT checkpoint explicitly (.ckpt, .pt or .safetensors)")
