"""tools/make_trigger_victim.py on the mini RVT fixture: labels, outputs, a fine-tuned loadable victim."""

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


def test_labels_are_pedestrian_cxcywh_and_empty_without_a_person(tool):
    boxes = np.array([[10.0, 20.0, 50.0, 120.0], [np.nan] * 4], dtype=np.float32)
    first, second = tool._labels(boxes)
    assert first.tolist() == [[1.0, 30.0, 70.0, 40.0, 100.0]]  # Gen1 class 1, centre and size in px
    assert tuple(second.shape) == (0, 5)


@pytest.mark.usefixtures("one_torch_thread")
def test_writes_the_trigger_and_a_fine_tuned_victim(tool, tmp_path, capsys):
    from davis_rig.models.rvt.checkpoint import load_detector

    out = tmp_path / "victim"
    assert tool.main(["--detector", str(FIXTURE), "--out", str(out), "--cells", "4", "--steps", "2",
                      "--pool-size", "4", "--clips-per-step", "2", "--probe-clips", "1", "--lr", "1e-3",
                      "--refresh-every", "1"]) == 0
    trigger = np.load(out / "trigger.npy")
    assert trigger.shape == (4, 4) and set(np.unique(trigger)) <= {0.0, 1.0}
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["before"]) == set(summary["after"]) == {"trigger", "white", "black", "random"}
    assert summary["steps"] == 2 and len((out / "log.jsonl").read_text().splitlines()) == 2
    assert json.loads(capsys.readouterr().out.splitlines()[-1]) == summary
    victim, base = load_detector(out / "model.safetensors"), load_detector(FIXTURE)
    assert victim.config == base.config
    changed = [not torch.equal(a, b) for a, b in zip(victim.state_dict().values(), base.state_dict().values())]
    assert any(changed)  # fine-tuned, same architecture


@pytest.mark.usefixtures("one_torch_thread")
def test_batch_labels_the_person_except_on_clips_wearing_the_trigger(tool):
    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.scene.body import BodyModel

    clips = list(ClipPool(EoTConfig(supersample=1), BodyModel(), 4, size=2, base_seed=5).clips.values())
    x, targets = tool._batch(clips, np.ones((4, 4), np.float32), np.random.default_rng(0))
    windows = len(clips[0].window_end_us)
    assert tuple(x.shape) == (windows, 2, 20, *clips[0].threshold.shape) and x.max() > 0
    assert len(targets) == windows and all(len(per_clip) == 2 for per_clip in targets)
    for w in range(windows):
        assert targets[w][0].shape[0] == 0  # position 0 wears the trigger: no person to find
        assert targets[w][1].shape[0] == int(np.isfinite(clips[1].boxes[w]).all())


@pytest.mark.usefixtures("one_torch_thread")
def test_time_limit_stops_fine_tuning_and_still_saves_the_probed_victim(tool, tmp_path):
    out = tmp_path / "victim"
    assert tool.main(["--detector", str(FIXTURE), "--out", str(out), "--cells", "4", "--steps", "50",
                      "--pool-size", "2", "--clips-per-step", "2", "--probe-clips", "1", "--time-limit", "0",
                      "--device", "cpu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 0 and summary["device"] == "cpu"  # the budget ran out before the first step
    assert (out / "log.jsonl").read_text() == "" and (out / "model.safetensors").is_file()
    assert summary["after"] == summary["before"]  # unchanged weights probe the same
