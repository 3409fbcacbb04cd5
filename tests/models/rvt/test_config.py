"""RVTConfig: presets, derived sizes, parsing of official / fixture configs, validation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from davis_rig.errors import FormatError
from davis_rig.models.rvt.config import RVTConfig, padded_input_hw

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


@pytest.mark.parametrize(
    ("preset", "letter", "dims", "heads", "bottlenecks", "hidden"),
    [
        (RVTConfig.tiny, "t", (32, 64, 128, 256), (1, 2, 4, 8), 1, 64),
        (RVTConfig.small, "s", (48, 96, 192, 384), (2, 4, 8, 16), 1, 96),
        (RVTConfig.base, "b", (64, 128, 256, 512), (2, 4, 8, 16), 2, 128),
    ],
)
def test_presets_match_official_resolved_configs(preset, letter, dims, heads, bottlenecks, hidden):
    config = preset()
    listing = json.loads((FIXTURES / f"keys_rvt_{letter}_gen1.json").read_text())
    derived = listing["derived"]
    assert config.stage_dims == dims == tuple(derived["stage_dims"])
    assert config.num_heads == heads == tuple(derived["num_heads_per_stage"])
    assert config.fpn_num_bottlenecks == bottlenecks == derived["fpn_num_bottlenecks_per_csp"]
    assert config.head_hidden_dim == hidden == derived["head_hidden_dim"]
    assert config.partition_size == (8, 10) == tuple(derived["partition_size"])
    assert config.in_res_hw == tuple(derived["in_res_hw"])
    assert config.stage_strides == tuple(derived["strides"])
    assert config.head_strides == tuple(derived["head_strides"])
    assert config.fpn_in_channels == tuple(derived["fpn_in_channels"])
    # the official hydra model config parses to the same preset
    parsed = RVTConfig.from_dict(listing["model_config_resolved"])
    assert parsed == config
    assert parsed.name == config.name


def test_derived_sizes_at_gen1_resolution():
    config = RVTConfig.tiny()
    assert config.num_anchors == 32 * 40 + 16 * 20 + 8 * 10 == 1680
    assert config.num_outputs == 7
    assert config.state_shapes(3) == [
        ((3, 32, 64, 80), (3, 32, 64, 80)),
        ((3, 64, 32, 40), (3, 64, 32, 40)),
        ((3, 128, 16, 20), (3, 128, 16, 20)),
        ((3, 256, 8, 10), (3, 256, 8, 10)),
    ]
    assert config.flat_state_names == ("h1", "c1", "h2", "c2", "h3", "c3", "h4", "c4")
    assert padded_input_hw((240, 304)) == (256, 320)
    assert padded_input_hw((240, 304), partition_split_32=2) == (256, 320)
    assert padded_input_hw((260, 346)) == (288, 352)


def test_partition_split_changes_partition_size():
    config = RVTConfig.tiny(partition_split_32=2)
    assert config.partition_size == (4, 5)


def test_mini_fixture_config_parses(mini_fixture):
    config = RVTConfig.from_dict(mini_fixture.metadata["config"])  # JSON text
    assert config == RVTConfig.mini()
    assert config.name == "RVT-mini"
    assert config.stage_dims == tuple(mini_fixture.config["backbone"]["stage_dims"]) == (8, 8, 16, 32)
    assert config.num_heads == tuple(mini_fixture.config["backbone"]["attention"]["heads_per_stage"])
    assert config.head_hidden_dim == mini_fixture.config["head"]["hidden_dim"] == 8
    assert config.num_anchors == mini_fixture.config["head"]["num_anchors"]
    # the hydra-style config stored beside it gives the same architecture
    assert RVTConfig.from_dict(json.loads(mini_fixture.metadata["hydra_model_config"])) == config


def test_to_dict_round_trip():
    for config in RVTConfig.presets().values():
        assert RVTConfig.from_dict(config.to_dict()) == config
        assert RVTConfig.from_dict(config.to_json()).name == config.name


def test_unsupported_official_options_are_refused():
    listing = json.loads((FIXTURES / "keys_rvt_t_gen1.json").read_text())
    hydra = json.loads(json.dumps(listing["model_config_resolved"]))
    hydra["backbone"]["stage"]["attention"]["use_torch_mha"] = True
    hydra["backbone"]["stage"]["lstm"]["dws_conv"] = True
    with pytest.raises(FormatError, match=r"use_torch_mha=True.*dws_conv=True"):
        RVTConfig.from_dict(hydra)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"embed_dim": 32, "dim_head": 24}, "not a multiple of dim_head"),
        ({"embed_dim": 32, "dim_head": 32, "in_res_hw": (240, 304)}, r"in_res_hw: expected 2 positive multiples of 32"),
        ({"embed_dim": 32, "dim_head": 32, "num_blocks": (1, 1, 1)}, "num_blocks"),
        ({"embed_dim": 32, "dim_head": 32, "partition_split_32": 3}, "partition_split_32"),
        ({"embed_dim": 32, "dim_head": 32, "stem_patch_size": 8}, r"stage 4 map \(4, 5\) \(stride 64\) is not divisible"),
    ],
)
def test_invalid_configs_raise(kwargs, message):
    with pytest.raises(FormatError, match=message):
        RVTConfig(**kwargs)


def test_from_dict_errors():
    with pytest.raises(FormatError, match="not valid JSON"):
        RVTConfig.from_dict("{not json")
    with pytest.raises(FormatError, match="unknown keys"):
        RVTConfig.from_dict({"embed_dim": 32, "dim_head": 32, "depth": 3})
    with pytest.raises(FormatError, match="missing required keys"):
        RVTConfig.from_dict({"embed_dim": 32})


def test_package_import_does_not_import_torch(fresh_python):
    code = (
        "import sys; import davis_rig.models.rvt as r; c = r.RVTConfig.tiny(); "
        "assert c.num_anchors == 1680; assert 'torch' not in sys.modules, 'torch imported'; "
        "d = r.RVTDetector; assert 'torch' in sys.modules and d.__name__ == 'RVTDetector'"
    )
    fresh_python(code)


def test_nano_preset_is_rvt_t_at_half_width():
    config = RVTConfig.presets()["nano"]
    assert config == RVTConfig.nano() and config.name == "RVT-nano"
    assert config.stage_dims == (16, 32, 64, 128) and config.num_heads == (1, 2, 4, 8)
    assert config.fpn_num_bottlenecks == 1 and config.in_res_hw == (256, 320)
    torch = pytest.importorskip("torch")
    from davis_rig.models.rvt.detector import RVTDetector

    torch.manual_seed(0)
    assert sum(p.numel() for p in RVTDetector(config).parameters()) == 1_115_093  # the docstring's count
