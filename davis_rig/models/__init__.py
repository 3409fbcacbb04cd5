"""Detectors used by the rig: ``davis_rig.models.rvt`` (RVT, recurrent event-camera detector)."""

from pathlib import Path as _Path

#: Where the bundled synthetic-trained default detector (issue 7) will live inside the package.
DEFAULT_DETECTOR_DIR = _Path(__file__).resolve().parent.parent / "assets" / "detector"
DEFAULT_DETECTOR_FILE = "rvt_default.onnx"


def default_detector_path() -> _Path:
    """Path of the bundled default RVT step ONNX (``davis_rig/assets/detector/rvt_default.onnx``).

    Returns:
        The path of the bundled model.

    Raises:
        MissingDependencyError: the bundled model is not there (issue 7 has not landed it yet); pass an RVT step
            ONNX explicitly (``davis-eval --model rvt.onnx``, exported with ``export_step_onnx``).
    """
    path = DEFAULT_DETECTOR_DIR / DEFAULT_DETECTOR_FILE
    if not path.is_file():
        from davis_rig.errors import MissingDependencyError

        raise MissingDependencyError(
            f"the bundled default detector {path} is missing (the synthetic-trained model of issue 7 is not "
            "shipped yet); pass --model RVT_STEP.onnx (davis_rig.models.rvt.onnx_export.export_step_onnx)"
        )
    return path
