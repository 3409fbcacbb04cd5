"""Benchmark: physical evaluation of a 60 s DAVIS346 session on the CPU (RVT-T and RVT-B, random weights).

The session is synthesised through the real capture path: events of a person-sized blob walking back and forth
across the sensor (90 % of the events inside the blob, 10 % background noise; default 0.5 M ev/s) are encoded
slice by slice into the DAVIS346 USB word stream (:class:`~davis_rig.protocol.encoder.StreamEncoder`), decoded
again (:class:`~davis_rig.protocol.decoder.StreamDecoder`, timed: the **decode** stage) and written with
:class:`~davis_rig.session.SessionWriter`; pedestrian labels at 25 Hz follow the blob (written like
``davis-label`` does; the YOLO labeller is measured separately by ``tools/measure_labeler.py``).

Then, per model (RVT-T, RVT-B exported to ONNX from random weights — latency does not depend on the values):
a warm-up run on the first 2 s, then ``--repeats`` full runs of :func:`davis_rig.evaluation.physical.score_session`
+ :func:`compute_metrics` at the paper's four thresholds; medians of the stage times **read** (h5 read + crop),
**histogram**, **inference** (ORT steps), **postprocess** (4 thresholds), **metrics** (COCO AP + SeqASR), the
total and the real-time factor (session seconds / wall seconds; > 1 = faster than real time).

Run: ``python benchmarks/evaluation.py [--duration-s 60] [--rate-mevs 0.5] [--models tiny base] [--threads 2]
[--repeats 1]`` (needs torch for the export).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, make_events

REPO_ROOT = Path(__file__).resolve().parents[1]
PERSON_WH = (60, 170)


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


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
    from davis_rig.evaluation.physical import compute_metrics, score_session

    tic = time.perf_counter()
    scores = score_session(session, runner, settings)
    tac = time.perf_counter()
    metrics = compute_metrics(scores, settings)
    toc = time.perf_counter()
    out = dict(scores.timings_s)
    out["metrics"] = toc - tac
    out["total"] = toc - tic
    out["windows"] = len(scores.window_end_us)
    out["detections_0.001"] = sum(0 if d is None else len(d) for d in scores.detections[min(scores.detections)])
    out["AP_0.001"] = metrics[min(metrics)]["AP"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration-s", type=float, default=60.0)
    parser.add_argument("--rate-mevs", type=float, default=0.5)
    parser.add_argument("--models", nargs="+", default=["tiny", "base"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()

    import onnxruntime

    from davis_rig.evaluation.physical import EvalSettings
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    print(f"commit {_commit()}  python {platform.python_version()}  numpy {np.__version__}  onnxruntime "
          f"{onnxruntime.__version__}  cpus {os.cpu_count()}  intra-op threads {args.threads}  "
          f"load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = tmp / "bench.h5"
        synth = synthesize_session(session, args.duration_s, args.rate_mevs)
        mev = synth["events"] / 1e6
        print(f"session: {args.duration_s:.0f} s, {mev:.1f} M events ({args.rate_mevs} M ev/s), "
              f"{synth['bytes'] / 1e6:.0f} MB USB stream, {synth['labels']} labels; "
              f"encode {synth['encode_s']:.2f} s, decode {synth['decode_s']:.2f} s "
              f"({mev / synth['decode_s']:.1f} M ev/s, {args.duration_s / synth['decode_s']:.0f}x real time), "
              f"session write {synth['write_s']:.2f} s")
        warm = tmp / "warm.h5"
        synthesize_session(warm, min(2.0, args.duration_s), args.rate_mevs, seed=1)
        settings = EvalSettings(intra_op_threads=args.threads)
        stages = ("read", "histogram", "inference", "postprocess", "metrics", "total")
        print(f"{'model':6s} " + " ".join(f"{s:>11s}" for s in stages) + "   real-time factor  per-window inference")
        for variant in args.models:
            runner = RVTOnnxRunner(export_model(variant, tmp), intra_op_threads=args.threads)
            run_once(warm, runner, settings)  # warm-up
            runs = [run_once(session, runner, settings) for _ in range(args.repeats)]
            med = {s: statistics.median(r[s] for r in runs) for s in stages}
            windows = runs[0]["windows"]
            print(f"{variant:6s} " + " ".join(f"{med[s]:10.2f}s" for s in stages)
                  + f"   {args.duration_s / med['total']:6.2f}x"
                  + f"            {1000 * med['inference'] / windows:6.1f} ms/window ({windows} windows; "
                    f"{runs[0]['detections_0.001']} boxes at 0.001)")


if __name__ == "__main__":
    main()
