"""``davis-attack``: the digital optimizer's commands (``optimize``, ``search``, ``evaluate``, ``reproduce``,
``export``).

Each subcommand maps its arguments onto one API call (:mod:`davis_rig.cli._attack_commands` for ``optimize``,
``evaluate`` and ``reproduce``; :mod:`davis_rig.cli._search_command` for ``search``;
:mod:`davis_rig.cli._export_command` for ``export``); bad values exit 2 naming the
option, errors become one message and an exit code in :mod:`davis_rig.cli.common`. Heavy imports happen in the
actions, so ``--help`` is fast. Under torchrun:
``torchrun --nproc_per_node N -m davis_rig.cli.attack optimize ...``.
"""

from __future__ import annotations

import argparse
import sys

from davis_rig.cli._attack_commands import (
    CONFIG_OPTIONS,
    add_evaluate_parser,
    add_optimize_parser,
    add_reproduce_parser,
)
from davis_rig.cli.common import EXIT_USAGE, new_parser, run_command
from davis_rig.cli._export_command import add_export_parser
from davis_rig.cli._search_command import add_search_parser

NAME = "davis-attack"


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-attack`` with its subcommands."""
    parser = new_parser(NAME, "Adversarial texture attack on an event-camera pedestrian detector: optimize (paper), "
                              "search (gradient-free), evaluate (paper's digital protocol), reproduce Tables 1-2, "
                              "export.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_optimize_parser(sub)
    add_search_parser(sub)
    add_evaluate_parser(sub)
    add_reproduce_parser(sub)
    add_export_parser(sub)
    return parser


def _parse(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse and apply the subcommand's cross-option rules (``check`` of its defaults, reported by its parser)."""
    args = parser.parse_args(argv)
    check = getattr(args, "check", None)
    if check is not None:
        check(parser._subparsers._group_actions[0].choices[args.command], args)
    return args


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-attack``; returns the exit code (argparse's 0 and 2 included)."""
    try:
        args = _parse(build_parser(), argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    args.argv = sys.argv[1:] if argv is None else list(argv)  # the command a run records, as it was given
    # messages name the subcommand, as argparse's do: "davis-attack optimize: error: argument --cells: ..."
    return run_command(f"{NAME} {args.command}", lambda: args.func(args), CONFIG_OPTIONS)


if __name__ == "__main__":
    sys.exit(main())
