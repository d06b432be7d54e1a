"""Sequential decisions under a false-alarm budget: a bank of robust CUSUM tests.

A per-sample test at level alpha raises ``alpha x rate`` false alarms a second (3,600 an
hour at 1 % and 100 Hz). A user who records for hours acts on decisions that are wrong
about once a day, and still wants a real fault caught within a fraction of a second. That
is quickest change detection: accumulate the evidence of each fault hypothesis over time
and decide when it is strong enough (Page 1954; Lorden 1971; Basseville & Nikiforov,
*Detection of Abrupt Changes*, 1993, §2.2 and §7.2).

**Evidence.** A detector hands in, per sample t and sensor i, a standardized signed
statistic ``z_t,i``: N(0, 1) without a fault, and shifted by ``delta_i = g_i f`` by a
step ``f`` (SI) on sensor i (``g_i``, the sensor's *sensitivity*, in z units per SI unit).
For the parity tests ``z_i = r_i / sqrt(P_ii)`` (r the whitened parity residual,
``P = I - H_w H_w^+``): the log-likelihood ratio of "a step of whitened size a on sensor i"
against "no fault", given the whole parity vector, is ``a r_i - a^2 P_ii / 2``, i.e.
``mu z_i - mu^2 / 2`` with ``mu = a sqrt(P_ii)``. A CUSUM on column i is therefore the
optimal test of the hypothesis "sensor i has a step of that size", correlations between
the sensors' residuals included.

**The bank.** For every sensor i, sign s = +-1 and design shift ``mu_d`` (z units,
:attr:`CusumDesign.shifts`), Page's CUSUM of the log-likelihood ratio of the clipped
evidence::

    l_t = mu_d s clip(z'_t,i, -c, c) - mu_d^2 / 2                       (1)
    S_t = max(0, S_{t-1} + l_t)                                         (2)

The clip (in the spirit of Huber's robust tests, 1965) bounds what one outlier can add
(``mu_d c - mu_d^2 / 2``), so that a decision needs several samples of evidence and an
isolated spike raises no alarm; for Gaussian noise it costs almost nothing (``c = 3.5``
is 2.5 standard deviations above the largest design's ``mu / 2``). An alarm episode starts at the first sample where any
``S > h`` (2 n D hypotheses); its isolated sensor is the one whose unclipped evidence
summed since the estimated onset is largest in magnitude (the generalized likelihood
ratio of a step on it: the clip saturates a large fault's evidence on every sensor
correlated with it). While it lasts, a second CUSUM tests "the fault has ended" on that
sensor and sign, with the increments ``-l_t`` of a design shift equal to the fault's mean
evidence since the onset; when that reaches ``h`` the episode ends and every statistic
restarts from 0 (a renewal: each false episode costs one average run length).

**The threshold.** ``h`` is set so that the expected number of false alarm episodes per
sample is the budget's ``lambda = rate / f_s``: with the average run length ``ARL_d(h)``
of one CUSUM of design d without fault, computed by the Markov-chain method of Brook &
Evans (Biometrika 59, 1972) for the exact distribution of (1), the union bound
``sum_d 2 n / ARL_d(h) = lambda`` (:func:`budget_threshold`). The bound counts every
hypothesis as if alone, so the realised rate is at or below the budget.

**Slow reference.** Real MEMS biases wander (0.1–0.3 deg/s over minutes): a CUSUM with a
small design shift would accumulate the wander. Each column's offset is followed by an
exponential average of time constant ``tau`` of its innovations clipped at ``+-gate``,
frozen while an episode is open (so a fault is never absorbed once it is detected, and
before that only ``delay / tau`` of it), and subtracted causally: ``z'_t = z_t - b_{t-1}``.
A step of size delta is absorbed by ``delta (1 - exp(-t / tau))`` until detected, a
drift of rate k leaves a lag ``k tau``: a drift slower than the wander it must follow is
indistinguishable from it.

**Correlated noise.** A CUSUM sums its evidence, so what matters is the variance of sums
(the long-run variance), not of single samples: ``kappa`` = (variance of means of L
consecutive samples) x L / (variance of one), estimated on the calibration window and
pooled over the sensors (:func:`long_run_factor`), divides the evidence's variance
(``z / sqrt(kappa)``); white noise gives ``kappa ~ 1``.

**Reference delay.** Against a step whose evidence has non-centrality ``delta^2`` per
sample, no test with an average run length ``gamma`` between false alarms over K
hypotheses detects faster, asymptotically, than ``2 ln(gamma K) / delta^2`` samples
(Lorden 1971: Page's CUSUM attains it): :func:`lorden_delay_samples`.

The parts: the design and the isolation codes in :mod:`.design`, run lengths and
thresholds in :mod:`.thresholds`, the streaming bank in :mod:`.bank`; every name is
importable from here.
"""

from imufdi_cli.maths.sequential.bank import CusumBank, Decisions, MotionModel
from imufdi_cli.maths.sequential.design import NO_ISOLATION, NOT_ISOLABLE, CusumDesign
from imufdi_cli.maths.sequential.thresholds import (
    OUTLIER_LEVEL,
    average_run_length,
    budget_threshold,
    effective_shifts,
    false_alarm_rate,
    increments,
    long_run_factor,
    lorden_delay_samples,
    lorden_drift_samples,
    outlier_share,
    outlier_size,
    step_information,
)

__all__ = [
    "NOT_ISOLABLE",
    "NO_ISOLATION",
    "OUTLIER_LEVEL",
    "CusumBank",
    "CusumDesign",
    "Decisions",
    "MotionModel",
    "average_run_length",
    "budget_threshold",
    "effective_shifts",
    "false_alarm_rate",
    "increments",
    "long_run_factor",
    "lorden_delay_samples",
    "lorden_drift_samples",
    "outlier_share",
    "outlier_size",
    "step_information",
]
