"""Run an exported RVT step graph with onnxruntime — no torch needed (numpy + onnxruntime only).

Typical use: score a recorded event stream window by window with the recurrent states carried::

    runner = RVTOnnxRunner("rvt_t.onnx", intra_op_threads=2)
    detections = runner.score_stream(x, y, t_us, p, window_end_us=ends, conf_threshold=0.1)
    # detections[i]: float32 [K, 7] (x1, y1, x2, y2, obj, class_conf, class_id) or None

The graph must have the signature written by :func:`davis_rig.models.rvt.onnx_export.export_step_onnx`
(checked on load; anything else raises :class:`~davis_rig.errors.ModelFormatError`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from davis_rig.errors import FormatError, MissingDependencyError, ModelFormatError, ShapeError
from davis_rig.events.histogram import NUM_BINS, WINDOW_US, stacked_histograms
from davis_rig.models.rvt.config import STAGE_STRIDES, RVTConfig
from davis_rig.models.rvt.onnx_export import INPUT_NAME, OUTPUT_NAME, state_input_names, state_output_names
from davis_rig.models.rvt.postprocess import postprocess
from davis_rig.types import RVT_HW, RVT_NMS_IOU

__all__ = ["RVTOnnxRunner", "GraphSignature", "SplitStep"]

_STATE_NAMES = state_input_names()
_STATE_OUT_NAMES = state_output_names()
_INPUT_CHANNELS = 2 * NUM_BINS
#: Files of PyTorch weights (what :mod:`davis_rig.models.rvt.checkpoint` loads), named when onnxruntime refuses one.
_PYTORCH_WEIGHT_SUFFIXES = (".ckpt", ".pt", ".pth", ".safetensors")

#: One recurrent state: 4 × (h, c), float32 numpy arrays [B, C_s, H_s, W_s].
States = list[tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class GraphSignature:
    """What the runner learned from the graph: sizes of the input, states and output.

    Attributes:
        in_res_hw: padded input (height, width), px.
        input_channels: histogram channels (20).
        state_channels: channels C_s of the 4 stages.
        state_hw: (height, width) of the 4 stages' state maps.
        num_anchors: anchors A of the decoded output (1680 at 256x320).
        num_outputs: values per anchor (5 + number of classes).
        batch: the fixed batch size, or ``None`` when the graph's batch is dynamic.
        config: the model config from the metadata, or ``None`` if the graph has none.
    """

    in_res_hw: tuple[int, int]
    input_channels: int
    state_channels: tuple[int, int, int, int]
    state_hw: tuple[tuple[int, int], ...]
    num_anchors: int
    num_outputs: int
    batch: int | None
    config: RVTConfig | None


def _dims(shape) -> list[int | None]:
    return [d if isinstance(d, int) and d > 0 else None for d in shape]


def _read_signature(session, path: Path) -> GraphSignature:
    """Check the graph's inputs/outputs against the RVT step signature; raise ModelFormatError otherwise."""
    inputs = {arg.name: arg for arg in session.get_inputs()}
    outputs = {arg.name: arg for arg in session.get_outputs()}
    want_out = [OUTPUT_NAME, *_STATE_OUT_NAMES]
    _check_names_and_types(inputs, outputs, path)
    config = _metadata_config(session, path)
    problems: list[str] = []
    channels, height, width = _input_size(inputs[INPUT_NAME], config, path, problems)
    state_channels, state_hw = _state_sizes(inputs, outputs, config, (height, width), problems)
    num_anchors = sum((height // s) * (width // s) for s in STAGE_STRIDES[1:])  # the head's levels: stages 2-4
    num_outputs = config.num_outputs if config is not None else _dims(outputs[OUTPUT_NAME].shape)[2]
    out_dims = _dims(outputs[OUTPUT_NAME].shape)
    if out_dims[1] not in (None, num_anchors) or out_dims[2] not in (None, num_outputs) or (num_outputs or 0) < 6:
        problems.append(f"detections: expected [B, {num_anchors}, 5 + classes], got {outputs[OUTPUT_NAME].shape}")
    batches = {_dims(arg.shape)[0] for arg in list(inputs.values()) + [outputs[n] for n in want_out]}
    if len(batches) != 1:
        problems.append(f"inconsistent batch dimensions {sorted(map(str, batches))}")
    if problems:
        raise ModelFormatError(f"{path}: wrong RVT step graph: " + "; ".join(problems))
    return GraphSignature(
        in_res_hw=(int(height), int(width)),
        input_channels=int(channels),
        state_channels=tuple(int(c) for c in state_channels),
        state_hw=tuple(state_hw),
        num_anchors=num_anchors,
        num_outputs=int(num_outputs),
        batch=batches.pop(),
        config=config,
    )


def _check_names_and_types(inputs: dict, outputs: dict, path: Path) -> None:
    """The step graph's input and output names, float tensors of rank 4 (rank 3: detections); ModelFormatError."""
    want_in = [INPUT_NAME, *_STATE_NAMES]
    want_out = [OUTPUT_NAME, *_STATE_OUT_NAMES]
    if sorted(inputs) != sorted(want_in) or not set(want_out) <= set(outputs):
        raise ModelFormatError(
            f"{path}: not an RVT step graph: expected inputs {want_in} and outputs {want_out}, "
            f"got inputs {list(inputs)} and outputs {list(outputs)}"
        )
    problems = []
    for name, arg in list(inputs.items()) + [(n, outputs[n]) for n in want_out]:
        if arg.type != "tensor(float)":
            problems.append(f"{name}: expected tensor(float), got {arg.type}")
        if len(arg.shape) != (3 if name == OUTPUT_NAME else 4):
            problems.append(f"{name}: expected rank {3 if name == OUTPUT_NAME else 4}, got shape {arg.shape}")
    if problems:
        raise ModelFormatError(f"{path}: wrong RVT step graph: " + "; ".join(problems))


def _metadata_config(session, path: Path) -> RVTConfig | None:
    """The :class:`RVTConfig` stored in the graph's ``config`` metadata, or ``None``; ModelFormatError if unreadable."""
    meta = session.get_modelmeta().custom_metadata_map
    if "config" not in meta:
        return None
    try:
        return RVTConfig.from_dict(json.loads(meta["config"]))
    except (json.JSONDecodeError, FormatError) as exc:
        raise ModelFormatError(f"{path}: unreadable config in the ONNX metadata: {exc}") from exc


def _input_size(histogram, config: RVTConfig | None, path: Path, problems: list[str]) -> tuple[int, int, int]:
    """``(channels, height, width)`` of the histogram input (from the config when there is one); what is wrong
    with it is appended to ``problems`` (ModelFormatError when its C/H/W are symbolic and there is no config)."""
    hist_shape = _dims(histogram.shape)
    if config is not None:
        channels, height, width = config.input_channels, *config.in_res_hw
    else:
        channels, height, width = hist_shape[1:]
    if None in (channels, height, width):
        raise ModelFormatError(f"{path}: histogram input {histogram.shape} has symbolic C/H/W and no config metadata")
    if hist_shape[1:] != [channels, height, width]:
        problems.append(f"histogram: expected [B, {channels}, {height}, {width}], got {histogram.shape}")
    if channels != _INPUT_CHANNELS:  # what stacked_histograms makes: 2 polarities x NUM_BINS bins
        problems.append(f"histogram: {channels} input channels, expected {_INPUT_CHANNELS} (2 polarities x "
                        f"{NUM_BINS} time bins, the stacked histogram)")
    if height < RVT_HW[0] or width < RVT_HW[1]:
        problems.append(f"histogram: input {height}x{width} (h x w) is smaller than the {RVT_HW[0]}x{RVT_HW[1]} "
                        "event frame (RVT pads it up, e.g. to 256x320)")
    return channels, height, width


def _state_sizes(inputs: dict, outputs: dict, config: RVTConfig | None, input_hw: tuple[int, int],
                 problems: list[str]) -> tuple[list, list[tuple[int, int]]]:
    """Channels C_s and map sizes (H/s, W/s) of the 4 stages' states, checked on every ``h``/``c`` input and
    output (the channels from the config, else from the graph); mismatches are appended to ``problems``."""
    state_channels, state_hw = [], []
    for stage, stride in enumerate(STAGE_STRIDES, start=1):
        hw = (input_hw[0] // stride, input_hw[1] // stride)
        expected_c = config.stage_dims[stage - 1] if config is not None else None
        for name in (f"h{stage}", f"c{stage}", f"h{stage}_out", f"c{stage}_out"):
            arg = inputs.get(name) or outputs[name]
            dims = _dims(arg.shape)
            if expected_c is None:
                expected_c = dims[1]
            if dims[1:] != [expected_c, *hw]:
                problems.append(f"{name}: expected [B, {expected_c}, {hw[0]}, {hw[1]}], got {arg.shape}")
        if expected_c is None:
            problems.append(f"h{stage}: symbolic channel dimension and no config metadata")
        state_channels.append(expected_c)
        state_hw.append(hw)
    return state_channels, state_hw


def _session_options(ort, intra_op_threads: int | None, allow_spinning: bool):
    options = ort.SessionOptions()
    if intra_op_threads is not None:
        options.intra_op_num_threads = int(intra_op_threads)
        options.inter_op_num_threads = 1
    options.log_severity_level = 3
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if allow_spinning else "0")
    return options


class SplitStep:
    """One RVT step as three onnxruntime sessions, ``pre`` → ``recur`` → ``head`` (:mod:`.onnx_split`).

    ``recur`` alone carries the states, so a caller can run ``pre`` of the next window and ``head`` of the
    previous one beside ``recur`` of the current one, each in its own thread (onnxruntime releases the GIL).
    Chained, the three calls compute what :meth:`RVTOnnxRunner.step` computes: the same nodes and weights.
    Made by :meth:`RVTOnnxRunner.split`; takes checked inputs (:meth:`RVTOnnxRunner.prepare_histogram`, states
    shaped like :meth:`RVTOnnxRunner.initial_states`).
    """

    def __init__(self, runner: "RVTOnnxRunner", threads: tuple[int | None, int | None, int | None]):
        import onnxruntime as ort

        from davis_rig.models.rvt.onnx_split import split_step_file

        parts = split_step_file(runner.path)
        self._x1 = parts.x1_name
        self._sessions = [
            ort.InferenceSession(part.SerializeToString(), providers=runner.providers,
                                 sess_options=_session_options(ort, part_threads, runner.allow_spinning))
            for part, part_threads in zip((parts.pre, parts.recur, parts.head), threads)
        ]

    def pre(self, x: np.ndarray) -> np.ndarray:
        """Stage 1 before its LSTM: padded float32 histogram [B, 20, H, W] → float32 [B, C_1, H/4, W/4]."""
        return self._sessions[0].run(None, {INPUT_NAME: x})[0]

    def recur(self, x1: np.ndarray, states: States) -> States:
        """The recurrent part: :meth:`pre`'s output and the 4 (h, c) states → the 4 new (h, c) states."""
        feeds = {self._x1: x1}
        for stage, (h_state, c_state) in enumerate(states, start=1):
            feeds[f"h{stage}"] = h_state
            feeds[f"c{stage}"] = c_state
        results = self._sessions[1].run(list(_STATE_OUT_NAMES), feeds)
        return [(results[2 * i], results[2 * i + 1]) for i in range(4)]

    def head(self, states: States) -> np.ndarray:
        """PAFPN + YOLOX head of the new states' h2, h3, h4 → decoded float32 [B, A, 5 + classes]."""
        feeds = {f"h{stage}_out": states[stage - 1][0] for stage in (2, 3, 4)}
        return self._sessions[2].run([OUTPUT_NAME], feeds)[0]


class RVTOnnxRunner:
    """onnxruntime session for one RVT recurrent step, with explicit numpy states.

    Args:
        path: the ``.onnx`` file written by ``export_step_onnx``.
        providers: onnxruntime execution providers; default ``["CPUExecutionProvider"]``.
        intra_op_threads: onnxruntime intra-op threads; default: onnxruntime's choice (the physical cores).
        allow_spinning: let idle intra-op threads busy-wait for the next operator (onnxruntime's default). Off
            here: on a shared CPU the spinning threads take the cores from the threads that read, histogram and
            post-process beside the inference (benchmarks/model.py measures both).

    Raises:
        MissingDependencyError: onnxruntime is not installed.
        ModelFormatError: the file is not a loadable ONNX model or has the wrong inputs/outputs/shapes.
    """

    def __init__(
        self,
        path: str | Path,
        providers: Sequence[str] | None = None,
        intra_op_threads: int | None = None,
        *,
        allow_spinning: bool = False,
    ):
        try:
            import onnxruntime as ort
        except ImportError as exc:  # pragma: no cover - onnxruntime is a core dependency
            raise MissingDependencyError("RVTOnnxRunner needs onnxruntime: pip install onnxruntime") from exc
        self.path = Path(path)
        self.providers = list(providers or ["CPUExecutionProvider"])
        self.allow_spinning = bool(allow_spinning)
        options = _session_options(ort, intra_op_threads, self.allow_spinning)
        self._splits: dict = {}
        try:
            self._session = ort.InferenceSession(str(self.path), sess_options=options, providers=self.providers)
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph/NoSuchFile types
            hint = (" (PyTorch weights? scoring needs an RVT step ONNX: export one with tools/convert_checkpoint.py "
                    "--onnx)" if self.path.suffix.lower() in _PYTORCH_WEIGHT_SUFFIXES else "")
            raise ModelFormatError(f"{self.path}: onnxruntime cannot load the model: {exc}{hint}") from exc
        self.signature = _read_signature(self._session, self.path)

    @property
    def config(self) -> RVTConfig | None:
        """The model config stored in the graph's metadata (``None`` if absent)."""
        return self.signature.config

    # ------------------------------------------------------------------ states
    def initial_states(self, batch: int = 1) -> States:
        """Zero LSTM states: 4 × (h, c), float32 [B, C_s, H_s, W_s]."""
        return [
            (np.zeros((batch, c, *hw), np.float32), np.zeros((batch, c, *hw), np.float32))
            for c, hw in zip(self.signature.state_channels, self.signature.state_hw)
        ]

    def _check_states(self, states, batch: int) -> States:
        if len(states) != 4:
            raise ShapeError(f"states: expected 4 (h, c) pairs, got {len(states)}")
        checked = []
        for stage, (pair, c, hw) in enumerate(zip(states, self.signature.state_channels, self.signature.state_hw), 1):
            h_state, c_state = (np.ascontiguousarray(a, dtype=np.float32) for a in pair)
            expected = (batch, c, *hw)
            if h_state.shape != expected or c_state.shape != expected:
                raise ShapeError(
                    f"state of stage {stage}: expected h, c {expected}, got {h_state.shape}, {c_state.shape}"
                )
            checked.append((h_state, c_state))
        return checked

    def prepare_histogram(self, hist) -> np.ndarray:
        """The graph's input for ``hist``: float32 [B, 20, H, W], zero-padded bottom/right (see :meth:`step`).

        Raises:
            ShapeError: wrong channels or resolution.
        """
        hist = np.asarray(hist)
        channels = self.signature.input_channels
        height, width = self.signature.in_res_hw
        if hist.ndim != 4 or hist.shape[1] != channels:
            raise ShapeError(f"histogram: expected [B, {channels}, H, W], got shape {hist.shape}")
        if hist.shape[2:] == (height, width):
            return np.ascontiguousarray(hist, dtype=np.float32)
        if hist.shape[2] > height or hist.shape[3] > width:
            raise ShapeError(
                f"histogram: expected [B, {channels}, {RVT_HW[0]}, {RVT_HW[1]}] (padded automatically) or "
                f"[B, {channels}, {height}, {width}], got shape {hist.shape}"
            )
        if hist.shape[2:] != RVT_HW:
            raise ShapeError(
                f"histogram: expected spatial size {RVT_HW} or {(height, width)}, got {hist.shape[2:]}"
            )
        padded = np.zeros((hist.shape[0], channels, height, width), np.float32)
        padded[:, :, : hist.shape[2], : hist.shape[3]] = hist
        return padded

    def split(self, pre_threads: int | None = 1, recur_threads: int | None = 1,
              head_threads: int | None = 1) -> SplitStep:
        """The step as three sessions that a pipeline can run side by side (:class:`SplitStep`); cached.

        Args:
            pre_threads, recur_threads, head_threads: onnxruntime intra-op threads of each part's session
                (``None``: onnxruntime's choice).

        Raises:
            ModelFormatError: the graph does not split (:func:`~davis_rig.models.rvt.onnx_split.split_step_graph`);
                :meth:`step` still runs it whole.
        """
        key = tuple(None if t is None else int(t) for t in (pre_threads, recur_threads, head_threads))
        if key not in self._splits:
            self._splits[key] = SplitStep(self, key)
        return self._splits[key]

    # ------------------------------------------------------------------ inference
    def step(self, hist, states: States | None = None) -> tuple[np.ndarray, States]:
        """Run one recurrent step.

        Args:
            hist: uint8 or float histogram [B, 20, 240, 304] (zero-padded bottom/right here) or already
                padded [B, 20, 256, 320].
            states: the previous 4 × (h, c) float32 states, or ``None`` for zeros.

        Returns:
            (decoded float32 [B, A, 5 + classes] — cx, cy, w, h in px, obj, class probs — and the new states).

        Raises:
            ShapeError: wrong histogram resolution/channels or state shapes, or a batch the graph cannot take.
        """
        x = self.prepare_histogram(hist)
        batch = x.shape[0]
        if self.signature.batch is not None and batch != self.signature.batch:
            raise ShapeError(f"histogram: this graph has a fixed batch of {self.signature.batch}, got {batch}")
        states = self.initial_states(batch) if states is None else self._check_states(states, batch)
        feeds = {INPUT_NAME: x}
        for stage, (h_state, c_state) in enumerate(states, start=1):
            feeds[f"h{stage}"] = h_state
            feeds[f"c{stage}"] = c_state
        results = self._session.run([OUTPUT_NAME, *_STATE_OUT_NAMES], feeds)
        new_states = [(results[1 + 2 * i], results[2 + 2 * i]) for i in range(4)]
        return results[0], new_states

    def score_stream(
        self,
        x,
        y,
        t_us,
        p,
        window_end_us,
        conf_threshold: float = 0.1,
        *,
        nms_threshold: float = RVT_NMS_IOU,
        window_us: int = WINDOW_US,
        states: States | None = None,
        return_states: bool = False,
        correct_time: bool = False,
    ) -> list[np.ndarray | None] | tuple[list[np.ndarray | None], States]:
        """Score a time-sorted event stream: one histogram + step + postprocess per window, states carried.

        Args:
            x, y: event columns/rows in the 304x240 RVT frame, integer [N] (crop DAVIS346 events first).
            t_us: timestamps, int µs [N], non-decreasing (or see ``correct_time``).
            p: polarities {0, 1}, integer [N].
            window_end_us: window ends, int µs [T]; window i holds ``end_i - window_us <= t <= end_i``.
            conf_threshold: postprocess confidence threshold (obj · class prob).
            nms_threshold: class-wise NMS IoU threshold.
            window_us: window duration, µs.
            states: initial states (batch 1), ``None`` = zeros (start of a sequence).
            return_states: also return the states after the last window (to continue a long recording
                chunk by chunk).
            correct_time: make out-of-order timestamps non-decreasing first, as the official reader does
                (running maximum over the given stream, ``events.histogram.monotonic_timestamps``). To score a
                long recording chunk by chunk with the whole recording's correction, start each chunk at the
                first event whose corrected time reaches its first window's start (the events at that instant
                belong to both chunks): that event is not late, so each chunk's own running maximum equals the
                whole recording's.

        Returns:
            One entry per window: float32 [K, 7] ``(x1, y1, x2, y2, obj, class_conf, class_id)`` by decreasing
            obj · class_conf, or ``None``; with ``return_states`` the tuple ``(detections, states)``.

        Raises:
            ShapeError, FormatError: bad event columns (see ``stacked_histogram``) or states.
        """
        ends = np.atleast_1d(np.asarray(window_end_us, dtype=np.int64))
        hists = stacked_histograms((x, y, t_us, p), ends, window_us=window_us, correct_time=correct_time)
        detections: list[np.ndarray | None] = []
        for hist in hists:
            decoded, states = self.step(hist[None], states)
            detections.extend(postprocess(decoded, conf_threshold, nms_threshold))
        if return_states:
            return detections, states if states is not None else self.initial_states(1)
        return detections

    def __repr__(self) -> str:
        name = self.config.name if self.config is not None else "unknown config"
        return f"RVTOnnxRunner({str(self.path)!r}, {name}, in_res_hw={self.signature.in_res_hw})"
