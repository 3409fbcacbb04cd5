"""Shared helpers of the benchmark scripts: timing with warm-up, run metadata, thread setup, random-weight RVT.

The scripts run as ``python benchmarks/<name>.py``, so this folder is on ``sys.path`` and they import
``from _common import ...``. The module imports neither numpy nor torch: a script may set the BLAS thread count
(:func:`limit_blas_threads`) before numpy is first imported, and package versions come from the installed
distributions' metadata.

Method (after kornia's benchmarks): ``warmup`` untimed calls, then ``repeats`` timed calls of
``time.perf_counter`` wall-clock; reported as median, interquartile range (``statistics.quantiles(n=4)``,
exclusive method) and minimum, in milliseconds.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

REPO_ROOT = Path(__file__).resolve().parents[1]

#: Environment variables read by the BLAS/OpenMP runtimes numpy and torch link against.
BLAS_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


class Timing(NamedTuple):
    """Summary of repeated timings, all in milliseconds."""

    median_ms: float
    iqr_ms: float
    min_ms: float

    def scaled(self, factor: float) -> Timing:
        """The same summary times ``factor`` (e.g. ``1 / frames`` for a per-frame figure)."""
        return Timing(self.median_ms * factor, self.iqr_ms * factor, self.min_ms * factor)

    def __str__(self) -> str:
        return f"median {self.median_ms:9.2f} ms  IQR {self.iqr_ms:7.2f} ms  min {self.min_ms:9.2f} ms"


def summarize_ms(samples_ms: Sequence[float]) -> Timing:
    """Median, IQR (exclusive quartiles) and minimum of timing samples in ms.

    Args:
        samples_ms: at least one duration, ms.

    Returns:
        :class:`Timing`; the IQR of a single sample is 0.

    Raises:
        ValueError: if ``samples_ms`` is empty.
    """
    if len(samples_ms) == 0:
        raise ValueError("summarize_ms needs at least one sample")
    if len(samples_ms) == 1:
        return Timing(float(samples_ms[0]), 0.0, float(samples_ms[0]))
    q1, _, q3 = statistics.quantiles(samples_ms, n=4)
    return Timing(float(statistics.median(samples_ms)), float(q3 - q1), float(min(samples_ms)))


def time_ms(fn: Callable[[], object], warmup: int, repeats: int, sync: Callable[[], None] | None = None) -> Timing:
    """Wall-clock time of ``fn()`` in ms: ``warmup`` untimed calls, then ``repeats`` timed ones.

    Args:
        fn: the work, called without arguments.
        warmup: untimed calls first (≥ 0).
        repeats: timed calls (≥ 1).
        sync: called before the clock starts and before it stops (e.g. ``torch.cuda.synchronize``), so that
            asynchronous device work is inside the measured interval.

    Raises:
        ValueError: if ``warmup < 0`` or ``repeats < 1``.
    """
    return time_interleaved_ms({"fn": fn}, warmup, repeats, sync)["fn"]


def time_interleaved_ms(
    fns: Mapping[str, Callable[[], object]], warmup: int, repeats: int, sync: Callable[[], None] | None = None
) -> dict[str, Timing]:
    """Like :func:`time_ms` for several functions called in turn, so that load drift hits all of them alike.

    Returns:
        ``{name: Timing}`` in the order of ``fns``.

    Raises:
        ValueError: if ``warmup < 0`` or ``repeats < 1``.
    """
    if warmup < 0 or repeats < 1:
        raise ValueError(f"need warmup >= 0 and repeats >= 1, got warmup={warmup}, repeats={repeats}")
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            if sync is not None:
                sync()
            start = time.perf_counter()
            fn()
            if sync is not None:
                sync()
            samples[name].append((time.perf_counter() - start) * 1e3)
    return {name: summarize_ms(values) for name, values in samples.items()}


def git_commit() -> str:
    """Short hash of the repository's HEAD, with ``+dirty`` when tracked files differ; ``unknown`` without git."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "diff", "--quiet", "HEAD", "--"], cwd=REPO_ROOT, capture_output=True, check=False
        ).returncode
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return commit + ("+dirty" if dirty == 1 else "")


def package_version(name: str) -> str:
    """Installed version of distribution ``name`` (without importing it), or ``absent``."""
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


def load_average() -> str:
    """The 1, 5 and 15 min load averages as ``'a b c'``, or ``n/a`` where the platform has none."""
    if not hasattr(os, "getloadavg"):
        return "n/a"
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


