"""The CUSUM bank's fixed design and the isolation codes (:mod:`imufdi_cli.maths.sequential`)."""

from __future__ import annotations

from dataclasses import dataclass

NO_ISOLATION = -1
NOT_ISOLABLE = -2


@dataclass(frozen=True)
class CusumDesign:
    """The bank's fixed design.

    Attributes
    ----------
    shifts : tuple of float
        Design shifts ``mu_d`` (z units, i.e. per-sample standard deviations of the
        evidence): each is optimal for a step of that size; between two of them the
        efficiency loss is at most 1 - (2 sqrt(r) - 1) / r for a ratio r of neighbours
        (25 % for r = 3), and a shift below ``mu_min / 2`` is never detected.
    clip : float
        Clip c of the evidence in (1): one outlier adds at most ``mu_d c - mu_d^2 / 2``.
    tau_s : float
        Time constant of the slow reference, seconds (0: no reference).
    gate : float
        Clip of the reference's innovations, z units.
    block : int
        L of :func:`long_run_factor`.
    scale_tau_s : float
        Time constant of each column's tracked variance, seconds (0: the calibrated
        sigma is kept): a running mean of the squared evidence (winsorized at 4 standard
        deviations) from the calibration window on, then an exponential average; the
        sigma estimated from a short window is off by a few percent per sensor, and a
        sensor whose sigma was underestimated by 10 % raises about three times the false
        alarms of the others at h ~ 17.
    """

    shifts: tuple[float, ...] = (1.0, 3.0)
    clip: float = 3.5
    tau_s: float = 60.0
    gate: float = 3.0
    block: int = 10
    scale_tau_s: float = 300.0
