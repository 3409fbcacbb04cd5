"""A victim's controls report: scene choice of the bound, the paper's fingerprint rule, files and resume."""

from __future__ import annotations

import json
from dataclasses import replace
import math
from pathlib import Path

import numpy as np
import pytest

from davis_rig.attack.evaluate import EvalConfig
from davis_rig.controls.bounds import BoundConfig
from davis_rig.controls.report import bound_scene_indices, paper_fingerprint, shape_split_indices, victim_controls
from davis_rig.errors import ConfigError
from davis_rig.models.rvt.checkpoint import load_detector

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_bound_scene_indices_spread_over_each_scale():
    scales = ["large"] * 5 + ["small"] * 3
    assert bound_scene_indices(scales, 2) == [0, 4, 5, 7]
    assert bound_scene_indices(scales, 10) == list(range(8))
    with pytest.raises(ValueError):
        bound_scene_indices(scales, 0)


def test_paper_fingerprint_is_white_detected_best():
    assert paper_fingerprint({"white": 0.505, "black": 0.438, "random 60x60": 0.452})
    assert not paper_fingerprint({"white": 0.408, "black": 0.658, "random 60x60": 0.658})


def test_victim_controls_writes_the_report_and_resumes(tmp_path):
    config = EvalConfig(scales=("small",), shapes=(1, 5), headings_rad=(math.pi / 2,), phases=(0.0,),
                        supersample=1, thresholds=(0.25,))
    detector = load_detector(FIXTURE)
    kwargs = dict(name="tiny", eval_config=config, bound_config=BoundConfig(steps=1, grid_n=4),
                  scenes_per_scale=1)
    report = victim_controls(detector, tmp_path, **kwargs)
    assert (tmp_path / "controls_tiny.md").is_file() and (tmp_path / "fingerprint.json").is_file()
    assert report["bound"]["scenes"] == 1 and len(list((tmp_path / "bound").glob("scene_*.npz"))) == 1
    assert [r["texture"] for r in report["fingerprint"]["rows"] if r["scale"] == "all"] == [
        "white", "black", "random 60x60", "random 4x4", "checker 4x4"]
    again = victim_controls(detector, tmp_path, **kwargs)  # from the kept parts
    assert json.dumps(again["bound"]["rows"]) == json.dumps(report["bound"]["rows"])
    assert json.dumps(again["fingerprint"]["rows"]) == json.dumps(report["fingerprint"]["rows"])  # NaN-safe
    # kept parts are reused only for the detector and protocol that made them
    with pytest.raises(ValueError, match="fingerprint.json was scored for another detector"):
        victim_controls(detector, tmp_path, **kwargs, detector_name="another.safetensors")
    official = EvalConfig.official(scales=("small",), shapes=(1, 5), headings_rad=(math.pi / 2,), phases=(0.0,),
                                   supersample=1, thresholds=(0.25,))
    with pytest.raises(ValueError, match="fingerprint.json was scored for another"):
        victim_controls(detector, tmp_path, **{**kwargs, "eval_config": official})
    with pytest.raises(ValueError, match=r"other bound settings \(other background, light, walk_in_place\)"):
        victim_controls(detector, tmp_path, **{**kwargs, "eval_config": official}, fingerprint=False)
    with pytest.raises(ValueError, match=r"other bound settings \(other detector\)"):
        victim_controls(detector, tmp_path, **kwargs, detector_name="another.safetensors", fingerprint=False)


def test_a_bound_part_gains_the_kinds_it_lacks_and_keeps_the_rest(tmp_path, monkeypatch):
    import davis_rig.controls.bounds as bounds

    config = EvalConfig(scales=("small",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,),
                        supersample=1, thresholds=(0.25,))
    detector = load_detector(FIXTURE)
    kwargs = dict(name="tiny", eval_config=config, scenes_per_scale=1, fingerprint=False)
    first = victim_controls(detector, tmp_path, bound_config=BoundConfig(steps=1, grid_n=4, kinds=("per-pixel",)),
                            **kwargs)
    assert [r["appearance"] for r in first["bound"]["rows"]] == ["white", "black", "per-pixel"]
    optimised = []
    original = bounds.optimise_appearance
    monkeypatch.setattr(bounds, "optimise_appearance",
                        lambda scene, det, kind, *a, **k: optimised.append(kind) or original(scene, det, kind, *a, **k))
    both = victim_controls(detector, tmp_path, bound_config=BoundConfig(steps=1, grid_n=4,
                                                                        kinds=("per-pixel", "static texture")),
                           **kwargs)
    assert optimised == ["static texture"]  # the kept per-pixel appearance is not optimised again
    rows = {r["appearance"]: r for r in both["bound"]["rows"]}
    assert list(rows) == ["white", "black", "per-pixel", "static texture"]
    assert json.dumps(rows["per-pixel"]) == json.dumps(first["bound"]["rows"][2])
    # parts made with other settings are not mixed in
    with pytest.raises(ValueError, match="other bound settings"):
        victim_controls(detector, tmp_path, bound_config=BoundConfig(steps=1, grid_n=5, kinds=("static texture",)),
                        **kwargs)


