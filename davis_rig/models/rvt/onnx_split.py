"""Split an exported RVT step graph into its three parts, so that consecutive windows can run them in a pipeline.

One RVT step (:mod:`davis_rig.models.rvt.onnx_export`) is, in data-flow order:

==========  ====================================================  ===========================================
part        inputs → outputs                                      depends on the previous window?
==========  ====================================================  ===========================================
``pre``     ``histogram`` → ``x1``                                no: stage 1's downsampling conv + attention
``recur``   ``x1``, ``h1, c1 .. h4, c4`` → ``h1_out .. c4_out``   yes: the 4 ConvLSTMs and stages 2–4
``head``    ``h2_out, h3_out, h4_out`` → ``detections``           no: PAFPN + YOLOX head of the new states
==========  ====================================================  ===========================================

``x1`` is the tensor the first ConvLSTM concatenates with ``h1`` (the stage-1 feature map before its LSTM). Only
``recur`` carries the states from window to window, so ``pre`` of window k+1 and ``head`` of window k−1 can run
beside ``recur`` of window k. The parts are the original graph's own nodes, weights and tensor names (nothing is
recomputed or re-exported): run one after the other they compute exactly what the whole graph computes.

Any graph with the step signature whose stage-1 LSTM input is a two-input ``Concat`` with ``h1`` splits; others
(e.g. a graph whose head reads the histogram) raise :class:`~davis_rig.errors.ModelFormatError` and are run
whole. Needs the ``onnx`` package (graph editing; onnxruntime has no such API).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from davis_rig.errors import MissingDependencyError, ModelFormatError

if TYPE_CHECKING:  # pragma: no cover
    import onnx

__all__ = ["StepParts", "split_step_file", "split_step_graph"]

_STATES = tuple(f"{kind}{stage}" for stage in range(1, 5) for kind in ("h", "c"))
_HEAD_INPUTS = ("h2_out", "h3_out", "h4_out")


@dataclass(frozen=True)
class StepParts:
    """The three parts of one RVT step, as ONNX models (see the module docstring).

    Attributes:
        pre: ``histogram`` [B, 20, H, W] → ``x1`` [B, C_1, H/4, W/4].
        recur: ``x1`` and the 8 states → the 8 new states ``h1_out .. c4_out``.
        head: ``h2_out, h3_out, h4_out`` → ``detections`` [B, A, 5 + classes].
        x1_name: the graph's own name of ``x1`` (``pre``'s output, ``recur``'s first input).
    """

    pre: "onnx.ModelProto"
    recur: "onnx.ModelProto"
    head: "onnx.ModelProto"
    x1_name: str


def _import_onnx():
    try:
        import onnx
    except ImportError as exc:  # pragma: no cover - onnx is a core dependency
        raise MissingDependencyError("splitting an RVT graph needs onnx: pip install 'onnx>=1.15'") from exc
    return onnx


def _subgraph_reads(node) -> set[str]:
    """Names a node's subgraphs (``Loop``/``If`` bodies) read from the enclosing scope."""
    onnx = _import_onnx()
    reads: set[str] = set()
    for attribute in node.attribute:
        graphs = [attribute.g] if attribute.type == onnx.AttributeProto.GRAPH else list(attribute.graphs)
        for graph in graphs:
            local = {i.name for i in graph.input} | {i.name for i in graph.initializer}
            for inner in graph.node:
                local.update(inner.output)
            for inner in graph.node:
                reads.update(name for name in inner.input if name and name not in local)
                reads.update(name for name in _subgraph_reads(inner) if name not in local)
    return reads


