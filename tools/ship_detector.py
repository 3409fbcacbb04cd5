"""Package a finished ``davis-train`` run as a detector folder, with its held-out scores and model card.

Writes into ``--out DIR``, or with ``--install`` into the package's bundled detector folder
``davis_rig/assets/detector/`` (the default detector of ``davis-eval`` and ``davis-attack``; nothing is written
there without ``--install``). The files are made in a temporary folder beside the target and moved in only when
all of them are complete, so a failure leaves the target as it was:

* ``rvt_default.safetensors``: the run's exported fp16 weights (best validation checkpoint) with the
  ``RVTConfig`` in the metadata (``davis_rig.models.default_detector_weights_path``, the attack's default);
* ``rvt_default.onnx``: one recurrent step exported from **those fp16 weights** (loaded back as fp32), so that
  ``davis-eval`` and the attack score the very same numbers (``default_detector_path``);
* ``rvt_default_int8.onnx``: that step with Conv and MatMul in int8 (``davis-quantize``'s recipe, calibrated on 64
  windows of the dataset's train split; ``davis-eval --int8``), scored on the test split beside the fp32 one;
* ``test_scores.json``: :func:`davis_rig.training.evaluate.evaluate_split` on the held-out test split
  (``davis-eval-dataset DATA_DIR`` prints the same table);
* ``MODEL_CARD.md``: data, recipe, compute (from the run's checkpoint and log), validation and test metrics.

Run: ``python tools/ship_detector.py RUN_DIR DATA_DIR (--out DIR | --install) [--threshold 0.25]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

from davis_rig.cli.common import add_out, add_threshold, new_parser, removing_new_empty_dirs, run_main

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The bundled detector folder inside the package (written only with --install).
INSTALL_DIR = REPO_ROOT / "davis_rig" / "assets" / "detector"
NAME = Path(__file__).name

EXAMPLES = """\
examples:
  python tools/ship_detector.py runs/rvt_t data/synth --out shipped/rvt_t        # a detector folder to try
  python tools/ship_detector.py runs/rvt_t data/synth --install                  # replace the bundled detector

RUN_DIR is a finished davis-train run (export/model_fp16.safetensors, checkpoints/last.pt, log.jsonl); DATA_DIR
its dataset (generation.json, dataset_card.json, test/). The folder gets rvt_default.safetensors,
rvt_default.onnx, test_scores.json and MODEL_CARD.md, all at once when everything succeeded.
"""


def _compute(run_dir: Path, checkpoint: dict) -> dict:
    """What training took, from the checkpoint and the run's log (train records carry elapsed_s)."""
    records = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines() if line.strip()]
    train = [r for r in records if r.get("kind") == "train"]
    import torch

    return {"device": "cpu (2 cores, shared)" if checkpoint["train_config"].get("device") == "cpu"
            else checkpoint["train_config"].get("device"),
            "torch": torch.__version__, "steps": checkpoint["step"],
            "train_hours": round(checkpoint["history_s"] / 3600, 3),
            "seconds_per_step": round(checkpoint["history_s"] / max(1, checkpoint["step"]), 3),
            "final_train_loss": round(train[-1]["loss"], 4) if train else None}


def _commands(run_dir: Path, data_dir: Path, train_config: dict, out: Path) -> list[str]:
    """The shell commands that made this model (``out`` is where it was written: ``INSTALL_DIR`` = ``--install``)."""
    from davis_rig.training.synthetic import CLOTHING_KINDS

    generation = json.loads((data_dir / "generation.json").read_text(encoding="utf-8"))
    sizes = generation["split_sizes"]
    settings = generation["settings"]
    c = train_config
    train = (f"davis-train {data_dir.name} --out {run_dir.name} --preset {c['model']} --steps {c['steps']} "
             f"--batch {c['batch_size']} --seq-len {c['seq_len']} --lr {c['lr']:g} --device {c['device']} "
             f"--seed {c['seed']} --val-every {c['val_every']}")
    if c.get("ema_decay"):
        train += f" --ema {c['ema_decay']:g}"
    clothing = settings.get("config", {}).get("clothing_kinds")
    if clothing is not None and tuple(clothing) != CLOTHING_KINDS:
        clothing_flag = " --clothing " + " ".join(clothing)
    else:
        clothing_flag = ""
    ship = f"python tools/ship_detector.py {run_dir.name} {data_dir.name}"
    if out == INSTALL_DIR:
        ship += " --install"
    else:
        ship += f" --out {out.relative_to(REPO_ROOT) if out.is_relative_to(REPO_ROOT) else out}"
    return [f"davis-make-dataset {data_dir.name} --sequences {sum(sizes.values())} --split-sizes "
            + ",".join(f"{k}={v}" for k, v in sizes.items())
            + f" --seed {settings['seed']} --seconds {settings['duration_s']:g} --workers 2 --threads 1"
            + clothing_flag,
            train, ship,
            f"davis-eval-dataset {data_dir.name}    # prints the test table above"]


