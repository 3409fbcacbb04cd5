"""``davis-make-dataset``: generate a synthetic pedestrian event dataset in RVT's layout (resumable).

Thin front end over :func:`davis_rig.training.synthetic.generate_dataset`; errors become one message and an exit
code in :mod:`davis_rig.cli.common`. torch is imported after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import json
import sys

from davis_rig.cli.common import (EXIT_OK, add_out, add_quiet, add_threads, float_in, new_parser,
                                   non_negative_int, positive_float, positive_int, probability,
                                   removing_new_empty_dirs, run_main)

NAME = "davis-make-dataset"

EXAMPLES = """\
examples:
  davis-make-dataset --out data/synth --sequences 24 --seconds 2       # 18 train, 3 val, 3 test (75/12.5/12.5 %)
  davis-make-dataset --out data/synth --sequences 1000 --split-sizes train=900,val=46,test=54 --workers 4
  davis-make-dataset --out data/synth --sequences 1000 --device cuda    # same command again = resume
  davis-make-dataset --out data/gen1like --recipe gen1like --sequences 400 --split-sizes train=372,val=10,test=18 \
      --workers 15 --threads 1 --time-budget-min 3     # as many training sequences as 3 minutes allow

OUT_DIR gets train/ val/ test/ sequences (event_representations_v2/stacked_histogram_dt=50_nbins=10 + labels_v2,
Gen1 class 1 = pedestrian), generation.json (the settings) and dataset_card.json (counts, sizes, seeds).
Finished sequences are skipped, so rerunning the command resumes; a resumed run must use all the same settings
(--seed, --seconds, --compression and every scene option), else it is refused and the differing keys are named.
Splits are disjoint in body shapes (0-17 / 18-20 / 21-23), seeds and gait speeds; test sequence i is the
held-out subset (white, black, random 60x60 pattern) x (large, middle, small) number i mod 9.
--recipe gen1like is a recipe closer to the paper's Gen1 victim (small people, ATIS-like sensor with refractory
period, low bandwidth, leak and hot pixels, moving camera, plain grey clothing, 1-3 high-contrast painted cars per
scene; davis_rig.training.synthetic.GEN1_LIKE_SCENES); --clothing, --vehicles, --person-height and
--test-scale-probability override its values. Validation and test sequences are made first, so a run cut by
--time-budget-min trains and scores; rerunning it continues.
OUT_DIR may also be given as the first argument (the older spelling). A run that fails before its first
sequence leaves no empty OUT_DIR behind.
"""

#: SyntheticSceneConfig field -> the option that sets it (names the option in a ConfigError).
OPTIONS = {"clothing_kinds": "--clothing", "vehicle_counts": "--vehicles", "person_height_px": "--person-height",
           "test_scale_probability": "--test-scale-probability", "duration_s": "--seconds", "workers": "--workers"}


def parse_split_sizes(text: str | None, total: int) -> dict[str, int]:
    """``train=..,val=..,test=..`` (missing splits = 0) or, when ``text`` is None, 75 / 12.5 / 12.5 % of ``total``.

    Raises:
        ValueError: malformed text, unknown split, negative sizes or sizes that do not add up to ``total``.
    """
    if text is None:
        val = test = int(round(total * 0.125))
        if total >= 3:
            val, test = max(val, 1), max(test, 1)
        return {"train": total - val - test, "val": val, "test": test}
    sizes = {"train": 0, "val": 0, "test": 0}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in sizes or not value.strip().isdigit():
            raise ValueError(f"expected train=N,val=N,test=N, got {text!r}")
        sizes[key] = int(value)
    if sum(sizes.values()) != total:
        raise ValueError(f"the sizes add up to {sum(sizes.values())}, but --sequences is {total}")
    return sizes


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-make-dataset``."""
    parser = new_parser(NAME, "Generate synthetic pedestrian event sequences (RVT histograms + Gen1 labels).",
                        EXAMPLES)
    add_out(parser, metavar="OUT_DIR", help="dataset folder (created; rerun to resume)")
    parser.add_argument("out_dir", nargs="?", default=None, metavar="OUT_DIR", help=argparse.SUPPRESS)
    parser.add_argument("--sequences", type=positive_int, required=True, help="number of sequences in all splits")
    parser.add_argument("--split-sizes", default=None, metavar="train=N,val=N,test=N",
                        help="sequences per split (default: 75 / 12.5 / 12.5 %%)")
    parser.add_argument("--seconds", type=float_in(0.05), default=2.0,
                        help="seconds per sequence, >= 0.05 (default: 2)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="dataset seed (default: 0)")
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:1 ...")
    parser.add_argument("--workers", type=positive_int, default=1, help="worker processes (default: 1)")
    add_threads(parser, help="torch CPU threads per process (default: torch's choice; 1 on a busy machine)")
    parser.add_argument("--compression", choices=["blosc-zstd", "gzip", "lzf", "none"], default="blosc-zstd",
                        help="histogram compression (default: blosc-zstd, as RVT)")
    parser.add_argument("--recipe", choices=["bundled", "gen1like"], default="bundled",
                        help="scene recipe: bundled (the bundled detector's, default) or gen1like (closer to the "
                             "paper's Gen1 victim)")
    parser.add_argument("--time-budget-min", type=positive_float, default=None, metavar="MIN",
                        help="start no new sequence after MIN minutes (those started finish; rerun to continue)")
    parser.add_argument("--clothing", nargs="+", default=None, metavar="KIND",
                        help="clothing kinds of the train/val people (default: the recipe's; bundled: all of "
                             "parts_grey parts_colour stripes checks grid white black pattern60); the test subsets "
                             "are fixed")
    parser.add_argument("--vehicles", type=non_negative_int, nargs=2, default=None, metavar=("MIN", "MAX"),
                        help="labelled side-view cars (Gen1 class 0) per train/val scene, MIN..MAX (default: the "
                             "recipe's; bundled: none, single-class); the test subsets have none")
    parser.add_argument("--person-height", type=positive_float, nargs=2, default=None, metavar=("MIN", "MAX"),
                        help="height range (px) of a 1.75 m train/val person at mid-clip, drawn log-uniformly "
                             "(default: the recipe's; bundled 50 230, gen1like 25 180); the test subsets stay at the "
                             "paper's three scales")
    parser.add_argument("--test-scale-probability", type=probability, default=None, metavar="P",
                        help="chance that a train/val person stands exactly at one of the paper's scales (131, 150, "
                             "175 px) instead (default: the recipe's; bundled 0.4, gen1like 0.1; 0 keeps the test "
                             "scales unseen)")
    add_quiet(parser, help="no progress bar on stderr")
    return parser


def _scene_config(args: argparse.Namespace):
    """The :class:`~davis_rig.training.synthetic.SyntheticSceneConfig` of the flags: ``--recipe`` with the other
    scene options over it (ConfigError if invalid)."""
    import dataclasses

    from davis_rig.training.synthetic import SCENE_RECIPES

    overrides = {}
    if args.clothing is not None:
        overrides["clothing_kinds"] = tuple(args.clothing)
    if args.vehicles is not None:
        overrides["vehicle_counts"] = tuple(args.vehicles)
    if args.person_height is not None:
        overrides["person_height_px"] = tuple(args.person_height)
    if args.test_scale_probability is not None:
        overrides["test_scale_probability"] = args.test_scale_probability
    return dataclasses.replace(SCENE_RECIPES[args.recipe], **overrides)


def _make(args: argparse.Namespace) -> int:
    from davis_rig.training.synthetic import generate_dataset

    config = _scene_config(args)  # ConfigError (exit 2, the option named) before anything is created
    with removing_new_empty_dirs(args.out):
        summary = generate_dataset(args.out, args.sizes, duration_s=args.seconds, seed=args.seed, device=args.device,
                                   workers=args.workers, compression=args.compression, progress=not args.quiet,
                                   threads=args.threads, config=config,
                                   time_budget_s=None if args.time_budget_min is None else 60.0 * args.time_budget_min)
    print(json.dumps(summary, indent=1, default=str))
    return EXIT_OK


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """OUT_DIR given once (``--out`` or the positional), the split sizes add up (exit 2 with argparse's message)."""
    if args.out is not None and args.out_dir is not None:
        parser.error("argument --out: not allowed with a positional OUT_DIR (give the folder once)")
    args.out = args.out if args.out is not None else args.out_dir
    if args.out is None:
        parser.error("the following arguments are required: --out")
    try:
        args.sizes = parse_split_sizes(args.split_sizes, args.sequences)
    except ValueError as exc:
        parser.error(f"argument --split-sizes: {exc}")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-make-dataset``; returns the exit code."""
    return run_main(build_parser(), argv, _make, check=_check, options=OPTIONS)


if __name__ == "__main__":
    sys.exit(main())
