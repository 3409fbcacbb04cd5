"""Benchmark: RVT detector step latency, PyTorch eager vs onnxruntime, on the CPU (batch 1, 256x320, fp32).

For RVT-T and RVT-B (**random weights** — latency does not depend on the values) at 1 and 2 intra-op threads:

* ``eager_step``: one recurrent step (backbone + FPN + head, with states) under ``torch.inference_mode``;
* ``ort_step``: the same step exported with ``export_step_onnx`` and run by :class:`RVTOnnxRunner`
  (input already padded float32, idle threads not spinning: the runner's default); ``ort_spinning``: the same
  with onnxruntime's busy-waiting threads; ratio eager / ORT (the three are timed alternately, so load drift
  on a shared machine affects all alike);
* ``bptt_3steps``: 3 recurrent steps forward + backward w.r.t. the three inputs (the digital optimizer's inner
  cost; loss = Σ obj · max class prob of the last step);
* split parts: thread CPU time of one whole step and of the three parts davis-eval pipelines (``pre``,
  ``recur``, ``head``, :meth:`RVTOnnxRunner.split`) on one thread — where a window's inference time goes;
* ``postprocess``: numpy confidence filter + class-wise NMS of one decoded output at conf 0.001 and 0.1, and at
  the paper's four thresholds: one call per threshold vs ``postprocess_thresholds`` (identical output).

Accuracy: max |ORT − PyTorch| over 3 steps with states carried, for the random-weight models and, when the
``shared/rvt/rvt_t_fixture.safetensors`` reference is beside the repository, for RVT-T with the fixture's
weights on its official histograms (also vs the official decoded output stored in the fixture).

Run: ``python benchmarks/model.py [--repeats N] [--variants tiny base] [--threads 1 2] [--no-bptt]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import REPO_ROOT, bptt_case, metadata_line, random_detector, time_interleaved_ms, time_ms

from davis_rig.evaluation.physical import PAPER_THRESHOLDS
from davis_rig.models.rvt.detector import RVTDetector, pad_to_input
from davis_rig.models.rvt.onnx_export import export_step_onnx
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
from davis_rig.models.rvt.postprocess import postprocess, postprocess_thresholds

RVT_T_FIXTURE = (REPO_ROOT / ".." / "shared" / "rvt" / "rvt_t_fixture.safetensors").resolve()


def _compare(model: RVTDetector, runner: RVTOnnxRunner, hists: list[np.ndarray]) -> dict[str, float]:
    """Max abs differences ORT vs PyTorch over the steps (states carried separately in each)."""
    torch_states = ort_states = None
    diffs = {"scores": 0.0, "boxes_px": 0.0, "boxes_rel": 0.0, "states": 0.0}
    decoded_steps = []
    for hist in hists:
        with torch.no_grad():
            decoded, torch_states = model(torch.from_numpy(hist), torch_states)
        ort_decoded, ort_states = runner.step(hist, ort_states)
        ref = decoded.numpy()
        decoded_steps.append(ort_decoded)
        box_err = np.abs(ort_decoded[..., :4] - ref[..., :4])
        diffs["scores"] = max(diffs["scores"], float(np.abs(ort_decoded[..., 4:] - ref[..., 4:]).max()))
        diffs["boxes_px"] = max(diffs["boxes_px"], float(box_err.max()))
        diffs["boxes_rel"] = max(diffs["boxes_rel"], float((box_err / np.maximum(np.abs(ref[..., :4]), 1)).max()))
        for (th, tc), (oh, oc) in zip(torch_states, ort_states):
            diffs["states"] = max(
                diffs["states"], float(np.abs(th.numpy() - oh).max()), float(np.abs(tc.numpy() - oc).max())
            )
    diffs["_decoded"] = decoded_steps  # type: ignore[assignment]
    return diffs


def _format_diffs(diffs: dict) -> str:
    return ", ".join(f"{k} {v:.2e}" for k, v in diffs.items() if not k.startswith("_"))


def split_parts_cpu_ms(runner: RVTOnnxRunner, hists: list[np.ndarray], warmup: int, repeats: int) -> dict:
    """Thread CPU ms (median) of a whole step and of the split parts ``pre``, ``recur``, ``head``, interleaved.

    With one onnxruntime thread the session computes in the calling thread, so its thread CPU time is the work
    itself, unaffected by other processes on a shared machine.
    """
    split = runner.split(1)
    x = runner.prepare_histogram(hists[1])
    _, states = runner.step(hists[0])
    x1 = split.pre(x)
    new_states = split.recur(x1, states)
    cases = {"whole": lambda: runner.step(x, states), "pre": lambda: split.pre(x),
             "recur": lambda: split.recur(x1, states), "head": lambda: split.head(new_states)}
    samples = {name: [] for name in cases}
    for index in range(warmup + repeats):
        for name, case in cases.items():
            start = time.thread_time()
            case()
            if index >= warmup:
                samples[name].append(1e3 * (time.thread_time() - start))
    return {name: float(np.median(values)) for name, values in samples.items()}


def _histograms(rng: np.random.Generator) -> list[np.ndarray]:
    """Three padded random histograms, float32 [1, 20, 256, 320] (Poisson counts clipped at 10 in the crop)."""
    hists = []
    for _ in range(3):
        hist = np.zeros((1, 20, 256, 320), np.float32)
        hist[:, :, :240, :304] = np.minimum(rng.poisson(0.3, size=(1, 20, 240, 304)), 10)
        hists.append(hist)
    return hists


def _time_steps(model: RVTDetector, onnx_path: Path, hists: list[np.ndarray], threads: int,
                args: argparse.Namespace) -> dict[str, tuple[float, float, float]]:
    """Eager, ORT and spinning-ORT steps (timed alternately) and the 3-step BPTT at ``threads`` threads, ms."""
    torch.set_num_threads(threads)
    inputs = [torch.from_numpy(h) for h in hists]
    with torch.no_grad():
        _, warm_states = model(inputs[0])
    runner = RVTOnnxRunner(onnx_path, intra_op_threads=threads)
    spinning = RVTOnnxRunner(onnx_path, intra_op_threads=threads, allow_spinning=True)
    _, ort_warm = runner.step(hists[0])

    def eager_step():
        with torch.inference_mode():
            model(inputs[1], warm_states)

    def ort_step():
        runner.step(hists[1], ort_warm)

    def ort_spinning():
        spinning.step(hists[1], ort_warm)

    timings = time_interleaved_ms(
        {"eager_step": eager_step, "ort_step": ort_step, "ort_spinning": ort_spinning},
        args.warmup, args.repeats,
    )
    if not args.no_bptt:
        timings["bptt_3steps"] = time_ms(bptt_case(model, inputs), 1, max(3, args.repeats // 2))
    return timings


def _time_variant(variant: str, hists: list[np.ndarray], tmp: Path, args: argparse.Namespace,
                  results: dict[tuple[str, int, str], float]) -> list[np.ndarray]:
    """Export one random-weight variant, time it at each thread count (medians into ``results``) and print its
    accuracy against PyTorch; returns ORT's decoded outputs of the three steps."""
    model = random_detector(variant)
    config = model.config
    start = time.perf_counter()
    onnx_path = export_step_onnx(model, tmp / f"{variant}.onnx")
    print(f"{config.name}: ONNX export {time.perf_counter() - start:.1f} s, "
          f"{onnx_path.stat().st_size / 1e6:.1f} MB")
    for threads in args.threads:
        for name, (median_ms, iqr_ms, min_ms) in _time_steps(model, onnx_path, hists, threads, args).items():
            results[(variant, threads, name)] = median_ms
            print(
                f"{config.name:6s} threads {threads}  {name:12s} median {median_ms:8.1f} ms  "
                f"IQR {iqr_ms:6.1f} ms  min {min_ms:8.1f} ms"
            )
        eager, ort_ms = results[(variant, threads, "eager_step")], results[(variant, threads, "ort_step")]
        spin_ms = results[(variant, threads, "ort_spinning")]
        print(f"{config.name:6s} threads {threads}  ratio eager/ORT {eager / ort_ms:.2f}  "
              f"spinning/not {spin_ms / ort_ms:.2f}")
    diffs = _compare(model, RVTOnnxRunner(onnx_path), hists)
    print(f"{config.name:6s} ORT vs PyTorch (random weights, 3 steps): {_format_diffs(diffs)}")
    parts = split_parts_cpu_ms(RVTOnnxRunner(onnx_path, intra_op_threads=1), hists, args.warmup, args.repeats)
    print(f"{config.name:6s} 1 thread, thread CPU ms (median): whole step {parts['whole']:.1f}; split parts "
          f"pre {parts['pre']:.1f} + recur {parts['recur']:.1f} + head {parts['head']:.1f} = "
          f"{parts['pre'] + parts['recur'] + parts['head']:.1f} (davis-eval runs the three side by side)")
    return diffs["_decoded"]