def _extract(model, inputs: dict, outputs: list[str], part: str, known: dict | None = None):
    """The sub-model computing ``outputs`` from the tensors named in ``inputs`` ({name: ValueInfoProto}).

    ``known`` adds type/shape declarations ({name: ValueInfoProto}) for outputs the graph does not declare.

    Raises:
        ModelFormatError: an output needs a graph input that is not in ``inputs``, or a name is produced nowhere.
    """
    onnx = _import_onnx()
    graph = model.graph
    producer = {name: index for index, node in enumerate(graph.node) for name in node.output if name}
    initializers = {init.name: init for init in graph.initializer}
    graph_inputs = {value.name for value in graph.input}
    needed_nodes: set[int] = set()
    needed_inits: set[str] = set()
    seen: set[str] = set()
    stack = list(outputs)
    while stack:
        name = stack.pop()
        if name in seen or name in inputs:
            continue
        seen.add(name)
        if name in initializers:
            needed_inits.add(name)
        elif name in producer:
            index = producer[name]
            if index not in needed_nodes:
                needed_nodes.add(index)
                node = graph.node[index]
                stack.extend(n for n in node.input if n)
                stack.extend(_subgraph_reads(node))
        elif name in graph_inputs:
            raise ModelFormatError(f"the '{part}' part of the RVT step needs the graph input '{name}' (it may only "
                                   f"read {sorted(inputs)}): the graph cannot be split")
        else:
            raise ModelFormatError(f"the '{part}' part of the RVT step reads '{name}', which no node produces")
    value_infos = {value.name: value for value in list(graph.value_info) + list(graph.output) + list(graph.input)}
    value_infos.update(known or {})
    missing = [name for name in outputs if name not in value_infos and name not in producer]
    if missing:
        raise ModelFormatError(f"the '{part}' part: no tensor named {missing} in the graph")
    new_outputs = []
    for name in outputs:
        info = onnx.ValueInfoProto()
        if name in value_infos:
            info.CopyFrom(value_infos[name])
        else:
            info.name = name
            info.type.tensor_type.elem_type = onnx.TensorProto.FLOAT
        new_outputs.append(info)
    new_graph = onnx.helper.make_graph(
        [graph.node[i] for i in sorted(needed_nodes)], f"{graph.name}_{part}", list(inputs.values()), new_outputs,
        initializer=[initializers[name] for name in initializers if name in needed_inits],
        value_info=[value for value in graph.value_info if value.name in seen],
    )
    sub = onnx.helper.make_model(new_graph, opset_imports=list(model.opset_import), ir_version=model.ir_version,
                                 producer_name=model.producer_name)
    sub.metadata_props.extend(model.metadata_props)
    return sub


def split_step_graph(model) -> StepParts:
    """Split an RVT step graph into ``pre``, ``recur`` and ``head`` (see the module docstring).

    Args:
        model: an ``onnx.ModelProto`` with the :mod:`~davis_rig.models.rvt.onnx_export` signature (checked by
            :class:`~davis_rig.models.rvt.ort_runner.RVTOnnxRunner` beforehand).

    Returns:
        :class:`StepParts`; each part keeps the original node, weight and tensor names.

    Raises:
        ModelFormatError: no two-input ``Concat`` of ``h1`` with another tensor (the first ConvLSTM's input), or
            a part would need a tensor outside its inputs.
        MissingDependencyError: onnx is not installed.
    """
    onnx = _import_onnx()
    graph = model.graph
    concats = [node for node in graph.node if node.op_type == "Concat" and "h1" in node.input]
    if len(concats) != 1 or len(concats[0].input) != 2:
        raise ModelFormatError("the RVT step graph has no single two-input Concat of h1 (the first ConvLSTM's "
                               "input): it cannot be split")
    x1 = next(name for name in concats[0].input if name != "h1")
    declared = {value.name: value for value in list(graph.input) + list(graph.output)}
    missing = [name for name in ("histogram", "detections", *_STATES, *_HEAD_INPUTS) if name not in declared]
    if missing:
        raise ModelFormatError(f"the RVT step graph lacks {missing}: it cannot be split")
    # x1 has the shape of h1: the ConvLSTM concatenates two maps of C_1 channels
    x1_info = onnx.ValueInfoProto()
    x1_info.CopyFrom(declared["h1"])
    x1_info.name = x1
    pre = _extract(model, {"histogram": declared["histogram"]}, [x1], "pre", known={x1: x1_info})
    recur = _extract(model, {x1: x1_info, **{name: declared[name] for name in _STATES}},
                     [f"{name}_out" for name in _STATES], "recur")
    head = _extract(model, {name: declared[name] for name in _HEAD_INPUTS}, ["detections"], "head")
    for part in (pre, recur, head):
        try:
            onnx.checker.check_model(part)
        except onnx.checker.ValidationError as exc:
            raise ModelFormatError(f"a split part of the RVT step graph is not a valid graph: {exc}") from exc
    return StepParts(pre=pre, recur=recur, head=head, x1_name=x1)


def split_step_file(path) -> StepParts:
    """:func:`split_step_graph` of the ONNX file ``path``.

    Raises:
        ModelFormatError: onnx cannot read the file, or the graph does not split.
        MissingDependencyError: onnx is not installed.
    """
    onnx = _import_onnx()
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # onnx raises DecodeError/OSError variants
        raise ModelFormatError(f"{path}: onnx cannot read the model: {exc}") from exc
    return split_step_graph(model)
