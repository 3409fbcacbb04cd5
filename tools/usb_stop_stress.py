"""Stress the capture path's start/read/stop on an emulated libusb-1.0 with data flowing; count what goes wrong.

Run: ``python tools/usb_stop_stress.py [--cycles 500] [--level camera ring] [--faults plain late race all]
[--interval-us 250]``

Each run plugs one emulated DAVIS346 (``tests/helpers/libusb_emu``: a C libusb-1.0 built with the system compiler,
below pyusb's unmodified libusb1 backend; the device model is ``VirtualDavis346`` streaming without end) and runs
``--cycles`` cycles of start / read 3 / stop at two levels: ``camera`` (``Davis346``: the stop sequence, then the
transfer ring stops) and ``ring`` (``RingReader`` on a device that keeps streaming, so transfers complete with data
while the ring stops). Per run it prints the cycles that raised, the emulation's misuse counters (use after free,
double free, free or close with transfers in flight, ...), transfers left in flight, the cancels / cancel races /
callbacks run in a synchronous transfer's thread, the data received and the time. Exit status 1 if any cycle raised
or any misuse was counted.
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib.util
import platform
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
HELPER = REPO_ROOT / "tests" / "helpers" / "libusb_emu.py"


def load_helper():
    """Import the emulation helper module from the test folder."""
    spec = importlib.util.spec_from_file_location("libusb_emu", HELPER)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def fault_sets(emu_module) -> dict:
    """Named libusb-level fault settings of the runs."""
    EmuFaults = emu_module.EmuFaults
    return {
        "plain": EmuFaults(),
        "late": EmuFaults(completion_delay_us=2000, cancel_delay_us=1000),
        "race": EmuFaults(cancel_race_every=2, poll_ms=1),
        "all": EmuFaults(completion_delay_us=1000, cancel_delay_us=500, cancel_race_every=3, poll_ms=1),
    }


def main(argv: list[str] | None = None) -> int:
    from davis_rig.cli.common import new_parser, non_negative_float, positive_int, run_main

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/usb_stop_stress.py --cycles 500\n"
                        "  python tools/usb_stop_stress.py --level ring --interval-us 0\n\n"
                        "Exit 1 also when a cycle raised or the emulation counted a misuse of the transfer API.\n")
    parser.add_argument("--cycles", type=positive_int, default=500, help="start/read/stop cycles per run (default 500)")
    parser.add_argument("--level", nargs="+", default=["camera", "ring"], choices=["camera", "ring"])
    parser.add_argument("--faults", nargs="+", default=["plain", "late", "race", "all"],
                        choices=["plain", "late", "race", "all"])
    parser.add_argument("--interval-us", type=non_negative_float, default=None, metavar="US",
                        help="device time between two 8 KiB device transfers, µs (default 250 = 33 MB/s; "
                             "0 = as fast as the host takes them)")
    return run_main(parser, argv, _stress)


def _stress(args: argparse.Namespace) -> int:
    emu_module = load_helper()
    interval_us = emu_module.STRESS_INTERVAL_US if args.interval_us is None else args.interval_us
    try:
        emu = emu_module.EmulatedLibusb.load()
    except emu_module.EmulatorUnavailable as exc:
        print(f"usb_stop_stress: {exc}", file=sys.stderr)
        return 5
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=REPO_ROOT).stdout.strip()
    print(f"# tools/usb_stop_stress.py --cycles {args.cycles} --interval-us {interval_us:g}  {platform.node()}  "
          f"{dt.date.today()}  commit {commit or 'unknown'}")
    print(f"{'level':7s} {'faults':6s} {'cycles':>6s} {'raised':>6s} {'misuse':>6s} {'left':>4s} {'cancels':>7s} "
          f"{'races':>5s} {'sync_cb':>7s} {'MB':>7s} {'s':>6s}")
    bad = False
    sets = fault_sets(emu_module)
    for level in args.level:
        for name in args.faults:
            result = emu_module.start_stop_cycles(emu, args.cycles, level=level, faults=sets[name],
                                                  interval_us=interval_us)
            c = result.counters
            misuse = sum(result.misuse.values())
            print(f"{level:7s} {name:6s} {result.cycles:6d} {result.failed_cycles:6d} {misuse:6d} "
                  f"{result.in_flight_after:4d} {c['cancels']:7d} {c['cancel_races']:5d} {c['sync_callbacks']:7d} "
                  f"{result.bytes / 1e6:7.1f} {result.seconds:6.1f}")
            for message, count in result.exceptions.most_common(3):
                print(f"    {count} x {message[:100]}")
            if result.misuse:
                print(f"    misuse: {result.misuse}")
            bad = bad or result.failed_cycles > 0 or misuse > 0 or result.in_flight_after > 0
    if emu.host_errors:
        print(f"device model errors: {emu.host_errors[:3]}")
        bad = True
    emu.close()
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
