"""Pedestrian labels from APS frames with a YOLO detector exported to ONNX (onnxruntime, no torch).

Supported output layouts (``layout="auto"`` picks one from the output shape and the ONNX metadata):

* ``"yolov5"`` — ``[B, N, 5 + nc]`` rows ``(cx, cy, w, h, obj, class probs…)``, score = obj · class prob
  (YOLOv5 ``export.py``; YOLOv7 ``export.py --grid`` without ``--end2end``);
* ``"yolov8"`` — ``[B, 4 + nc, N]`` rows ``(cx, cy, w, h, class probs…)`` transposed, score = class prob
  (Ultralytics YOLOv8/11 ``model.export(format="onnx")``);
* ``"yolov7-nms"`` — ``[K, 7]`` rows ``(batch, x1, y1, x2, y2, class, score)`` (YOLOv7
  ``--grid --end2end --max-wh N``, the onnxruntime variant: NMS inside the graph);
* ``"ultralytics-nms"`` — ``[B, K, 6]`` rows ``(x1, y1, x2, y2, score, class)`` (Ultralytics ``nms=True``).

A YOLOv7 ``export.py`` run without ``--grid`` (and without ``--end2end``) is not supported: its outputs are the raw
per-level head tensors ``[B, 3, H_l, W_l, 5 + nc]`` (logits before the sigmoid and the anchor grid decoding); such a
model is refused with a :class:`~davis_rig.errors.ModelFormatError` that asks for a re-export with ``--grid``
(optionally with ``--end2end --max-wh N``).

Pre-processing like Ultralytics' ``LetterBox`` (keep aspect, scale up, centre, pad with 114) on the frame as
8-bit grey repeated into 3 channels (the DAVIS346 APS is monochrome), RGB order, ``/ 255``, NCHW float32.
Post-processing: score threshold, class-wise greedy NMS (IoU > ``iou`` suppressed; torchvision semantics,
the same kernel as RVT's post-processing), at most ``max_det`` boxes, boxes mapped back to frame pixels.
"""

from __future__ import annotations

import ast
import json
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Final, Sequence

import numpy as np

from davis_rig.errors import FormatError, MissingDependencyError, ModelFormatError, ShapeError

__all__ = ["AUTO_LAYOUT", "COCO_PERSON", "LAYOUTS", "YOLO_CONF_THRESHOLD", "YOLO_NMS_IOU", "YoloLayout",
           "YoloOnnxDetector", "letterbox", "to_gray_u8"]


class YoloLayout(StrEnum):
    """The output layouts of YOLO ONNX exports the labeler reads (module docstring)."""

    YOLOV5 = "yolov5"
    YOLOV8 = "yolov8"
    YOLOV7_NMS = "yolov7-nms"
    ULTRALYTICS_NMS = "ultralytics-nms"


#: Every layout name, in :class:`YoloLayout` order.
LAYOUTS: Final = tuple(layout.value for layout in YoloLayout)
#: ``layout=`` / ``--layout`` value that picks the layout from the output shape and the ONNX metadata.
AUTO_LAYOUT: Final = "auto"
#: Default score threshold and class-wise NMS IoU of the labeler (YOLOv5 ``detect.py``'s ``conf_thres``/``iou_thres``).
YOLO_CONF_THRESHOLD: Final = 0.25
YOLO_NMS_IOU: Final = 0.45
#: COCO class 0 is "person" in every YOLOv5/v7/v8 COCO model.
COCO_PERSON: Final = "person"
PAD_VALUE: Final = 114