def _time_postprocess(decoded: np.ndarray, repeats: int) -> None:
    """Time the post-processing of one decoded output at two thresholds, and at the paper's four both ways."""
    for conf in (0.001, 0.1):
        median_ms, iqr_ms, min_ms = time_ms(lambda: postprocess(decoded, conf), 2, repeats)
        kept = postprocess(decoded, conf)[0]
        print(f"postprocess conf {conf:<5}  median {median_ms:6.1f} ms  IQR {iqr_ms:5.1f} ms  min {min_ms:6.1f} ms  "
              f"({0 if kept is None else len(kept)} detections kept)")
    paper = PAPER_THRESHOLDS
    both = time_interleaved_ms({
        "one call per threshold": lambda: [postprocess(decoded, conf) for conf in paper],
        "postprocess_thresholds": lambda: postprocess_thresholds(decoded, paper),
    }, 2, repeats)
    for name, timing in both.items():
        print(f"postprocess at {paper}, {name:22s} {timing}")


def _check_fixture(tmp: Path) -> None:
    """Print ORT's accuracy with the RVT-T fixture's weights against PyTorch and the official decoded output."""
    if not RVT_T_FIXTURE.is_file():
        print(f"# RVT-T fixture not found at {RVT_T_FIXTURE}: fixture accuracy check skipped")
        return
    from safetensors.numpy import load_file

    from davis_rig.models.rvt.checkpoint import load_detector

    torch.set_num_threads(2)
    model = load_detector(RVT_T_FIXTURE)
    fixture = load_file(str(RVT_T_FIXTURE))
    path = export_step_onnx(model, tmp / "rvt_t_fixture.onnx")
    fixture_hists = [pad_to_input(torch.from_numpy(h[None].astype(np.float32))).numpy()
                     for h in fixture["input.hist_uint8_unpadded"]]
    diffs = _compare(model, RVTOnnxRunner(path, intra_op_threads=2), fixture_hists)
    print(f"RVT-T fixture weights, ORT vs PyTorch (3 steps): {_format_diffs(diffs)}")
    official = [fixture[f"step{s}.head.decoded"] for s in range(3)]
    score_err = max(float(np.abs(d[..., 4:] - o[..., 4:]).max()) for d, o in zip(diffs["_decoded"], official))
    box_err = max(
        float((np.abs(d[..., :4] - o[..., :4]) / np.maximum(np.abs(o[..., :4]), 1)).max())
        for d, o in zip(diffs["_decoded"], official)
    )
    print(f"RVT-T fixture weights, ORT vs official decoded: scores {score_err:.2e}, boxes_rel {box_err:.2e}")


