#!/usr/bin/env python
"""Convert an AEDAT4 recording (iniVation DV) into a davis_rig session.h5.

Usage: python tools/aedat4_to_session.py INPUT.aedat4 OUTPUT.h5 [--overwrite]
Needs dv-processing: pip install "davis_rig[aedat4]".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run :func:`davis_rig.session.aedat4.import_aedat4`, print a summary; returns the exit code."""
    from davis_rig.cli.common import new_parser, run_main

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/aedat4_to_session.py in.aedat4 out.h5   # needs davis_rig[aedat4]\n")
    parser.add_argument("input", help="AEDAT4 file")
    parser.add_argument("output", help="session.h5 to create")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")

    def convert(args: argparse.Namespace) -> int:
        from davis_rig.session.aedat4 import import_aedat4

        summary = import_aedat4(args.input, args.output, overwrite=args.overwrite)
        print(f"{summary.path}: {summary.events} events, {summary.frames} frames, {summary.specials} triggers, "
              f"{summary.imu} IMU samples from {args.input} ({summary.camera_name})")
        return 0

    return run_main(parser, argv, convert)


if __name__ == "__main__":
    sys.exit(main())