def to_gray_u8(image) -> np.ndarray:
    """An APS frame (or any image) as 8-bit grey, uint8 [H, W].

    Args:
        image: uint16 [H, W] (libcaer 16-bit scale: the top 8 bits are kept), uint8 [H, W], or uint8 [H, W, 3]
            (converted with the BT.601 luma weights).

    Returns:
        uint8 [H, W] (a new array).

    Raises:
        ShapeError: not 2-D or 3-channel; FormatError: another dtype.
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        if image.dtype != np.uint8:
            raise FormatError(f"image: a colour image must be uint8, got {image.dtype}")
        luma = image.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
        return np.clip(np.rint(luma), 0, 255).astype(np.uint8)
    if image.ndim != 2:
        raise ShapeError(f"image: expected [H, W] or [H, W, 3], got shape {image.shape}")
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    if image.dtype == np.uint8:
        return image.copy()
    raise FormatError(f"image: expected uint16 (APS) or uint8, got {image.dtype}")


def letterbox(gray: np.ndarray, size_hw: tuple[int, int]) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Ultralytics ``LetterBox(auto=False, scaleup=True, center=True)`` of a grey image.

    Args:
        gray: uint8 [H, W].
        size_hw: network input (height, width), px.

    Returns:
        ``(image uint8 [h_in, w_in], gain, (pad_left, pad_top))``; a frame point ``(x, y)`` lands at
        ``(x · gain + pad_left, y · gain + pad_top)``.
    """
    import cv2

    h, w = gray.shape
    new_h, new_w = size_hw
    gain = min(new_h / h, new_w / w)
    unpad_w, unpad_h = int(round(w * gain)), int(round(h * gain))
    dw, dh = (new_w - unpad_w) / 2, (new_h - unpad_h) / 2
    resized = gray if (unpad_w, unpad_h) == (w, h) else cv2.resize(gray, (unpad_w, unpad_h), interpolation=cv2.INTER_LINEAR)
    top, bottom = int(round(dh - 0.1)), int(round(dh + 0.1))
    left, right = int(round(dw - 0.1)), int(round(dw + 0.1))
    out = cv2.copyMakeBorder(resized, top, bottom, left, right, cv2.BORDER_CONSTANT, value=PAD_VALUE)
    return out, gain, (left, top)


def _parse_names(meta: dict) -> list[str] | None:
    raw = meta.get("names")
    if raw is None:
        return None
    try:
        names = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        try:
            names = json.loads(raw)
        except json.JSONDecodeError:
            return None
    if isinstance(names, dict):
        return [str(names[k]) for k in sorted(names, key=int)]
    if isinstance(names, (list, tuple)):
        return [str(n) for n in names]
    return None


def _check_not_raw_heads(path: Path, outputs) -> None:
    """Refuse a model whose first output is a raw per-level head ``[B, 3, H_l, W_l, 5 + nc]``.

    That is what YOLOv7 ``export.py`` writes without ``--grid`` (one such output per detection level, logits
    before the sigmoid and the anchor-grid decoding); the labeler does not decode it.

    Raises:
        ModelFormatError: naming the outputs and the export options that give a supported layout.
    """
    shape = outputs[0].shape
    last = shape[-1] if len(shape) == 5 else None
    if isinstance(last, int) and last >= 6:
        shapes = ", ".join(f"{o.name} {list(o.shape)}" for o in outputs)
        raise ModelFormatError(
            f"{path}: raw per-level YOLO head outputs ({shapes}), as YOLOv7 export.py writes without --grid; "
            "re-export with `python export.py --grid` (or `--grid --end2end --max-wh 640` for onnxruntime NMS "
            "inside the graph)")


@dataclass(frozen=True)
class _Io:
    input_name: str
    input_hw: tuple[int, int]
    output_name: str
    output_shape: tuple


