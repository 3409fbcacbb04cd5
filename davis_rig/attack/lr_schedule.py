"""Learning-rate schedules of the texture optimisation: a pure function of the step (exact resume needs no state).

- ``"cosine_restarts"`` (the official code's default, ``CosineAnnealingLR_Restart`` of its training options):
  cosine annealing from the base rate to ``lr_min`` over ``period`` steps, then a warm restart at the base rate.
  The official settings are base 1e-4, ``eta_min`` 1e-7, restarts at 11,500, 23,000 and 34,500 with weight 1 and a
  first period of 11,500 = its ``niter``: within its 11,500 iterations the rate makes exactly one cosine from 1e-4
  down to 1e-7 (the later periods, one of them written 115,000, are never reached). The official loop steps the
  scheduler after each optimiser step and counts restarts one step late, so step ``k`` (0-based) uses
  ``lr_min + (base - lr_min) (1 + cos(pi k / period)) / 2`` for ``k = 0 .. period`` (base at step 0, ``lr_min`` at
  step ``period``) and the rate restarts at step ``period + 1``; cycles here repeat with the same period.
- ``"constant"``: the base rate at every step (the toolkit's schedule before the official one was the default).
"""

from __future__ import annotations

import math

__all__ = ["LR_SCHEDULES", "OFFICIAL_LR_MIN", "cosine_restarts_lr", "lr_at"]

#: Schedules of :func:`lr_at`.
LR_SCHEDULES = ("cosine_restarts", "constant")
#: The official code's ``eta_min``.
OFFICIAL_LR_MIN = 1e-7


def cosine_restarts_lr(step: int, base_lr: float, period: int, lr_min: float = OFFICIAL_LR_MIN) -> float:
    """Cosine annealing with warm restarts, as the official ``CosineAnnealingLR_Restart`` (restart weight 1).

    Args:
        step: 0-based optimisation step (>= 0).
        base_lr: rate at step 0 and after each restart (> 0).
        period: steps of one cosine (>= 1): ``lr_min`` is reached at step ``period``, the rate restarts at
            ``period + 1`` (a cycle is ``period + 1`` steps).
        lr_min: the floor of the cosine (>= 0).

    Returns:
        The learning rate of ``step``.

    Raises:
        ValueError: step < 0, period < 1, base_lr <= 0 or lr_min < 0.

    Example:
        >>> cosine_restarts_lr(0, 1e-4, 100), cosine_restarts_lr(100, 1e-4, 100), cosine_restarts_lr(101, 1e-4, 100)
        (0.0001, 1e-07, 0.0001)
    """
    if int(step) < 0 or int(period) < 1 or not base_lr > 0 or not lr_min >= 0:
        raise ValueError(f"need step >= 0, period >= 1, base_lr > 0, lr_min >= 0; got {step}, {period}, {base_lr}, "
                         f"{lr_min}")
    phase = int(step) % (int(period) + 1)
    return lr_min + (base_lr - lr_min) * (1.0 + math.cos(math.pi * phase / int(period))) / 2.0


def lr_at(schedule: str, step: int, base_lr: float, period: int, lr_min: float = OFFICIAL_LR_MIN) -> float:
    """The learning rate of ``step`` under a named schedule (:data:`LR_SCHEDULES`).

    Raises:
        ValueError: unknown schedule (and see :func:`cosine_restarts_lr`).
    """
    if schedule == "constant":
        return float(base_lr)
    if schedule == "cosine_restarts":
        return cosine_restarts_lr(step, base_lr, period, lr_min)
    raise ValueError(f"schedule must be one of {LR_SCHEDULES}, got {schedule!r}")
