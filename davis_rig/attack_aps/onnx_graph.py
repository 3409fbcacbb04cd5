"""Run an ONNX detector graph with torch ops, so that gradients flow to its input (the texture attack needs them).

onnxruntime runs the labeler's YOLO (:mod:`davis_rig.labelers.yolo`) but gives no gradient. :class:`OnnxGraph`
executes the same graph node by node with ``torch.nn.functional``, with the initializers as frozen buffers. It
supports the op types of an Ultralytics YOLOv8 detection export (Conv, Sigmoid, Mul, Add, Sub, Div, Concat, Split,
Slice, Reshape, Transpose, Softmax, MaxPool, Resize in nearest/asymmetric/floor mode) and refuses any other op
with a :class:`~davis_rig.errors.ModelFormatError` naming it, instead of computing something else. (onnx2torch
would convert it too, but imports torchvision, which has no wheel for this CPU torch.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import MissingDependencyError, ModelFormatError

with optional_dependency("the APS attack"):
    import torch
    import torch.nn.functional as F

__all__ = ["SUPPORTED_OPS", "OnnxGraph"]

SUPPORTED_OPS = ("Add", "Concat", "Constant", "Conv", "Div", "MaxPool", "Mul", "Reshape", "Resize", "Sigmoid",
                 "Slice", "Softmax", "Split", "Sub", "Transpose")


def _attrs(node) -> dict:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _pad_for(pads, x, value=0.0):
    """``pads`` [begin..., end...] of the spatial dims as F.pad's (last dim first) order."""
    half = len(pads) // 2
    spec = []
    for d in reversed(range(half)):
        spec += [int(pads[d]), int(pads[d + half])]
    return F.pad(x, spec, value=value) if any(spec) else x