class YoloOnnxDetector:
    """A YOLO ONNX model run with onnxruntime on grey frames.

    Args:
        path: the ``.onnx`` file.
        layout: one of :data:`LAYOUTS` or ``"auto"``.
        class_names: names of the model's classes (default: the ONNX ``names`` metadata, else COCO order is
            assumed only for the class ``person`` = 0).
        conf_threshold: keep boxes with score ≥ this.
        iou_threshold: class-wise NMS IoU threshold (boxes with IoU > it are suppressed).
        max_det: keep at most this many boxes per frame (highest scores).
        intra_op_threads: onnxruntime threads (default: its own choice).

    Raises:
        MissingDependencyError: onnxruntime is missing.
        ModelFormatError: not loadable, not one image input [1|B, 3, H, W], raw per-level head outputs (YOLOv7
            exported without ``--grid``), or an output no layout fits.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        layout: str = AUTO_LAYOUT,
        class_names: Sequence[str] | None = None,
        conf_threshold: float = YOLO_CONF_THRESHOLD,
        iou_threshold: float = YOLO_NMS_IOU,
        max_det: int = 300,
        intra_op_threads: int | None = None,
    ):
        try:
            import onnxruntime as ort
        except ImportError as exc:  # pragma: no cover - core dependency
            raise MissingDependencyError("the YOLO labeler needs onnxruntime: pip install onnxruntime") from exc
        self.path = Path(path)
        if not self.path.is_file():
            raise ModelFormatError(f"{self.path}: no such YOLO ONNX file")
        options = ort.SessionOptions()
        options.log_severity_level = 3
        if intra_op_threads is not None:
            options.intra_op_num_threads = int(intra_op_threads)
        try:
            self._session = ort.InferenceSession(str(self.path), sess_options=options,
                                                 providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types
            raise ModelFormatError(f"{self.path}: onnxruntime cannot load the model: {exc}") from exc
        self.metadata = dict(self._session.get_modelmeta().custom_metadata_map)
        self.io = self._read_io()
        names = list(class_names) if class_names is not None else _parse_names(self.metadata)
        self.class_names = names
        self.layout = self._resolve_layout(layout)
        self.conf_threshold = float(conf_threshold)
        self.iou_threshold = float(iou_threshold)
        self.max_det = int(max_det)

    def _read_io(self) -> _Io:
        inputs = self._session.get_inputs()
        outputs = self._session.get_outputs()
        if len(inputs) != 1:
            raise ModelFormatError(f"{self.path}: expected one image input, got {[i.name for i in inputs]}")
        shape = inputs[0].shape
        if len(shape) != 4 or shape[1] not in (3, "3") or inputs[0].type != "tensor(float)":
            raise ModelFormatError(f"{self.path}: expected a float image input [B, 3, H, W], got "
                                   f"{inputs[0].type} {shape}")
        _check_not_raw_heads(self.path, outputs)
        h, w = shape[2], shape[3]
        if not (isinstance(h, int) and isinstance(w, int)):
            size = self.metadata.get("imgsz")
            try:
                h, w = ast.literal_eval(size) if size else (640, 640)
            except (ValueError, SyntaxError) as exc:
                raise ModelFormatError(f"{self.path}: dynamic input size and unreadable imgsz {size!r}") from exc
        return _Io(inputs[0].name, (int(h), int(w)), outputs[0].name, tuple(outputs[0].shape))

    def _resolve_layout(self, layout: str) -> YoloLayout:
        if layout != AUTO_LAYOUT:
            if layout not in LAYOUTS:
                raise ValueError(f"layout: expected {AUTO_LAYOUT!r} or one of {LAYOUTS}, got {layout!r}")
            return YoloLayout(layout)
        shape = self.io.output_shape
        ultralytics = self.metadata.get("author", "").lower().startswith("ultralytics")
        if len(shape) == 2 and shape[1] == 7:
            return YoloLayout.YOLOV7_NMS
        if len(shape) != 3:
            raise ModelFormatError(f"{self.path}: output {self.io.output_name} {shape}: no YOLO layout fits "
                                   f"({LAYOUTS}); pass layout= explicitly")
        if ultralytics:
            args = self.metadata.get("args", "")
            nms = "'nms': True" in args or '"nms": true' in args
            return YoloLayout.ULTRALYTICS_NMS if nms else YoloLayout.YOLOV8
        a, b = shape[1], shape[2]
        nc = len(self.class_names) if self.class_names else None
        if isinstance(a, int) and isinstance(b, int):
            if nc is not None and a == 4 + nc and b != 5 + nc:
                return YoloLayout.YOLOV8
            if nc is not None and b == 5 + nc:
                return YoloLayout.YOLOV5
            return YoloLayout.YOLOV8 if a < b else YoloLayout.YOLOV5
        if isinstance(b, int) and b >= 6:
            return YoloLayout.YOLOV5
        if isinstance(a, int) and a >= 5:
            return YoloLayout.YOLOV8
        raise ModelFormatError(f"{self.path}: cannot tell the YOLO layout of output {shape}; pass layout=")

    # ----------------------------------------------------------------------------------------------
    def class_ids(self, names: Sequence[str | int]) -> list[int]:
        """Class indices of the given names (or integer ids, passed through).

        Raises:
            ModelFormatError: a name the model does not have.
        """
        ids = []
        for name in names:
            if isinstance(name, int) or str(name).isdigit():
                ids.append(int(name))
            elif self.class_names is not None and name in self.class_names:
                ids.append(self.class_names.index(name))
            elif self.class_names is None and name == COCO_PERSON:
                ids.append(0)
            else:
                raise ModelFormatError(f"{self.path}: class {name!r} not in the model's classes {self.class_names}")
        return ids

    def preprocess(self, image) -> tuple[np.ndarray, float, tuple[int, int]]:
        """Letterboxed float32 [1, 3, H_in, W_in] input, gain and padding (see :func:`letterbox`)."""
        boxed, gain, pad = letterbox(to_gray_u8(image), self.io.input_hw)
        x = np.repeat((boxed.astype(np.float32) / np.float32(255))[None, None], 3, axis=1)
        return np.ascontiguousarray(x), gain, pad

    def decode(self, output: np.ndarray) -> np.ndarray:
        """Raw network output of one image → candidate rows ``(x1, y1, x2, y2, score, class)`` in input px.

        Raises:
            ShapeError: the output does not fit the layout.
        """
        out = np.asarray(output, dtype=np.float32)
        if self.layout == YoloLayout.YOLOV7_NMS:
            if out.ndim != 2 or out.shape[1] != 7:
                raise ShapeError(f"yolov7-nms output: expected [K, 7], got {out.shape}")
            rows = out[out[:, 0] == 0]
            return np.stack([rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], rows[:, 6], rows[:, 5]], axis=1)
        if out.ndim != 3 or out.shape[0] < 1:
            raise ShapeError(f"{self.layout} output: expected [B, ., .], got {out.shape}")
        if self.layout == YoloLayout.ULTRALYTICS_NMS:
            if out.shape[2] != 6:
                raise ShapeError(f"ultralytics-nms output: expected [B, K, 6], got {out.shape}")
            return out[0].copy()
        if self.layout == YoloLayout.YOLOV8:
            pred = out[0].T  # [N, 4 + nc]
            if pred.shape[1] < 5:
                raise ShapeError(f"yolov8 output: expected [B, 4 + nc, N], got {out.shape}")
            scores_all = pred[:, 4:]
        else:
            pred = out[0]
            if pred.shape[1] < 6:
                raise ShapeError(f"yolov5 output: expected [B, N, 5 + nc], got {out.shape}")
            scores_all = pred[:, 5:] * pred[:, 4:5]
        cls = np.argmax(scores_all, axis=1)
        score = np.take_along_axis(scores_all, cls[:, None], axis=1)[:, 0]
        cx, cy, w, h = pred[:, 0], pred[:, 1], pred[:, 2] / 2, pred[:, 3] / 2
        return np.stack([cx - w, cy - h, cx + w, cy + h, score, cls.astype(np.float32)], axis=1)

    def detect(self, image, classes: Sequence[int] | None = None) -> np.ndarray:
        """Detect objects in one frame.

        Args:
            image: uint16 APS [H, W], uint8 grey [H, W] or uint8 RGB [H, W, 3].
            classes: keep only these class indices (``None``: all).

        Returns:
            float32 [K, 6] ``(x1, y1, x2, y2, score, class)`` in frame pixels (clipped to the frame), by
            decreasing score.
        """
        from davis_rig.models.rvt.postprocess import batched_nms

        x, gain, (pad_x, pad_y) = self.preprocess(image)
        output = self._session.run([self.io.output_name], {self.io.input_name: x})[0]
        rows = self.decode(output)
        keep = rows[:, 4] >= np.float32(self.conf_threshold)
        if classes is not None:
            keep &= np.isin(rows[:, 5].astype(np.int64), np.asarray(list(classes), dtype=np.int64))
        rows = rows[keep]
        if len(rows) and self.layout not in (YoloLayout.YOLOV7_NMS, YoloLayout.ULTRALYTICS_NMS):  # no NMS inside
            order = batched_nms(rows[:, :4], rows[:, 4], rows[:, 5].astype(np.int64), self.iou_threshold)
            rows = rows[order]
        else:
            rows = rows[np.argsort(-rows[:, 4], kind="stable")]
        rows = rows[: self.max_det].copy()
        height, width = np.asarray(image).shape[:2]
        rows[:, [0, 2]] = np.clip((rows[:, [0, 2]] - pad_x) / gain, 0, width)
        rows[:, [1, 3]] = np.clip((rows[:, [1, 3]] - pad_y) / gain, 0, height)
        return rows.astype(np.float32)

    def settings(self) -> dict:
        """The labeler's settings, JSON-ready (stored with the labels)."""
        return {"model": str(self.path), "model_name": self.path.name, "layout": self.layout.value,
                "input_hw": list(self.io.input_hw), "class_names": self.class_names,
                "conf_threshold": self.conf_threshold, "iou_threshold": self.iou_threshold, "max_det": self.max_det,
                "license": self.metadata.get("license"), "preprocess": "grey (uint16 >> 8) x3, letterbox 114, /255"}
