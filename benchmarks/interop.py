"""Benchmark: davis-export and the imports back — throughput and peak memory per format.

Run: ``python benchmarks/interop.py [--events 30e6] [--rate 2e6] [--formats npz prophesee-dat rvt aedat4]``.
Writes a synthetic labelled session (uniform events at ``--rate`` events/s, 25 Hz labels) into a temporary folder,
then runs each export, and each import of its output, in a fresh Python process: the figures are wall-clock
events per second (session events read; events written for imports) and that process's peak resident memory
(``ru_maxrss``), which stays flat as ``--events`` grows when the code streams. AEDAT4 is skipped without
dv-processing. One run each (an export is long enough not to need repeats); the metadata line gives the load.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _common import REPO_ROOT, metadata_line

from davis_rig.protocol.layout import SensorLayout
from davis_rig.session import SessionWriter
from davis_rig.session.labels import write_labels
from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, make_events

OUTPUT_NAMES = {"npz": "x.npz", "prophesee-dat": "x_td.dat", "rvt": "ds", "aedat4": "x.aedat4"}
IMPORTERS = {"npz": "davis_rig.session.npz:import_npz",
             "prophesee-dat": "davis_rig.session.prophesee:import_prophesee_dat",
             "aedat4": "davis_rig.session.aedat4:import_aedat4"}

_CHILD = """
import json, resource, sys, time
kind, fmt, src, dst = sys.argv[1:5]
tic = time.perf_counter()
if kind == "export":
    from davis_rig.interop import export_session
    count = export_session(src, fmt, dst, overwrite=True).events_read
else:
    import importlib
    module, name = sys.argv[5].split(":")
    count = getattr(importlib.import_module(module), name)(src, dst, overwrite=True).events
seconds = time.perf_counter() - tic
print(json.dumps({"events": count, "seconds": seconds,
                  "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def write_session(path: Path, n_events: int, rate_hz: float, seed: int = 0) -> None:
    """A DAVIS346 session of ``n_events`` uniform events at ``rate_hz``, with one box every 40 ms."""
    rng = np.random.default_rng(seed)
    t_last = 1_000_000
    with SessionWriter(path, device_info={"serial": "BENCH", "layout": SensorLayout.davis346()}) as writer:
        for start in range(0, n_events, 1 << 20):
            k = min(1 << 20, n_events - start)
            t = t_last + np.cumsum(rng.exponential(1e6 / rate_hz, k)).astype(np.int64)
            t_last = int(t[-1])
            x, y = rng.integers(0, DAVIS346_HW[1], k), rng.integers(0, DAVIS346_HW[0], k)
            writer.append_events(make_events(t, x, y, rng.integers(0, 2, k)))
    times = np.arange(1_100_000, t_last, 40_000)
    labels = np.zeros(len(times), BBOX_DTYPE)
    labels["t"], labels["x"], labels["y"], labels["w"], labels["h"] = times, 100.5, 50.25, 40, 90
    labels["class_id"] = 1
    write_labels(path, labels, {"labeler": "benchmark", "crop_origin_x": 21, "crop_origin_y": 10})


def run_child(*args: str) -> dict:
    """One export or import in a fresh interpreter; its JSON line (events, seconds, peak_rss_mib)."""
    proc = subprocess.run([sys.executable, "-c", _CHILD, *args], cwd=REPO_ROOT, capture_output=True, text=True,
                          check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _print_result(direction: str, fmt: str, result: dict) -> None:
    """One line of the table: events, seconds, rate and peak RSS of one child run."""
    print(f"{direction} {fmt:14s} {result['events'] / 1e6:6.1f} M events  {result['seconds']:7.2f} s  "
          f"{result['events'] / result['seconds'] / 1e6:6.2f} M ev/s  peak RSS {result['peak_rss_mib']:5.0f} MiB")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=float, default=30e6, help="events in the synthetic session")
    parser.add_argument("--rate", type=float, default=2e6, help="its event rate, events/s")
    parser.add_argument("--formats", nargs="+", choices=list(OUTPUT_NAMES), default=list(OUTPUT_NAMES))
    args = parser.parse_args(argv)
    formats = list(args.formats)
    if "aedat4" in formats and importlib.util.find_spec("dv_processing") is None:
        formats.remove("aedat4")
        print("aedat4 skipped: dv-processing is not installed")
    print(metadata_line(("numpy", "h5py", "hdf5plugin", "dv-processing"), events=f"{args.events:.3g}",
                        rate=f"{args.rate:.3g} ev/s"))
    with tempfile.TemporaryDirectory() as tmp:
        session = Path(tmp) / "bench.h5"
        write_session(session, int(args.events), args.rate)
        for fmt in formats:
            out = Path(tmp) / OUTPUT_NAMES[fmt]
            _print_result("export", fmt, run_child("export", fmt, str(session), str(out)))
            if fmt in IMPORTERS:
                back = Path(tmp) / f"back_{fmt}.h5"
                _print_result("import", fmt, run_child("import", fmt, str(out), str(back), IMPORTERS[fmt]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
