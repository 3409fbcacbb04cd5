"""Benchmark: physical evaluation of a 60 s DAVIS346 session on the CPU (RVT-T/RVT-B random weights, trained models).

The session is synthesised through the real capture path: events of a person-sized blob walking back and forth
across the sensor (90 % of the events inside the blob, 10 % background noise; default 0.5 M ev/s) are encoded
slice by slice into the DAVIS346 USB word stream (:class:`~davis_rig.protocol.encoder.StreamEncoder`), decoded
again (:class:`~davis_rig.protocol.decoder.StreamDecoder`, timed: the **decode** stage) and written with
:class:`~davis_rig.session.SessionWriter`; pedestrian labels at 25 Hz follow the blob (written like
``davis-label`` does; the YOLO labeller is measured separately by ``tools/measure_labeler.py``).

Models: RVT-T / RVT-B exported to ONNX from random weights (``--models``; inference latency does not depend on the
values, and random weights are the post-processing worst case: every one of the 1680 anchors passes every paper
threshold) and trained RVT step graphs (``--onnx``; default: the bundled detector when it exists), whose few
confident boxes are the realistic post-processing load.

Per model: a warm-up run on a 2 s session, then ``--repeats`` rounds of full runs of
:func:`davis_rig.evaluation.physical.score_session` + :func:`compute_metrics` at the paper's four thresholds, one
run per ``--modes`` entry in each round, the order reversed every other round (so load drift on a shared machine
hits the modes alike):

* ``pipelined`` (davis-eval's default): the step split into three parts of consecutive windows running side by
  side (``EvalSettings(pipeline=True)``: the recurrent part on 2 onnxruntime threads, the others on 1);
* ``pipelined-1``: the same with the recurrent part on one thread (``davis-eval --threads 1``);
* ``whole``: one session of ``--threads`` intra-op threads runs whole steps (the previous default).

``score_session`` overlaps its stages in threads, so the table gives each stage's **busy** seconds (read = h5
read + crop, histogram, inference = all model parts, postprocess = all four thresholds) next to the **scoring
wall** time; then **metrics** (COCO AP + SeqASR), the **total** wall time, the real-time factor (session seconds
/ total seconds; > 1 = faster than real time), the process **CPU** seconds (all threads) per window and the
**CPU bound** real-time factor a quiet machine with ``os.cpu_count()`` cores cannot exceed at that CPU cost
(session seconds / (CPU seconds / cores)). Medians over the repeats; the load average before each run is in its
line. Last, whether each mode's detections equal the first mode's bit for bit and the AP is the same.

``--int8`` adds each model's int8 graph (:mod:`davis_rig.models.rvt.quantize`) after it: the bundled detector's
shipped ``rvt_default_int8.onnx``, any other graph quantized here on 32 windows of the warm-up session; its lines
end with its AP next to the fp32 graph's and the CPU ratio.

Run: ``python benchmarks/evaluation.py [--duration-s 60] [--rate-mevs 0.5] [--models tiny base] [--onnx M.onnx ...]
[--threads 2] [--repeats 1] [--modes pipelined whole] [--session S.h5] [--int8]`` (torch is needed only to export
the random-weight models).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import metadata_line

from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, make_events

PERSON_WH = (60, 170)


def blob_x(t_us: np.ndarray, duration_us: int) -> np.ndarray:
    """Left edge of the blob (px): back and forth across the sensor, one crossing per 6 s."""
    span = DAVIS346_HW[1] - PERSON_WH[0] - 1
    phase = (np.asarray(t_us, np.float64) / 6e6) % 2.0
    return np.where(phase < 1, phase, 2 - phase) * span


def synthesize_session(path: Path, duration_s: float, rate_mevs: float, seed: int = 0) -> dict:
    """Write the benchmark session; returns timing and size figures of the encode/decode/write."""
    from davis_rig.labelers.session_labels import write_labels
    from davis_rig.protocol.decoder import StreamDecoder
    from davis_rig.protocol.encoder import StreamEncoder
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.session import SessionWriter

    rng = np.random.default_rng(seed)
    layout = SensorLayout.davis346()
    encoder, decoder = StreamEncoder(layout), StreamDecoder(layout)
    duration_us = int(duration_s * 1e6)
    y0 = (DAVIS346_HW[0] - PERSON_WH[1]) // 2
    encode_s = decode_s = write_s = 0.0
    n_events = n_bytes = 0
    with SessionWriter(path, overwrite=True) as writer:
        for t0 in range(0, duration_us, 1_000_000):
            n = int(rate_mevs * 1e6 * min(1_000_000, duration_us - t0) / 1e6)
            t = np.sort(rng.integers(t0, min(t0 + 1_000_000, duration_us), n))
            inside = rng.random(n) < 0.9
            x = np.where(inside, blob_x(t, duration_us) + rng.integers(0, PERSON_WH[0], n),
                         rng.integers(0, DAVIS346_HW[1], n))
            y = np.where(inside, y0 + rng.integers(0, PERSON_WH[1], n), rng.integers(0, DAVIS346_HW[0], n))
            events = make_events(t, x.astype(np.int64), y, rng.integers(0, 2, n))
            tic = time.perf_counter()
            data = encoder.encode(events)
            tac = time.perf_counter()
            chunk = decoder.feed(data)
            toc = time.perf_counter()
            writer.append_events(chunk.events)
            write_s += time.perf_counter() - toc
            encode_s += tac - tic
            decode_s += toc - tac
            n_events += len(chunk.events)
            n_bytes += len(data)
    t_labels = np.arange(7_100, duration_us, 40_000)
    labels = np.zeros(len(t_labels), BBOX_DTYPE)
    labels["t"] = t_labels
    labels["x"] = np.clip(blob_x(t_labels, duration_us) - 21, 0, 303)
    labels["y"] = y0 - 10
    labels["w"], labels["h"] = PERSON_WH
    labels["class_id"] = 1
    labels["class_confidence"] = 0.9
    write_labels(path, labels, {"labeler": "benchmark", "crop_origin_x": 21, "crop_origin_y": 10})
    return {"events": n_events, "bytes": n_bytes, "encode_s": encode_s, "decode_s": decode_s, "write_s": write_s,
            "labels": len(labels)}


def export_model(variant: str, directory: Path) -> Path:
    """Export a random-weight RVT of the preset ``variant`` to ONNX."""
    import torch

    from davis_rig.models.rvt import RVTConfig
    from davis_rig.models.rvt.detector import RVTDetector
    from davis_rig.models.rvt.onnx_export import export_step_onnx

    torch.manual_seed(0)
    config = RVTConfig.presets()[variant]
    return export_step_onnx(RVTDetector(config).eval(), directory / f"rvt_{variant}.onnx")


def run_once(session: Path, runner, settings) -> dict:
    """One scoring + metrics run; stage seconds, totals, CPU seconds, detections and AP."""
    from davis_rig.evaluation.physical import compute_metrics, score_session

    load = os.getloadavg()[0]
    cpu = time.process_time()
    tic = time.perf_counter()
    scores = score_session(session, runner, settings)
    tac = time.perf_counter()
    metrics = compute_metrics(scores, settings)
    toc = time.perf_counter()
    out = dict(scores.timings_s)
    out["metrics"] = toc - tac
    out["total"] = toc - tic
    out["cpu"] = time.process_time() - cpu
    out["load"] = load
    out["windows"] = len(scores.window_end_us)
    lowest = min(scores.detections)
    out["boxes_lowest"] = sum(0 if d is None else len(d) for d in scores.detections[lowest])
    out["AP"] = {th: m["AP"] for th, m in metrics.items()}
    out["detections"] = scores.detections
    return out


def same_detections(a: dict, b: dict) -> bool:
    """Whether two ``SessionScores.detections`` are equal bit for bit (thresholds, windows, rows)."""
    if a.keys() != b.keys():
        return False
    return all(len(a[th]) == len(b[th]) and all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
        for x, y in zip(a[th], b[th])) for th in a)


def bundled_detector() -> list[Path]:
    """The bundled trained detector, if this checkout has it."""
    from davis_rig.errors import MissingDependencyError
    from davis_rig.models import default_detector_path

    try:
        return [default_detector_path()]
    except MissingDependencyError:
        return []


def int8_graph(fp32: Path, calibration_session: Path, tmp: Path) -> Path:
    """The int8 graph of ``fp32``: the bundled one for the bundled detector, else quantized on 32 windows of
    ``calibration_session``."""
    from davis_rig.cli.quantize import quantize_from_sources
    from davis_rig.models import default_detector_path

    if bundled_detector() == [fp32]:
        return default_detector_path(int8=True)
    return quantize_from_sources(fp32, tmp / f"{fp32.stem}_int8.onnx", [calibration_session], seconds=2.0,
                                 windows=32, threads=1)[0]


STAGES = ("read", "histogram", "inference", "postprocess", "wall", "metrics", "total")
#: mode -> (pipelined, onnxruntime threads of the recurrent part or of the whole step; None: --threads / davis-eval's)
MODES = {"pipelined": (True, None), "pipelined-1": (True, 1), "whole": (False, None)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration-s", type=float, default=60.0)
    parser.add_argument("--rate-mevs", type=float, default=0.5)
    parser.add_argument("--models", nargs="*", default=["tiny", "base"], help="random-weight presets")
    parser.add_argument("--onnx", nargs="*", type=Path, default=None,
                        help="trained RVT step graphs (default: the bundled detector, if present)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads of the whole step")
    parser.add_argument("--modes", nargs="+", choices=list(MODES), default=["pipelined", "whole"])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--session", type=Path, default=None,
                        help="reuse this benchmark session (written first if missing)")
    parser.add_argument("--int8", action="store_true", help="also run each model's int8 graph")
    args = parser.parse_args()

    from davis_rig.evaluation.physical import EvalSettings
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    cores = os.cpu_count() or 1
    print(metadata_line(("numpy", "onnxruntime", "h5py"), intra_op_threads=args.threads, repeats=args.repeats))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = args.session or tmp / "bench.h5"
        if session.is_file():
            print(f"session: {session} (reused)")
        else:
            synth = synthesize_session(session, args.duration_s, args.rate_mevs)
            mev = synth["events"] / 1e6
            print(f"session: {args.duration_s:.0f} s, {mev:.1f} M events ({args.rate_mevs} M ev/s), "
                  f"{synth['bytes'] / 1e6:.0f} MB USB stream, {synth['labels']} labels; "
                  f"encode {synth['encode_s']:.2f} s, decode {synth['decode_s']:.2f} s "
                  f"({mev / synth['decode_s']:.1f} M ev/s, {args.duration_s / synth['decode_s']:.0f}x real time), "
                  f"session write {synth['write_s']:.2f} s")
        warm = tmp / "warm.h5"
        synthesize_session(warm, min(2.0, args.duration_s), args.rate_mevs, seed=1)
        settings = {mode: EvalSettings(intra_op_threads=MODES[mode][1] if MODES[mode][0] else args.threads,
                                       pipeline=MODES[mode][0])
                    for mode in args.modes}
        models = [(f"{variant} (random)", lambda v=variant: export_model(v, tmp)) for variant in args.models]
        trained = bundled_detector() if args.onnx is None else args.onnx
        models += [(f"{path.parent.name}/{path.name}", lambda p=path: p) for path in trained]
        if args.int8:
            models = [entry for name, make in models
                      for entry in ((name, make), (f"{name} int8", lambda m=make: int8_graph(m(), warm, tmp)))]
        fp32_cpu_ap: dict[str, tuple[float, float]] = {}
        print(f"stage seconds: busy time per stage (the stages overlap), wall = scoring wall time; CPU = process "
              f"CPU seconds; CPU bound = session s / (CPU s / {cores} cores)")
        for name, make in models:
            runner = RVTOnnxRunner(make(), intra_op_threads=args.threads)
            for mode in args.modes:
                run_once(warm, runner, settings[mode])  # warm-up
            runs = {mode: [] for mode in args.modes}
            for round_index in range(args.repeats):
                for mode in args.modes if round_index % 2 == 0 else args.modes[::-1]:
                    run = run_once(session, runner, settings[mode])
                    runs[mode].append(run)
                    print(f"  {name} {mode}: total {run['total']:.1f} s, CPU {run['cpu']:.1f} s, load average "
                          f"{run['load']:.2f} before the run", flush=True)
            print(f"{name:28s} {'mode':9s} " + " ".join(f"{s:>10s}" for s in STAGES)
                  + "  real time  CPU ms/window  CPU bound  inference ms/window  boxes/window (lowest threshold)")
            first = args.modes[0]
            for mode in args.modes:
                med = {s: statistics.median(r[s] for r in runs[mode]) for s in (*STAGES, "cpu")}
                windows = runs[mode][0]["windows"]
                duration_s = windows * settings[mode].window_us / 1e6
                print(f"{name:28s} {mode:9s} " + " ".join(f"{med[s]:9.2f}s" for s in STAGES)
                      + f"  {duration_s / med['total']:8.2f}x  {1000 * med['cpu'] / windows:13.1f}"
                        f"  {duration_s * cores / med['cpu']:8.2f}x  {1000 * med['inference'] / windows:19.1f}"
                        f"  {runs[mode][0]['boxes_lowest'] / windows:10.1f}")
            if args.int8:
                med_cpu = statistics.median(r["cpu"] for r in runs[first])
                if not name.endswith(" int8"):
                    fp32_cpu_ap[name] = (med_cpu, runs[first][0]["AP"][min(runs[first][0]["AP"])])
                else:
                    cpu32, ap32 = fp32_cpu_ap[name.removesuffix(" int8")]
                    ap8 = runs[first][0]["AP"][min(runs[first][0]["AP"])]
                    print(f"{name} vs fp32 ({first}): CPU {cpu32 / med_cpu:.2f}x less, AP {ap8:.4f} vs {ap32:.4f}")
            for mode in args.modes[1:]:
                same = all(same_detections(r["detections"], runs[first][0]["detections"]) for r in runs[mode])
                same_ap = all(r["AP"] == runs[first][0]["AP"] for r in runs[mode])
                print(f"{name}: {mode} vs {first}: detections bit-identical {same}, AP identical {same_ap}")


if __name__ == "__main__":
    main()
