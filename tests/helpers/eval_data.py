"""Shared helpers of the labeler / evaluation / cli tests: tiny ONNX graphs with known outputs and small sessions
recorded through the virtual DAVIS346 (encoder → fake USB backend → Davis346 → record_session)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from davis_rig.types import DAVIS346_HW, make_events

#: Anchors of the RVT head at the padded 256x320 input (strides 8, 16, 32).
RVT_ANCHORS = 32 * 40 + 16 * 20 + 8 * 10
#: Frame → YOLO 640x640 letterbox of a 346x260 frame: gain and padding (Ultralytics rounding).
YOLO_GAIN = 640 / 346
YOLO_PAD_XY = (0, int(round((640 - round(260 * YOLO_GAIN)) / 2 - 0.1)))


def _save(graph, path: Path, metadata: dict | None = None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, str(value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return Path(path)


def _constant_plus_zero_times_input(input_name: str, rank: int, constant: np.ndarray, out_name: str):
    """Nodes computing ``constant + 0 * sum(input)`` (the output depends on the input only formally)."""
    const = helper.make_tensor("const", TensorProto.FLOAT, constant.shape, constant.astype(np.float32).ravel())
    zero = helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0])
    nodes = [
        helper.make_node("ReduceSum", [input_name], ["total"], keepdims=0, noop_with_empty_axes=0),
        helper.make_node("Mul", ["total", "zero"], ["nothing"]),
        helper.make_node("Add", ["const", "nothing"], [out_name]),
    ]
    return nodes, [const, zero]


def oracle_rvt_onnx(path: Path, rows: np.ndarray) -> Path:
    """A graph with the RVT step signature (channels 8/8/16/32, batch 1) whose decoded output is fixed.

    Args:
        path: output file.
        rows: float [R, 7] decoded rows ``(cx, cy, w, h, obj, p_car, p_pedestrian)`` put in the first R anchors;
            the other anchors have obj = 0.
    """
    decoded = np.zeros((1, RVT_ANCHORS, 7), np.float32)
    decoded[0, : len(rows)] = rows
    inputs = [helper.make_tensor_value_info("histogram", TensorProto.FLOAT, [1, 20, 256, 320])]
    outputs = [helper.make_tensor_value_info("detections", TensorProto.FLOAT, [1, RVT_ANCHORS, 7])]
    nodes, inits = _constant_plus_zero_times_input("histogram", 4, decoded, "detections")
    for stage, (stride, channels) in enumerate(zip((4, 8, 16, 32), (8, 8, 16, 32)), start=1):
        shape = [1, channels, 256 // stride, 320 // stride]
        for kind in ("h", "c"):
            inputs.append(helper.make_tensor_value_info(f"{kind}{stage}", TensorProto.FLOAT, shape))
            outputs.append(helper.make_tensor_value_info(f"{kind}{stage}_out", TensorProto.FLOAT, shape))
            nodes.append(helper.make_node("Identity", [f"{kind}{stage}"], [f"{kind}{stage}_out"]))
    return _save(helper.make_graph(nodes, "oracle_rvt", inputs, outputs, initializer=inits), path)


def yolo_onnx(path: Path, output: np.ndarray, *, input_hw=(640, 640), metadata: dict | None = None) -> Path:
    """A YOLO-like graph: input ``images`` [1, 3, H, W], one output equal to ``output`` (any layout)."""
    inputs = [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, *input_hw])]
    outputs = [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(output.shape))]
    nodes, inits = _constant_plus_zero_times_input("images", 4, np.asarray(output, np.float32), "output0")
    return _save(helper.make_graph(nodes, "yolo", inputs, outputs, initializer=inits), path, metadata)


def frame_box_to_yolo_input(box_xyxy) -> np.ndarray:
    """A frame box (x1, y1, x2, y2) in the 640x640 letterboxed input of a 346x260 frame."""
    x1, y1, x2, y2 = box_xyxy
    px, py = YOLO_PAD_XY
    g = YOLO_GAIN
    return np.array([x1 * g + px, y1 * g + py, x2 * g + px, y2 * g + py], np.float64)


def yolov8_output(boxes_xyxy, scores, num_classes=1, anchors=50) -> np.ndarray:
    """[1, 4 + nc, anchors]: the given boxes (input px) in the first anchors, class 0, other anchors score 0."""
    out = np.zeros((1, 4 + num_classes, anchors), np.float32)
    for i, (box, score) in enumerate(zip(boxes_xyxy, scores)):
        x1, y1, x2, y2 = box
        out[0, :4, i] = [(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1]
        out[0, 4, i] = score
    return out


def moving_blob_events(rng, duration_us: int, rate_hz: float, t0_us: int = 0, box=(120, 60, 200, 220)):
    """Time-sorted events of a blob (the "person" box x1, y1, x2, y2 on the sensor) plus 10 % background noise."""
    n = int(duration_us * rate_hz / 1e6)
    t = np.sort(rng.integers(t0_us, t0_us + duration_us, n))
    x1, y1, x2, y2 = box
    inside = rng.random(n) < 0.9
    x = np.where(inside, rng.integers(x1, x2, n), rng.integers(0, DAVIS346_HW[1], n))
    y = np.where(inside, rng.integers(y1, y2, n), rng.integers(0, DAVIS346_HW[0], n))
    return make_events(t, x, y, rng.integers(0, 2, n))


def aps_frames(rng, t0_us: int, duration_us: int, interval_us: int = 40_000, exposure_us: int = 4_000):
    """Full-sensor ApsFrames every ``interval_us`` (random 10-bit pixels << 6)."""
    from davis_rig.protocol.frames import ApsFrame

    frames = []
    for t in range(t0_us + 5_000, t0_us + duration_us - interval_us, interval_us):
        pixels = (rng.integers(0, 1024, DAVIS346_HW) << 6).astype(np.uint16)
        frames.append(ApsFrame(pixels, 0, 0, t, t + 100, t + 100 + exposure_us, t + 2_000 + exposure_us))
    return frames


def record_scene(path: Path, events: np.ndarray, frames) -> Path:
    """Record events and frames into ``path`` through the virtual DAVIS346 and the real capture stack."""
    from davis_rig.device.camera import Davis346
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.session.record import record_session
    from davis_rig.usb.sources import EncodedSource
    from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

    source = EncodedSource(events, frames, layout=SensorLayout.davis346(), paced=False)
    stop = threading.Event()

    def progress(p):
        if p.events >= len(events) and p.frames >= len(frames):
            stop.set()

    with Davis346.open(backend=VirtualDavis346Backend(VirtualDavis346(source=source)), queue_transfers=1 << 14) as cam:
        summary = record_session(cam, path, stop_event=stop, progress=progress, progress_interval_s=0.02,
                                 duration_s=60, journal=False)
    assert summary.events == len(events) and summary.frames == len(frames), summary
    return Path(path)


#: The "person" on the sensor in :func:`scene_session` (x1, y1, x2, y2), and in the centred RVT crop.
PERSON_BOX = (120, 60, 200, 220)
PERSON_BOX_CROP = (120 - 21, 60 - 10, 200 - 21, 220 - 10)
SCENE_US = 2_000_000
_CACHE: dict = {}


def scene_session(directory: Path, name: str = "scene.h5") -> Path:
    """A fresh copy of a 2 s session (blob events at 200 kev/s, 49 APS frames at 25 fps) recorded through the
    virtual DAVIS346 once per test process."""
    import shutil

    if "scene" not in _CACHE:
        rng = np.random.default_rng(11)
        source = Path(directory) / "_recorded_scene.h5"
        record_scene(source, moving_blob_events(rng, SCENE_US, 200_000, box=PERSON_BOX), aps_frames(rng, 0, SCENE_US))
        _CACHE["scene"] = source
    target = Path(directory) / name
    shutil.copyfile(_CACHE["scene"], target)
    return target


def person_yolo(directory: Path, score: float = 0.9) -> Path:
    """A YOLOv8-layout ONNX (class 'person') that always finds :data:`PERSON_BOX`."""
    out = yolov8_output([frame_box_to_yolo_input(PERSON_BOX)], [score])
    return yolo_onnx(Path(directory) / "person_yolo.onnx", out, metadata={"names": "{0: 'person'}"})


def person_rvt(directory: Path, *, shift_px: float = 0.0, score: float = 0.9, extra_rows=(), name="rvt.onnx") -> Path:
    """An oracle RVT step ONNX whose pedestrian box is :data:`PERSON_BOX_CROP` shifted by ``shift_px`` in x,
    with obj = ``score`` and p_pedestrian = 1 (so obj · class = ``score``); ``score=0`` gives no detections."""
    x1, y1, x2, y2 = PERSON_BOX_CROP
    rows = [[(x1 + x2) / 2 + shift_px, (y1 + y2) / 2, x2 - x1, y2 - y1, score, 0.0, 1.0], *extra_rows]
    return oracle_rvt_onnx(Path(directory) / name, np.array(rows, np.float32))


def sha256(path: Path) -> str:
    """Hex digest of a file (to show a file was left untouched)."""
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
