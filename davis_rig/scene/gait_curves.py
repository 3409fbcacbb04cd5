"""Normative sagittal joint-angle curves of walking and running, as Fourier series of the gait phase.

Sagittal hip / knee / ankle angles versus gait-cycle % are Fourier series (order 6) fitted by
:func:`fit_fourier` to key values of published normative curves (tables :data:`NORMATIVE_TABLES`):

- **Walking** (self-selected speed, ~1.3 m/s, toe-off at 62 %): the rounded event values of Perry &
  Burnfield, *Gait Analysis: Normal and Pathological Function*, 2nd ed. (SLACK, 2010), chapters on the hip,
  knee and ankle (hip 30° flexion at initial contact, ~10° apparent hyperextension at 50 %, 0° at toe-off,
  ~33° peak flexion in terminal swing; knee 5° at contact, ~18° loading-response flexion at 15 %, ~3° at
  40 %, 40° at toe-off, 60° peak at 73 %; ankle 0° at contact, 5° plantarflexion at 10 %, 10°
  dorsiflexion at 48 %, 20° plantarflexion at 62 %, neutral from mid swing), with intermediate points read
  off the same normative curves (±2°).
- **Running** (~3.2 m/s, toe-off at 39 %): values read off the mean curves of Novacheck, "The biomechanics
  of running", *Gait & Posture* 7 (1998) 77-95, Fig. 4 (hip ~38° at contact, ~-8° at toe-off, ~50° peak in
  late swing; knee ~20° at contact, ~42° stance peak, ~18° at toe-off, ~95° swing peak; ankle ~20° stance
  dorsiflexion, ~-22° at toe-off), ±3°.

The curves are approximations of population means (values rounded / read from figures), not a
re-publication of the tables; the fit errors at the tabulated points are ≤ 0.4° (:data:`FIT_MAX_ERROR_DEG`).
Angles: flexion / dorsiflexion positive, degrees; phase 0 = heel strike of the leg.

:func:`joint_angles_deg` blends the walking and running curves (after aligning their toe-off);
:mod:`davis_rig.scene.gait` builds poses from them.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FIT_MAX_ERROR_DEG",
    "FOURIER_COEFFICIENTS",
    "FOURIER_ORDER",
    "FOURIER_RIDGE",
    "NATIVE_STANCE_FRACTION",
    "NORMATIVE_TABLES",
    "evaluate_fourier",
    "fit_fourier",
    "joint_angles_deg",
    "blended_stance_fraction",
]


#: Key values (gait-cycle %, angle in degrees) of the normative curves; see the module docstring for sources.
NORMATIVE_TABLES: dict[str, tuple[tuple[float, float], ...]] = {
    "walk_hip": ((0, 30), (10, 28), (20, 20), (30, 10), (40, 0), (50, -10), (56, -7), (62, 0), (75, 20), (87, 33),
                 (95, 31)),
    "walk_knee": ((0, 5), (7, 13), (15, 18), (25, 12), (40, 3), (50, 8), (56, 22), (62, 40), (73, 60), (80, 52),
                  (87, 30), (94, 8)),
    "walk_ankle": ((0, 0), (10, -5), (20, 2), (30, 5), (40, 8), (48, 10), (55, 0), (62, -20), (75, -5), (87, 0),
                   (95, 0)),
    "run_hip": ((0, 38), (10, 28), (20, 15), (30, 3), (39, -8), (50, 0), (60, 20), (75, 40), (85, 50), (93, 45)),
    "run_knee": ((0, 20), (8, 35), (15, 42), (25, 32), (39, 18), (50, 50), (60, 80), (70, 95), (80, 80), (90, 40)),
    "run_ankle": ((0, 5), (8, 15), (15, 20), (25, 12), (39, -22), (50, -12), (60, -5), (70, 3), (80, 8), (90, 7)),
}  # fmt: skip


#: Fourier order and ridge weight (on harmonic k: lambda * k^4) of the fits.
FOURIER_ORDER = 6
FOURIER_RIDGE = 1e-3


#: Coefficients ``(a0, a1, b1, ..., a6, b6)`` of ``a0 + sum_k a_k cos(2 pi k p) + b_k sin(2 pi k p)``
#: (p = phase in cycles, result in degrees) = ``fit_fourier(NORMATIVE_TABLES[name])``.
FOURIER_COEFFICIENTS: dict[str, tuple[float, ...]] = {
    "walk_hip": (14.7588, 19.8274, -2.0375, -3.5960, -2.0639, -0.0869, 0.6359, -1.0005, 0.3692, 0.2042, 0.1317,
                 -0.1165, 0.1663),
    "walk_knee": (21.9099, -0.7706, -20.3690, -14.6498, 6.9949, -0.9177, 3.6025, -0.7942, 0.7446, 0.1320, 0.2901,
                  0.0573, 0.2656),
    "walk_ankle": (-1.1935, -0.7545, 6.4560, 2.4033, -7.4391, -3.8638, 0.9057, 3.1723, 0.6848, 0.0327, -0.9169,
                   0.0808, 0.5868),
    "run_hip": (22.3933, 19.5387, -17.5703, -2.9243, 1.5278, -0.3950, -1.8263, -0.5584, 1.0231, -0.1493, 0.3387,
                0.1041, -0.0882),
    "run_knee": (48.5031, -9.3285, -28.7805, -13.2831, 14.8104, -4.7458, 1.4865, 0.0116, 0.9511, -0.7852, 0.2712,
                 -0.1600, -0.1075),
    "run_ankle": (1.8251, 13.3022, 0.3755, -6.1699, 7.0011, -3.7720, -2.0901, 0.9509, 0.3527, -0.9097, 0.3809,
                  -0.1023, -0.0330),
}  # fmt: skip


#: Largest |fit - table| over the tabulated points (degrees), per curve, as measured when fitting.
FIT_MAX_ERROR_DEG: dict[str, float] = {
    "walk_hip": 0.10, "walk_knee": 0.22, "walk_ankle": 0.34, "run_hip": 0.09, "run_knee": 0.21, "run_ankle": 0.16,
}  # fmt: skip


#: Toe-off (end of stance) as a fraction of the cycle in the source curves.
NATIVE_STANCE_FRACTION = {"walk": 0.62, "run": 0.39}


def _design(phase: np.ndarray, order: int) -> np.ndarray:
    p = np.asarray(phase, dtype=np.float64)
    cols = [np.ones_like(p)]
    for k in range(1, order + 1):
        cols += [np.cos(2 * np.pi * k * p), np.sin(2 * np.pi * k * p)]
    return np.stack(cols, axis=-1)


def fit_fourier(
    table: tuple[tuple[float, float], ...], order: int = FOURIER_ORDER, ridge: float = FOURIER_RIDGE
) -> np.ndarray:
    """Least-squares Fourier series through periodic samples, with a ridge penalty ``ridge * k^4`` on harmonic k.

    Args:
        table: ``(percent of cycle, value)`` pairs.
        order: number of harmonics.
        ridge: smoothness weight (keeps the curve from oscillating between sparse points).

    Returns:
        float64 [2 * order + 1] coefficients ``(a0, a1, b1, ..., a_order, b_order)``.
    """
    pts = np.asarray(table, dtype=np.float64)
    a = _design((pts[:, 0] / 100.0) % 1.0, order)
    penalty = np.concatenate([[0.0], np.repeat(np.arange(1, order + 1, dtype=np.float64) ** 4, 2)])
    return np.linalg.solve(a.T @ a + ridge * np.diag(penalty), a.T @ pts[:, 1])


def evaluate_fourier(coefficients, phase) -> np.ndarray:
    """Value of a Fourier series at ``phase`` (cycles, any real), float64 with the shape of ``phase``."""
    c = np.asarray(coefficients, dtype=np.float64)
    order = (len(c) - 1) // 2
    return _design(phase, order) @ c


def _warp(phase: np.ndarray, stance: float, native: float) -> np.ndarray:
    """Map a cycle with toe-off at ``stance`` onto a source curve with toe-off at ``native`` (piecewise linear)."""
    p = np.mod(phase, 1.0)
    return np.where(p < stance, p * native / stance, native + (p - stance) * (1 - native) / (1 - stance))


def joint_angles_deg(phase, run: float = 0.0, stance_fraction: float | None = None) -> dict[str, np.ndarray]:
    """Sagittal hip / knee / ankle angles of one leg, blended between walking and running.

    Args:
        phase: gait phase of the leg (cycles; 0 = its heel strike), float [N].
        run: 0 = walking curves, 1 = running curves, in between = blend (after aligning toe-off).
        stance_fraction: toe-off of the blended cycle (default: blend of the native 0.62 / 0.39).

    Returns:
        ``{"hip", "knee", "ankle"}`` -> float64 [N] degrees (flexion / dorsiflexion positive).
    """
    run = float(np.clip(run, 0.0, 1.0))
    s = stance_fraction if stance_fraction is not None else blended_stance_fraction(run)
    out = {}
    for joint in ("hip", "knee", "ankle"):
        walk = evaluate_fourier(FOURIER_COEFFICIENTS[f"walk_{joint}"], _warp(phase, s, NATIVE_STANCE_FRACTION["walk"]))
        running = evaluate_fourier(FOURIER_COEFFICIENTS[f"run_{joint}"], _warp(phase, s, NATIVE_STANCE_FRACTION["run"]))
        out[joint] = (1 - run) * walk + run * running
    return out


def blended_stance_fraction(run: float) -> float:
    """Toe-off as a fraction of the cycle for a walk (0) to run (1) blend: the blend of the native 0.62 / 0.39."""
    return (1 - run) * NATIVE_STANCE_FRACTION["walk"] + run * NATIVE_STANCE_FRACTION["run"]
