"""Checkpoint io: Lightning .ckpt, plain .pt/.pth, safetensors; safe unpickling; strict readable reports."""

from __future__ import annotations

import os
from dataclasses import replace

import pytest
import torch

from davis_rig.errors import CheckpointError, FormatError
from davis_rig.models.rvt import RVTConfig, load_detector, read_state_dict, save_safetensors
from davis_rig.models.rvt.checkpoint import infer_config, metadata_config
from davis_rig.models.rvt.detector import RVTDetector


@pytest.fixture(scope="module")
def mini_weights(mini_fixture) -> dict[str, torch.Tensor]:
    return mini_fixture.state_dict()


def _assert_same_weights(model: RVTDetector, weights: dict[str, torch.Tensor]) -> None:
    ours = model.state_dict()
    assert list(ours) == list(RVTDetector(model.config).state_dict())
    assert set(ours) == set(weights)
    for key, value in weights.items():
        assert torch.equal(ours[key], value), key


def test_lightning_ckpt_is_loaded_with_prefix_stripped(tmp_path, mini_weights):
    path = tmp_path / "rvt.ckpt"
    torch.save(
        {
            "epoch": 7,
            "global_step": 123,
            "pytorch-lightning_version": "1.8.6",
            "state_dict": {"mdl." + key: value for key, value in mini_weights.items()},
            "optimizer_states": [{"state": {0: {"exp_avg": torch.zeros(3)}}, "param_groups": [{"lr": 1e-3}]}],
        },
        path,
    )
    weights = read_state_dict(path)
    assert set(weights) == set(mini_weights)
    model = load_detector(path, config=RVTConfig.mini())
    assert not model.training
    _assert_same_weights(model, mini_weights)
    # without a config the variant is inferred from the shapes (mini preset)
    assert load_detector(path).config.name == "RVT-mini"


@pytest.mark.parametrize("suffix", [".pt", ".pth"])
@pytest.mark.parametrize("prefixed", [False, True])
def test_plain_state_dict_files(tmp_path, mini_weights, suffix, prefixed):
    path = tmp_path / f"weights{suffix}"
    torch.save({("mdl." if prefixed else "") + k: v for k, v in mini_weights.items()}, path)
    _assert_same_weights(load_detector(path), mini_weights)


def test_safetensors_round_trip_keeps_config(tmp_path, mini_weights):
    config = replace(RVTConfig.mini(), num_classes=2, name="my-mini")
    model = RVTDetector(config)
    model.load_state_dict(mini_weights)
    path = save_safetensors(model, tmp_path / "mini.safetensors", metadata={"source": "test"})
    assert metadata_config(path) == config
    loaded = load_detector(path)
    assert loaded.config == config and loaded.config.name == "my-mini"
    _assert_same_weights(loaded, mini_weights)
    with pytest.raises(FormatError, match="must be str"):
        save_safetensors(model, tmp_path / "bad.safetensors", metadata={"epoch": 3})


def test_fixture_safetensors_is_read_as_a_checkpoint(mini_fixture, mini_weights):
    weights = read_state_dict(mini_fixture.path)  # skips the input./step* tensors, strips state_dict.mdl.
    assert set(weights) == set(mini_weights)


def _save_checkpoint_with_code(tmp_path, weights: dict[str, torch.Tensor]):
    """Save a Lightning-like checkpoint whose unpickling would run ``touch <marker>``.

    Returns:
        (checkpoint path, marker path): the marker exists only if the payload was executed.
    """
    marker = tmp_path / "executed"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {"mdl." + k: v for k, v in weights.items()}, "callbacks": Payload()}, path)
    return path, marker


def test_pickle_with_code_is_refused_and_not_executed(tmp_path, mini_weights):
    path, marker = _save_checkpoint_with_code(tmp_path, mini_weights)
    with pytest.raises(CheckpointError, match=r"refused to unpickle.*weights_only=True.*'(posix|os|nt)\.system'"):
        load_detector(path)
    assert not marker.exists()


def test_inert_mode_extracts_weights_without_running_code(tmp_path, mini_weights):
    path, marker = _save_checkpoint_with_code(tmp_path, mini_weights)
    model = load_detector(path, inert_unknown_globals=True)
    assert not marker.exists()
    _assert_same_weights(model, mini_weights)


def test_inert_mode_reads_lightning_like_checkpoint_with_scheduler_objects(tmp_path, mini_weights):
    """Old Lightning/torch checkpoints keep e.g. a scheduler's bound method: weights_only refuses, inert mode works."""
    parameter = torch.nn.Parameter(torch.zeros(3))
    optimizer = torch.optim.AdamW([parameter], lr=1e-3)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=1e-3, total_steps=10)
    checkpoint = {
        "epoch": 1,
        "state_dict": {"mdl." + k: v for k, v in mini_weights.items()},
        "optimizer_states": [optimizer.state_dict()],
        "lr_schedulers": [{**scheduler.state_dict(), "anneal_func": scheduler.step}],  # a bound method
    }
    path = tmp_path / "lightning.ckpt"
    torch.save(checkpoint, path)
    with pytest.raises(CheckpointError, match="inert_unknown_globals=True"):
        read_state_dict(path)
    weights = read_state_dict(path, inert_unknown_globals=True)
    assert set(weights) == set(mini_weights)
    assert all(torch.equal(weights[k], v) for k, v in mini_weights.items())


def test_custom_class_is_refused(tmp_path):
    path = tmp_path / "paths.pt"
    torch.save({"state_dict": {"a": torch.zeros(1)}, "dirpath": tmp_path}, path)
    with pytest.raises(CheckpointError, match=r"global 'pathlib\.\w*Path'"):
        read_state_dict(path)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty"])
