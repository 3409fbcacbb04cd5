"""tools/measure_labeler.py --make-synthetic: rendered APS frames with the drawn person's boxes, and the tool
scoring them (scoring of hand-made frames: tests/labelers/test_measure_labeler.py)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from davis_rig.metrics.seqasr import box_iou  # noqa: E402
from davis_rig.scene import scene  # noqa: E402
from davis_rig.scene.aps import ADC_MAX_DN, ADC_SHIFT, ApsConfig, to_adc  # noqa: E402
from tests.helpers.eval_data import PERSON_BOX, person_yolo  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NUM, SEED = 3, 0
H, W = 260, 346  # DAVIS346 APS frame, px


@pytest.fixture(scope="module")
def tool(load_tool):
    return load_tool("measure_labeler")


@pytest.fixture(scope="module")
def drawn(tool, tmp_path_factory):
    """``make_synthetic(NUM, SEED)`` watched: (its file, its arrays, the rendered clip of each kept frame)."""
    out = tmp_path_factory.mktemp("synthetic") / "frames.npz"
    clips = []
    render = scene.render_clip

    def recording_render(*args, **kwargs):
        clips.append(render(*args, **kwargs))
        return clips[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scene, "render_clip", recording_render)
        tool.make_synthetic(out, NUM, SEED)
    with np.load(out) as data:
        arrays = {key: data[key] for key in data.files}
    by_seed = {clip.spec.seed: clip for clip in clips}
    return out, arrays, [by_seed[spec["seed"]] for spec in json.loads(str(arrays["specs"]))]


def noiseless_dn(intensity: np.ndarray) -> np.ndarray:
    """The ADC value (DN, 0..1023) of linear intensity [H, W] under the tool's default ApsConfig, without noise."""
    config = dataclasses.replace(ApsConfig(), shot_noise=False, read_noise_dn=0.0)
    return (to_adc(intensity, config) >> ADC_SHIFT).astype(np.float64)


def test_file_holds_uint16_aps_frames_float_boxes_and_specs(drawn):
    _, arrays, _ = drawn
    assert set(arrays) == {"frames", "boxes", "specs"}
    frames, boxes = arrays["frames"], arrays["boxes"]
    assert frames.dtype == np.uint16 and frames.shape == (NUM, H, W)
    assert not (frames & ((1 << ADC_SHIFT) - 1)).any() and (frames >> ADC_SHIFT).max() <= ADC_MAX_DN  # DN << 6
    assert boxes.dtype == np.float64 and boxes.shape == (NUM, 4) and np.isfinite(boxes).all()
    specs = json.loads(str(arrays["specs"]))
    assert [set(spec) for spec in specs] == [{"shape_index", "heading_rad", "scale", "offset_m", "seed"}] * NUM


def test_boxes_are_the_drawn_persons_visible_extent_inside_the_frame(drawn):
    _, arrays, clips = drawn
    for box, clip in zip(arrays["boxes"], clips):
        ys, xs = np.nonzero(clip.coverage[0].numpy() > 0)
        assert box.tolist() == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]  # pixel edges
        assert 0 <= box[0] < box[2] <= W and 0 <= box[1] < box[3] <= H
        assert min(box[2] - box[0], box[3] - box[1]) >= 8  # smaller persons are re-drawn


def test_frames_show_the_background_outside_the_box_and_the_person_inside(drawn):
    _, arrays, clips = drawn
    for frame, box, clip in zip(arrays["frames"], arrays["boxes"], clips):
        dn = (frame >> ADC_SHIFT).astype(np.float64)
        off_background = np.abs(dn - noiseless_dn(clip.background.numpy()))
        x0, y0, x1, y1 = box.astype(int)
        outside = np.ones((H, W), bool)
        outside[y0:y1, x0:x1] = False
        person = clip.coverage[0].numpy() == 1
        assert np.abs(dn - noiseless_dn(clip.video[0].numpy())).mean() < 8  # the noisy ADC frame of this render
        assert off_background[outside].mean() < 8 and off_background[person].mean() > 100


def test_main_make_synthetic_writes_the_file_and_exits_0(tool, drawn, tmp_path, capsys):
    out = tmp_path / "cli.npz"
    assert tool.main(["--make-synthetic", str(out), "--num", str(NUM), "--seed", str(SEED)]) == 0
    assert f"{out}: {NUM} synthetic APS frames" in capsys.readouterr().out
    with np.load(out) as data:  # the same seed gives the same arrays (not bytes: zip entries carry a write time)
        assert all(np.array_equal(data[key], value) for key, value in drawn[1].items())


def test_another_seed_gives_other_frames_and_boxes(tool, drawn, tmp_path):
    tool.make_synthetic(tmp_path / "other.npz", NUM, SEED + 1)
    with np.load(tmp_path / "other.npz") as data:
        assert data["frames"].shape == (NUM, H, W)
        assert not np.array_equal(data["frames"], drawn[1]["frames"])
        assert not np.array_equal(data["boxes"], drawn[1]["boxes"])


def test_make_synthetic_with_yolo_scores_the_new_file(tool, drawn, tmp_path):
    # the graph finds PERSON_BOX in every frame: its best IoU per frame is PERSON_BOX against the drawn box
    out, result = tmp_path / "frames.npz", tmp_path / "result.json"
    assert tool.main(["--make-synthetic", str(out), "--num", str(NUM), "--seed", str(SEED),
                      "--yolo", str(person_yolo(tmp_path)), "--json", str(result)]) == 0
    data = json.loads(result.read_text())
    ious = box_iou(drawn[1]["boxes"], np.array([PERSON_BOX]))[:, 0]
    assert data["frames_file"] == str(out) and data["frames"] == data["labelled_frames"] == NUM
    assert data["median_best_iou"] == pytest.approx(np.median(ious), abs=1e-3)
    assert data["recall_at_0.25_iou_0.5"] == np.mean(ious >= 0.5)


def test_zero_frames_is_a_usage_error(tool, tmp_path, capsys):
    assert tool.main(["--make-synthetic", str(tmp_path / "none.npz"), "--num", "0"]) == 2
    assert "argument --num: expected an integer >= 1, got '0'" in capsys.readouterr().err
    assert not (tmp_path / "none.npz").exists()
