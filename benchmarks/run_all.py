"""Run every benchmark script in turn, one subprocess each, and keep their output in one report file.

Each ``benchmarks/<name>.py`` stays runnable alone; this is the one command that runs the set:

    python benchmarks/run_all.py                       # all, default settings
    python benchmarks/run_all.py --only decode io model evaluation
    python benchmarks/run_all.py --quick               # fewer repeats / shorter inputs (a few minutes)

The report (default ``benchmarks/results/<UTC date>_<commit>.txt``) holds, per script, the exact command, its
exit code, wall time and everything it printed; the metadata line each script prints (commit, versions, cores,
load average) tells how quiet the machine was. A failing script is reported and the others still run; the exit
code is the number of failed scripts (capped at 100).
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
import sys
import time
from pathlib import Path

from _common import REPO_ROOT, git_commit

HERE = Path(__file__).resolve().parent

#: Benchmarks in the order data flows through the toolkit (capture, representation, detector, scene, attack).
ORDER = ("decode", "usb_pipeline", "io", "fuzz_capture", "interop", "representation", "model", "rvt_eager",
         "evaluation", "view_live", "body", "motion", "render", "v2e", "digital_cost", "synthetic", "train_step",
         "attack_step", "attack_validation")

#: ``--quick`` arguments per script (the defaults otherwise).
QUICK_ARGS = {
    "decode": ["--repeats", "3", "--seconds", "1.0"],
    "usb_pipeline": ["--repeats", "3"],
    "io": ["--seconds", "1", "--repeats", "2"],
    "fuzz_capture": ["--seeds", "70", "--garbage-seeds", "1"],
    "interop": ["--events", "3e6"],
    "representation": ["--repeats", "3"],
    "model": ["--repeats", "3"],
    "rvt_eager": ["--repeats", "3"],
    "evaluation": ["--duration-s", "10"],
    "view_live": ["--seconds", "1"],
    "body": ["--repeats", "3"],
    "motion": ["--repeats", "3"],
    "render": ["--repeats", "3"],
    "v2e": ["--repeats", "3"],
    "digital_cost": ["--quick"],
    "synthetic": ["--scenes", "2", "--seconds", "0.5"],
    "train_step": ["--repeats", "2"],
    "attack_step": ["--repeats", "2"],
    "attack_validation": ["--clips", "4", "--repeats", "1"],
}


def scripts() -> list[str]:
    """Names of the benchmark scripts in this folder (``<name>.py`` without helpers), in :data:`ORDER` first."""
    found = {p.stem for p in HERE.glob("*.py") if not p.stem.startswith("_") and p.stem != "run_all"}
    return [n for n in ORDER if n in found] + sorted(found - set(ORDER))


def run_one(name: str, extra: list[str]) -> tuple[int, float, str]:
    """Run ``benchmarks/<name>.py`` with ``extra`` arguments; returns (exit code, wall s, stdout + stderr)."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, str(HERE / f"{name}.py"), *extra], cwd=REPO_ROOT,
                          capture_output=True, text=True, check=False)
    return proc.returncode, time.perf_counter() - start, proc.stdout + proc.stderr


def main(argv: list[str] | None = None) -> int:
    available = scripts()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=available, metavar="NAME",
                        help=f"run these only (of: {' '.join(available)})")
    parser.add_argument("--skip", nargs="+", choices=available, default=[], metavar="NAME", help="leave these out")
    parser.add_argument("--quick", action="store_true", help="fewer repeats and shorter inputs")
    parser.add_argument("--out", type=Path, default=None, help="report file (default benchmarks/results/...)")
    args = parser.parse_args(argv)

    names = [n for n in (args.only or available) if n not in args.skip]
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")
    out = args.out or HERE / "results" / f"{stamp}_{git_commit().replace('+', '_')}.txt"
    out.parent.mkdir(parents=True, exist_ok=True)
    failed = 0
    with out.open("w", encoding="utf-8") as report:
        for name in names:
            extra = QUICK_ARGS.get(name, []) if args.quick else []
            command = " ".join(["python", f"benchmarks/{name}.py", *extra])
            code, wall_s, text = run_one(name, extra)
            failed += code != 0
            block = f"== {command}\n{text.rstrip()}\n-- exit {code}, {wall_s:.1f} s wall\n\n"
            report.write(block)
            report.flush()
            print(block, end="", flush=True)
    print(f"report: {out} ({len(names)} scripts, {failed} failed)")
    return min(failed, 100)


if __name__ == "__main__":
    sys.exit(main())