def build_parser() -> argparse.ArgumentParser:
    """The arguments of ``tools/ship_detector.py``."""
    parser = new_parser(NAME, "Package a finished davis-train run as a detector folder (weights, ONNX, test scores, "
                              "model card).", EXAMPLES)
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="a finished davis-train run folder")
    parser.add_argument("data_dir", type=Path, metavar="DATA_DIR", help="the run's dataset folder")
    target = parser.add_mutually_exclusive_group(required=True)
    add_out(target, metavar="DIR", type=Path, help="write the detector folder here (created; its files replaced)")
    target.add_argument("--install", action="store_true",
                        help=f"write into the package's bundled detector folder ({INSTALL_DIR.relative_to(REPO_ROOT)}),"
                             " replacing the default detector")
    parser.add_argument("--name", default="davis_rig default detector",
                        help="model name in the card (default: 'davis_rig default detector')")
    add_threshold(parser, default=(0.25,), help="SeqASR confidence threshold(s) of the test scores")
    return parser


def _required_inputs(run_dir: Path, data_dir: Path) -> None:
    """Refuse (FormatError, exit 4) before anything is written when a file of the run or dataset is missing."""
    from davis_rig.errors import FormatError

    exported = run_dir / "export" / "model_fp16.safetensors"
    if not exported.is_file():
        raise FormatError(f"{exported}: missing (the run has not reached its --steps and exported)")
    for path in (run_dir / "checkpoints" / "last.pt", run_dir / "log.jsonl", data_dir / "generation.json",
                 data_dir / "dataset_card.json"):
        if not path.is_file():
            raise FormatError(f"{path}: missing (RUN_DIR must be a davis-train run, DATA_DIR its dataset)")


def _ship(args: argparse.Namespace) -> int:
    out = INSTALL_DIR if args.install else args.out
    _required_inputs(args.run_dir, args.data_dir)

    import torch

    from davis_rig.models.rvt.checkpoint import load_detector, metadata_config
    from davis_rig.models.rvt.onnx_export import export_step_onnx
    from davis_rig.training.cards import write_model_card
    from davis_rig.training.evaluate import SplitScoreConfig, evaluate_split, format_scores

    config = SplitScoreConfig(seqasr_thresholds=tuple(args.threshold))
    with removing_new_empty_dirs(out):  # a failure leaves no folder it made (the staging folder is removed)
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
        try:
            weights = staging / "rvt_default.safetensors"
            shutil.copyfile(args.run_dir / "export" / "model_fp16.safetensors", weights)
            model = load_detector(weights)
            export_step_onnx(model, staging / "rvt_default.onnx")
            _quantize(staging / "rvt_default.onnx", staging / "rvt_default_int8.onnx", args.data_dir)
            result = evaluate_split(args.data_dir, weights, config=config)
            int8_all = evaluate_split(args.data_dir, staging / "rvt_default_int8.onnx", config=config)["groups"]["all"]
            result["weights"] = weights.name
            (staging / "test_scores.json").write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
            print(format_scores(result))

            checkpoint = torch.load(args.run_dir / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)
            dataset_card = json.loads((args.data_dir / "dataset_card.json").read_text(encoding="utf-8"))
            test_metrics = {}
            for group, scores in result["groups"].items():
                row = {"AP": scores["AP"], "AP50": scores["AP_50"], "labels": scores["num_labels"]}
                for t in config.seqasr_thresholds:
                    row[f"SeqASR@{t:g} %"] = round(100 * scores["seqasr"][t]["seq_asr"], 1)
                test_metrics[f"test {group}"] = row
            test_metrics["test all, int8 graph"] = {"AP": int8_all["AP"], "AP50": int8_all["AP_50"],
                                                    "labels": int8_all["num_labels"]} | {
                f"SeqASR@{t:g} %": round(100 * int8_all["seqasr"][t]["seq_asr"], 1) for t in config.seqasr_thresholds}
            write_model_card(
                staging / "MODEL_CARD.md",
                model_name=f"{args.name}, {metadata_config(weights).name} trained on synthetic events",
                model_config=metadata_config(weights).to_dict(), train_config=checkpoint["train_config"],
                dataset_card=dataset_card, validation=checkpoint["best"] if checkpoint["best"].get("AP") is not None
                else None, test_metrics=test_metrics, compute=_compute(args.run_dir, checkpoint),
                files={weights.name: "fp16 weights + RVTConfig metadata (safetensors; the attack's default)",
                       "rvt_default.onnx": "one recurrent step, fp32 ONNX from the fp16 weights (davis-eval's default)",
                       "rvt_default_int8.onnx": "the same step with Conv and MatMul in int8, calibrated on 64 training "
                                                "windows (davis-quantize; davis-eval --int8)",
                       "test_scores.json": "davis-eval-dataset on the held-out test split (full record)"},
                commands=_commands(args.run_dir, args.data_dir, checkpoint["train_config"], out.resolve()))
            sizes = {p.name: p.stat().st_size for p in sorted(staging.iterdir())}
            out.mkdir(exist_ok=True)
            for name in sizes:
                (staging / name).replace(out / name)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    print(json.dumps({"out": str(out), "bytes": sizes, "total_mb": round(sum(sizes.values()) / 2**20, 2)}))
    return 0


def _quantize(fp32: Path, out: Path, data_dir: Path) -> None:
    """``fp32``'s int8 graph, calibrated on 64 windows of the train split (``davis-quantize``'s recipe)."""
    from davis_rig.cli.quantize import quantize_from_sources

    quantize_from_sources(fp32, out, [data_dir], split="train", windows=64)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    return run_main(build_parser(), argv, _ship)


if __name__ == "__main__":
    sys.exit(main())
