"""``davis-attack``: the digital optimizer's commands (``optimize``, ``evaluate``, ``reproduce``, ``export``).

Each subcommand maps its arguments onto one API call (:mod:`davis_rig.cli._attack_commands` for ``optimize``,
``evaluate`` and ``reproduce``; :mod:`davis_rig.cli._export_command` for ``export``); errors become one message
and an exit code in :mod:`davis_rig.cli._common`. Heavy imports happen in the actions, so ``--help`` is fast.
Under torchrun:
``torchrun --nproc_per_node N -m davis_rig.cli.attack optimize ...``.
"""

from __future__ import annotations

import argparse
import sys

from davis_rig.cli._attack_commands import add_evaluate_parser, add_optimize_parser, add_reproduce_parser
from davis_rig.cli._common import new_parser, run_command
from davis_rig.cli._export_command import add_export_parser

NAME = "davis-attack"


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-attack`` with its subcommands."""
    parser = new_parser(NAME, "Adversarial texture attack on an event-camera pedestrian detector: optimize, evaluate "
                              "(paper's digital protocol), reproduce Tables 1-2, export.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_optimize_parser(sub)
    add_evaluate_parser(sub)
    add_reproduce_parser(sub)
    add_export_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-attack``; returns the exit code."""
    args = build_parser().parse_args(argv)
    return run_command(f"{NAME} {args.command}", lambda: args.func(args))


if __name__ == "__main__":
    sys.exit(main())
