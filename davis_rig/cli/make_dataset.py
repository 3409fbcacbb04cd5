"""``davis-make-dataset``: generate a synthetic pedestrian event dataset in RVT's layout (resumable).

Thin front end over :func:`davis_rig.training.synthetic.generate_dataset`; errors become one message and an exit
code in :mod:`davis_rig.cli._common`. torch is imported after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import json
import sys

from davis_rig.cli._common import EXIT_OK, EXIT_USAGE, run_command

NAME = "davis-make-dataset"

EPILOG = """\
examples:
  davis-make-dataset data/synth --sequences 24 --seconds 2             # 18 train, 3 val, 3 test (75/12.5/12.5 %)
  davis-make-dataset data/synth --sequences 1000 --split-sizes train=900,val=46,test=54 --workers 4
  davis-make-dataset data/synth --sequences 1000 --device cuda          # same command again = resume

OUT_DIR gets train/ val/ test/ sequences (event_representations_v2/stacked_histogram_dt=50_nbins=10 + labels_v2,
Gen1 class 1 = pedestrian), generation.json (the settings) and dataset_card.json (counts, sizes, seeds).
Finished sequences are skipped, so rerunning the command resumes; a resumed run must use all the same settings
(--seed, --seconds, --compression and every scene option), else it is refused and the differing keys are named.
Splits are disjoint in body shapes (0-17 / 18-20 / 21-23), seeds and gait speeds; test sequence i is the
held-out subset (white, black, random 60x60 pattern) x (large, middle, small) number i mod 9.
Exit codes: 0 ok, 1 error, 2 bad arguments, 4 file problem, 5 missing dependency.
"""


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
            raise ValueError(f"--split-sizes: expected train=N,val=N,test=N, got {text!r}")
        sizes[key] = int(value)
    if sum(sizes.values()) != total:
        raise ValueError(f"--split-sizes add up to {sum(sizes.values())}, but --sequences is {total}")
    return sizes


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-make-dataset``."""
    parser = argparse.ArgumentParser(
        prog=NAME, description="Generate synthetic pedestrian event sequences (RVT histograms + Gen1 labels).",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", metavar="OUT_DIR", help="dataset folder (created; rerun to resume)")
    parser.add_argument("--sequences", type=int, required=True, help="number of sequences in all splits")
    parser.add_argument("--split-sizes", default=None, metavar="train=N,val=N,test=N",
                        help="sequences per split (default: 75 / 12.5 / 12.5 %%)")
    parser.add_argument("--seconds", type=float, default=2.0, help="seconds per sequence (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="dataset seed (default: 0)")
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:1 ...")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default: 1)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads per process (default: torch's choice; 1 on a busy machine)")
    parser.add_argument("--compression", choices=["blosc-zstd", "gzip", "lzf", "none"], default="blosc-zstd",
                        help="histogram compression (default: blosc-zstd, as RVT)")
    parser.add_argument("--clothing", nargs="+", default=None, metavar="KIND",
                        help="clothing kinds of the train/val people (default: all of parts_grey parts_colour "
                             "stripes checks grid white black pattern60); the test subsets are fixed")
    parser.add_argument("--vehicles", type=int, nargs=2, default=None, metavar=("MIN", "MAX"),
                        help="labelled side-view cars (Gen1 class 0) per train/val scene, MIN..MAX (default: none, "
                             "the single-class bundled recipe); the test subsets have none")
    parser.add_argument("--person-height", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
                        help="height range (px) of a 1.75 m train/val person at mid-clip, drawn log-uniformly "
                             "(default: 50 230); the test subsets stay at the paper's three scales")
    parser.add_argument("--test-scale-probability", type=float, default=None, metavar="P",
                        help="chance that a train/val person stands exactly at one of the paper's scales (131, 150, "
                             "175 px) instead (default: 0.4; 0 with a Gen1-like --person-height keeps the test "
                             "scales unseen)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    return parser


def _scene_config(args: argparse.Namespace):
    """The :class:`~davis_rig.training.synthetic.SyntheticSceneConfig` of the flags (ValueError if invalid)."""
    from davis_rig.training.synthetic import SyntheticSceneConfig

    overrides = {}
    if args.clothing is not None:
        overrides["clothing_kinds"] = tuple(args.clothing)
    if args.vehicles is not None:
        overrides["vehicle_counts"] = tuple(args.vehicles)
    if args.person_height is not None:
        overrides["person_height_px"] = tuple(args.person_height)
    if args.test_scale_probability is not None:
        overrides["test_scale_probability"] = args.test_scale_probability
    return SyntheticSceneConfig(**overrides)


def _make(args: argparse.Namespace, sizes: dict[str, int]) -> int:
    from davis_rig.training.synthetic import generate_dataset

    config = _scene_config(args)
    summary = generate_dataset(args.out_dir, sizes, duration_s=args.seconds, seed=args.seed, device=args.device,
                               workers=args.workers, compression=args.compression, progress=not args.no_progress,
                               threads=args.threads, config=config)
    print(json.dumps(summary, indent=1, default=str))
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-make-dataset``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.sequences < 1 or args.workers < 1 or not args.seconds >= 0.05 or (
            args.threads is not None and args.threads < 1):
        print(f"{NAME}: error: need --sequences >= 1, --workers >= 1, --seconds >= 0.05 and --threads >= 1 (when "
              "given)", file=sys.stderr)
        return EXIT_USAGE
    try:
        sizes = parse_split_sizes(args.split_sizes, args.sequences)
        _scene_config(args)
    except ValueError as exc:
        print(f"{NAME}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    return run_command(NAME, lambda: _make(args, sizes))


if __name__ == "__main__":
    sys.exit(main())
