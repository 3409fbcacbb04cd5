"""``davis-train``: train an RVT detector on a dataset in RVT's preprocessed layout (resumable).

Thin front end over :func:`davis_rig.training.trainer.train`; errors become one message and an exit code in
:mod:`davis_rig.cli.common`. torch is imported after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import json
import sys

from davis_rig.cli.common import (EXIT_INTERRUPTED, EXIT_OK, add_hidden_alias, add_out, add_quiet, add_threads, float_in, new_parser,
                                   non_negative_float, non_negative_int, positive_float, positive_int,
                                   removing_new_empty_dirs, run_main)
from davis_rig.metrics.ap import SKIP_FIRST_US
from davis_rig.models.rvt.config import RVTConfig  # pure Python: keeps --help fast

NAME = "davis-train"

EXAMPLES = """\
examples:
  davis-train data/synth --out runs/rvt_t                       # RVT-T, Gen1 recipe, 400k steps, batch 8, L 21
  davis-train data/synth --out runs/rvt_t --resume              # continue from runs/rvt_t/checkpoints/last.pt
  davis-train data/synth --out runs/t --steps 20000 --chunk-steps 500   # CPU: 500 steps per call, then --resume
  davis-train data/synth --out runs/mini --preset mini --steps 50 --batch 2 --seq-len 3 --device cpu
  davis-train data/mine --out runs/ft --init rvt-t.ckpt --steps 2000 --lr 1e-4   # fine-tune trained weights

DATA_DIR holds train/ (and val/ for validation AP) sequences in RVT's layout (event_representations_v2/
stacked_histogram_dt=50_nbins=10 + labels_v2), e.g. a preprocessed Gen1 folder or davis_rig's synthetic data.
RUN_DIR gets log.jsonl (train losses, validation AP/AP50), checkpoints/last.pt (full state), checkpoints/
best.safetensors (best validation AP) and, when the run reaches --steps, export/model_fp16.safetensors and
export/model.onnx. With --resume the saved training settings are used (only --device, --workers and the
progress bar may change); without it an earlier run in RUN_DIR is replaced (last.pt overwritten, log.jsonl and
best.safetensors removed). Prints a JSON summary. A run that fails before its first checkpoint leaves no empty
RUN_DIR behind; Ctrl-C keeps the checkpoints written so far (continue with --resume).
"""


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-train``."""
    parser = new_parser(NAME, "Train an RVT event-camera detector (YOLOX losses, truncated BPTT, RVT Gen1 recipe).",
                        EXAMPLES)
    parser.add_argument("data_dir", metavar="DATA_DIR", help="dataset folder (train/, val/)")
    add_out(parser, metavar="RUN_DIR", required=True, help="output folder of the run")
    parser.add_argument("--preset", choices=sorted(RVTConfig.presets()), default="tiny",
                        help="architecture preset (default: tiny = RVT-T; nano = RVT-T at half width, for CPUs)")
    add_hidden_alias(parser, "--model", dest="preset", choices=sorted(RVTConfig.presets()))
    parser.add_argument("--steps", type=positive_int, default=400_000,
                        help="total optimizer steps (default: 400000, RVT)")
    parser.add_argument("--batch", type=positive_int, default=8, help="sequence chunks per batch (default: 8)")
    parser.add_argument("--seq-len", type=positive_int, default=21,
                        help="windows per chunk, the TBPTT length (default: 21)")
    parser.add_argument("--device", default="auto", help="auto (CUDA if available), cpu, cuda, cuda:1 ...")
    parser.add_argument("--resume", action="store_true", help="continue RUN_DIR/checkpoints/last.pt")
    parser.add_argument("--init", metavar="WEIGHTS", default=None,
                        help="start from these RVT weights (fine-tuning: an official or davis_rig .ckpt, "
                             ".safetensors, a davis-train last.pt); the architecture is theirs (--preset unused); "
                             "not with --resume")
    parser.add_argument("--lr", type=positive_float, default=2e-4, help="peak learning rate (default: 2e-4)")
    parser.add_argument("--precision", choices=["auto", "fp32", "bf16", "fp16"], default="auto",
                        help="mixed precision on CUDA (auto: bf16 if supported, else fp16; CPU: fp32)")
    parser.add_argument("--ema", type=float_in(0, 1, low_open=True, high_open=True), default=None, metavar="DECAY",
                        help="EMA of the weights, e.g. 0.9998")
    parser.add_argument("--val-every", type=non_negative_int, default=5_000,
                        help="validation interval in steps (0 = only at the end)")
    parser.add_argument("--val-batch", type=positive_int, default=8, help="streaming lanes for validation (default: 8)")
    parser.add_argument("--val-max-sequences", type=positive_int, default=None,
                        help="validate on the first N val sequences")
    parser.add_argument("--val-skip-first-ms", type=non_negative_float, default=SKIP_FIRST_US / 1000,
                        help=f"ignore labels/detections in the first ms of each val sequence (RVT: "
                             f"{SKIP_FIRST_US // 1000})")
    parser.add_argument("--min-box-side", type=non_negative_float, default=0.0, metavar="PX",
                        help="drop training boxes with a side <= PX after clipping to the frame (default: 0)")
    parser.add_argument("--ckpt-every", type=non_negative_int, default=1_000,
                        help="checkpoint interval in steps (default: 1000)")
    parser.add_argument("--log-every", type=non_negative_int, default=50, help="log interval in steps (default: 50)")
    parser.add_argument("--workers", type=non_negative_int, default=0,
                        help="DataLoader workers reading histograms (default: 0)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of init, data order and augmentation")
    parser.add_argument("--sampling", choices=["mixed", "random"], default="mixed",
                        help="mixed (RVT: half streaming lanes with carried states, half random chunks) or random")
    parser.add_argument("--no-augment", action="store_true", help="disable flip/zoom augmentation")
    parser.add_argument("--chunk-steps", type=positive_int, default=None,
                        help="stop after this many steps in this call (checkpointed; continue with --resume)")
    parser.add_argument("--time-budget-min", type=positive_float, default=None,
                        help="stop this call after this many minutes (checkpointed; continue with --resume)")
    parser.add_argument("--no-export", action="store_true", help="do not export the final model")
    add_threads(parser, help="torch CPU threads (default: torch's choice)")
    add_quiet(parser, help="no progress bar on stderr")
    return parser


