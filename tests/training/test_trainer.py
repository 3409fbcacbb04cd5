"""The TBPTT trainer on a tiny dataset of moving boxes: loss falls, exact resume, checkpoint and export."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from davis_rig.errors import CheckpointError
from davis_rig.training.augment import AugmentConfig
from davis_rig.training.trainer import TrainConfig, Trainer, _finite_mean, train


def _config(**overrides) -> TrainConfig:
    base = dict(model="mini", steps=12, batch_size=2, seq_len=2, lr=5e-3, val_every=0, ckpt_every=0, log_every=1,
                val_batch_size=2, val_seq_len=4, val_skip_first_us=0, device="cpu", seed=3)
    base.update(overrides)
    return TrainConfig(**base)


def _log(run_dir):
    return [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]


def test_loss_falls_and_validation_runs(moving_boxes_dataset, tmp_path):
    from davis_rig.training.batches import collate_chunks

    torch.set_num_threads(2)
    trainer = Trainer(moving_boxes_dataset, tmp_path / "run", _config(lr=2e-2, augment=AugmentConfig.off(),
                                                                     stream_augment=AugmentConfig.off()))
    batch = collate_chunks([trainer.train_set[3], trainer.train_set[20]])  # one box, two boxes
    losses = [trainer.train_step(batch)["loss"] for _ in range(10)]
    assert all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.8 * np.mean(losses[:3]), losses
    result = trainer.validate()
    assert {"AP", "AP_50", "num_images", "num_labels"} <= set(result)
    assert result["num_labels"] > 0 and 0.0 <= result["AP"] <= 1.0


def test_resume_is_bit_identical_on_cpu(moving_boxes_dataset, tmp_path):
    torch.set_num_threads(2)
    config = _config(steps=3, log_every=1)  # augmentation on: its generator state must be restored too
    straight = Trainer(moving_boxes_dataset, tmp_path / "a", config)
    straight.fit()
    first = Trainer(moving_boxes_dataset, tmp_path / "b", config)
    first.fit(max_steps=1)
    resumed = Trainer(moving_boxes_dataset, tmp_path / "b", config)
    resumed.load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")
    assert resumed.step == 1
    resumed.fit()
    assert _log(tmp_path / "a")[-1]["kind"] == "val"  # val_every=0: validated once, at the end
    assert ([r["loss"] for r in _log(tmp_path / "a") if r["kind"] == "train"]
            == [r["loss"] for r in _log(tmp_path / "b") if r["kind"] == "train"])
    for (name, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.equal(a, b), name
    opt_a, opt_b = straight.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
    assert all(torch.equal(opt_a[k]["exp_avg"], opt_b[k]["exp_avg"]) for k in opt_a)
    assert straight.scheduler.get_last_lr() == resumed.scheduler.get_last_lr()


@pytest.mark.parametrize(("val_every", "val_steps"), [(0, [3]), (2, [2, 3]), (3, [3])])
def test_finished_run_is_validated_at_its_last_step(moving_boxes_dataset, tmp_path, val_every, val_steps):
    torch.set_num_threads(2)
    trainer = Trainer(moving_boxes_dataset, tmp_path / "run", _config(steps=3, val_every=val_every))
    trainer.fit(max_steps=2)  # an unfinished chunk validates only on its val_every steps
    assert [r["step"] for r in _log(tmp_path / "run") if r["kind"] == "val"] == [s for s in val_steps if s <= 2]
    summary = trainer.fit()
    assert [r["step"] for r in _log(tmp_path / "run") if r["kind"] == "val"] == val_steps
    assert summary["val"]["num_labels"] > 0 and summary["best"]["step"] is not None


def test_checkpoint_round_trip_export_and_errors(moving_boxes_dataset, tmp_path):
    from davis_rig.models.rvt.checkpoint import load_detector

    torch.set_num_threads(2)
    config = _config(steps=2, log_every=0, ema_decay=0.99, val_every=2, val_seq_len=8)
    summary = train(moving_boxes_dataset, tmp_path / "run", config)
    assert summary["finished"] and set(summary["export"]) == {"safetensors", "onnx", "model_card"}
    card = (tmp_path / "run" / "export" / "MODEL_CARD.md").read_text()
    assert "synthetic" in card and "| train | 4 | 32 | 32 |" in card and "validation (synthetic, step 2)" in card
    assert (tmp_path / "run" / "checkpoints" / "best.safetensors").is_file()
    trainer = Trainer(moving_boxes_dataset, tmp_path / "run", config)
    trainer.load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    saved = torch.load(tmp_path / "run" / "checkpoints" / "last.pt", weights_only=True)
    for key, value in trainer.model.state_dict().items():
        assert torch.equal(value, saved["model"][key])
    assert trainer.ema.updates == 2 and trainer.step == 2
    exported = load_detector(summary["export"]["safetensors"])
    for key, value in exported.state_dict().items():
        reference = trainer.ema.model.state_dict()[key]
        if value.dtype.is_floating_point:
            assert torch.equal(value, reference.half().float()), key
    vals = [r for r in _log(tmp_path / "run") if r["kind"] == "val"]
    assert len(vals) == 1 and vals[0]["step"] == 2
    # resume of a finished run trains no further; a wrong architecture or a corrupt file is refused
    again = train(moving_boxes_dataset, tmp_path / "run", config, resume=True, export=False)
    assert again["step"] == 2
    other = Trainer(moving_boxes_dataset, tmp_path / "other", _config(model="tiny", steps=2))
    with pytest.raises(CheckpointError):
        other.load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        trainer.load_checkpoint(tmp_path / "bad.pt")
    with pytest.raises(CheckpointError):
        train(moving_boxes_dataset, tmp_path / "nothing", config, resume=True)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (mixed-precision training path)")
@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_cuda_mixed_precision_steps(moving_boxes_dataset, tmp_path, precision):
    config = _config(steps=3, device="cuda", precision=precision, log_every=1, val_every=3, val_seq_len=8)
    trainer = Trainer(moving_boxes_dataset, tmp_path / "run", config)
    summary = trainer.fit()
    assert summary["finished"] and np.isfinite(summary["train"]["loss"])
    assert trainer.amp_dtype == (torch.bfloat16 if precision == "bf16" else torch.float16)
    assert all(p.dtype == torch.float32 for p in trainer.model.parameters())  # fp32 master weights
    resumed = Trainer(moving_boxes_dataset, tmp_path / "run", config)
    resumed.load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    assert resumed.step == 3


def test_log_window_mean_skips_unlabelled_steps_without_warning():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _finite_mean([1.0, float("nan"), 3.0]) == 2.0
        assert np.isnan(_finite_mean([float("nan"), float("nan")]))  # no "Mean of empty slice"


def test_scaler_state_is_restored_only_into_an_enabled_scaler():
    from davis_rig.training.trainer import _restore_scaler

    class FakeScaler:  # an fp16 GPU scaler, without needing a GPU
        def __init__(self, enabled):
            self.enabled, self.loaded = enabled, None

        def is_enabled(self):
            return self.enabled

        def load_state_dict(self, state):
            if not state:
                raise RuntimeError("The source state dict is empty, possibly because it was saved from a disabled "
                                   "instance of GradScaler.")
            self.loaded = state

    gpu = FakeScaler(enabled=True)
    assert not _restore_scaler(gpu, {}) and gpu.loaded is None  # a CPU checkpoint resumed with fp16 on a GPU
    assert not _restore_scaler(FakeScaler(enabled=False), {"scale": 1024.0})  # fp16 state resumed on a CPU
    assert _restore_scaler(gpu, {"scale": 1024.0}) and gpu.loaded == {"scale": 1024.0}


def test_fresh_run_in_a_reused_run_dir_forgets_the_earlier_run(moving_boxes_dataset, tmp_path):
    from safetensors.torch import load_file

    torch.set_num_threads(2)
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best.safetensors").write_bytes(b"weights of an earlier run")
    (run / "log.jsonl").write_text('{"kind": "train", "step": 99}\n')
    with pytest.warns(UserWarning, match="earlier run"):
        summary = train(moving_boxes_dataset, run, _config(steps=1, val_every=0, val_max_sequences=1), export=False)
    assert summary["finished"] and [r["step"] for r in _log(run)] == [1, 1]  # a new log: train + final val
    assert summary["best"]["step"] is None or (run / "checkpoints" / "best.safetensors").stat().st_size > 100
    # a trainer whose run recorded no best exports its own weights, never a best.safetensors left in RUN_DIR
    trainer = Trainer(moving_boxes_dataset, run, _config(steps=1))
    (run / "checkpoints" / "best.safetensors").write_bytes(b"weights of an earlier run")
    paths = trainer.export(tmp_path / "export", onnx=False)
    exported = load_file(paths["safetensors"])
    for key, value in trainer.model.state_dict().items():
        if value.dtype.is_floating_point:
            assert torch.equal(exported[key].float(), value.half().float()), key


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", "foreign"])
def test_resume_from_a_bad_last_pt_is_a_checkpoint_error(moving_boxes_dataset, tmp_path, content):
    last = tmp_path / "run" / "checkpoints" / "last.pt"
    last.parent.mkdir(parents=True)
    if content == "foreign":
        torch.save({"model": {}, "step": 1}, last)  # a torch file of another program
    else:
        last.write_bytes(content)  # empty = truncated
    with pytest.raises(CheckpointError, match=str(last).replace("\\", "\\\\")):
        train(moving_boxes_dataset, tmp_path / "run", _config(), resume=True)


@pytest.mark.parametrize(("field", "value"), [("lr", -1e-3), ("lr", 0.0), ("val_every", -5), ("ckpt_every", -1),
                                              ("log_every", -1), ("num_workers", -1), ("val_max_sequences", 0)])
def test_config_rejects_negative_rates_and_intervals(field, value):
    from davis_rig.errors import ConfigError

    with pytest.raises(ConfigError, match=f"^{field}: "):
        _config(**{field: value})


def test_init_weights_fine_tune_a_trained_detector_and_resume_without_them(moving_boxes_dataset, tmp_path):
    from davis_rig.errors import ConfigError
    from davis_rig.models.rvt.checkpoint import load_detector

    torch.set_num_threads(2)
    first = train(moving_boxes_dataset, tmp_path / "first", _config(steps=2), export=False)
    assert first["finished"]
    weights = tmp_path / "first" / "checkpoints" / "last.pt"
    start = load_detector(weights)
    tuned = Trainer(moving_boxes_dataset, tmp_path / "probe", _config(steps=2, ema_decay=0.99))
    tuned.init_from(start, str(weights))
    for (name, a), b in zip(tuned.model.state_dict().items(), start.state_dict().values()):
        assert torch.equal(a, b), name  # the model and its EMA start at the given weights
    assert all(torch.equal(a, b) for a, b in zip(tuned.ema.model.state_dict().values(), start.state_dict().values()))
    summary = train(moving_boxes_dataset, tmp_path / "ft", _config(steps=3, model="tiny"), init_weights=weights,
                    max_steps=1, export=False)  # the architecture is the weights' (mini), not the preset's
    assert summary["step"] == 1
    rest = train(moving_boxes_dataset, tmp_path / "ft", _config(steps=3, model="tiny"), resume=True, export=False)
    assert rest["finished"] and rest["step"] == 3
    assert torch.load(tmp_path / "ft" / "checkpoints" / "last.pt", weights_only=False)["init_source"] == str(weights)
    card = Trainer(moving_boxes_dataset, tmp_path / "ft", _config(steps=3, model="mini"))
    card.load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt")
    paths = card.export(tmp_path / "ft_export", onnx=False)
    assert f"initial weights: {weights}" in paths["model_card"].read_text()
    with pytest.raises(ConfigError, match="no initial weights"):
        train(moving_boxes_dataset, tmp_path / "ft", _config(steps=3), resume=True, init_weights=weights)
    with pytest.raises(CheckpointError, match="this run is"):
        Trainer(moving_boxes_dataset, tmp_path / "other", _config(model="tiny")).init_from(start, "mini.pt")
    with pytest.raises(CheckpointError):
        train(moving_boxes_dataset, tmp_path / "bad", _config(), init_weights=tmp_path / "missing.safetensors")
    assert not (tmp_path / "bad").exists()