class OnnxGraph(torch.nn.Module):
    """An ONNX graph as a torch module (float32, frozen weights, differentiable w.r.t. its inputs).

    Args:
        path: the ``.onnx`` file.

    Raises:
        MissingDependencyError: the ``onnx`` package is missing.
        ModelFormatError: unreadable file, or an op outside :data:`SUPPORTED_OPS`.
    """

    def __init__(self, path: str | Path):
        super().__init__()
        try:
            import onnx
            from onnx import numpy_helper
        except ImportError as exc:
            raise MissingDependencyError("running an ONNX graph in torch needs onnx: pip install onnx") from exc
        try:
            model = onnx.load(str(path))
        except Exception as exc:  # onnx raises its own decode errors
            raise ModelFormatError(f"{path}: not a readable ONNX model ({exc})") from exc
        graph = model.graph
        unknown = sorted({n.op_type for n in graph.node} - set(SUPPORTED_OPS))
        if unknown:
            raise ModelFormatError(f"{path}: ops {unknown} are not supported (supported: {', '.join(SUPPORTED_OPS)})")
        self._names: dict[str, str] = {}
        for k, init in enumerate(graph.initializer):
            array = numpy_helper.to_array(init)
            tensor = torch.from_numpy(np.array(array, dtype=np.float32 if array.dtype.kind == "f" else np.int64))
            self.register_buffer(f"c{k}", tensor, persistent=False)
            self._names[init.name] = f"c{k}"
        self.nodes = [(n.op_type, list(n.input), list(n.output), _attrs(n)) for n in graph.node]
        initializers = {i.name for i in graph.initializer}
        self.input_names = [i.name for i in graph.input if i.name not in initializers]
        self.output_names = [o.name for o in graph.output]
        self.metadata = {p.key: p.value for p in model.metadata_props}

    def forward(self, *inputs: torch.Tensor):
        """Run the graph; returns its output tensor (or a tuple when it has several)."""
        if len(inputs) != len(self.input_names):
            raise ModelFormatError(f"the graph takes {len(self.input_names)} inputs, got {len(inputs)}")
        env = {name: getattr(self, buf) for name, buf in self._names.items()}
        env.update(zip(self.input_names, inputs))
        for op, ins, outs, attrs in self.nodes:
            args = [env[i] if i else None for i in ins]
            result = self._run(op, args, attrs)
            for name, value in zip(outs, result if isinstance(result, tuple) else (result,)):
                env[name] = value
        out = tuple(env[o] for o in self.output_names)
        return out[0] if len(out) == 1 else out

    @staticmethod
    def _ints(t) -> list[int]:
        return [int(v) for v in t.reshape(-1).tolist()]

    def _run(self, op: str, x: list, a: dict):
        if op == "Conv":
            w, b = x[1], x[2] if len(x) > 2 else None
            group = int(a.get("group", 1))
            pads = a.get("pads", [0] * (2 * (w.ndim - 2)))
            inp = _pad_for(pads, x[0])
            return F.conv2d(inp, w, b, stride=a.get("strides", 1), dilation=a.get("dilations", 1), groups=group)
        if op == "Sigmoid":
            return torch.sigmoid(x[0])
        if op in ("Add", "Sub", "Mul", "Div"):
            fn = {"Add": torch.add, "Sub": torch.sub, "Mul": torch.mul, "Div": torch.div}[op]
            return fn(x[0], x[1])
        if op == "Concat":
            return torch.cat(x, dim=int(a["axis"]))
        if op == "Split":
            axis = int(a.get("axis", 0))
            sizes = self._ints(x[1]) if len(x) > 1 and x[1] is not None else list(a["split"])
            return tuple(torch.split(x[0], sizes, dim=axis))
        if op == "Slice":
            data, starts, ends = x[0], self._ints(x[1]), self._ints(x[2])
            axes = self._ints(x[3]) if len(x) > 3 and x[3] is not None else list(range(len(starts)))
            steps = self._ints(x[4]) if len(x) > 4 and x[4] is not None else [1] * len(starts)
            index = [slice(None)] * data.ndim
            for s, e, ax, st in zip(starts, ends, axes, steps):
                size = data.shape[ax]
                s = max(0, min(size, s + size if s < 0 else s))
                e = max(0, min(size, e + size if e < 0 else e))
                index[ax] = slice(s, e, st)
            return data[tuple(index)]
        if op == "Reshape":
            shape = self._ints(x[1])
            shape = [x[0].shape[k] if v == 0 and not a.get("allowzero", 0) else v for k, v in enumerate(shape)]
            return x[0].reshape(shape)
        if op == "Transpose":
            return x[0].permute(*a["perm"])
        if op == "Softmax":
            return torch.softmax(x[0], dim=int(a.get("axis", -1)))
        if op == "MaxPool":
            if a.get("ceil_mode", 0) or any(d != 1 for d in a.get("dilations", [1])):
                raise ModelFormatError("MaxPool with ceil_mode or dilation is not supported")
            inp = _pad_for(a.get("pads", [0, 0, 0, 0]), x[0], value=float("-inf"))
            return F.max_pool2d(inp, a["kernel_shape"], stride=a.get("strides", a["kernel_shape"]))
        if op == "Resize":
            mode = a.get("mode", b"nearest")
            ctm = a.get("coordinate_transformation_mode", b"half_pixel")
            nearest = a.get("nearest_mode", b"round_prefer_floor")
            if (mode, ctm, nearest) != (b"nearest", b"asymmetric", b"floor"):
                raise ModelFormatError(f"Resize {mode}/{ctm}/{nearest} is not supported (nearest/asymmetric/floor)")
            scales = x[2] if len(x) > 2 and x[2] is not None and x[2].numel() else None
            if scales is not None:
                factors = [float(v) for v in scales.tolist()[2:]]
                return F.interpolate(x[0], scale_factor=factors, mode="nearest")
            size = self._ints(x[3])[2:]
            return F.interpolate(x[0], size=size, mode="nearest")
        if op == "Constant":
            from onnx import numpy_helper

            return torch.from_numpy(np.array(numpy_helper.to_array(a["value"])))
        raise ModelFormatError(f"op {op} is not supported")  # unreachable: checked at load