def test_shared_texture_control_fits_one_texture_and_scores_it_fitted_and_held_out(tmp_path):
    from davis_rig.controls.report import shared_texture_control

    config = EvalConfig(scales=("small",), shapes=(1, 5), headings_rad=(math.pi / 2,), phases=(0.0,),
                        supersample=1, thresholds=(0.25,))
    detector = load_detector(FIXTURE)
    kwargs = dict(name="tiny", eval_config=config, bound_config=BoundConfig(steps=2, grid_n=4), scenes_per_scale=1)
    report = shared_texture_control(detector, tmp_path, **kwargs)
    grey = np.load(tmp_path / "shared_texture.npy")
    assert grey.shape == (4, 4) and grey.dtype == np.float32 and ((grey > 0) & (grey < 1)).all()
    assert report["fitted_scenes"] == [0] and report["held_out_scenes"] == [1]
    for key in ("fitted", "held_out"):
        assert {r["texture"] for r in report[key]["rows"]} == {"white", "black", "shared grey 4x4",
                                                                "shared binary 4x4"}
    assert (tmp_path / "shared_tiny.md").read_text().count("## On the") == 2
    again = shared_texture_control(detector, tmp_path, **kwargs)  # the kept texture, scored again
    assert json.dumps(again["held_out"]["rows"]) == json.dumps(report["held_out"]["rows"])
    # a kept texture is scored again only for the fit that made it: other settings or other scenes are refused
    with pytest.raises(ConfigError, match="other grid_n than"):
        shared_texture_control(detector, tmp_path, **{**kwargs, "bound_config": BoundConfig(steps=2, grid_n=5)})
    with pytest.raises(ConfigError, match="other scenes than"):
        shared_texture_control(detector, tmp_path, **{**kwargs, "scenes_per_scale": 2})
    with pytest.raises(ConfigError, match="other walk than"):
        shared_texture_control(detector, tmp_path, **{**kwargs, "eval_config": replace(config, walk="bundled")})
    with pytest.raises(ConfigError, match="other detector, steps than"):
        shared_texture_control(detector, tmp_path, **{**kwargs, "bound_config": BoundConfig(steps=3, grid_n=4),
                                                      "detector_name": "another.ckpt"})
    (tmp_path / "shared_texture.json").unlink()
    with pytest.raises(ConfigError, match="no shared_texture.json saying what it was fitted to"):
        shared_texture_control(detector, tmp_path, **kwargs)


def test_shape_split_takes_every_scene_of_the_first_bodies():
    shapes = [3, 3, 5, 5, 7, 3, 7]
    assert shape_split_indices(shapes, 1) == [0, 1, 5]
    assert shape_split_indices(shapes, 2) == [0, 1, 2, 3, 5]
    for bad in (0, 3):  # none fitted, or none left out
        with pytest.raises(ConfigError, match="fit_shapes"):
            shape_split_indices(shapes, bad)


def test_shared_texture_control_can_hold_out_whole_bodies(tmp_path):
    from davis_rig.controls.report import shared_texture_control

    config = EvalConfig(scales=("small", "large"), shapes=(1, 5), headings_rad=(math.pi / 2,), phases=(0.0,),
                        supersample=1, thresholds=(0.25,))
    report = shared_texture_control(load_detector(FIXTURE), tmp_path, name="bodies", eval_config=config,
                                    bound_config=BoundConfig(steps=1, grid_n=4), fit_shapes=1)
    assert report["fitted_scenes"] == [0, 2] and report["held_out_scenes"] == [1, 3]  # body 1 at both scales
    assert report["config"]["fit_shapes"] == 1
    assert "held-out ones show only bodies [5], never fitted" in (tmp_path / "shared_bodies.md").read_text()


def test_shared_texture_control_can_fit_the_black_and_white_texture_itself(tmp_path):
    from davis_rig.controls.report import shared_texture_control

    config = EvalConfig(scales=("small",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,),
                        supersample=1, thresholds=(0.25,))
    report = shared_texture_control(load_detector(FIXTURE), tmp_path, name="tiny", eval_config=config,
                                    bound_config=BoundConfig(steps=2, grid_n=4), binary=True)
    grid = np.load(tmp_path / "shared_texture_binary.npy")
    assert set(np.unique(grid)) <= {0.0, 1.0} and 0.0 < grid.mean() < 1.0  # a fair coin per cell to start
    assert [r["texture"] for r in report["fitted"]["rows"] if r["scale"] == "all"] == [
        "white", "black", "shared binary-fitted 4x4"]
    assert "held_out" not in report and not (tmp_path / "shared_texture.npy").exists()


def test_victim_controls_in_the_official_scene_on_relaxed_counts(tmp_path):
    config = EvalConfig.official(scales=("small",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,),
                                 supersample=1, thresholds=(0.25,), events="official_relaxed")
    detector = load_detector(FIXTURE)
    kwargs = dict(name="tiny", eval_config=config, scenes_per_scale=1, fingerprint=False)
    report = victim_controls(detector, tmp_path, bound_config=BoundConfig(steps=1, grid_n=4, kinds=("per-pixel",),
                                                                          events="official_relaxed"), **kwargs)
    assert report["eval_config"]["events"] == "official_relaxed" and report["eval_config"]["background"] == 1.0
    text = (tmp_path / "controls_tiny.md").read_text()
    assert "the official code's scene" in text and "scored on the official relaxed counts" in text
    # a part kept from relaxed counts is not reused for exact events
    with pytest.raises(ValueError, match="other bound settings"):
        victim_controls(detector, tmp_path, bound_config=BoundConfig(steps=1, grid_n=4, kinds=("per-pixel",)),
                        **{**kwargs, "eval_config": EvalConfig.official(
                            scales=("small",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,),
                            supersample=1, thresholds=(0.25,))})
