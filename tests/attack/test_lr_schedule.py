"""The learning-rate schedules: the official cosine annealing with warm restarts, step by step, and constant."""

from __future__ import annotations

import math

import pytest

from davis_rig.attack.lr_schedule import OFFICIAL_LR_MIN, cosine_restarts_lr, lr_at


def _official(steps: int, base: float, period: int, eta_min: float) -> list[float]:
    """The rate each step trains with under the official loop: optimiser step, then ``scheduler.step()`` of
    ``CosineAnnealingLR_Restart`` (restarts given one step late, ``[v + 1 for v in restarts]``, weight 1), whose
    ``get_lr`` is the recursive form below."""
    restarts = [period + 1, 2 * (period + 1)]
    lr, last_restart, out = base, 0, []
    for epoch in range(steps):
        out.append(lr)  # the rate of this step's optimiser update
        epoch += 1  # scheduler.step()
        if epoch in restarts:
            last_restart, lr = epoch, base
        elif (epoch - last_restart - 1 - period) % (2 * period) == 0:
            lr = lr + (base - eta_min) * (1 - math.cos(math.pi / period)) / 2
        else:
            t = epoch - last_restart
            lr = (1 + math.cos(math.pi * t / period)) / (1 + math.cos(math.pi * (t - 1) / period)) * (lr - eta_min) \
                + eta_min
    return out


def test_cosine_restarts_matches_the_official_recursion_step_by_step():
    period = 20
    official = _official(3 * (period + 1), 1e-4, period, OFFICIAL_LR_MIN)
    ours = [cosine_restarts_lr(k, 1e-4, period) for k in range(len(official))]
    assert ours == pytest.approx(official, rel=1e-9)
    assert ours[0] == 1e-4 and ours[period] == pytest.approx(OFFICIAL_LR_MIN) and ours[period + 1] == 1e-4
    assert all(a > b for a, b in zip(ours[: period], ours[1 : period + 1]))  # strictly falling inside a cycle


def test_the_official_11500_step_run_is_one_cosine_and_constant_is_constant():
    assert cosine_restarts_lr(0, 1e-4, 11_500) == 1e-4
    assert cosine_restarts_lr(5_750, 1e-4, 11_500) == pytest.approx((1e-4 + 1e-7) / 2)
    assert cosine_restarts_lr(11_499, 1e-4, 11_500) == pytest.approx(1e-7, rel=1e-3)
    assert lr_at("constant", 9_999, 1e-4, 11_500) == 1e-4
    assert lr_at("cosine_restarts", 7, 1e-4, 11_500) == cosine_restarts_lr(7, 1e-4, 11_500)
    with pytest.raises(ValueError, match="schedule"):
        lr_at("step", 0, 1e-4, 10)
    with pytest.raises(ValueError):
        cosine_restarts_lr(0, 1e-4, 0)
