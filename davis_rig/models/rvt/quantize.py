"""int8 RVT step graphs: static post-training quantization of an exported step with onnxruntime.

The fp32 step graph (:mod:`davis_rig.models.rvt.onnx_export`) spends two thirds of its CPU time in ``Conv`` and
``MatMul``; onnxruntime runs those in 8 bits with AVX-512 VNNI / AVX2 integer kernels. :func:`quantize_step_onnx`
writes a QDQ graph (``QuantizeLinear`` → op → ``DequantizeLinear``, which onnxruntime fuses into ``QLinearConv`` /
``QLinearMatMul``) in which only those two op types run in int8:

* weights int8 on 7 bits (−64..64, onnxruntime's ``reduce_range``), symmetric, one scale per output channel;
  activations uint8 with a zero point, one scale per tensor, their ranges the min/max seen on calibration windows
  (onnxruntime's ``MinMax`` calibrator). The 7-bit weights make one graph right on every x86 CPU: without VNNI
  (AVX2, AVX-512 without VNNI: e.g. AMD Zen 3) onnxruntime multiplies uint8 × int8 with ``VPMADDUBSW``, whose
  pairwise sums saturate at 16 bits (255 · 127 · 2 > 32767) unless the weights stay within 7 bits (255 · 64 · 2 fits). Measured on an
  AVX2-only AMD EPYC (``tests/models/rvt/test_quantize.py``'s mini model, random windows): mean score error against
  fp32 0.055 with 8-bit weights, 0.0066 with 7; on the bundled RVT-T's windows of ``recordings/sample.h5``
  1.00e-4 and 1.03e-4;
* their inputs and outputs pass through 8 bits (the next fp32 op reads the dequantized value), everything else
  (LayerNorm, softmax, GELU, the ConvLSTM gates, the head's decoding) computes in fp32, so the boxes, objectness
  and class scores keep their fp32 scale;
* the calibration windows are real model inputs: histograms of whole sequences run through the **fp32** graph
  from zero states, each calibration feed being a window's histogram together with the fp32 states that precede
  it (the recurrent inputs are calibrated on the states the model really carries).

The int8 graph keeps the step signature and the metadata (config, state names, input size), adds a
``quantization`` entry (JSON: scheme, op types, calibration windows and sources), and splits into the
``pre`` / ``recur`` / ``head`` parts of :mod:`davis_rig.models.rvt.onnx_split` like the fp32 graph (a graph
exported before the ConvLSTM's ``Split`` replaced its ``Loop`` does not split once quantized: re-export it).
Its outputs are *not* the fp32 graph's: the CLI ``davis-quantize`` and ``benchmarks/evaluation.py`` report the
score differences and AP of both.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from davis_rig.errors import MissingDependencyError, ModelFormatError
from davis_rig.models.rvt.onnx_export import INPUT_NAME

__all__ = ["QUANTIZED_OPS", "calibration_feeds", "quantization_info", "quantize_step_onnx"]

#: The op types :func:`quantize_step_onnx` runs in int8.
QUANTIZED_OPS = ("Conv", "MatMul")
#: Metadata key of the quantization record.
QUANTIZATION_KEY = "quantization"


def calibration_feeds(runner, sequences: Sequence, max_windows: int) -> list[dict[str, np.ndarray]]:
    """Graph feeds of calibration windows: each window's histogram with the fp32 states that precede it.

    ``max_windows`` windows evenly spaced over all sequences end to end are chosen; every sequence that holds one
    runs through ``runner`` (the fp32 step) from zero states up to its last chosen window, one window read at a
    time (memory: one window, whatever the sequences' length).

    Args:
        runner: :class:`~davis_rig.models.rvt.ort_runner.RVTOnnxRunner` of the fp32 graph.
        sequences: whole sequences, each with ``len()`` and ``seq[a:b]`` giving uint8/float histograms
            [b - a, 20, 240, 304] (a numpy array qualifies).
        max_windows: most feeds in all (>= 1).

    Returns:
        list of ``{input name: float32 array [1, ...]}``, in sequence and window order.

    Raises:
        ValueError: ``max_windows`` < 1 or no sequence has a window.
        ShapeError: a histogram of the wrong shape.
    """
    if int(max_windows) < 1:
        raise ValueError(f"max_windows must be >= 1, got {max_windows}")
    lengths = np.array([len(s) for s in sequences], dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        raise ValueError("calibration needs at least one window")
    picks = np.unique(np.linspace(0, total - 1, min(int(max_windows), total)).round().astype(np.int64))
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    owner = np.searchsorted(starts, picks, side="right") - 1
    feeds = []
    for index in np.unique(owner):
        chosen = set((picks[owner == index] - starts[index]).tolist())
        states = runner.initial_states(1)
        for window in range(max(chosen) + 1):
            x = runner.prepare_histogram(np.asarray(sequences[index][window : window + 1]))
            if window in chosen:
                feed = {INPUT_NAME: x}
                for stage, (h_state, c_state) in enumerate(states, start=1):
                    feed[f"h{stage}"], feed[f"c{stage}"] = h_state, c_state
                feeds.append(feed)
            if window < max(chosen):
                states = runner.step(x, states)[1]
    return feeds


class _Feeds:
    """onnxruntime's ``CalibrationDataReader`` protocol over a list of feeds."""

    def __init__(self, feeds: Sequence[dict]):
        self._items: Iterator[dict] = iter(feeds)

    def get_next(self) -> dict | None:
        return next(self._items, None)

    def rewind(self) -> None:  # pragma: no cover - the MinMax calibrator reads once
        raise NotImplementedError


def quantize_step_onnx(src: str | Path, dst: str | Path, feeds: Sequence[dict], *, sources: Sequence[str] = ()
                       ) -> Path:
    """Write the int8 (QDQ) version of the fp32 step graph ``src`` to ``dst`` (see the module docstring).

    Args:
        src: fp32 step ``.onnx`` (:func:`~davis_rig.models.rvt.onnx_export.export_step_onnx`).
        dst: output ``.onnx``; written atomically (a temporary file, then renamed).
        feeds: calibration feeds (:func:`calibration_feeds`), at least one.
        sources: names of the calibration recordings, stored in the metadata.

    Returns:
        ``dst``.

    Raises:
        MissingDependencyError: ``onnx`` or ``onnxruntime.quantization`` is missing.
        ModelFormatError: ``src`` is not a loadable graph or is already quantized.
        ValueError: no feeds.
    """
    try:
        import onnx
        from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
        from onnxruntime.quantization.shape_inference import quant_pre_process
    except ImportError as exc:  # pragma: no cover - both are core dependencies
        raise MissingDependencyError(f"quantization needs onnx and onnxruntime ({exc.name} missing)") from exc
    if not feeds:
        raise ValueError("quantization needs at least one calibration feed")
    src, dst = Path(src), Path(dst)
    try:
        model = onnx.load(str(src))
    except Exception as exc:  # onnx raises DecodeError / OSError
        raise ModelFormatError(f"{src}: not a loadable ONNX graph: {exc}") from exc
    metadata = {p.key: p.value for p in model.metadata_props}
    if QUANTIZATION_KEY in metadata or any(n.op_type in ("QuantizeLinear", "QLinearConv") for n in model.graph.node):
        raise ModelFormatError(f"{src}: already quantized")
    with tempfile.TemporaryDirectory(dir=dst.parent) as tmp:
        prepared, written = Path(tmp) / "prepared.onnx", Path(tmp) / "int8.onnx"
        quant_pre_process(str(src), str(prepared), skip_symbolic_shape=True)
        quantize_static(str(prepared), str(written), _Feeds(feeds), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, reduce_range=True,
                        op_types_to_quantize=list(QUANTIZED_OPS), calibrate_method=CalibrationMethod.MinMax)
        quantized = onnx.load(str(written))
        record = {"scheme": "static QDQ: int8 weights on 7 bits per output channel (symmetric), uint8 activations "
                            "per tensor (min/max calibration)",
                  "ops": list(QUANTIZED_OPS), "calibration_windows": len(feeds), "calibration_sources": list(sources),
                  "fp32_graph": src.name}
        del quantized.metadata_props[:]
        for key, value in {**metadata, QUANTIZATION_KEY: json.dumps(record)}.items():
            entry = quantized.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(quantized, str(written))
        os.replace(written, dst)
    return dst


def quantization_info(path: str | Path) -> dict | None:
    """The ``quantization`` record of a step graph's metadata (``None``: an fp32 graph)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    value = {p.key: p.value for p in model.metadata_props}.get(QUANTIZATION_KEY)
    return json.loads(value) if value is not None else None
