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
        Design shifts ``mu_d`` in standard deviations of the evidence *at rest*: each is
        optimal for a step of that size. In motion, where the evidence's standard
        deviation grows by a factor ``s_t``, a design of the same physical size has the
        effective shift ``mu_d / s_t``, so the larger designs, inert at rest (a shift
        above ``2 c`` never has a positive increment), take over: a geometric grid of
        ratio 2 (at most 9 % efficiency lost between neighbours) from 2 to 32 covers rest
        and hand motion. A step below ``mu_min / 2`` (one standard deviation at rest) is
        never detected: the bias wander of real chips lives below it.
    clip : float
        Clip c of the standardized evidence in (1): one outlier adds at most
        ``mu c - mu^2 / 2``.
    tau_s : float
        Time constant of the slow bias reference, seconds (0: none).
    gate : float
        Clip of the reference's innovations, standard deviations of a sub-block's sum.
    block : int
        L of :func:`long_run_factor`.
    scale_tau_s : float
        Time constant of each column's tracked variance at rest, seconds (0: the
        calibrated sigma is kept): a running mean of the squared evidence (winsorized at 4
        standard deviations) from the calibration window on, then an exponential average;
        a sigma estimated from a short window is off by a few percent per sensor, and a
        sensor whose sigma was underestimated by 10 % raises about three times the false
        alarms of the others at h ~ 17.
    hold_s : float
        Longest time the references stay frozen in an episode, seconds: after it they
        resume (a fault that lasts is then absorbed, at the rate the innovation gate
        allows: ``gate sqrt(b) / (tau f_s)`` standard deviations per sub-block of b
        samples), so that a false alarm raised by bias wander does not latch.
    rest_factor : float
        Rows whose motion variance factor exceeds this are in motion: they teach the offset
        and variance references nothing (the noise model covers them).
    min_shift : float
        Effective shifts below this are not run (they would need more than ``2 h /
        min_shift^2`` samples).
    motion_outliers : float
        Share of outliers beyond the clip that the threshold allows for when the noise
        variance of the rows in motion is the rows' own (``CusumBank(spatial=True)``):
        hand motion leaves 2.0-2.3 % of the MIMU4444 accelerometers' evidence beyond 3.5
        of the rows' own spread (fewer beyond the clip, applied after the margin).
    """

    shifts: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0)
    clip: float = 3.5
    tau_s: float = 30.0
    gate: float = 3.0
    block: int = 10
    scale_tau_s: float = 300.0
    hold_s: float = 10.0
    rest_factor: float = 2.0
    min_shift: float = 0.25
    motion_outliers: float = 0.02
