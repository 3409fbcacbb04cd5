"""``davis-quantize``: an int8 version of an RVT step ONNX, calibrated on recordings or a dataset.

Thin front end over :mod:`davis_rig.models.rvt.quantize`. Calibration windows come from session.h5 recordings
(the first ``--seconds`` of each, cropped as davis-eval crops them) and from RVT-layout dataset folders (a dataset
root's ``--split``, or a split or sequence folder). After writing, both graphs run on the calibration feeds and
the command prints their CPU time per step and how far the int8 scores are from the fp32 ones.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from davis_rig.cli.common import (EXIT_OK, add_detector, add_out, add_quiet, add_threads, new_parser, positive_float,
                                  positive_int, run_main)

NAME = "davis-quantize"

EXAMPLES = """\
examples:
  davis-quantize --calibration data/synth --out rvt_int8.onnx              # bundled detector, train split
  davis-quantize --detector rvt.onnx --calibration a.h5 b.h5 --out rvt_int8.onnx --windows 128
  davis-eval session.h5 --detector rvt_int8.onnx                           # then score with it

Only Conv and MatMul run in int8 (7-bit weights per output channel, activations per tensor from the calibration
windows' min/max); the outputs differ from the fp32 graph's: check the AP on your data (davis-eval, or
davis-eval-dataset --detector rvt_int8.onnx) before relying on it."""


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-quantize``."""
    parser = new_parser(NAME, "Write an int8 RVT step ONNX, calibrated on recordings or a dataset.", EXAMPLES)
    add_detector(parser, help="fp32 RVT step ONNX to quantize (default: the bundled detector's)")
    parser.add_argument("--calibration", nargs="+", required=True, metavar="PATH",
                        help="session.h5 recordings and/or RVT-layout dataset folders (root, split or sequence)")
    parser.add_argument("--split", default="train", help="split of a dataset root (default train)")
    parser.add_argument("--windows", type=positive_int, default=64,
                        help="calibration windows in all, evenly spaced (default 64)")
    parser.add_argument("--seconds", type=positive_float, default=10.0,
                        help="seconds read from the start of each session (default 10)")
    add_out(parser, required=True, help="the int8 .onnx to write")
    add_threads(parser, help="onnxruntime CPU threads (default: onnxruntime's choice)")
    add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if not args.out.endswith(".onnx"):
            parser.error("argument --out: must end in .onnx")
        if args.detector is not None and Path(args.detector).resolve() == Path(args.out).resolve():
            parser.error("argument --out: must differ from --detector")

    return run_main(build_parser(), argv, _run, check=check)


class DatasetSequence:
    """One dataset sequence as :func:`~davis_rig.models.rvt.quantize.calibration_feeds` reads it: ``len()`` and
    ``seq[a:b]`` (uint8 histograms read from its h5 file on demand)."""

    def __init__(self, folder: Path):
        from davis_rig.training.dataset import SequenceData

        self._data = SequenceData(folder)

    def __len__(self) -> int:
        return len(self._data)

    def __getitem__(self, window: slice):
        return self._data.histograms(window.start, window.stop)


def calibration_sequences(paths, *, split: str, seconds: float) -> list[tuple[str, object]]:
    """``(name, histograms)`` of every calibration source: a session's first ``seconds`` (:class:`SessionSequence`),
    each sequence of a dataset folder (:class:`DatasetSequence`); both read window by window on demand.

    Raises:
        FormatError / SessionError: a path is neither a readable session nor a dataset folder.
    """
    from davis_rig.errors import FormatError
    from davis_rig.training.dataset import list_sequences

    out: list[tuple[str, object]] = []
    for path in map(Path, paths):
        if path.is_file():
            out.append((path.name, SessionSequence(path, seconds)))
            continue
        if not path.is_dir():
            raise FormatError(f"{path}: no such file or folder")
        if (path / "event_representations_v2").is_dir():
            folders = [path]
        elif (path / split).is_dir():
            folders = list_sequences(path, split)
        else:
            folders = list_sequences(path, None)
        if not folders:
            raise FormatError(f"{path}: no RVT-layout sequence in it")
        out.extend((f"{path.name}/{folder.name}", DatasetSequence(folder)) for folder in folders)
    return out


def source_names(paths, split: str) -> list[str]:
    """How the quantization record names the calibration sources: file and folder names, a dataset root's split."""
    return [f"{Path(p).name} ({split} split)" if (Path(p) / split).is_dir() else Path(p).name for p in paths]


class SessionSequence:
    """The first ``seconds`` of a session as davis-eval's windows (its crop origin, 50 ms, back to back), read
    window by window: ``len()`` and ``seq[a:b]`` (uint8 histograms [b - a, 20, 240, 304]).

    Raises:
        SessionError / FormatError: the session cannot be read or has no events in that span.
    """

    def __init__(self, path: Path, seconds: float):
        from davis_rig.errors import SessionError
        from davis_rig.evaluation.physical import scoring_crop_origin
        from davis_rig.evaluation.windows import window_grid
        from davis_rig.events.histogram import WINDOW_US
        from davis_rig.session.reader import SessionReader

        self.path = path
        with SessionReader(path) as reader:
            t0 = int(reader.t_offset_us)
            last = reader.events_between(t0, t0 + int(seconds * 1e6))["t"][-1:]
            attrs = reader.labels_attrs()
        if not len(last):
            raise SessionError(f"{path}: no events in its first {seconds:g} s to calibrate on")
        self.origin = scoring_crop_origin(path, None, attrs)
        self.window_end_us = window_grid(t0, int(last[0]), WINDOW_US)
        self.window_us = WINDOW_US

    def __len__(self) -> int:
        return len(self.window_end_us)

    def __getitem__(self, window: slice):
        from davis_rig.events.crop import crop_events
        from davis_rig.events.histogram import stacked_histograms
        from davis_rig.session.reader import SessionReader

        ends = self.window_end_us[window]
        with SessionReader(self.path) as reader:  # windows are inclusive at both ends: read to end + 1 µs
            events = reader.events_between(int(ends[0]) - self.window_us, int(ends[-1]) + 1)
        return stacked_histograms(crop_events(events, self.origin), ends, window_us=self.window_us)


def quantize_from_sources(src: Path, out, paths, *, split: str = "train", seconds: float = 10.0, windows: int = 64,
                          threads: int | None = None):
    """Calibrate on ``paths`` (sessions / dataset folders, :func:`calibration_sequences`) and write ``src``'s int8
    graph to ``out``; returns ``(out, fp32 runner, calibration feeds)``."""
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
    from davis_rig.models.rvt.quantize import calibration_feeds, quantize_step_onnx

    fp32 = RVTOnnxRunner(src, intra_op_threads=threads)
    sequences = calibration_sequences(paths, split=split, seconds=seconds)
    feeds = calibration_feeds(fp32, [h for _, h in sequences], windows)
    return quantize_step_onnx(src, out, feeds, sources=source_names(paths, split)), fp32, feeds


def _run(args: argparse.Namespace) -> int:
    import numpy as np

    from davis_rig.models import default_detector_path
    from davis_rig.models.rvt.onnx_export import INPUT_NAME
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    src = Path(args.detector) if args.detector is not None else default_detector_path()
    t0 = time.perf_counter()
    out, fp32, feeds = quantize_from_sources(src, args.out, args.calibration, split=args.split, seconds=args.seconds,
                                             windows=args.windows, threads=args.threads)
    say(f"{NAME}: calibrated on {len(feeds)} windows in {time.perf_counter() - t0:.1f} s")
    int8 = RVTOnnxRunner(out, intra_op_threads=args.threads)
    cpu = {"fp32": [], "int8": []}
    diffs = []
    for feed in feeds:
        scores = {}
        for name, runner in (("fp32", fp32), ("int8", int8)):
            states = [(feed[f"h{k}"], feed[f"c{k}"]) for k in range(1, 5)]
            start = time.process_time()
            decoded, _ = runner.step(feed[INPUT_NAME], states)
            cpu[name].append(time.process_time() - start)
            scores[name] = decoded[0, :, 4] * decoded[0, :, 5:].max(axis=1)
        diffs.append(np.abs(scores["int8"] - scores["fp32"]))
    diffs = np.concatenate(diffs)
    fp32_ms, int8_ms = (1000 * float(np.median(cpu[k])) for k in ("fp32", "int8"))
    print(f"wrote {out}: {len(feeds)} calibration windows; CPU per step (median, these windows) fp32 {fp32_ms:.1f} ms, "
          f"int8 {int8_ms:.1f} ms ({fp32_ms / int8_ms:.2f}x); |score int8 - fp32| mean {diffs.mean():.2e}, "
          f"99.9th percentile {np.quantile(diffs, 0.999):.3f}, max {diffs.max():.3f}")
    return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
