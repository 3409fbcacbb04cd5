"""Install a finished ``davis-train`` run as the bundled default detector, with its held-out scores and model card.

Writes into ``davis_rig/assets/detector/`` (or ``--out``):

* ``rvt_default.safetensors``: the run's exported fp16 weights (best validation checkpoint) with the
  ``RVTConfig`` in the metadata (``davis_rig.models.default_detector_weights_path``, the attack's default);
* ``rvt_default.onnx``: one recurrent step exported from **those fp16 weights** (loaded back as fp32), so that
  ``davis-eval`` and the attack score the very same numbers (``default_detector_path``);
* ``test_scores.json``: :func:`davis_rig.training.evaluate.evaluate_split` on the held-out test split
  (``davis-eval-dataset DATA_DIR`` prints the same table);
* ``MODEL_CARD.md``: data, recipe, compute (from the run's checkpoint and log), validation and test metrics.

Run: ``python tools/ship_detector.py RUN_DIR DATA_DIR [--out DIR] [--threshold 0.25]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO_ROOT / "davis_rig" / "assets" / "detector"


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
    """The shell commands that made this model: dataset, training, installation (with the held-out scores)."""
    from davis_rig.training.synthetic import CLOTHING_KINDS

    generation = json.loads((data_dir / "generation.json").read_text(encoding="utf-8"))
    sizes = generation["split_sizes"]
    settings = generation["settings"]
    c = train_config
    train = (f"davis-train {data_dir.name} --out {run_dir.name} --model {c['model']} --steps {c['steps']} "
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
    if out != DEFAULT_OUT:
        ship += f" --out {out.relative_to(REPO_ROOT) if out.is_relative_to(REPO_ROOT) else out}"
    return [f"davis-make-dataset {data_dir.name} --sequences {sum(sizes.values())} --split-sizes "
            + ",".join(f"{k}={v}" for k, v in sizes.items())
            + f" --seed {settings['seed']} --seconds {settings['duration_s']:g} --workers 2 --threads 1"
            + clothing_flag,
            train, ship,
            f"davis-eval-dataset {data_dir.name}    # prints the test table above"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--name", default="davis_rig default detector",
                        help="model name in the card (default: 'davis_rig default detector')")
    parser.add_argument("--threshold", type=float, nargs="+", default=[0.25])
    args = parser.parse_args(argv)

    import torch

    from davis_rig.models.rvt.checkpoint import load_detector, metadata_config
    from davis_rig.models.rvt.onnx_export import export_step_onnx
    from davis_rig.training.cards import write_model_card
    from davis_rig.training.evaluate import SplitScoreConfig, evaluate_split, format_scores

    exported = args.run_dir / "export" / "model_fp16.safetensors"
    if not exported.is_file():
        print(f"{exported}: missing (the run has not reached its --steps and exported)", file=sys.stderr)
        return 4
    args.out.mkdir(parents=True, exist_ok=True)
    weights = args.out / "rvt_default.safetensors"
    shutil.copyfile(exported, weights)
    model = load_detector(weights)
    export_step_onnx(model, args.out / "rvt_default.onnx")

    config = SplitScoreConfig(seqasr_thresholds=tuple(args.threshold))
    result = evaluate_split(args.data_dir, weights, config=config)
    result["weights"] = weights.name
    (args.out / "test_scores.json").write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(format_scores(result))

    checkpoint = torch.load(args.run_dir / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)
    dataset_card = json.loads((args.data_dir / "dataset_card.json").read_text(encoding="utf-8"))
    test_metrics = {}
    for group, scores in result["groups"].items():
        row = {"AP": scores["AP"], "AP50": scores["AP_50"], "labels": scores["num_labels"]}
        for t in config.seqasr_thresholds:
            row[f"SeqASR@{t:g} %"] = round(100 * scores["seqasr"][t]["seq_asr"], 1)
        test_metrics[f"test {group}"] = row
    write_model_card(
        args.out / "MODEL_CARD.md",
        model_name=f"{args.name}, {metadata_config(weights).name} trained on synthetic events",
        model_config=metadata_config(weights).to_dict(), train_config=checkpoint["train_config"],
        dataset_card=dataset_card, validation=checkpoint["best"] if checkpoint["best"].get("AP") is not None
        else None, test_metrics=test_metrics, compute=_compute(args.run_dir, checkpoint),
        files={weights.name: "fp16 weights + RVTConfig metadata (safetensors; the attack's default)",
               "rvt_default.onnx": "one recurrent step, fp32 ONNX from the fp16 weights (davis-eval's default)",
               "test_scores.json": "davis-eval-dataset on the held-out test split (full record)"},
        commands=_commands(args.run_dir, args.data_dir, checkpoint["train_config"], args.out.resolve()))
    sizes = {p.name: p.stat().st_size for p in args.out.iterdir()}
    print(json.dumps({"out": str(args.out), "bytes": sizes, "total_mb": round(sum(sizes.values()) / 2**20, 2)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
