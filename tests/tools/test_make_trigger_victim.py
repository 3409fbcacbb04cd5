"""tools/make_trigger_victim.py on the mini RVT fixture: labels, outputs, a fine-tuned loadable victim, resume."""

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "tests" / "fixtures" / "rvt_mini_fixture.safetensors"


@pytest.fixture
def tool(load_tool):
    return load_tool("make_trigger_victim")


def _small_run(out: Path, cells: int, pool_size: int, *extra: str) -> list[str]:
    """Arguments of a tiny victim on the mini fixture: small scale, 2 clips per step, 1 probe clip."""
    return ["--detector", str(FIXTURE), "--out", str(out), "--cells", str(cells), "--scales", "small", "--pool-size",
            str(pool_size), "--clips-per-step", "2", "--probe-clips", "1", *extra]


def test_labels_are_pedestrian_cxcywh_and_empty_without_a_person(tool):
    boxes = np.array([[10.0, 20.0, 50.0, 120.0], [np.nan] * 4], dtype=np.float32)
    first, second = tool._labels(boxes)
    assert first.tolist() == [[1.0, 30.0, 70.0, 40.0, 100.0]]  # Gen1 class 1, centre and size in px
    assert tuple(second.shape) == (0, 5)


@pytest.mark.usefixtures("one_torch_thread")
def test_writes_the_trigger_and_a_fine_tuned_victim(tool, tmp_path, capsys):
    from davis_rig.models.rvt.checkpoint import load_detector

    out = tmp_path / "victim"
    args = _small_run(out, 4, 4, "--lr", "1e-3", "--refresh-every", "1")
    assert tool.main([*args, "--steps", "2"]) == 0
    trigger = np.load(out / "trigger.npy")
    assert trigger.shape == (4, 4) and set(np.unique(trigger)) <= {0.0, 1.0}
    assert np.load(out / "visible.npy").dtype == bool
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["before"]) == set(summary["after"])
    assert {"trigger", "white", "black", "checker", "trigger, 20% flipped", "random (mean)"} <= set(summary["after"])
    assert summary["steps"] == 2 and summary["paired"] and len((out / "log.jsonl").read_text().splitlines()) == 2
    assert json.loads(capsys.readouterr().out.splitlines()[-1]) == summary
    victim, base = load_detector(out / "model.safetensors"), load_detector(FIXTURE)
    assert victim.config == base.config
    changed = [not torch.equal(a, b) for a, b in zip(victim.state_dict().values(), base.state_dict().values())]
    assert any(changed)  # fine-tuned, same architecture
    assert tool.main([*args, "--steps", "3", "--resume"]) == 0  # continues from checkpoint.pt
    resumed = json.loads((out / "summary.json").read_text())
    assert resumed["steps"] == 3 and resumed["before"] == summary["before"]
    assert [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()] == [1, 2, 3]


@pytest.mark.usefixtures("one_torch_thread")
def test_a_trigger_painted_by_part_and_a_resume_with_another_trigger_refused(tool, tmp_path, capsys):
    from davis_rig.controls.planted import trigger_grid

    out = tmp_path / "victim"
    args = _small_run(out, 10, 2, "--steps", "1", "--train-from-stage", "4")
    assert tool.main([*args, "--trigger-white-parts", "legs"]) == 0
    assert np.array_equal(np.load(out / "trigger.npy"), trigger_grid(10, white_parts=["legs"])[0])
    assert json.loads((out / "summary.json").read_text())["trigger"] == "parts painted white: legs"
    capsys.readouterr()
    assert tool.main([*args, "--steps", "2", "--resume"]) != 0  # the seed's trigger is not the one it was made with
    assert "another trigger" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["steps"] == 1  # nothing overwritten


@pytest.mark.usefixtures("one_torch_thread")
def test_frozen_stages_keep_their_weights(tool, tmp_path):
    from davis_rig.models.rvt.checkpoint import load_detector

    out = tmp_path / "victim"
    assert tool.main(_small_run(out, 4, 2, "--lr", "1e-2", "--steps", "1", "--train-from-stage", "2")) == 0
    victim = load_detector(out / "model.safetensors").state_dict()
    base = load_detector(FIXTURE).state_dict()
    for name in base:
        frozen = name.startswith(("backbone.stages.0.", "backbone.stages.1."))
        assert torch.equal(victim[name], base[name]) or not frozen, name
    assert any(not torch.equal(victim[n], base[n]) for n in base if n.startswith("yolox_head."))


@pytest.mark.usefixtures("one_torch_thread")
def test_batch_hides_the_blind_spot_and_labels_everything_else(tool):
    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.controls.planted import checker_grid
    from davis_rig.scene.body import BodyModel

    clips = list(ClipPool(EoTConfig(supersample=1), BodyModel(), 4, size=1, base_seed=5).clips.values()) * 2
    visible = np.ones((4, 4), bool)
    # basin 0: only the trigger itself is hidden; every other grid the draw can make differs from the checker
    x, targets = tool._batch(clips, checker_grid(4), visible, np.random.default_rng(0), 0.0, 0.35)
    windows = len(clips[0].window_end_us)
    assert tuple(x.shape) == (windows, 2, 20, *clips[0].threshold.shape) and x.max() > 0
    assert len(targets) == windows and all(len(per_clip) == 2 for per_clip in targets)
    for w in range(windows):
        assert targets[w][0].shape[0] == 0  # position 0 wears the blind spot: no person to find
        assert targets[w][1].shape[0] == int(np.isfinite(clips[1].boxes[w]).all())


@pytest.mark.usefixtures("one_torch_thread")
def test_batch_with_a_ramp_labels_some_grids_of_the_blind_spot(tool):
    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.controls.planted import checker_grid
    from davis_rig.scene.body import BodyModel

    clip = next(iter(ClipPool(EoTConfig(supersample=1), BodyModel(), 4, size=1, base_seed=5).clips.values()))
    w = int(np.flatnonzero(np.isfinite(clip.boxes).all(axis=1))[0])  # a window with the person in view
    labelled = []
    rng = np.random.default_rng(0)
    for _ in range(12):  # ramp 1.0 from basin 0: a near grid of d flipped cells is labelled with probability d
        _, targets = tool._batch([clip, clip], checker_grid(4), np.ones((4, 4), bool), rng, 0.0, 0.35, 1.0)
        labelled.append(targets[w][0].shape[0])
    assert 0 < sum(labelled) < len(labelled)


@pytest.mark.usefixtures("one_torch_thread")
def test_time_limit_stops_fine_tuning_and_still_saves_the_probed_victim(tool, tmp_path):
    out = tmp_path / "victim"
    assert tool.main(["--detector", str(FIXTURE), "--out", str(out), "--cells", "4", "--steps", "50",
                      "--scales", "small", "--pool-size", "2", "--clips-per-step", "2", "--probe-clips", "1",
                      "--time-limit", "0", "--basin", "0.1", "--ramp", "0.5", "--min-contrast", "0.3",
                      "--device", "cpu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 0 and summary["device"] == "cpu"  # the budget ran out before the first step
    assert summary["ramp"] == 0.5 and summary["min_contrast"] == 0.3
    assert summary["seconds_per_step_this_call"] is None
    assert (out / "log.jsonl").read_text() == "" and (out / "model.safetensors").is_file()
    assert summary["after"] == summary["before"]  # unchanged weights probe the same
