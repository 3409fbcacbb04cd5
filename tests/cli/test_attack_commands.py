"""``davis-attack optimize`` / ``evaluate`` argument mapping (API patched: the exact call is asserted)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from davis_rig.cli import _attack_commands as cmd


def _parser():
    from davis_rig.cli.attack import build_parser

    return build_parser()


def test_optimize_maps_arguments_onto_one_call(monkeypatch, tmp_path):
    import davis_rig.attack.optimize as opt

    calls = {}
    monkeypatch.setattr(opt, "load_attack_detector",
                        lambda path, device=None: calls.setdefault("det", (path, str(device))))

    def fake(config, detector, out, **kw):
        calls["run"] = (config, detector, out, kw)
        return SimpleNamespace(out_dir=Path(out), steps=3, seconds_per_step=0.5, best_step=3, best_seq_asr=math.nan,
                               final_validation=None)

    monkeypatch.setattr(opt, "optimize_texture", fake)
    args = _parser().parse_args(["optimize", "--out", str(tmp_path), "--cells", "20", "--parts", "torso",
                                 "--iterations", "30", "--max-steps", "3", "--detector", "d.ckpt", "--device", "cpu",
                                 "--resume", "--clips-per-step", "2", "--seed", "4", "--no-progress"])
    assert args.func(args) == 0
    config, detector, out, kw = calls["run"]
    assert calls["det"] == ("d.ckpt", "cpu") and detector == calls["det"] and out == str(tmp_path)
    got = (config.grid_n, config.parts, config.iterations, config.clips_per_step, config.seed)
    assert got == (20, ("torso",), 30, 2, 4)
    assert (config.lr, config.lambda_obj, config.betas) == (1e-4, 1e4, (0.9, 0.99))
    assert config.v2e_gradient == "relaxed"
    assert kw == {"resume": True, "device": __import__("torch").device("cpu"), "progress": False, "max_steps": 3,
                  "motions": ()}


def test_start_takes_a_plain_name_or_a_grid_file_of_the_runs_cells(monkeypatch, tmp_path, capsys):
    import davis_rig.attack.optimize as opt
    from davis_rig.cli.attack import main

    calls = {}
    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: "detector")

    def fake(config, detector, out, **kw):
        calls["config"] = config
        return SimpleNamespace(out_dir=Path(out), steps=1, seconds_per_step=0.5, best_step=1, best_seq_asr=math.nan,
                               final_validation=None)

    monkeypatch.setattr(opt, "optimize_texture", fake)
    grid = (np.arange(16).reshape(4, 4) % 3 == 0).astype(np.float32)
    np.save(tmp_path / "near.npy", grid)
    base = ["optimize", "--out", str(tmp_path / "run"), "--cells", "4", "--device", "cpu", "--quiet"]
    assert main([*base, "--start", str(tmp_path / "near.npy")]) == 0
    assert calls["config"].start == "grid" and np.array_equal(np.array(calls["config"].start_grid), grid)
    assert main([*base, "--start", "black"]) == 0
    assert (calls["config"].start, calls["config"].start_grid) == ("black", None)
    np.save(tmp_path / "small.npy", grid[:2, :2])
    capsys.readouterr()
    assert main([*base, "--start", str(tmp_path / "small.npy")]) == 4  # a 2x2 grid for a 4x4 run: a file error
    assert "small.npy: a 2x2 grid, the run's --cells is 4" in capsys.readouterr().err


def test_mocap_folders_map_onto_the_split_loaders(monkeypatch, tmp_path, capsys):
    """--bvh / --amass DIR: train-split motions for optimize (test split for evaluate); the flags exclude each other."""
    import davis_rig.attack.eot as eot
    import davis_rig.attack.optimize as opt

    calls = []
    monkeypatch.setattr(eot, "bvh_motions", lambda root, split, max_trials=None: calls.append(
        ("bvh", root, split, max_trials)) or ["BVH"])
    monkeypatch.setattr(eot, "amass_motions", lambda root, split, max_trials=None: calls.append(
        ("amass", root, split, max_trials)) or ["AMASS"])
    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: "DET")
    seen = {}

    def fake(config, detector, out, **kw):
        seen.update(kw)
        return SimpleNamespace(out_dir=Path(out), steps=0, seconds_per_step=0.0, best_step=0, best_seq_asr=math.nan,
                               final_validation=None)

    monkeypatch.setattr(opt, "optimize_texture", fake)
    base = ["optimize", "--out", str(tmp_path), "--device", "cpu", "--no-progress"]
    args = _parser().parse_args([*base, "--bvh", "cmu_bvh", "--max-trials", "3"])
    assert args.func(args) == 0 and seen["motions"] == ("BVH",)
    args = _parser().parse_args([*base, "--amass", "amass_cmu"])
    assert args.func(args) == 0 and seen["motions"] == ("AMASS",)
    assert calls == [("bvh", "cmu_bvh", "train", 3), ("amass", "amass_cmu", "train", None)]
    with pytest.raises(SystemExit):
        _parser().parse_args([*base, "--amass", "a", "--bvh", "b"])
    assert "not allowed with argument" in capsys.readouterr().err


def test_evaluate_table1_maps_textures(monkeypatch, tmp_path):
    import davis_rig.attack.optimize as opt
    import davis_rig.attack.report as report
    from davis_rig.attack.evaluate import PAPER_THRESHOLDS

    np.save(tmp_path / "t10.npy", np.eye(10, dtype=np.float32))
    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: "DET")
    seen = {}

    def fake_table1(grids, detector, out, **kw):
        seen.update(grids=grids, detector=detector, out=out, kw=kw)
        md = Path(out) / "table1.md"
        Path(out).mkdir(parents=True, exist_ok=True)
        md.write_text("| Texture |\n")
        return {"markdown": md, "json": md, "plot": md, "rows": []}

    monkeypatch.setattr(report, "table1", fake_table1)
    args = _parser().parse_args(["evaluate", "--table", "1", "--out", str(tmp_path / "o"), "--texture",
                                 f"10={tmp_path / 't10.npy'}", "--scales", "middle", "--headings", "1",
                                 "--no-progress"])
    assert args.func(args) == 0
    assert list(seen["grids"]) == [10] and np.array_equal(seen["grids"][10], np.eye(10, dtype=np.float32))
    config = seen["kw"]["config"]
    assert config.thresholds == PAPER_THRESHOLDS and config.scales == ("middle",)
    assert config.headings_rad == (math.pi / 2,) and seen["kw"]["parts"] == ("torso", "arms", "legs")


FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
BAD_VALUES = [  # (argv after the subcommand, the option the one-line message must name)
    (["optimize", "--lr-min", "1"], "--lr-min"),  # above --lr: ConfigError of AttackConfig
    (["optimize", "--lr-period", "0"], "--lr-period"),
    (["optimize", "--test-sensor-probability", "2"], "--test-sensor-probability"),
    (["optimize", "--walk", "run"], "--walk"),
    (["optimize", "--loss-anchors", "box"], "--loss-anchors"),
    (["optimize", "--cells", "0"], "--cells"),
    (["optimize", "--cells", "300"], "--cells"),  # ConfigError of AttackConfig, mapped onto the option
    (["optimize", "--iterations", "-1"], "--iterations"),
    (["optimize", "--lr", "nan"], "--lr"),
    (["optimize", "--lr", "0"], "--lr"),
    (["optimize", "--parts", "nose"], "--parts"),
    (["optimize", "--parts", "all", "torso"], "--parts"),
    (["optimize", "--clips-per-step", "64"], "--clips-per-step"),
    (["optimize", "--checkpoint-every", "0"], "--checkpoint-every"),
    (["optimize", "--box-margin", "-2"], "--box-margin"),
    (["optimize", "--playback-speed", "inf"], "--playback-speed"),
    (["optimize", "--threads", "0"], "--threads"),
    (["optimize", "--device", "gpu"], "--device"),
    (["optimize", "--seed", "-1"], "--seed"),
    (["optimize", "--max-steps", "0"], "--max-steps"),
    (["optimize", "--detector-step", "cuda_graph", "--device", "cpu"], "--detector-step"),  # needs CUDA
    (["evaluate", "--texture", "nokey"], "--texture"),
    (["evaluate", "--table", "1", "--texture", "ten=x.npy"], "--texture"),
    (["evaluate"], "--texture"),
    (["evaluate", "--texture", "a=x.npy", "--threshold", "1.5"], "--threshold"),
    (["evaluate", "--texture", "a=x.npy", "--thresholds", "nan"], "--thresholds"),
    (["evaluate", "--texture", "a=x.npy", "--scales", "huge"], "--scales"),
    (["evaluate", "--texture", "a=x.npy", "--phases", "-1"], "--phases"),
    (["reproduce", "--table", "2", "--combinations", "torso+nose"], "--combinations"),
    (["reproduce", "--table", "1", "--grids", "0"], "--grids"),
    (["export", "TEXTURE", "--shape", "-1"], "--shape"),
    (["export", "TEXTURE", "--ease", "nan"], "--ease"),
    (["export", "TEXTURE", "--size-mm", "0"], "--size-mm"),
]


@pytest.mark.parametrize("argv, option", BAD_VALUES)
def test_a_bad_value_exits_2_with_one_line_naming_the_option_and_leaves_nothing(argv, option, tmp_path, capsys):
    from davis_rig.cli.attack import main

    out = tmp_path / "out"
    argv = [tmp_path / "grid.npy" if a == "TEXTURE" else a for a in argv]
    np.save(tmp_path / "grid.npy", np.eye(4, dtype=np.float32))
    code = main([str(a) for a in argv] + ["--out", str(out), "--device", "cpu", *(["--quiet"] if argv[0] != "export"
                                                                                  else ["--no-preview"])])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith(f"davis-attack {argv[0]}: error: argument {option}")
    assert not any(line.startswith("Traceback") for line in err) and not out.exists()


@pytest.mark.parametrize("argv", [["optimize", "--detector", "MISSING"], ["evaluate", "--texture", "a=MISSING"],
                                  ["export", "MISSING"], ["optimize", "--resume", "--detector", "FIXTURE"],
                                  ["optimize", "--start", "MISSING"]])
def test_a_missing_or_corrupt_file_exits_4_with_one_line_and_leaves_nothing(argv, tmp_path, capsys):
    from davis_rig.cli.attack import main

    out = tmp_path / "out"
    if "--resume" in argv:  # a corrupt checkpoint
        (out / "checkpoints").mkdir(parents=True)
        (out / "checkpoints" / "last.pt").write_bytes(b"corrupt")
    argv = [str(FIXTURE) if a == "FIXTURE" else str(tmp_path / "missing.npy") if a == "MISSING" else
            a.replace("MISSING", str(tmp_path / "missing.npy")) for a in argv]
    extra = ["--no-preview"] if argv[0] == "export" else ["--device", "cpu", "--quiet"]
    assert main([*argv, "--out", str(out), *extra]) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"davis-attack {argv[0]}: error: ")
    if "--resume" in argv:
        assert str(out / "checkpoints" / "last.pt") in err[0] and "unreadable attack checkpoint" in err[0]
    else:
        assert "missing" in err[0] and not out.exists()


def test_help_lists_the_exit_codes_and_the_vocabulary(capsys):
    from davis_rig.cli.attack import main

    for command in ([], ["optimize"], ["evaluate"], ["reproduce"], ["export"]):
        assert main([*command, "--help"]) == 0
        text = capsys.readouterr().out
        assert "exit codes: 0 ok, 1 internal error, 2 usage" in text and "130 interrupted" in text
        assert "--no-progress" not in text and "--thresholds" not in text
    for command in ("optimize", "evaluate", "reproduce"):
        main([command, "--help"])
        text = capsys.readouterr().out
        assert all(option in text for option in ("--quiet", "--threads", "--detector", "--out"))
    main(["evaluate", "--help"])
    assert "--threshold T" in capsys.readouterr().out
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("davis-attack (davis_rig ")


def test_threshold_takes_one_value_per_use_comma_lists_and_the_old_spelling(monkeypatch, tmp_path):
    seen = _patch_reproduce(monkeypatch)
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--threshold", "0.1,0.25",
                                 "--thresholds", "0.5", "-q"])
    assert args.func(args) == 0 and seen["kw"]["eval_config"].thresholds == (0.1, 0.25, 0.5)


def test_cli_choices_match_the_library():
    from davis_rig.attack.texture import ALPHA_SCHEDULES, TEXTURE_STARTS
    from davis_rig.scene.body import PART_NAMES
    from davis_rig.scene.camera import TEST_SCALES_PX

    assert cmd.ALPHA_SCHEDULE_CHOICES == tuple(ALPHA_SCHEDULES)
    assert (*cmd.START_CHOICES, "grid") == TEXTURE_STARTS  # "grid": --start PATH
    assert cmd.PART_CHOICES == (*PART_NAMES, "all") and cmd.SCALE_NAMES == tuple(TEST_SCALES_PX)


def test_main_entry_point_exit_codes(tmp_path, capsys):
    from davis_rig.cli.attack import main

    assert main(["evaluate", "--out", str(tmp_path), "--texture", "nokey"]) == 2
    assert main(["optimize", "--out", str(tmp_path), "--detector", str(tmp_path / "missing.ckpt"),
                 "--device", "cpu"]) == 4  # CheckpointError -> data exit code, one message
    err = capsys.readouterr().err
    assert "davis-attack optimize: error:" in err and "missing.ckpt" in err


def test_optimize_interrupted_exits_130_with_one_line_and_maps_the_checkpoint_period(monkeypatch, tmp_path, capsys):
    import davis_rig.attack.optimize as opt

    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: "DET")
    seen = {}

    def fake(config, detector, out, **kw):
        seen["config"] = config
        raise opt.AttackInterrupted(7, 11_500, Path(out) / "checkpoints" / "last.pt", "SIGINT")

    monkeypatch.setattr(opt, "optimize_texture", fake)
    args = _parser().parse_args(["optimize", "--out", str(tmp_path), "--device", "cpu", "--checkpoint-every", "50"])
    assert args.func(args) == 130
    assert seen["config"].checkpoint_every == 50
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("davis-attack optimize: loading")  # the first line comes before any slow import
    assert err[-1] == (f"davis-attack optimize: interrupted (SIGINT: checkpoint {tmp_path}/checkpoints/last.pt "
                       f"holds step 7 of 11500; continue with --resume)")
    args = _parser().parse_args(["optimize", "--out", str(tmp_path), "--device", "cpu", "--no-progress"])
    assert args.func(args) == 130 and seen["config"].checkpoint_every is None
    assert len(capsys.readouterr().err.splitlines()) == 1


def _patch_reproduce(monkeypatch) -> dict:
    """Patch the detector loader and ``reproduce_table``; returns the dict the fake fills with its call."""
    import davis_rig.attack.optimize as opt
    import davis_rig.attack.reproduce as rep

    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: "DET")
    seen = {}

    def fake(table, detector, out, **kw):
        seen.update(table=table, detector=detector, out=out, kw=kw)
        md = Path(out) / f"table{table}.md"
        md.parent.mkdir(parents=True, exist_ok=True)
        md.write_text("| Texture |\n")
        return {"markdown": md, "json": md, "plot": md, "record": md, "rows": [], "runs": {}}

    monkeypatch.setattr(rep, "reproduce_table", fake)
    return seen


def test_reproduce_maps_budget_and_scenes_onto_one_call(monkeypatch, tmp_path):
    seen = _patch_reproduce(monkeypatch)
    args = _parser().parse_args(["reproduce", "--table", "2", "--out", str(tmp_path), "--combinations", "legs",
                                 "torso+legs", "--iterations", "300", "--lr", "0.01", "--box-margin", "8",
                                 "--headings", "2", "--phases", "0", "--detector", "d.ckpt", "--no-progress"])
    assert args.func(args) == 0
    kw = seen["kw"]
    assert (seen["table"], seen["detector"], seen["out"]) == (2, "DET", str(tmp_path))
    assert kw["combinations"] == [("legs",), ("torso", "legs")] and kw["grids"] is None
    attack = kw["attack"]
    assert (attack.iterations, attack.lr, attack.box_margin_px, attack.v2e_gradient) == (300, 0.01, 8.0, "relaxed")
    scenes = kw["eval_config"]
    assert scenes.thresholds == (0.25,) and scenes.headings_rad == (math.pi / 2, -math.pi / 2)
    assert scenes.phases == (0.0,) and kw["detector_name"] == "d.ckpt"
    assert (scenes.background, scenes.walk_in_place, attack.eot.advance_probability) == (0.5, False, 0.5)


def test_scene_official_selects_the_official_renders_for_training_and_test(monkeypatch, tmp_path):
    from davis_rig.attack.eot import EoTConfig
    from davis_rig.attack.evaluate import EvalConfig

    seen = _patch_reproduce(monkeypatch)
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--grids", "10",
                                 "--scene", "official", "--headings", "1", "--no-progress"])
    assert args.func(args) == 0
    assert seen["kw"]["attack"].eot == EoTConfig.official()
    assert seen["kw"]["eval_config"] == EvalConfig.official(headings_rad=(math.pi / 2,))
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--grids", "10",
                                 "--scene", "official", "--playback-speed", "1.667", "--no-progress"])
    assert args.func(args) == 0
    assert seen["kw"]["attack"].eot == EoTConfig.official(playback_speed=1.667)
    assert seen["kw"]["eval_config"].playback_speed == 1.667


def test_events_official_relaxed_trains_validates_and_scores_on_the_relaxed_counts(monkeypatch, tmp_path):
    seen = _patch_reproduce(monkeypatch)
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--grids", "10",
                                 "--scene", "official", "--events", "official_relaxed", "--no-progress"])
    assert args.func(args) == 0
    attack, scenes = seen["kw"]["attack"], seen["kw"]["eval_config"]
    assert (attack.v2e_mode, attack.v2e_gradient, attack.events) == ("official_relaxed", "ste", "official_relaxed")
    assert scenes.events == "official_relaxed" and scenes.background == 1.0
    default = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--no-progress"])
    assert default.func(default) == 0
    assert (seen["kw"]["attack"].v2e_mode, seen["kw"]["attack"].events) == ("dvs", "exact")
    assert seen["kw"]["eval_config"].events == "exact"


def test_select_by_reaches_the_attack_config(monkeypatch, tmp_path):
    seen = _patch_reproduce(monkeypatch)
    for argv, rule in ((["--select-by", "score"], "score"), ([], "seqasr")):
        args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--no-progress", *argv])
        assert args.func(args) == 0
        assert seen["kw"]["attack"].select_by == rule


def test_recorded_command_quotes_arguments_so_it_reruns(monkeypatch, tmp_path):
    seen = _patch_reproduce(monkeypatch)
    argv = ["reproduce", "--table", "1", "--out", str(tmp_path / "my runs"), "--no-progress"]
    monkeypatch.setattr(sys, "argv", ["davis-attack", *argv])
    args = _parser().parse_args(argv)
    assert args.func(args) == 0
    assert seen["kw"]["command"] == f"davis-attack reproduce --table 1 --out '{tmp_path / 'my runs'}' --no-progress"


def test_events_official_relaxed_on_the_toolkit_scene_turns_off_the_threshold_mismatch(monkeypatch, tmp_path):
    # the relaxed counts take one threshold per clip: the toolkit EoT's per-pixel mismatch (sigma 0.02) would make
    # the first training step raise after the whole pool was rendered
    seen = _patch_reproduce(monkeypatch)
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--grids", "10",
                                 "--events", "official_relaxed", "--v2e-gradient", "relaxed", "--no-progress"])
    assert args.func(args) == 0
    attack = seen["kw"]["attack"]
    assert (attack.v2e_mode, attack.v2e_gradient, attack.eot.threshold_sigma) == ("official_relaxed", "ste", 0.0)
    assert attack.eot.background_level_range == (0.2, 0.8)  # still the toolkit's scene
    exact = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "--no-progress"])
    assert exact.func(exact) == 0 and seen["kw"]["attack"].eot.threshold_sigma == 0.02


def test_reproduce_examples_share_a_folder_only_with_the_same_budget():
    # runs under one --out are resumed, and a resumed run refuses other settings (only iterations and the
    # refinement's may change): two examples writing to one folder with different --lr made the second one fail
    import shlex

    from davis_rig.attack.checkpoint import FREE_ON_RESUME as free

    configs: dict[str, list[dict]] = {}
    for line in cmd.REPRODUCE_EPILOG.splitlines():
        if not line.strip().startswith("davis-attack reproduce"):
            continue
        argv = shlex.split(line.split("#")[0])[1:]
        args = _parser().parse_args(argv)
        config = {k: v for k, v in cmd._attack_config(args, 10, None).to_dict().items() if k not in free}
        configs.setdefault(args.out, []).append(config)
    assert len(configs) >= 2 and any(len(v) > 1 for v in configs.values())
    for out, group in configs.items():
        assert all(c == group[0] for c in group), out


def test_evaluate_cells_sets_the_grid_size_of_every_texture_map(monkeypatch, tmp_path):
    import cv2

    import davis_rig.attack.optimize as opt
    import davis_rig.attack.report as report
    from davis_rig.attack.export import upsample

    coarse = (np.random.default_rng(0).random((5, 5)) > 0.5).astype(np.float32)
    grid = np.kron(coarse, np.ones((2, 2), np.float32))  # a 10 x 10 grid that is also a 5 x 5 one
    cv2.imwrite(str(tmp_path / "map.png"), (upsample(grid, 400) * 255).astype(np.uint8))
    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: "DET")
    seen = {}

    def fake_table2(grids, detector, out, **kw):
        seen.update(grids)
        md = Path(out) / "table2.md"
        md.parent.mkdir(parents=True, exist_ok=True)
        md.write_text("| Texture |\n")
        return {"markdown": md, "json": md, "plot": md, "rows": []}

    monkeypatch.setattr(report, "table2", fake_table2)
    base = ["evaluate", "--table", "2", "--out", str(tmp_path / "o"), "--texture", f"torso={tmp_path / 'map.png'}",
            "--texture", f"legs={tmp_path / 'map.png'}", "--no-progress"]
    args = _parser().parse_args(base)
    assert args.func(args) == 0 and np.array_equal(seen["torso"], coarse)  # detected: the smallest grid
    args = _parser().parse_args([*base, "--cells", "10"])
    assert args.func(args) == 0
    assert np.array_equal(seen["torso"], grid) and np.array_equal(seen["legs"], grid)


def test_help_documents_resume_schedule_refine_start_and_relaxed_gradient():
    # behaviour the flags' help used to leave out: the alpha schedule runs over a changed --iterations total, the
    # refinement may start from plain white, official_relaxed replaces --v2e-gradient
    text = " ".join(_parser()._subparsers._group_actions[0].choices["optimize"].format_help().split())
    assert "alpha schedule then runs over the new total" in text
    assert "best of the best texture, plain white and plain black" in text
    assert "replacing --v2e-gradient" in text


def test_ctrl_c_on_a_real_run_exits_130_after_a_checkpoint_and_resume_continues(tmp_path):
    # the command as a user runs it: SIGINT once steps are logged -> exit 130, one line, a checkpoint at the last
    # logged step; --resume continues at the next step (the library test pins the bit-identical losses)
    import json
    import subprocess

    import torch

    from tests.helpers.interrupt import interrupt_after_log_lines, repo_env

    fixture = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "davis_rig.cli.attack", "optimize", "--out", str(run), "--cells", "2",
            "--pool-size", "1", "--val-clips", "1", "--iterations", "1000", "--validate-every", "1000",
            "--detector", str(fixture), "--device", "cpu", "--threads", "1", "--no-progress"]
    log = run / "log.jsonl"
    stopped = interrupt_after_log_lines(argv, log)
    assert stopped.returncode == 130, stopped.stderr
    assert "Traceback" not in stopped.stderr and stopped.last_line.startswith("davis-attack optimize: interrupted")
    step = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["step"]
    logged = [json.loads(line)["step"] for line in log.read_text().splitlines()]
    assert step >= 2 and logged == list(range(1, step + 1))
    done = subprocess.run([*argv, "--resume", "--max-steps", "2"], capture_output=True, text=True, timeout=240,
                          env=repo_env())
    assert done.returncode == 0, done.stderr
    logged = [json.loads(line)["step"] for line in log.read_text().splitlines()]
    assert logged == list(range(1, step + 3))


def test_optimizer_fidelity_options_map_onto_the_configs(monkeypatch, tmp_path):
    seen = _patch_reproduce(monkeypatch)
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "-q"])
    assert args.func(args) == 0
    attack, scenes = seen["kw"]["attack"], seen["kw"]["eval_config"]
    # the defaults: the official schedule, 64 validation clips, the test sensor in half the clips, natural walk
    assert (attack.lr_schedule, attack.lr_min, attack.lr_period) == ("cosine_restarts", 1e-7, None)
    assert attack.num_validation_clips == 64 and attack.loss_anchors == "all"
    assert (attack.eot.test_sensor_probability, attack.eot.walk, scenes.walk) == (0.5, "natural", "natural")
    args = _parser().parse_args(["reproduce", "--table", "1", "--out", str(tmp_path), "-q", "--lr-schedule",
                                 "constant", "--lr-period", "300", "--lr-min", "0", "--val-clips", "16",
                                 "--loss-anchors", "person", "--test-sensor-probability", "0", "--walk", "bundled"])
    assert args.func(args) == 0
    attack, scenes = seen["kw"]["attack"], seen["kw"]["eval_config"]
    assert (attack.lr_schedule, attack.lr_min, attack.lr_period) == ("constant", 0.0, 300)
    assert attack.num_validation_clips == 16 and attack.loss_anchors == "person"
    assert (attack.eot.test_sensor_probability, attack.eot.walk, scenes.walk) == (0.0, "bundled", "bundled")


def test_cli_limits_match_the_library():
    from davis_rig.attack.texture import MAX_CELLS

    assert cmd.MAX_CELLS == MAX_CELLS
