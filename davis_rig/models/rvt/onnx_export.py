"""Export one recurrent RVT step to ONNX (histogram + 8 LSTM state tensors in, detections + new states out).

Graph signature (all float32, batch dimension ``B`` dynamic unless ``batch_dynamic=False``):

=================  ==================================  ====================================================
name               shape                               meaning
=================  ==================================  ====================================================
``histogram``      [B, 20, H, W] (H, W = in_res_hw)    zero-padded stacked histogram (counts 0..10)
``h1, c1 .. c4``   [B, C_s, H/s, W/s], s = 4, 8, 16, 32  LSTM states of the previous step (zeros at start)
``detections``     [B, A, 5 + num_classes]             decoded head: cx, cy, w, h (px), obj, class probs
``h1_out .. c4_out``  as the inputs                    the new LSTM states
=================  ==================================  ====================================================

The model's config is stored in the ONNX metadata (``metadata_props``): ``config`` (``RVTConfig.to_json()``),
``format`` (:data:`ONNX_FORMAT`), ``state_names``, ``in_res_hw`` and ``producer``. The exporter is PyTorch's
TorchScript-based ``torch.onnx.export(dynamo=False)``, which needs only ``torch`` and ``onnx`` (the dynamo
exporter would need ``onnxscript`` as well).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from davis_rig.errors import MissingDependencyError, ModelFormatError

if TYPE_CHECKING:  # pragma: no cover
    from davis_rig.models.rvt.detector import RVTDetector

__all__ = ["ONNX_FORMAT", "INPUT_NAME", "OUTPUT_NAME", "state_input_names", "state_output_names", "export_step_onnx"]

#: ``format`` metadata value of graphs written by :func:`export_step_onnx`.
ONNX_FORMAT = "davis_rig-rvt-step/1"
#: Name of the histogram input.
INPUT_NAME = "histogram"
#: Name of the decoded detections output.
OUTPUT_NAME = "detections"


def state_input_names() -> tuple[str, ...]:
    """``("h1", "c1", "h2", "c2", "h3", "c3", "h4", "c4")`` — flat state order of ``RVTDetector.step_flat``."""
    return tuple(f"{kind}{stage}" for stage in range(1, 5) for kind in ("h", "c"))


def state_output_names() -> tuple[str, ...]:
    """``("h1_out", "c1_out", ..., "c4_out")``."""
    return tuple(f"{name}_out" for name in state_input_names())


def _import_export_deps():
    try:
        import onnx
        import torch
    except ImportError as exc:
        raise MissingDependencyError(
            f"ONNX export needs torch and onnx ({exc.name} missing): pip install 'davis_rig[torch]'"
        ) from exc
    return torch, onnx


def export_step_onnx(
    model: "RVTDetector",
    path: str | Path,
    *,
    opset: int = 17,
    batch_dynamic: bool = True,
    example_batch: int = 1,
    check: bool = True,
) -> Path:
    """Export one recurrent step of ``model`` (its ``step_flat``) to an ONNX file.

    The model is exported in eval mode (BatchNorm with running statistics); its training flag is restored
    afterwards and its weights are not changed.

    Args:
        model: an :class:`~davis_rig.models.rvt.detector.RVTDetector` with float32 weights (traced on the
            device of its parameters).
        path: output ``.onnx`` file (its folder must exist).
        opset: ONNX opset version (17 has ``LayerNormalization``; GELU is exported as its exact erf form).
        batch_dynamic: make the batch dimension symbolic (``"batch"``) on every input and output.
        example_batch: batch size of the tracing example (also the fixed batch when not ``batch_dynamic``).
        check: run ``onnx.checker.check_model`` on the written file.

    Returns:
        The path written.

    Raises:
        MissingDependencyError: torch or onnx is not installed.
        ModelFormatError: the written graph fails ``onnx.checker``.
    """
    torch, onnx = _import_export_deps()
    path = Path(path)
    _trace_step(torch, model, path, opset=opset, batch_dynamic=batch_dynamic, example_batch=example_batch)
    proto = onnx.load(str(path))
    _write_static_output_dims(proto, model.config, "batch" if batch_dynamic else example_batch, example_batch)
    _write_metadata(proto, model.config, f"davis_rig onnx_export (torch {torch.__version__}, opset {opset})")
    onnx.save(proto, str(path))
    if check:
        try:
            onnx.checker.check_model(str(path), full_check=True)
        except onnx.checker.ValidationError as exc:
            raise ModelFormatError(f"{path}: exported graph fails onnx.checker: {exc}") from exc
    return path


def _trace_step(torch, model: "RVTDetector", path: Path, *, opset: int, batch_dynamic: bool,
                example_batch: int) -> None:
    """Trace ``model.step_flat`` in eval mode on zero inputs of batch ``example_batch`` and write the ONNX graph
    (TorchScript exporter, constant folding); the model's training flag is restored."""
    config = model.config
    device = next(model.parameters()).device

    class _Step(torch.nn.Module):
        def __init__(self, detector):
            super().__init__()
            self.detector = detector

        def forward(self, histogram, h1, c1, h2, c2, h3, c3, h4, c4):
            return self.detector.step_flat(histogram, h1, c1, h2, c2, h3, c3, h4, c4)

    example_x = torch.zeros(
        (example_batch, config.input_channels, *config.in_res_hw), dtype=torch.float32, device=device
    )
    example_states = []
    for h_shape, c_shape in config.state_shapes(example_batch):
        example_states.extend(
            (torch.zeros(h_shape, dtype=torch.float32, device=device), torch.zeros(c_shape, dtype=torch.float32, device=device))
        )
    input_names = [INPUT_NAME, *state_input_names()]
    output_names = [OUTPUT_NAME, *state_output_names()]
    dynamic_axes = {name: {0: "batch"} for name in input_names + output_names} if batch_dynamic else None

    was_training = model.training
    model.eval()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", category=DeprecationWarning)  # the TorchScript exporter is "legacy"
            warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
            torch.onnx.export(
                _Step(model),
                (example_x, *example_states),
                str(path),
                input_names=input_names,
                output_names=output_names,
                dynamic_axes=dynamic_axes,
                opset_version=opset,
                do_constant_folding=True,
                dynamo=False,
            )
    finally:
        model.train(was_training)


def _write_static_output_dims(proto, config, batch_dim: int | str, example_batch: int) -> None:
    """Write the known output sizes into ``proto`` (the tracer leaves some symbolic: ``Concatdetections_dim_2``);
    ``batch_dim`` is ``"batch"`` or the fixed batch size."""
    output_shapes = {OUTPUT_NAME: (batch_dim, config.num_anchors, config.num_outputs)}
    for name, (shape, _) in zip(state_output_names()[0::2], config.state_shapes(example_batch)):
        output_shapes[name] = output_shapes[name.replace("h", "c", 1)] = (batch_dim, *shape[1:])
    for output in proto.graph.output:
        dims = output.type.tensor_type.shape.dim
        for dim, value in zip(dims, output_shapes[output.name]):
            if isinstance(value, str):
                dim.dim_param = value
            else:
                dim.dim_value = value


def _write_metadata(proto, config, producer: str) -> None:
    """Replace ``proto``'s ``metadata_props`` with the step graph's: config, format, state names, input size."""
    metadata = {
        "config": config.to_json(),
        "format": ONNX_FORMAT,
        "state_names": json.dumps(list(state_input_names())),
        "in_res_hw": json.dumps(list(config.in_res_hw)),
        "producer": producer,
    }
    del proto.metadata_props[:]
    for key, value in metadata.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