#: TrainConfig field -> the option that sets it (names the option in a ConfigError).
OPTIONS = {"model": "--preset", "steps": "--steps", "batch_size": "--batch", "seq_len": "--seq-len", "lr": "--lr",
           "precision": "--precision", "ema_decay": "--ema", "val_every": "--val-every",
           "val_batch_size": "--val-batch", "val_max_sequences": "--val-max-sequences",
           "val_skip_first_us": "--val-skip-first-ms", "min_box_side_px": "--min-box-side",
           "ckpt_every": "--ckpt-every", "log_every": "--log-every", "num_workers": "--workers",
           "sampling": "--sampling", "init_weights": "--init"}


def _train(args: argparse.Namespace) -> int:
    from davis_rig.stop import StopOnSignal
    from davis_rig.training.trainer import train

    config = _config(args)  # a bad combination raises ConfigError before anything is created
    if args.threads is not None:
        import torch

        torch.set_num_threads(args.threads)
    # Ctrl-C (or SIGTERM) finishes the step in progress and writes its checkpoint; a second one stops at once
    with removing_new_empty_dirs(args.out), StopOnSignal() as stop:
        summary = train(args.data_dir, args.out, config, resume=args.resume, max_steps=args.chunk_steps,
                        time_budget_s=None if args.time_budget_min is None else args.time_budget_min * 60.0,
                        export=not args.no_export, init_weights=args.init, stop=stop)
    print(json.dumps(summary, indent=1, default=str))
    if summary["stopped_by"] is not None:
        print(f"{NAME}: checkpoint of step {summary['step']} written; continue with: {NAME} {args.data_dir} --out "
              f"{args.out} --resume", file=sys.stderr)
        print(f"{NAME}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not summary["finished"]:
        print(f"{NAME}: stopped at step {summary['step']}; continue with: {NAME} {args.data_dir} --out {args.out} "
              "--resume", file=sys.stderr)
    return EXIT_OK


def _config(args: argparse.Namespace):
    """The :class:`TrainConfig` of the options (raises its ``ConfigError`` for a bad value)."""
    from davis_rig.training.augment import AugmentConfig
    from davis_rig.training.trainer import TrainConfig

    return TrainConfig(
        model=args.preset, steps=args.steps, batch_size=args.batch, seq_len=args.seq_len, lr=args.lr,
        precision=args.precision, ema_decay=args.ema, val_every=args.val_every, val_batch_size=args.val_batch,
        val_max_sequences=args.val_max_sequences, val_skip_first_us=int(round(args.val_skip_first_ms * 1000)),
        min_box_side_px=args.min_box_side, ckpt_every=args.ckpt_every, log_every=args.log_every,
        sampling=args.sampling, augment=AugmentConfig.off() if args.no_augment else AugmentConfig(),
        stream_augment=AugmentConfig.off() if args.no_augment else AugmentConfig.rvt_stream(), seed=args.seed,
        device=args.device,
        num_workers=args.workers, progress=not args.quiet)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-train``; returns the exit code."""
    return run_main(build_parser(), argv, _train, options=OPTIONS)


if __name__ == "__main__":
    sys.exit(main())
