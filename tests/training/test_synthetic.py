"""Synthetic dataset generator: written data read back, labels on the rendered people, splits, determinism."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

pytest.importorskip("torch")

from davis_rig.cli import make_dataset as cli  # noqa: E402
from davis_rig.errors import FormatError  # noqa: E402
from davis_rig.events.simulator import SimulatorConfig  # noqa: E402
from davis_rig.scene.body import PART_NAMES  # noqa: E402
from davis_rig.scene.camera import TEST_SCALES_PX  # noqa: E402
from davis_rig.scene.masks import part_label_map  # noqa: E402
from davis_rig.training import synthetic as syn  # noqa: E402
from davis_rig.training.synthetic.paint import vehicle_layers  # noqa: E402
from davis_rig.training.synthetic.scenes import sample_distractor  # noqa: E402
from davis_rig.training.dataset import SequenceData, list_sequences  # noqa: E402
from davis_rig.types import PEDESTRIAN_CLASS_ID, RVT_HW  # noqa: E402

SHORT = syn.SyntheticSceneConfig(duration_s=0.15)
SIZES = {"train": 1, "val": 0, "test": 1}
pytestmark = pytest.mark.usefixtures("one_torch_thread")  # rendering on oversubscribed threads is ~20x slower


@pytest.fixture(scope="module")
def model():
    from davis_rig.scene.body import BodyModel

    return BodyModel(device="cpu")


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "ds"
    summary = syn.generate_dataset(root, SIZES, duration_s=0.15, seed=5, compression="gzip", threads=1)
    return root, summary


def _one_person_scene(seed: int = 0, **person_changes) -> syn.SyntheticScene:
    """A test-split scene with one person, no distractors, ideal sensor (events only where something moves)."""
    scene = syn.held_out_scene(np.random.default_rng(seed), "white", "middle", SHORT)
    person = dataclasses.replace(scene.people[0], **person_changes)
    return dataclasses.replace(scene, people=(person,), distractors=(), simulator=SimulatorConfig())


def test_tiny_dataset_reads_back_in_rvt_layout(tiny_dataset):
    root, summary = tiny_dataset
    assert summary["generated"] == 2 and summary["skipped"] == 0
    (train,) = list_sequences(root, "train")
    (test,) = list_sequences(root, "test")
    assert test.name == "test_white_large_00000"  # test index 0 = first held-out subset
    for path in (train, test):
        seq = SequenceData(path)
        assert len(seq) == 3 and seq.window_end_us.tolist() == [50_000, 100_000, 150_000]
        hist = seq.histograms(0, 3)
        assert hist.dtype == np.uint8 and hist.shape == (3, 20, *RVT_HW) and hist.max() <= 10 and hist.sum() > 0
        assert seq.labelled_windows().tolist() == [0, 1, 2]  # every window is supervised
        for w in range(3):
            boxes = seq.labels_at(w)
            assert np.all(boxes["class_id"] == PEDESTRIAN_CLASS_ID) and np.all(boxes["t"] == seq.window_end_us[w])
        seq.close()
    meta = json.loads((test / "meta.json").read_text())
    assert meta["subset"] == "white/large" and meta["scene"]["people"][0]["clothing"] == "white"
    card = json.loads((root / "dataset_card.json").read_text())
    assert card["splits"]["train"]["sequences"] == 1 and card["splits"]["test"]["sequences"] == 1
    assert card["settings"]["seed"] == 5 and card["split_shapes"]["test"] == [21, 22, 23]


def test_generation_resumes_and_refuses_other_settings(tiny_dataset):
    root, _ = tiny_dataset
    again = syn.generate_dataset(root, SIZES, duration_s=0.15, seed=5, compression="gzip")
    assert again["generated"] == 0 and again["skipped"] == 2
    with pytest.raises(FormatError, match="other settings"):
        syn.generate_dataset(root, SIZES, duration_s=0.15, seed=6, compression="gzip")


def test_smaller_rerun_warns_and_cards_the_sequences_left_on_disk(tiny_dataset, tmp_path):
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset[0], root)
    with pytest.warns(RuntimeWarning, match=r"1 sequence folder.*1 in .*train"):
        again = syn.generate_dataset(root, {"train": 0, "val": 0, "test": 1}, duration_s=0.15, seed=5,
                                     compression="gzip")
    assert again["generated"] == 0 and again["skipped"] == 1
    assert [p.name for p in list_sequences(root, "train")] == ["train_00000"]  # kept: training still reads it
    card = json.loads((root / "dataset_card.json").read_text())
    assert card["unplanned_sequences"] == {"train": {"sequences": 1, "names": ["train_00000"]}}
    assert "train" not in card["splits"] and card["splits"]["test"]["sequences"] == 1


def test_refused_resume_names_every_setting_that_differs(tiny_dataset):
    root, _ = tiny_dataset
    with pytest.raises(FormatError) as info:
        syn.generate_dataset(root, SIZES, duration_s=0.15, seed=5, compression="lzf",
                             config=syn.SyntheticSceneConfig(vehicle_counts=(0, 2)))
    message = str(info.value)
    assert "compression (stored 'gzip', now 'lzf')" in message and "config.vehicle_counts" in message
    assert "seed" not in message.split("differing:")[1] and "duration_s" not in message
    assert "all the same settings" in message and "all the same settings" in " ".join(cli.EXAMPLES.split())


def test_generation_is_deterministic_per_seed(tiny_dataset, model):
    root, _ = tiny_dataset
    (job,) = [j for j in syn.dataset_plan(SIZES) if j.split == "train"]
    config = dataclasses.replace(syn.SyntheticSceneConfig(), duration_s=0.15)
    scene = syn.scene_for_job(job, 5, config)
    assert scene.to_dict() == syn.scene_for_job(job, 5, config).to_dict()
    assert scene.to_dict() != syn.scene_for_job(job, 6, config).to_dict()
    seq = syn.render_sequence(scene, model=model)
    stored = SequenceData(root / "train" / job.name)
    np.testing.assert_array_equal(seq.histograms, stored.histograms(0, 3))
    for w, boxes in enumerate(seq.labels):
        np.testing.assert_array_equal(boxes, stored.labels_at(w))
    stored.close()


def test_labels_lie_on_the_rendered_person(model):
    scene = _one_person_scene(3)
    seq = syn.render_sequence(scene, model=model, keep_events=True)
    ev = seq.events
    assert ev.shape[0] > 1000
    for i, (end, boxes) in enumerate(zip(seq.window_end_us, seq.labels)):
        (box,) = boxes
        assert 100 <= box["h"] <= 170  # middle scale: a 1.75 m person spans 150 px, shapes differ in height
        # events of the last 5 ms before the label time lie on the person (static camera, ideal sensor)
        last = ev[(ev["t"] > end - 5_000) & (ev["t"] <= end)]
        assert last.shape[0] > 100
        inside = ((last["x"] >= box["x"] - 3) & (last["x"] < box["x"] + box["w"] + 3)
                  & (last["y"] >= box["y"] - 3) & (last["y"] < box["y"] + box["h"] + 3))
        assert inside.all()
        # and the box is tight: events near its top and bottom rows
        assert last["y"].min() <= box["y"] + 6 and last["y"].max() >= box["y"] + box["h"] - 8


def test_occluded_person_gets_no_label(model):
    front = _one_person_scene(4, heading_rad=0.0, x_mid_m=0.0, depth_mid_m=5.0)
    hidden = dataclasses.replace(front.people[0], depth_mid_m=20.0, shape_index=22, clothing="black")
    scene = dataclasses.replace(front, people=(front.people[0], hidden))
    seq = syn.render_sequence(scene, model=model, min_visible_px=100.0)
    alone = syn.render_sequence(dataclasses.replace(scene, people=(hidden,)), model=model, min_visible_px=100.0)
    # the z-merged coverage: only what shows between the near person's legs remains of the far one
    assert np.all(alone.visible_px[:, 0] > 400) and np.all(seq.visible_px[:, 1] < 0.15 * alone.visible_px[:, 0])
    assert np.all(seq.visible_px[:, 0] > 3000)
    assert [len(b) for b in seq.labels] == [1, 1, 1] and all(b["track_id"][0] == 0 for b in seq.labels)
    assert all(len(b) == 1 for b in alone.labels)


def test_empty_scene_with_distractors_fires_events_but_has_no_labels(model):
    rng = np.random.default_rng(1)
    base = syn.sample_scene(rng, "train", SHORT)
    distractors = tuple(sample_distractor(rng, "train", RVT_HW, SHORT.duration_s, 0.5) for _ in range(3))
    distractors = tuple(dataclasses.replace(d, start_xy_px=(150.0, 120.0), velocity_px_s=(200.0, 0.0), level=0.9)
                        for d in distractors)
    scene = dataclasses.replace(base, people=(), distractors=distractors, ego_motion=None,
                                simulator=SimulatorConfig())
    seq = syn.render_sequence(scene, model=model, keep_events=True)
    assert seq.events.shape[0] > 500 and seq.histograms.sum() > 0
    assert [len(b) for b in seq.labels] == [0, 0, 0] and seq.object_boxes.shape == (3, 0, 4)


def _car(length_px: float = 100.0, x: float = 150.0, y: float = 150.0, vx: float = 200.0) -> syn.VehicleSpec:
    return syn.VehicleSpec(length_px=length_px, start_xy_px=(x, y), velocity_px_s=(vx, 0.0), level=0.9,
                           contrast=0.0, pattern="flat", period_px=10.0, window_level=0.1)


def test_car_silhouette_area_box_and_paint():
    length = 100.0
    ((alpha, value),) = vehicle_layers((_car(length, 150.0, 150.0),), np.array([0.0, 0.1]), RVT_HW, 4)
    # body 1 x 0.26 L, cabin 0.5 x 0.2 L, the lower halves of two wheels of radius 0.11 L below the body
    area = (0.26 + 0.5 * 0.2 + math.pi * 0.11**2) * length**2
    np.testing.assert_allclose(alpha.sum(axis=(1, 2)), area, rtol=0.01)
    rows, cols = np.nonzero(alpha[0] > 0)
    assert (cols.min(), cols.max()) == (100, 199)  # centre 150 +- L / 2
    assert (rows.min(), rows.max()) == (122, 178)  # cabin roof at -0.28 L, wheel bottoms at +0.29 L
    assert np.argwhere(alpha[1] > 0)[:, 1].min() == 120  # 200 px/s for 0.1 s
    # the windows are dark, the body has its paint, the wheels are 0.05; the cabin sits towards the rear (left)
    full = alpha[0] == 1.0
    shade = np.where(full, value[0], np.nan)
    assert np.nanmax(shade) == pytest.approx(0.9) and np.nanmin(shade) == pytest.approx(0.05)
    assert np.isclose(shade[150, 150], 0.9) and np.isclose(shade[176, 180], 0.05)
    window = np.argwhere(np.isclose(shade, 0.1))
    assert window[:, 1].mean() < 150 and window[:, 0].max() < 142
    mirrored = vehicle_layers((_car(length, 150.0, 150.0, vx=-200.0),), np.array([0.0]), RVT_HW, 4)
    np.testing.assert_allclose(mirrored[0][1][0], value[0][:, ::-1][:, np.r_[4:304, 0:4]], atol=1e-6)


def test_cars_are_labelled_class_zero_and_hidden_by_people(model):
    person_scene = _one_person_scene(4, heading_rad=0.0, x_mid_m=0.0, depth_mid_m=5.0)
    car = _car(180.0, 152.0, 150.0, vx=0.0)
    alone = syn.render_sequence(dataclasses.replace(person_scene, people=(), vehicles=(car,)), model=model)
    assert [b["class_id"].tolist() for b in alone.labels] == [[0], [0], [0]]
    (box,) = alone.labels[0]
    assert (box["x"], box["w"]) == (62.0, 180.0) and alone.object_classes.tolist() == [0]
    both = syn.render_sequence(dataclasses.replace(person_scene, vehicles=(car,)), model=model)
    assert both.object_classes.tolist() == [PEDESTRIAN_CLASS_ID, 0]
    assert all(sorted(b["class_id"].tolist()) == [0, 1] and b["track_id"].tolist() == [0, 1] for b in both.labels)
    # the person stands in front of the car: the car loses exactly the coverage the person has over it
    assert np.all(both.visible_px[:, 1] < alone.visible_px[:, 0] - 1000)
    np.testing.assert_allclose(both.visible_px[:, 0], syn.render_sequence(person_scene, model=model).visible_px[:, 0])


def test_person_height_range_without_test_scales_keeps_train_people_small():
    from davis_rig.scene.camera import PinholeCamera, distance_for_height

    small = syn.SyntheticSceneConfig(person_height_px=(25.0, 125.0), test_scale_probability=0.0)
    nearest = distance_for_height(125.0, PinholeCamera.rvt_crop())
    depths = [p.depth_mid_m for seed in range(40) for p in syn.sample_scene(np.random.default_rng(seed), "train", small).people]
    assert len(depths) > 30 and min(depths) >= nearest - 1e-9
    for job in syn.dataset_plan({"train": 0, "val": 0, "test": 9}):  # the held-out subsets keep the paper's scales
        assert syn.scene_for_job(job, 0, small) == syn.scene_for_job(job, 0)
    with pytest.raises(ValueError, match="test_scale_probability"):
        syn.SyntheticSceneConfig(test_scale_probability=-0.1)


def test_vehicle_counts_add_cars_without_changing_the_rest_of_the_scene():
    cars = syn.SyntheticSceneConfig(vehicle_counts=(1, 2))
    for seed in range(6):
        plain = syn.sample_scene(np.random.default_rng(seed), "train")
        with_cars = syn.sample_scene(np.random.default_rng(seed), "train", cars)
        assert plain.vehicles == () and 1 <= len(with_cars.vehicles) <= 2
        assert dataclasses.replace(with_cars, vehicles=()) == plain
    for job in syn.dataset_plan({"train": 0, "val": 0, "test": 9}):
        assert syn.scene_for_job(job, 0, cars).vehicles == ()
    with pytest.raises(ValueError, match="vehicle_counts"):
        syn.SyntheticSceneConfig(vehicle_counts=(2, 1))


def test_splits_are_disjoint_in_shapes_seeds_and_speeds():
    plan = syn.dataset_plan({"train": 40, "val": 20, "test": 18})
    scenes = [syn.scene_for_job(job, 0) for job in plan]
    shapes, seeds, speeds = {}, {}, {}
    for job, scene in zip(plan, scenes):
        assert scene.split == job.split
        seeds.setdefault(job.split, set()).update(
            [scene.seed, scene.background_seed, scene.simulator.seed]
            + [s for p in scene.people for s in (p.gait_seed, p.clothing_seed)])
        shapes.setdefault(job.split, set()).update(p.shape_index for p in scene.people)
        speeds.setdefault(job.split, set()).update(p.speed_m_s for p in scene.people if p.motion == "gait")
    assert shapes["train"] <= set(range(18)) and shapes["val"] <= {18, 19, 20} and shapes["test"] <= {21, 22, 23}
    for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
        assert not seeds[a] & seeds[b]
    for split in ("val", "test"):
        for v in speeds[split]:
            assert not any(lo <= v < hi for kind in ("walk", "run") for lo, hi in syn.SPLIT_SPEEDS_M_S["train"][kind])
    # the held-out set cycles through white / black / pattern60 x large / middle / small
    test = [s for s in scenes if s.split == "test"]
    assert sorted({s.subset for s in test}) == sorted(f"{c}/{k}" for c, k in syn.TEST_SUBSETS)
    for s in test:
        clothing, scale = s.subset.split("/")
        (p,) = s.people
        assert p.clothing == clothing and s.ego_motion is None
        assert math.isclose(p.depth_mid_m, 648.6486 * 1.75 / TEST_SCALES_PX[scale], rel_tol=1e-4)
    counts = [len(s.people) for s in scenes if s.split == "train"]
    assert set(counts) <= {0, 1, 2, 3} and len(set(counts)) >= 3


def test_clothing_kinds_restrict_train_people_but_not_the_test_subsets():
    natural = syn.SyntheticSceneConfig(clothing_kinds=("white", "stripes"))
    plan = syn.dataset_plan({"train": 30, "val": 0, "test": 9})
    worn = {p.clothing for job in plan if job.split == "train" for p in syn.scene_for_job(job, 0, natural).people}
    assert worn == {"white", "stripes"}
    test = {syn.scene_for_job(job, 0, natural).subset.split("/")[0] for job in plan if job.split == "test"}
    assert test == set(syn.TEST_CLOTHING)
    with pytest.raises(ValueError, match="clothing_kinds"):
        syn.SyntheticSceneConfig(clothing_kinds=())
    with pytest.raises(ValueError, match="clothing_kinds"):
        syn.SyntheticSceneConfig(clothing_kinds=("white", "tartan"))


def test_generation_resumes_a_dataset_written_before_clothing_kinds_existed(tiny_dataset):
    root, _ = tiny_dataset
    gen = root / syn.GENERATION_FILE
    stored = json.loads(gen.read_text())
    del stored["settings"]["config"]["clothing_kinds"]
    gen.write_text(json.dumps(stored))
    again = syn.generate_dataset(root, SIZES, duration_s=0.15, seed=5, compression="gzip")
    assert again["generated"] == 0 and again["skipped"] == 2
    with pytest.raises(FormatError, match="other settings"):
        syn.generate_dataset(root, SIZES, duration_s=0.15, seed=5, compression="gzip",
                             config=syn.SyntheticSceneConfig(clothing_kinds=("white",)))


def test_clothing_textures():
    labels = part_label_map(256)
    cloth = np.isin(labels, [PART_NAMES.index(p) for p in ("torso", "arms", "legs")])
    white = syn.clothing_texture("white", 1)
    black = syn.clothing_texture("black", 1)
    assert np.all(white[cloth] == 1.0) and np.all(black[cloth] == 0.0)
    pattern = syn.clothing_texture("pattern60", 2)
    assert set(np.unique(pattern[cloth])) == {0.0, 1.0}
    cells = (np.arange(256) * 60) // 256  # nearest upsampling of the 60 x 60 grid: one value per cell
    cell_id = (cells[:, None] * 60 + cells[None, :])[cloth]
    lo = np.full(3600, 2.0)
    hi = np.full(3600, -1.0)
    np.minimum.at(lo, cell_id, pattern[cloth])
    np.maximum.at(hi, cell_id, pattern[cloth])
    used = hi >= 0
    assert used.sum() > 500 and np.array_equal(lo[used], hi[used])
    for kind in syn.CLOTHING_KINDS:
        tex = syn.clothing_texture(kind, 3)
        assert tex.shape == (256, 256) and tex.dtype == np.float32 and 0 <= tex.min() and tex.max() <= 1
        np.testing.assert_array_equal(tex, syn.clothing_texture(kind, 3))
    with pytest.raises(ValueError, match="kind"):
        syn.clothing_texture("tartan", 0)


def test_cli_maps_arguments_onto_generate_dataset(monkeypatch, tmp_path, capsys):
    calls = []
    monkeypatch.setattr(syn, "generate_dataset", lambda root, sizes, **kw: calls.append((root, sizes, kw)) or {"ok": 1})
    assert cli.main([str(tmp_path), "--sequences", "10", "--split-sizes", "train=7,test=3", "--seconds", "1.5",
                     "--seed", "9", "--device", "cuda", "--workers", "3", "--no-progress"]) == 0
    ((root, sizes, kw),) = calls
    assert root == str(tmp_path) and sizes == {"train": 7, "val": 0, "test": 3}
    assert kw == {"duration_s": 1.5, "seed": 9, "device": "cuda", "workers": 3, "compression": "blosc-zstd",
                  "progress": False, "threads": None, "config": syn.SyntheticSceneConfig(), "time_budget_s": None}
    assert json.loads(capsys.readouterr().out) == {"ok": 1}
    assert cli.main([str(tmp_path), "--sequences", "4", "--clothing", "white", "stripes"]) == 0
    assert calls[-1][2]["config"].clothing_kinds == ("white", "stripes")
    assert cli.main([str(tmp_path), "--sequences", "4", "--clothing", "tartan"]) == 2
    assert "davis-make-dataset: error: argument --clothing: expected a non-empty subset" in capsys.readouterr().err
    assert cli.main([str(tmp_path), "--sequences", "4", "--vehicles", "0", "2"]) == 0
    assert calls[-1][2]["config"] == syn.SyntheticSceneConfig(vehicle_counts=(0, 2))
    assert cli.main([str(tmp_path), "--sequences", "4", "--vehicles", "3", "1"]) == 2
    assert "argument --vehicles: expected 0 <= min <= max, got (3, 1)" in capsys.readouterr().err
    assert cli.main([str(tmp_path), "--sequences", "4", "--person-height", "25", "125",
                     "--test-scale-probability", "0"]) == 0
    assert calls[-1][2]["config"] == syn.SyntheticSceneConfig(person_height_px=(25.0, 125.0), test_scale_probability=0.0)
    assert cli.main([str(tmp_path), "--sequences", "4", "--test-scale-probability", "1.5"]) == 2
    assert "argument --test-scale-probability: expected a number in [0, 1], got '1.5'" in capsys.readouterr().err
    assert cli.parse_split_sizes(None, 24) == {"train": 18, "val": 3, "test": 3}
    assert cli.main([str(tmp_path), "--sequences", "10", "--split-sizes", "train=7"]) == 2
    assert cli.main([str(tmp_path), "--sequences", "0"]) == 2
    assert cli.main([str(tmp_path), "--sequences", "4", "--threads", "0"]) == 2  # torch.set_num_threads(0) crashes
    assert "argument --threads: expected an integer >= 1, got '0'" in capsys.readouterr().err
    assert cli.main(["--out", str(tmp_path / "new"), "--sequences", "4", "-q"]) == 0  # the vocabulary's spelling
    assert calls[-1][0] == str(tmp_path / "new") and calls[-1][2]["progress"] is False
    assert cli.main([str(tmp_path), "--out", str(tmp_path), "--sequences", "4"]) == 2
    assert "argument --out: not allowed with a positional OUT_DIR" in capsys.readouterr().err
    # --recipe gen1like, with the scene options over it; --time-budget-min in seconds
    assert cli.main([str(tmp_path), "--sequences", "4", "--recipe", "gen1like", "--time-budget-min", "2.5"]) == 0
    assert calls[-1][2]["config"] == syn.GEN1_LIKE_SCENES and calls[-1][2]["time_budget_s"] == 150.0
    assert cli.main([str(tmp_path), "--sequences", "4", "--recipe", "gen1like", "--vehicles", "0", "0"]) == 0
    assert calls[-1][2]["config"] == dataclasses.replace(syn.GEN1_LIKE_SCENES, vehicle_counts=(0, 0))
    assert cli.main([str(tmp_path), "--sequences", "4", "--recipe", "gen2"]) == 2
    assert cli.main([str(tmp_path), "--sequences", "4", "--time-budget-min", "0"]) == 2


def test_gen1like_recipe_draws_an_atis_like_sensor_and_painted_cars_and_keeps_the_test_subsets():
    recipe = syn.SCENE_RECIPES["gen1like"]
    assert syn.SCENE_RECIPES["bundled"] == syn.SyntheticSceneConfig()
    for seed in range(8):
        scene = syn.sample_scene(np.random.default_rng(seed), "train", recipe)
        sim = scene.simulator
        assert 0.25 * 0.85 <= sim.threshold_on <= 0.45 * 1.15 and 500 <= sim.refractory_us <= 2000
        assert 50 <= sim.cutoff_hz <= 300 and 1e-4 <= sim.hot_pixel_fraction <= 1e-3 and sim.hot_pixel_rate_hz >= 20
        assert 1 <= len(scene.vehicles) <= 3
        assert all(c.contrast >= 0.5 and c.pattern in ("stripes", "checks") for c in scene.vehicles)
        assert all(p.clothing == "parts_grey" for p in scene.people)
    # the bundled recipe draws exactly what it drew before hot pixels and car paints were options
    plain = syn.sample_scene(np.random.default_rng(3), "train", syn.SyntheticSceneConfig(vehicle_counts=(1, 2)))
    assert plain.simulator.hot_pixel_fraction == 0.0
    assert {c.pattern for seed in range(12) for c in syn.sample_scene(
        np.random.default_rng(seed), "train", syn.SyntheticSceneConfig(vehicle_counts=(2, 2))).vehicles} == set(
        syn.PAINT_PATTERNS)
    for job in syn.dataset_plan({"train": 0, "val": 0, "test": 9}):
        held_out = syn.scene_for_job(job, 0, recipe)
        assert held_out.vehicles == () and held_out.people[0].clothing == syn.scene_for_job(job, 0).people[0].clothing
    with pytest.raises(ValueError, match="vehicle_patterns"):
        syn.SyntheticSceneConfig(vehicle_patterns=("tartan",))


def test_time_budget_renders_val_and_test_first_and_a_rerun_continues(tmp_path, monkeypatch):
    from davis_rig.training.synthetic import plan

    order = []
    real = plan._generate_one
    monkeypatch.setattr(plan, "_generate_one", lambda root, job, *a: order.append(job.split) or real(root, job, *a))
    sizes = {"train": 2, "val": 1, "test": 1}
    root = tmp_path / "ds"
    nothing = syn.generate_dataset(root, sizes, duration_s=0.05, seed=1, compression="gzip", threads=1,
                                   time_budget_s=0.0)
    assert (nothing["generated"], nothing["remaining"], order) == (0, 4, [])
    ticks = iter(range(1000))  # a clock that moves 1 s per reading: the budget of 1.5 s lets one sequence start
    monkeypatch.setattr(plan.time, "perf_counter", lambda: float(next(ticks)))
    first = syn.generate_dataset(root, sizes, duration_s=0.05, seed=1, compression="gzip", threads=1,
                                 time_budget_s=1.5)
    monkeypatch.undo()
    monkeypatch.setattr(plan, "_generate_one", lambda root, job, *a: order.append(job.split) or real(root, job, *a))
    assert (first["generated"], first["remaining"], order) == (1, 3, ["val"])
    rest = syn.generate_dataset(root, sizes, duration_s=0.05, seed=1, compression="gzip", threads=1)
    assert (rest["generated"], rest["skipped"], rest["remaining"]) == (3, 1, 0)
    assert order == ["val", "test", "train", "train"]
    card = json.loads((root / "dataset_card.json").read_text())
    assert {k: v["sequences"] for k, v in card["splits"].items()} == sizes


def test_held_out_evaluation_scores_each_subset(tiny_dataset, tmp_path):
    import torch

    from davis_rig.models.rvt import RVTConfig, RVTDetector
    from davis_rig.models.rvt.checkpoint import save_safetensors
    from davis_rig.training.evaluate import SplitScoreConfig, evaluate_split

    root, _ = tiny_dataset
    torch.manual_seed(0)
    weights = save_safetensors(RVTDetector(RVTConfig.mini()), tmp_path / "mini.safetensors")
    result = evaluate_split(root, weights, config=SplitScoreConfig(skip_first_us=0, seq_len=1))
    assert sorted(result["groups"]) == ["all", "white", "white/large"]
    for r in result["groups"].values():
        assert r["sequences"] == 1 and r["num_labels"] == 3 and 0.0 <= r["AP"] <= 1.0
        assert r["seqasr"][0.25]["num_sequences"] == 3