def test_corrupt_files_raise_checkpoint_error(tmp_path, mini_weights, damage):
    good = tmp_path / "good.ckpt"
    torch.save({"state_dict": mini_weights}, good)
    path = tmp_path / "bad.ckpt"
    data = good.read_bytes()
    damaged = {"garbage": b"\x00not a checkpoint" * 64, "truncated": data[: len(data) // 2], "empty": b""}
    path.write_bytes(damaged[damage])
    with pytest.raises(CheckpointError, match="not a readable PyTorch checkpoint"):
        load_detector(path)
    bad_st = tmp_path / "bad.safetensors"
    bad_st.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{broken json}...")
    with pytest.raises(CheckpointError, match="not a readable safetensors file"):
        read_state_dict(bad_st)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        read_state_dict(tmp_path / "absent.ckpt")
    other = tmp_path / "weights.bin"
    other.write_bytes(b"1234")
    with pytest.raises(CheckpointError, match=r"unknown checkpoint type '\.bin'"):
        read_state_dict(other)


def test_train_checkpoint_last_pt_is_read_as_its_model_weights(tmp_path, mini_weights):
    from davis_rig.models.rvt.checkpoint import TRAIN_CHECKPOINT_FORMAT
    from davis_rig.training.trainer import CHECKPOINT_FORMAT

    assert TRAIN_CHECKPOINT_FORMAT == CHECKPOINT_FORMAT
    path = tmp_path / "last.pt"  # the layout of davis-train's runs/*/checkpoints/last.pt
    torch.save({"format": CHECKPOINT_FORMAT, "step": 3, "model_config": RVTConfig.mini().to_json(),
                "model": dict(mini_weights), "optimizer": {"state": {}, "param_groups": [{"lr": 1e-3}]},
                "scaler": {}, "best": {"AP": None, "step": None}}, path)
    model = load_detector(path)
    assert model.config.name == "RVT-mini"
    _assert_same_weights(model, mini_weights)
    torch.save({"format": CHECKPOINT_FORMAT, "step": 3}, path)
    with pytest.raises(CheckpointError, match="without model weights"):
        read_state_dict(path)


def test_presets_named_in_the_docstrings_are_all_the_presets():
    for name in RVTConfig.presets():
        assert name in " ".join(infer_config.__doc__.split()) and name in load_detector.__doc__


def test_not_a_state_dict(tmp_path):
    path = tmp_path / "list.pt"
    torch.save([torch.zeros(1)], path)
    with pytest.raises(CheckpointError, match="expected a state dict"):
        read_state_dict(path)
    path = tmp_path / "mixed.pt"
    torch.save({"a": torch.zeros(1), "b": 3}, path)
    with pytest.raises(CheckpointError, match=r"not tensors: \['b'\]"):
        read_state_dict(path)


def test_wrong_variant_gives_a_readable_report(tmp_path, mini_weights):
    path = tmp_path / "mini.pt"
    torch.save(mini_weights, path)
    with pytest.raises(CheckpointError) as info:
        load_detector(path, config=RVTConfig.tiny())
    report = str(info.value)
    assert "does not match the RVT-T model (376 entries expected, 376 found)" in report
    assert "0 missing, 0 unexpected" in report
    assert "backbone.stages.0.downsample_cf2cl.conv.weight: model (32, 20, 7, 7)" in report
    assert "(8, 20, 7, 7)" in report
    assert "... and" in report  # long lists are cut
    assert "hint: the checkpoint's shapes match RVT-mini" in report


def test_missing_and_unexpected_keys_are_listed(tmp_path, mini_weights):
    weights = dict(mini_weights)
    del weights["yolox_head.obj_preds.2.bias"]
    weights["yolox_head.extra.weight"] = torch.zeros(2)
    path = tmp_path / "edited.pt"
    torch.save(weights, path)
    with pytest.raises(CheckpointError) as info:
        load_detector(path, config=RVTConfig.mini())
    report = str(info.value)
    assert "1 missing, 1 unexpected, 0 with a different shape" in report
    assert "missing (1):\n    yolox_head.obj_preds.2.bias" in report
    assert "unexpected (1):\n    yolox_head.extra.weight" in report


@pytest.mark.parametrize("preset", [RVTConfig.tiny, RVTConfig.small, RVTConfig.base])
def test_variant_inferred_from_shapes(preset):
    weights = RVTDetector(preset()).state_dict()
    assert infer_config(weights) == preset()
    assert infer_config(weights).name == preset().name


def test_unknown_shapes_need_an_explicit_config():
    config = RVTConfig(embed_dim=16, dim_head=16, dim_multiplier=(1, 2, 2, 4))
    weights = RVTDetector(config).state_dict()
    with pytest.raises(CheckpointError, match="pass config=RVTConfig"):
        infer_config(weights)
    with pytest.raises(CheckpointError, match="is this an RVT detector checkpoint"):
        infer_config({"conv.weight": torch.zeros(1)})


def test_weights_holding_nan_are_refused_naming_the_file(tmp_path, mini_weights):
    damaged = {k: v.clone() for k, v in mini_weights.items()}
    first_float = next(k for k, v in damaged.items() if v.is_floating_point())
    damaged[first_float].view(-1)[0] = float("nan")
    path = tmp_path / "damaged.pt"
    torch.save(damaged, path)
    with pytest.raises(CheckpointError, match=r"damaged.pt: 1 weight tensors hold NaN or inf"):
        load_detector(path, config=RVTConfig.mini())
