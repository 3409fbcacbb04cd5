"""davis-train: argument mapping onto training.trainer.train (patched), exit codes, one real tiny run."""

from __future__ import annotations

import json

import pytest

from davis_rig.cli import train as cli
from davis_rig.errors import CheckpointError


def test_arguments_map_onto_one_train_call(monkeypatch, tmp_path, capsys):
    calls = []

    def fake_train(data_dir, run_dir, config, **kwargs):
        calls.append((data_dir, run_dir, config, kwargs))
        return {"step": 7, "finished": False, "stopped_by": None}

    monkeypatch.setattr("davis_rig.training.trainer.train", fake_train)
    code = cli.main([str(tmp_path / "data"), "--out", str(tmp_path / "run"), "--preset", "small", "--steps", "100",
                     "--batch", "4", "--seq-len", "5", "--device", "cpu", "--resume", "--ema", "0.999",
                     "--chunk-steps", "7", "--no-augment", "--no-export", "--no-progress", "--workers", "2",
                     "--val-skip-first-ms", "0", "--min-box-side", "4", "--sampling", "random"])
    assert code == 0
    (data_dir, run_dir, config, kwargs), = calls
    assert data_dir == str(tmp_path / "data") and run_dir == str(tmp_path / "run")
    assert (config.model, config.steps, config.batch_size, config.seq_len, config.device) == ("small", 100, 4, 5, "cpu")
    assert config.ema_decay == 0.999 and config.num_workers == 2 and not config.progress
    assert config.val_skip_first_us == 0 and config.min_box_side_px == 4.0 and config.sampling == "random"
    assert config.augment.prob_hflip == 0 and config.augment.zoom_prob == 0 and config.stream_augment.zoom_prob == 0
    from davis_rig.stop import StopOnSignal

    assert isinstance(kwargs.pop("stop"), StopOnSignal)
    assert kwargs == {"resume": True, "max_steps": 7, "time_budget_s": None, "export": False, "init_weights": None}
    out = capsys.readouterr()
    assert json.loads(out.out)["step"] == 7 and "--resume" in out.err
    assert cli.main([str(tmp_path / "data"), "--out", str(tmp_path / "run"), "--init", "w.safetensors", "-q"]) == 0
    assert calls[-1][3]["init_weights"] == "w.safetensors"


def test_init_with_resume_is_an_argument_error_naming_init(tmp_path, capsys):
    assert cli.main([str(tmp_path), "--out", str(tmp_path / "r"), "--resume", "--init", "w.pt",
                     "--preset", "mini", "--device", "cpu", "-q"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "davis-train: error: argument --init: a resumed run continues its checkpoint: no initial weights")
    assert not (tmp_path / "r").exists()


def test_defaults_are_the_rvt_recipe(monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr("davis_rig.training.trainer.train",
                        lambda d, r, c, **k: seen.update(config=c, kwargs=k) or {"step": 1, "finished": True, "stopped_by": None})
    assert cli.main([str(tmp_path), "--out", str(tmp_path / "r")]) == 0
    config = seen["config"]
    assert (config.model, config.steps, config.batch_size, config.seq_len, config.lr) == ("tiny", 400_000, 8, 21, 2e-4)
    assert (config.weight_decay, config.grad_clip, config.div_factor, config.final_div_factor) == (0.0, 1.0, 20, 10_000)
    assert seen["kwargs"]["export"] is True and config.sampling == "mixed"
    assert config.stream_augment.zoom_in_weight == 0 and config.stream_augment.zoom_prob == 0.5


@pytest.mark.parametrize("argv", [["--steps", "0"], ["--batch", "0"], ["--seq-len", "0"], ["--chunk-steps", "0"],
                                  ["--model", "huge"], ["--preset", "huge"], ["--threads", "0"], ["--lr", "nan"],
                                  ["--seed", "-1"]])
def test_bad_arguments_exit_2(tmp_path, argv, capsys):
    assert cli.main([str(tmp_path), "--out", str(tmp_path / "r"), *argv]) == 2
    assert f"davis-train: error: argument {argv[0]}: " in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_the_old_model_option_is_a_hidden_alias_of_preset(monkeypatch, tmp_path, capsys):
    seen = {}
    monkeypatch.setattr("davis_rig.training.trainer.train",
                        lambda d, r, c, **k: seen.update(config=c) or {"step": 1, "finished": True, "stopped_by": None})
    assert cli.main([str(tmp_path), "--out", str(tmp_path / "r"), "--model", "mini", "--threads", "1", "-q"]) == 0
    assert seen["config"].model == "mini" and not seen["config"].progress
    assert "--model" not in cli.build_parser().format_help()


def test_errors_become_messages(monkeypatch, tmp_path, capsys):
    def failing(*args, **kwargs):
        raise CheckpointError("no checkpoint to resume from")

    monkeypatch.setattr("davis_rig.training.trainer.train", failing)
    assert cli.main([str(tmp_path), "--out", str(tmp_path / "r"), "--resume"]) == 4
    assert "davis-train: error: no checkpoint" in capsys.readouterr().err


def test_missing_dataset_is_a_data_error_and_leaves_nothing(tmp_path, capsys):
    code = cli.main([str(tmp_path / "absent"), "--out", str(tmp_path / "r"), "--preset", "mini", "--device", "cpu",
                     "--no-progress"])
    assert code == 4
    assert "no such split folder" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # no empty RUN_DIR/checkpoints


@pytest.mark.parametrize(("argv", "option"), [(["--lr", "-1"], "--lr"), (["--val-every", "-5"], "--val-every"),
                                              (["--ema", "2"], "--ema"), (["--workers", "-1"], "--workers"),
                                              (["--batch", "1"], "--batch: sampling 'mixed' needs"),
                                              (["--time-budget-min", "0"], "")])
def test_bad_values_are_argument_errors_not_file_errors(monkeypatch, tmp_path, capsys, argv, option):
    monkeypatch.setattr("davis_rig.training.trainer.train", lambda *a, **k: pytest.fail("must not train"))
    assert cli.main([str(tmp_path), "--out", str(tmp_path / "r"), *argv]) == 2
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"davis-train: error: argument {option or argv[0]}") and "Traceback" not in err, err