#: CPU flags of 8-bit dot products (onnxruntime's int8 kernels take another, slower path without them).
INT8_DOT_FLAGS = ("avx512_vnni", "avx_vnni", "amx_int8", "asimddp")


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU's model name and its 8-bit dot-product flags (``AMD EPYC, int8 dot: none``), from ``/proc/cpuinfo``
    (or the given text); ``platform.processor()`` or the machine type where there is no such file."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return platform.processor() or platform.machine()
    fields = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name") or platform.processor() or platform.machine()
    flags = set((fields.get("flags") or fields.get("Features") or "").split())
    return f"{name}, int8 dot: {' '.join(f for f in INT8_DOT_FLAGS if f in flags) or 'none'}"


def metadata_line(packages: Sequence[str] = ("numpy", "torch"), **extra: object) -> str:
    """One ``# ...`` header line: commit, python, package versions, CPU, torch threads, load average, extras.

    Torch's intra-op thread count is reported only when the script has imported torch (this module never
    imports it). Extras are appended as ``key value`` in the order given.

    Args:
        packages: distribution names whose installed versions to report.
        **extra: further fields, e.g. ``device="cuda (NVIDIA H100)"``, ``repeats="7 (+2 warm-up)"``.
    """
    fields = [("commit", git_commit()), ("python", platform.python_version())]
    fields += [(name, package_version(name)) for name in packages]
    fields.append(("cpu", f"{cpu_description()}, {os.cpu_count()} cores"))
    torch = sys.modules.get("torch")
    if torch is not None:
        fields.append(("torch threads", str(torch.get_num_threads())))
    fields.append(("load average", load_average()))
    fields += [(key.replace("_", " "), str(value)) for key, value in extra.items()]
    return "# " + " | ".join(f"{key} {value}" for key, value in fields)


def limit_blas_threads(threads: int | None) -> None:
    """Set the BLAS/OpenMP thread variables to ``threads`` (no-op for ``None``).

    Takes effect only if called before numpy (or torch) is first imported.

    Raises:
        ValueError: if ``threads < 1``.
        RuntimeError: if numpy or torch is already imported.
    """
    if threads is None:
        return
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    loaded = [name for name in ("numpy", "torch") if name in sys.modules]
    if loaded:
        raise RuntimeError(f"limit_blas_threads must run before {' and '.join(loaded)} is imported")
    for variable in BLAS_THREAD_VARIABLES:
        os.environ[variable] = str(threads)


def set_torch_threads(threads: int | None) -> int:
    """Set torch's intra-op thread count (``None`` keeps torch's default) and return the count in effect.

    Raises:
        ValueError: if ``threads < 1``.
    """
    import torch

    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    return torch.get_num_threads()


def cuda_sync(device: object) -> Callable[[], None] | None:
    """``torch.cuda.synchronize`` for a CUDA device (``torch.device`` or string), else ``None`` (nothing to wait for)."""
    import torch

    device = torch.device(device)
    if device.type != "cuda":
        return None
    return lambda: torch.cuda.synchronize(device)


def random_detector(variant: str, device: object = "cpu", seed: int = 0):
    """An RVT detector preset with seeded random weights, in eval mode, parameters frozen.

    Latency does not depend on the weight values, so the timing benchmarks need no checkpoint.

    Args:
        variant: an ``RVTConfig`` preset name (``tiny``, ``small``, ``base``, ``mini``, ``nano``).
        device: where the weights live (``torch.device`` or string).
        seed: ``torch.manual_seed`` set before the weights are drawn.

    Returns:
        ``RVTDetector`` with ``requires_grad`` off on every parameter (gradients flow to the inputs only).
    """
    import torch

    from davis_rig.models.rvt import RVTConfig
    from davis_rig.models.rvt.detector import RVTDetector

    torch.manual_seed(seed)
    detector = RVTDetector(RVTConfig.presets()[variant]).to(device).eval()
    for parameter in detector.parameters():
        parameter.requires_grad_(False)
    return detector


def detection_score(decoded):
    """Σ objectness × max class probability over all anchors: the scalar the digital attack's gradient comes from.

    Args:
        decoded: decoded detector output, float tensor (B, A, 5 + classes): box (4), objectness, class probs.

    Returns:
        0-d tensor.
    """
    return (decoded[..., 4] * decoded[..., 5:].max(-1).values).sum()


def bptt_case(model, inputs) -> Callable[[], None]:
    """A timed case: ``len(inputs)`` recurrent steps from no state, then backward through all of them.

    Args:
        model: ``RVTDetector`` (``model(x, states) -> (decoded, states)``).
        inputs: padded histograms, float tensors (B, 20, H, W); each call clones them with ``requires_grad``.

    Returns:
        A function of no arguments: forward over the steps, backward of :func:`detection_score` of the last step.
    """

    def bptt() -> None:
        xs = [x.clone().requires_grad_(True) for x in inputs]
        states = None
        for x in xs:
            decoded, states = model(x, states)
        detection_score(decoded).backward()

    return bptt
