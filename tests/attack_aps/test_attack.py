"""The APS texture attack on a tiny YOLOv8-layout graph: steps, files, resume; recall rows on held-out scenes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper, numpy_helper

from davis_rig.attack.evaluate import EvalConfig, TextureSpec
from davis_rig.attack.texture import white_texture
from davis_rig.attack_aps.attack import (ApsAttackConfig, TorchYolo, aps_detection_rates, aps_scenes,
                                         cell_footprint, frame_loss, optimize_aps_texture, pool_order,
                                         validation_shapes)
from davis_rig.errors import CheckpointError
from davis_rig.labelers.yolo import YoloOnnxDetector
from davis_rig.scene.camera import PinholeCamera

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny_yolo(tmp_path_factory):
    """A 64 x 64 'YOLOv8' whose 64 anchors sit on an 8 x 8 grid: boxes fixed, 2 class scores from one conv."""
    path = tmp_path_factory.mktemp("yolo") / "tiny.onnx"
    rng = np.random.default_rng(0)
    ys, xs = np.meshgrid(np.arange(8) * 8 + 4, np.arange(8) * 8 + 4, indexing="ij")
    boxes = np.stack([xs.ravel(), ys.ravel(), np.full(64, 16), np.full(64, 32)]).astype(np.float32)[None]
    nodes = [helper.make_node("Conv", ["images", "w", "b"], ["c"], kernel_shape=[8, 8], strides=[8, 8]),
             helper.make_node("Sigmoid", ["c"], ["s"]),
             helper.make_node("Reshape", ["s", "shape"], ["cls"]),
             helper.make_node("Concat", ["boxes", "cls"], ["output0"], axis=1)]
    inits = [numpy_helper.from_array(rng.normal(0, 0.1, (2, 3, 8, 8)).astype(np.float32), "w"),
             numpy_helper.from_array(np.zeros(2, np.float32), "b"),
             numpy_helper.from_array(np.array([1, 2, 64], np.int64), "shape"),
             numpy_helper.from_array(boxes, "boxes")]
    graph = helper.make_graph(nodes, "tiny", [helper.make_tensor_value_info("images", TensorProto.FLOAT,
                                                                            [1, 3, 64, 64])],
                              [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 6, 64])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    for key, value in {"author": "Ultralytics", "imgsz": "[64, 64]", "names": "{0: 'Normal', 1: 'Fall'}"}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))
    return path


def test_torch_yolo_letterboxes_and_scores_every_anchor(tiny_yolo):
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    assert yolo.input_hw == (64, 64) and yolo.resized_hw == (48, 64) and yolo.pad_top == 8
    grey = torch.full((2, 260, 346), 0.5, requires_grad=True)
    scores = yolo(grey)
    assert scores.shape == (2, 64) and bool(((scores > 0) & (scores < 1)).all())
    scores.sum().backward()
    assert grey.grad.abs().sum() > 0


def test_attack_writes_texture_and_log_and_resumes(tiny_yolo, tmp_path):
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    config = ApsAttackConfig(grid_n=4, iterations=2, frames_per_step=1, scales=("small",), pool_size=1,
                             checkpoint_every=1)
    texture = optimize_aps_texture(config, yolo, tmp_path)
    assert texture.shape == (4, 4) and (tmp_path / "texture.png").is_file()
    resumed = optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "iterations": 3}), yolo, tmp_path,
                                   resume=True)
    assert resumed.shape == (4, 4)
    steps = [json.loads(line)["step"] for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3]
    # a checkpoint written before the loss and probe settings existed resumes as their defaults
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    for key in ("loss", "temperature", "scale_draw", "probe_every", "probe_clips", "lr_schedule", "lr_min", "binarize"):
        del state["config"][key]
    torch.save(state, tmp_path / "checkpoint.pt")
    optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "iterations": 4}), yolo, tmp_path, resume=True)
    with pytest.raises(CheckpointError):
        optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "grid_n": 5}), yolo, tmp_path, resume=True)


@pytest.mark.parametrize("binarize", ["threshold", "sample"])
def test_an_interrupted_run_resumed_repeats_the_uninterrupted_runs_steps_exactly(tiny_yolo, tmp_path, binarize):
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    config = ApsAttackConfig(grid_n=4, iterations=4, frames_per_step=1, scales=("small",), pool_size=1,
                             checkpoint_every=2, alpha_schedule="hard", lr=0.05, binarize=binarize)
    whole = optimize_aps_texture(config, yolo, tmp_path / "whole")
    optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "iterations": 2}), yolo, tmp_path / "parts")
    torch.manual_seed(123)  # whatever ran in between (another run, a new process) must not matter
    torch.rand(7)
    parts = optimize_aps_texture(config, yolo, tmp_path / "parts", resume=True)
    np.testing.assert_array_equal(parts, whole)
    logs = [(tmp_path / run / "log.jsonl").read_text().splitlines() for run in ("whole", "parts")]
    assert [json.loads(line)["loss"] for line in logs[1]] == [json.loads(line)["loss"] for line in logs[0]]


def test_frame_loss_kinds_on_known_scores():
    scores = torch.tensor([[0.05, 0.3, 0.2], [0.1, 0.12, 0.0]])
    # sum: every anchor above 0.125: (0.3 - 0.125) + (0.2 - 0.125)
    assert float(frame_loss(scores, 0.25, "sum")) == pytest.approx(0.25)
    # top: each frame's best anchor only; the second frame is already below 0.125
    assert float(frame_loss(scores, 0.25, "top")) == pytest.approx(0.175)
    t = 0.02
    soft = t * math.log(sum(math.exp(v / t) for v in (0.05, 0.3, 0.2)))
    soft2 = t * math.log(sum(math.exp(v / t) for v in (0.1, 0.12, 0.0)))
    assert float(frame_loss(scores, 0.25, "lse", t)) == pytest.approx(soft - 0.125 + max(soft2 - 0.125, 0.0))
    grad = torch.zeros_like(scores, requires_grad=True)
    frame_loss(grad + scores, 0.25, "top").backward()
    assert grad.grad.tolist() == [[0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]
    with pytest.raises(ValueError, match="unknown APS loss"):
        frame_loss(scores, 0.25, "mean")
    with pytest.raises(ValueError, match="temperature"):
        frame_loss(scores, 0.25, "lse", 0.0)


def test_pool_order_cycle_balances_and_random_draws_in_range():
    rng = np.random.default_rng(0)
    assert pool_order("cycle", 0, 3, 3, rng) == [0, 1, 2]
    assert pool_order("cycle", 1, 2, 3, rng) + pool_order("cycle", 2, 2, 3, rng) == [2, 0, 1, 2]
    draws = pool_order("random", 0, 50, 3, rng)
    assert len(draws) == 50 and set(draws) == {0, 1, 2}
    with pytest.raises(ValueError, match="scale draw"):
        pool_order("balanced", 0, 1, 3, rng)


def test_attack_logs_the_hard_probe(tiny_yolo, tmp_path):
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    config = ApsAttackConfig(grid_n=4, iterations=2, frames_per_step=2, scales=("small",), pool_size=1,
                             loss="top", scale_draw="cycle", alpha_schedule="hard", probe_every=1, probe_clips=1)
    optimize_aps_texture(config, yolo, tmp_path)
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["alpha"] for r in records] == [1.0, 1.0]
    assert [r["lr"] for r in records] == [config.lr, config.lr]
    for r in records:
        assert 0.0 < r["probe_top_score"] < 1.0 and set(r["probe_by_scale"]) == {"small"}
    with pytest.raises(ValueError, match="loss must be"):
        ApsAttackConfig(loss="max")


def test_sampled_binarization_draws_each_steps_cuts(tiny_yolo, tmp_path, monkeypatch):
    import davis_rig.attack.texture as texture_module
    from davis_rig.attack.step import binarization_threshold

    cuts = []
    real = texture_module.binarize_ste

    def recording(u, alpha=1.0, threshold=0.5):
        cuts.append((u.detach().clone(), threshold))
        return real(u, alpha, threshold)

    monkeypatch.setattr(texture_module, "binarize_ste", recording)
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    config = ApsAttackConfig(grid_n=4, iterations=3, frames_per_step=1, scales=("small",), pool_size=1,
                             alpha_schedule="hard", binarize="sample", seed=5)
    optimize_aps_texture(config, yolo, tmp_path / "sample")
    assert len(cuts) == 3
    for step, (soft, cut) in enumerate(cuts):
        assert isinstance(cut, torch.Tensor) and cut.shape == (4, 4)
        torch.testing.assert_close(cut, binarization_threshold("sample", 5, step, soft), rtol=0, atol=0)
    assert not torch.equal(cuts[0][1], cuts[1][1]) and not torch.equal(cuts[1][1], cuts[2][1])
    cuts.clear()
    optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "binarize": "threshold"}), yolo, tmp_path / "cut")
    assert [cut for _, cut in cuts] == [0.5, 0.5, 0.5]
    with pytest.raises(ValueError, match="binarize"):
        ApsAttackConfig(binarize="round")


def test_cosine_schedule_sets_each_steps_rate(tiny_yolo, tmp_path):
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    config = ApsAttackConfig(grid_n=4, iterations=3, frames_per_step=1, scales=("small",), pool_size=1, lr=1e-3,
                             lr_schedule="cosine_restarts", lr_min=1e-5)
    optimize_aps_texture(config, yolo, tmp_path)
    rates = [json.loads(line)["lr"] for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    # one cosine over the 3 steps: base, halfway at step 1.5 of 3, ... (lr_min + (lr - lr_min) (1 + cos(pi k / 3)) / 2)
    assert rates == pytest.approx([1e-3, 1e-5 + (1e-3 - 1e-5) * 0.75, 1e-5 + (1e-3 - 1e-5) * 0.25])
    with pytest.raises(ValueError, match="lr_schedule"):
        ApsAttackConfig(lr_schedule="step")
    with pytest.raises(ValueError, match="lr_min"):
        ApsAttackConfig(lr=1e-3, lr_min=1e-3)


def test_detection_rates_rows(tiny_yolo):
    labeler = YoloOnnxDetector(tiny_yolo, conf_threshold=0.001)
    config = EvalConfig(camera=PinholeCamera.davis346(), scales=("small",), shapes=(1,),
                        headings_rad=(math.pi / 2,), phases=(0.0,), supersample=1)
    rows = aps_detection_rates({"white": TextureSpec(white_texture(1))}, labeler, eval_config=config)
    assert len(rows) == 1 and rows[0]["texture"] == "white" and rows[0]["frames"] >= 1
    assert 0.0 <= rows[0]["rate"] <= 1.0 and set(rows[0]["by_scale"]) == {"small"}
    assert rows[0]["by_heading"] == {"90": rows[0]["rate"]}


def test_rates_by_key_are_the_share_of_each_keys_frames():
    from davis_rig.attack_aps.attack import _rate_by

    found = np.array([True, False, True, True, False, False])
    assert _rate_by(found, ["90", "90", "0", "0", "-90", "90"]) == {"90": 1 / 3, "0": 1.0, "-90": 0.0}


def test_validation_keeps_the_best_texture_and_resumes_with_it(tiny_yolo, tmp_path):
    yolo = TorchYolo(tiny_yolo, PinholeCamera.davis346().hw)
    config = ApsAttackConfig(grid_n=4, iterations=3, frames_per_step=1, scales=("small",), pool_size=1,
                             alpha_schedule="hard", validate_every=1, checkpoint_every=1)
    # a scripted validator: recall 0.5, then 0.25 (the best), then 0.75
    rates = iter([0.5, 0.25, 0.75, 0.9])
    seen = []

    def validate(grid):
        seen.append(np.array(grid))
        return {"rate": next(rates), "mean_top_score": 0.3}

    with pytest.raises(ValueError, match="validate callable"):
        optimize_aps_texture(config, yolo, tmp_path)
    optimize_aps_texture(config, yolo, tmp_path, validate=validate)
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["val_rate"] for r in records] == [0.5, 0.25, 0.75]
    assert json.loads((tmp_path / "best.json").read_text()) == {"step": 2, "rate": 0.25, "mean_top_score": 0.3}
    np.testing.assert_array_equal(np.load(tmp_path / "best_texture.npy"), seen[1])
    assert set(np.unique(seen[1])) <= {0.0, 1.0}
    # resuming restores the best from the checkpoint (a later, worse validation does not replace it)
    (tmp_path / "best.json").unlink()
    optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "iterations": 4}), yolo, tmp_path, resume=True,
                         validate=validate)
    assert json.loads((tmp_path / "best.json").read_text())["step"] == 2
    # validating more or less often is free on resume
    optimize_aps_texture(ApsAttackConfig(**{**config.__dict__, "iterations": 5, "validate_every": 0}), yolo,
                         tmp_path, resume=True)
    with pytest.raises(ValueError, match="validate_every"):
        ApsAttackConfig(validate_every=-1)


def test_pools_draw_only_the_configured_shapes():
    from davis_rig.attack_aps.attack import aps_pools
    from davis_rig.scene.body import BodyModel

    config = ApsAttackConfig(grid_n=4, scales=("small",), pool_size=4, shapes=(2, 6))
    (pool,) = aps_pools(config, BodyModel(), None)
    assert {clip.spec.shape_index for clip in pool.clips.values()} <= {2, 6}


def test_pools_walk_across_the_view_when_asked():
    from davis_rig.attack_aps.attack import aps_pools
    from davis_rig.scene.body import BodyModel

    config = ApsAttackConfig(grid_n=4, scales=("small",), pool_size=6, across_view_probability=1.0)
    (pool,) = aps_pools(config, BodyModel(), None)
    degrees = np.degrees([clip.spec.heading_rad for clip in pool.clips.values()])
    assert np.all(np.abs(np.abs(degrees) - 90.0) <= 30.0)
    with pytest.raises(ValueError, match="across_view_probability"):
        ApsAttackConfig(across_view_probability=-0.1)


def test_blended_shapes_join_the_clips_shapes():
    from davis_rig.attack_aps.attack import aps_pools, blended_body, shape_blends
    from davis_rig.scene.body import BodyModel

    blends = shape_blends((2, 6, 10), 5, seed=3)
    assert blends == shape_blends((2, 6, 10), 5, seed=3) != shape_blends((2, 6, 10), 5, seed=4)
    assert all(a != b and {a, b} <= {2, 6, 10} and 0.25 <= w <= 0.75 for a, b, w in blends)
    with pytest.raises(ValueError, match="two shapes"):
        shape_blends((2,), 1, seed=0)
    body = BodyModel()
    config = ApsAttackConfig(grid_n=4, scales=("small",), pool_size=6, shapes=(2, 6), blend_shapes=3)
    assert blended_body(ApsAttackConfig(shapes=(2, 6)), body) == (body, ApsAttackConfig(shapes=(2, 6)))
    clip_body, clip_config = blended_body(config, body)
    assert clip_body.num_shapes == body.num_shapes + 3 and clip_config.shapes == (2, 6, 24, 25, 26)
    (pool,) = aps_pools(clip_config, clip_body, None)
    drawn = {clip.spec.shape_index for clip in pool.clips.values()}
    assert drawn <= set(clip_config.shapes) and drawn & {24, 25, 26}
    with pytest.raises(ValueError, match="blend_shapes"):
        ApsAttackConfig(blend_shapes=-1)


def test_validation_shapes_are_training_shapes_apart_from_the_test_split():
    from davis_rig.attack.eot import split_shapes

    train, test = split_shapes(24)
    shapes = validation_shapes(24, 6)
    assert len(shapes) == 6 and set(shapes) <= set(train) and not set(shapes) & set(test)
    assert shapes[0] == train[0] and shapes[-1] == train[-1]
    assert validation_shapes(24, 100) == train


def test_prepared_scenes_score_as_fresh_ones(tiny_yolo):
    labeler = YoloOnnxDetector(tiny_yolo, conf_threshold=0.001)
    config = EvalConfig(camera=PinholeCamera.davis346(), scales=("small",), shapes=(1,),
                        headings_rad=(math.pi / 2,), phases=(0.0,), supersample=1)
    textures = {"white": TextureSpec(white_texture(1))}
    assert (aps_detection_rates(textures, labeler, scenes=aps_scenes(config))
            == aps_detection_rates(textures, labeler, eval_config=config))


def test_cell_footprint_counts_each_cells_pixels():
    from davis_rig.attack_aps.attack import aps_pools
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    config = ApsAttackConfig(grid_n=6, scales=("small",), pool_size=1)
    clip = next(iter(aps_pools(config, BodyModel(), part_mask(config.parts))[0].clips.values()))
    frame = len(clip.t_us) // 2
    area = cell_footprint(clip, frame)
    assert area.shape == (36,) and float(area.min()) >= 0.0 and int((area > 0).sum()) > 1
    y0, y1, x0, x1 = clip.active_box
    shade = clip.raster.shade
    for cell in torch.nonzero(area > 0)[:3, 0].tolist() + [int(torch.argmin(area))]:
        one_hot = torch.zeros(36)
        one_hot[cell] = 1.0
        # the renderer's own sum of this cell's samples, its shading divided out: the cell's area in pixels
        values = clip.lookup.sample(one_hot.view(6, 6), fill=0.0) / torch.where(shade > 0, shade, 1.0)
        rendered = clip.raster.person(values, pixels=clip.active_pixel, hw=(y1 - y0, x1 - x0))[frame].sum()
        assert float(area[cell]) == pytest.approx(float(rendered), rel=1e-5, abs=1e-6)
