"""Choosing among restarts of the APS attack by their validation recall, never by the held-out test.

Runs of ``tools/aps_attack.py`` that differ only in ``--seed`` end at textures of different quality (the held-out
recall of one recipe spans 15–29 % over seeds). Each run with ``--validate-every`` keeps its best texture on
validation scenes of body shapes held out of the optimisation and disjoint from the test shapes
(``aps_control.json``: ``attack.best_on_validation``); picking the run whose kept texture has the lowest
validation recall uses nothing the test measures, so the picked texture's held-out recall is an honest figure of
the recipe "K seeds, keep the best on validation".

A report is the dict ``tools/aps_attack.py`` writes as ``aps_control.json``; the fields read here are ``threshold``,
``model``, ``rows`` (``texture``, ``rate``, ``mean_top_score``, ``frames``), ``held_out`` and ``attack``
(``grid_n``, ``parts``, ``validation_shapes``, ``best_on_validation`` with ``step``, ``rate``,
``mean_top_score``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import PurePath

from davis_rig.errors import ConfigError

__all__ = ["RestartRow", "pick_on_validation", "restart_rows"]

#: Report fields that must agree for validation recalls to be comparable: (where, name).
_SAME = (("report", "threshold"), ("report", "model"), ("report", "held_out"), ("attack", "grid_n"),
         ("attack", "parts"), ("attack", "validation_shapes"))


@dataclass(frozen=True)
class RestartRow:
    """One run's figures; rates are shares of frames (0..1) where the labeler finds the person."""

    run: str  #: its name (the run's folder)
    validation_rate: float  #: validation recall of the texture it kept
    validation_step: int  #: the step that texture was validated at
    validation_top_score: float  #: its mean top score on validation
    held_out_rate: float  #: held-out (test shapes) recall of the kept texture
    final_held_out_rate: float  #: held-out recall of the last step's texture
    frames: int  #: held-out frames scored


def _value(report: Mapping, where: str, name: str):
    source = report if where == "report" else report.get("attack", {})
    value = source.get(name)
    return PurePath(value).name if name == "model" and isinstance(value, str) else value  # the file, not its folder


def _row(report: Mapping, name: str, *, prefix: bool = False) -> Mapping:
    rows = [r for r in report.get("rows", ())
            if (r.get("texture", "").startswith(name) if prefix else r.get("texture") == name)]
    if len(rows) != 1:
        raise ConfigError("rows", f"expected one held-out row {name!r}{'...' if prefix else ''}, found {len(rows)}")
    return rows[0]


def restart_rows(reports: Sequence[Mapping], names: Sequence[str]) -> list[RestartRow]:
    """The comparable figures of each run, in the given order.

    Args:
        reports: ``aps_control.json`` dicts of runs with validation (``--validate-every N > 0``).
        names: a name per report (its folder), used in messages and rows.

    Raises:
        ConfigError: ``field`` ``reports`` for no report or a names/reports length mismatch; ``field`` the
            offending report's name when it has no validation, no held-out row of its textures, or a set-up
            that differs from the first report's (validation scenes, held-out scenes, threshold, grid, parts,
            labeler model), since validation recalls of different set-ups do not measure the same thing.
    """
    if not reports or len(reports) != len(names):
        raise ConfigError("reports", f"expected one name per report and at least one, got {len(reports)} "
                                     f"reports and {len(names)} names")
    first = reports[0]
    for name, report in zip(names, reports):
        for where, field in _SAME:
            if _value(report, where, field) != _value(first, where, field):
                raise ConfigError(name, f"its {field} {_value(report, where, field)!r} differs from "
                                        f"{names[0]}'s {_value(first, where, field)!r}: validation recalls "
                                        "of different set-ups are not comparable")
    rows = []
    for name, report in zip(names, reports):
        best = report.get("attack", {}).get("best_on_validation")
        if not best:
            raise ConfigError(name, "the run has no texture kept on validation (run it with --validate-every N)")
        n = report["attack"]["grid_n"]
        try:
            chosen = _row(report, f"ours {n}x{n}, best on validation", prefix=True)  # "... (step S)"
            final = _row(report, f"ours {n}x{n}")
        except ConfigError as error:
            raise ConfigError(name, error.reason) from None
        rows.append(RestartRow(run=name, validation_rate=float(best["rate"]), validation_step=int(best["step"]),
                               validation_top_score=float(best["mean_top_score"]),
                               held_out_rate=float(chosen["rate"]), final_held_out_rate=float(final["rate"]),
                               frames=int(chosen["frames"])))
    return rows


def pick_on_validation(rows: Sequence[RestartRow]) -> int:
    """Index of the run whose kept texture has the lowest validation recall; a tie goes to the lower mean top
    score on validation, then to the earlier run. The held-out figures are not read."""
    if not rows:
        raise ConfigError("rows", "no runs to pick from")
    return min(range(len(rows)), key=lambda i: (rows[i].validation_rate, rows[i].validation_top_score, i))
