"""Labeler tests share ``tests/evaluation/eval_data.py`` (tiny ONNX graphs, recorded sessions)."""

import importlib.util
import sys
from pathlib import Path

if "eval_data" not in sys.modules:
    _spec = importlib.util.spec_from_file_location(
        "eval_data", Path(__file__).resolve().parents[1] / "evaluation" / "eval_data.py")
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["eval_data"] = _module
    _spec.loader.exec_module(_module)
