"""RVTDetector state_dict == the official checkpoint key listings (minus ``mdl.``): keys, order, shapes, dtypes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from davis_rig.models.rvt import RVTConfig
from davis_rig.models.rvt.detector import RVTDetector

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


@pytest.mark.parametrize(
    ("preset", "letter", "num_params", "num_entries"),
    [
        (RVTConfig.tiny, "t", 4_405_141, 376),
        (RVTConfig.small, "s", 9_870_165, 376),
        (RVTConfig.base, "b", 18_536_469, 424),
    ],
)
def test_state_dict_matches_official_listing(preset, letter, num_params, num_entries):
    listing = json.loads((FIXTURES / f"keys_rvt_{letter}_gen1.json").read_text())
    model = RVTDetector(preset())
    ours = {key: (tuple(t.shape), str(t.dtype).replace("torch.", "")) for key, t in model.state_dict().items()}
    prefix = listing["checkpoint_state_dict_prefix"]
    official = {
        entry["key"][len(prefix) :]: (tuple(entry["shape"]), entry["dtype"]) for entry in listing["state_dict"]
    }
    assert sorted(set(official) - set(ours)) == []  # missing
    assert sorted(set(ours) - set(official)) == []  # unexpected
    assert ours == official  # shapes and dtypes
    assert list(ours) == list(official)  # same order as the official module registers them
    assert len(ours) == num_entries == listing["num_state_dict_entries"]
    assert sum(p.numel() for p in model.parameters()) == num_params == listing["num_parameters_total"]
    per_part = {
        part: sum(p.numel() for p in getattr(model, part).parameters()) for part in ("backbone", "fpn", "yolox_head")
    }
    assert per_part == listing["num_parameters_per_part"]
    assert len(list(model.buffers())) == listing["num_buffer_tensors"]


def test_mini_state_dict_matches_fixture(mini_fixture):
    model = RVTDetector(RVTConfig.mini())
    fixture = mini_fixture.state_dict()
    ours = model.state_dict()
    assert set(ours) == set(fixture)
    assert {k: tuple(v.shape) for k, v in ours.items()} == {k: tuple(v.shape) for k, v in fixture.items()}
    assert {k: v.dtype for k, v in ours.items()} == {k: v.dtype for k, v in fixture.items()}
    assert sum(p.numel() for p in model.parameters()) == mini_fixture.config["num_parameters"] == 80_765


def test_first_window_block_has_no_norm1():
    keys = RVTDetector(RVTConfig.mini()).state_dict().keys()
    for stage in range(4):
        base = f"backbone.stages.{stage}.att_blocks.0"
        assert f"{base}.att_window.norm1.weight" not in keys
        assert f"{base}.att_grid.norm1.weight" in keys


def test_no_state_buffers_besides_batchnorm():
    model = RVTDetector(RVTConfig.mini())
    suffixes = {name.rsplit(".", 1)[-1] for name, _ in model.named_buffers()}
    assert suffixes == {"running_mean", "running_var", "num_batches_tracked"}