def _print_ratios(results: dict[tuple[str, int, str], float], args: argparse.Namespace) -> None:
    """RVT-B over RVT-T per case, and the 1 → 2 threads speed-ups."""
    print("# ratios")
    for threads in args.threads:
        for name in ("eager_step", "ort_step", "bptt_3steps"):
            if ("tiny", threads, name) in results and ("base", threads, name) in results:
                print(f"B/T  threads {threads}  {name:12s} {results[('base', threads, name)] / results[('tiny', threads, name)]:.2f}")
    if 1 in args.threads and 2 in args.threads:
        for variant in args.variants:
            for name in ("eager_step", "ort_step"):
                print(f"{variant:5s} 1->2 threads speed-up {name:12s} "
                      f"{results[(variant, 1, name)] / results[(variant, 2, name)]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--variants", nargs="+", default=["tiny", "base"], choices=["tiny", "small", "base", "mini"])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--no-bptt", action="store_true", help="skip the 3-step forward+backward timing")
    args = parser.parse_args()

    print("# RVT model benchmark: PyTorch eager vs onnxruntime (random weights, batch 1, 20x256x320, fp32, CPU)")
    print(metadata_line(("numpy", "torch", "onnxruntime"), torch_capability=torch.backends.cpu.get_cpu_capability(),
                        repeats=f"{args.repeats} (+{args.warmup} warm-up)"))
    hists = _histograms(np.random.default_rng(0))
    results: dict[tuple[str, int, str], float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for variant in args.variants:
            decoded = _time_variant(variant, hists, Path(tmp), args, results)
            if variant == args.variants[0]:
                _time_postprocess(decoded[-1], args.repeats)
        _check_fixture(Path(tmp))
    _print_ratios(results, args)


if __name__ == "__main__":
    main()
