"""noise-glr's sequential test under a false-alarm budget (:class:`NoiseBudget`).

With ``false_alarms`` > 0 noise-glr (and cnn-map's input test) decide on each leave-one-out
residual's variance by the bank of :mod:`imufdi_cli.maths.variance`: the residuals are
bounded at 4 sigma from their running level (:class:`~imufdi_cli.maths.contrasts.Winsorizer`),
cut into independent Helmert contrasts in blocks of 4 samples
(:class:`~imufdi_cli.maths.contrasts.HelmertContrasts`), standardized by their calibrated
variance (Huber's proposal 2, times the healthy spread) and, in motion, by the jitter
model's ``sqrt(1 + A_t)``, and fed to a variance-growth CUSUM bank whose threshold holds
half the budget (docs/algorithms/noise-glr.md, "Under a false-alarm budget").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.maths.contrasts import HelmertContrasts, ModelCheck, Winsorizer
from imufdi_cli.maths.quantiles import norm
from imufdi_cli.maths.robust import clipped_square_moments, equivalent_dof, robust_scale
from imufdi_cli.maths.sequential import outlier_share
from imufdi_cli.maths.variance import (
    VarianceCusumBank,
    VarianceDesign,
    lorden_variance_terms,
    threshold_schedule,
    variance_run_length,
)

#: Helmert block of the budgeted test, samples: a bias step inside a block leaves at most
#: two large terms, and 3/4 of the samples' variance information is kept.
BUDGET_BLOCK = 4
#: The budgeted test's threshold is set for this share of the budget: the union bound is
#: 0.7-0.9 of the realised rate on white noise, and a margin covers what the model knows
#: only approximately (as the parity detectors' :data:`~imufdi_cli.detectors.budget.BUDGET_SHARE`).
BUDGET_SHARE = 0.5
#: Design of the budgeted test: variance ratios 3 and 9 (noise x1.7 and x3), clip 4 sigma.
BUDGET_DESIGN = VarianceDesign()
#: Each residual sample is bounded at this many sigma from its running level before the
#: contrasts (:class:`~imufdi_cli.maths.contrasts.Winsorizer`): an outlier or a bias step
#: then adds about one term at the clip, as the threshold's outlier model assumes.
BUDGET_WINSOR = 4.0
#: Time constant of that running level, seconds.
BUDGET_LEVEL_TAU_S = 0.1
#: Under a budget detect warns when, over seconds of the log, the median sensor's residual
#: variance exceeded the calibrated one by this factor (motion or errors the residual model
#: does not remove: the level is not held there) ...
VARIANCE_WARNING = 2.0
#: ... on at least this share of the log's seconds (and 2 of them).
WARNING_SHARE = 0.005
#: Residuals whose correlation exceeds this in magnitude cannot be told apart.
PARALLEL = 1.0 - 1e-9


def independent_scale_dof(count: int, clip: float) -> float:
    """Equivalent degrees of freedom of :func:`robust_scale` on ``count`` independent
    N(0, tau) terms clipped at ``clip`` sigma: ``nu_N (s / mu)^2`` with ``nu_N`` of
    :func:`equivalent_dof` (no lag correlation) and s the clipped square's derivative
    (:func:`scale_estimator_dof` for differences)."""
    moments = clipped_square_moments(clip, 0.0)
    mean = moments[0]
    inner = mean - clip**2 * 2.0 * norm.sf(clip) if np.isfinite(clip) else 1.0
    dof = float(equivalent_dof(np.array([max(count, 1)]), (mean, moments[1], 0.0))[0])
    return dof * (inner / mean) ** 2


def residual_isolable(operator: np.ndarray, testable: np.ndarray) -> np.ndarray:
    """Whether each leave-one-out residual can be told from every other (equal sensor
    noise): False where two residuals are perfectly correlated (e.g. 4 sensors with one
    parity direction)."""
    covariance = operator @ operator.T
    sd = np.sqrt(np.maximum(np.diag(covariance), 1e-300))
    correlation = covariance / sd[:, None] / sd[None, :]
    np.fill_diagonal(correlation, 0.0)
    parallel = (np.abs(correlation) > PARALLEL) & testable[None, :]
    return testable & ~parallel.any(axis=1)


class NoiseBudget:
    """Budgeted sequential decisions on a noise growth of one sensor type's leave-one-out
    residuals (the variance CUSUM bank of :mod:`imufdi_cli.maths.variance`).

    Each residual stream is cut into Helmert contrasts in blocks of :data:`BUDGET_BLOCK`
    samples (independent N(0, tau_j) terms, blind to the residual's mean), standardized by
    their calibrated variance tau_j (Huber's proposal 2 at the design clip, times the
    healthy spread kappa_eff_j when the array carries one).

    Parameters
    ----------
    operator : ndarray, shape (n, n)
        The leave-one-out operator R.
    testable : ndarray, shape (n,), bool
    rate_hz : float
    budget_per_s : float
        False alarm episodes per second of fault-free data allowed on this channel.
    spread : ndarray, shape (n,), optional
        kappa_eff of the residuals (None: 1).
    design : VarianceDesign
    """

    def __init__(
        self,
        operator: np.ndarray,
        testable: np.ndarray,
        rate_hz: float,
        budget_per_s: float,
        spread: np.ndarray | None = None,
        design: VarianceDesign = BUDGET_DESIGN,
    ) -> None:
        if not rate_hz > 0:
            raise DetectorConfigError("a false-alarm budget needs the array's sample rate")
        self.design = design
        self.rate_hz = float(rate_hz)
        self.budget_per_s = float(budget_per_s)
        self.terms_per_s = self.rate_hz * (BUDGET_BLOCK - 1) / BUDGET_BLOCK
        self.per_term = BUDGET_SHARE * self.budget_per_s / self.terms_per_s
        if not 0.0 < self.per_term < 0.5:
            raise DetectorConfigError(
                f"noise-glr: false-alarm budget {budget_per_s * 3600:g}/h is not below 3/4 of"
                f" the sample rate ({rate_hz:g} Hz); give a rate such as 1/h"
            )
        self.testable = np.asarray(testable, bool)
        self.isolable = residual_isolable(operator, self.testable)
        # share of residual j's variance that sensor j's own noise makes (equal noise):
        # a growth of sensor j's variance by K grows its residual's by 1 + (K - 1) w_j
        weights = np.asarray(operator, float) ** 2
        totals = weights.sum(axis=1)
        self.own_share = np.where(
            totals > 0, np.diag(weights) / np.where(totals > 0, totals, 1.0), 0.0
        )
        self.spread = spread
        n = self.testable.size
        self.scale = np.ones(n)
        self.calibration_terms = 0
        self.calibration_dof = 0.0
        self.contamination = 0.0
        self.threshold = math.nan
        self.schedule = (np.zeros(1), np.full(1, math.nan))
        self.bank: VarianceCusumBank | None = None
        self.contrasts = HelmertContrasts(n, BUDGET_BLOCK)
        self.level = np.zeros(n)
        self.bounded = self._winsorizer(self.level)
        # the calibrated noise, checked second by second on the data
        self.check = ModelCheck(int(self.testable.sum()), round(self.rate_hz), VARIANCE_WARNING)

    def _winsorizer(self, level: np.ndarray) -> Winsorizer:
        return Winsorizer(
            np.sqrt(self.scale), BUDGET_WINSOR, BUDGET_LEVEL_TAU_S * self.rate_hz, level
        )

    def fit(self, residuals: np.ndarray) -> None:
        """Calibrate the contrasts' variances on the calibration window's residuals (N, n)
        and set the threshold; start the bank."""
        clip = self.design.clip
        mean = clipped_square_moments(clip, 0.0)[0]
        n = residuals.shape[1]

        def scale_of(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            terms = HelmertContrasts(n, BUDGET_BLOCK).push(values)
            terms = terms[~np.isnan(terms[:, 0])]
            scale = robust_scale(terms, clip, mean)
            if self.spread is not None:
                scale = scale * self.spread
            return np.where(self.testable & (scale > 0), scale, 1.0), terms

        self.scale, _ = scale_of(residuals)  # the raw residuals' contrasts: sigma
        self.level = residuals.mean(axis=0)
        bounded = self._winsorizer(self.level)
        self.scale, terms = scale_of(bounded.push(residuals))
        z = terms[:, self.testable] / np.sqrt(self.scale[self.testable])
        # outliers: samples far from their level beyond what a Gaussian puts there, each
        # one term at the clip, or terms beyond the outlier level, whichever is more
        per_term = bounded.outlier_share(self.testable) * BUDGET_BLOCK / (BUDGET_BLOCK - 1)
        self.contamination = max(outlier_share(z), per_term)
        self.calibration_terms = int(terms.shape[0])
        self.calibration_dof = independent_scale_dof(self.calibration_terms, clip)
        self.schedule = threshold_schedule(
            self.design,
            int(self.testable.sum()),
            self.per_term,
            self.calibration_dof,
            self.contamination,
        )
        self.threshold = float(self.schedule[1][-1])  # once the variance is learnt
        # with a healthy spread the scale is the top of the range: never learnt lower
        floor = None if self.spread is None else np.where(self.spread > 1.0, 1.0, 0.25)
        self.bank = VarianceCusumBank(
            self.design,
            self.schedule,
            self.isolable,
            self.rate_hz,
            calibration_terms=self.calibration_dof,
            floor=floor,
        )
        self.bounded = self._winsorizer(self.level)
        self.contrasts = HelmertContrasts(n, BUDGET_BLOCK)
        self.check = ModelCheck(int(self.testable.sum()), round(self.rate_hz), VARIANCE_WARNING)

    def process(self, residuals: np.ndarray, factors: np.ndarray | None = None) -> DetectionBlock:
        """Decisions on leave-one-out residuals (N, n), SI; ``factors`` (N,): the motion
        variance factors ``1 + A_t`` of the jitter model (None: 1)."""
        if self.bank is None:
            raise CalibrationError("noise-glr: call fit() before process()")
        z = self.contrasts.push(self.bounded.push(residuals)) / np.sqrt(self.scale)
        if factors is not None:
            z /= np.sqrt(factors)[:, None]
        z[:, ~self.testable] = np.nan
        self.check.push(np.square(z[:, self.testable]))
        decisions = self.bank.process(z)
        amplitude = decisions.amplitude
        if self.spread is not None:  # back to the calibration window's variance
            picked = np.where(decisions.isolated >= 0, decisions.isolated, 0)
            amplitude = amplitude * np.sqrt(self.spread[picked])
        scores = decisions.scores
        scores[:, ~self.testable] = np.nan
        return DetectionBlock(
            statistic=decisions.statistic,
            threshold=decisions.threshold,
            alarm=decisions.alarm,
            isolated=decisions.isolated,
            amplitude=amplitude,
            scores=scores,
        )

    def lorden_delay_s(self, sensor: int, factor: float) -> float:
        """Seconds an optimal test needs, asymptotically, to detect sensor ``sensor``'s
        noise standard deviation growing by ``factor`` (its residual's variance by
        ``1 + (factor^2 - 1) w``) at this budget (Lorden 1971,
        :func:`~imufdi_cli.maths.variance.lorden_variance_terms`)."""
        ratio = 1.0 + (factor**2 - 1.0) * float(self.own_share[sensor])
        hypotheses = int(self.testable.sum()) * len(self.design.ratios)
        gamma = self.terms_per_s / max(self.budget_per_s, 1e-300)
        return lorden_variance_terms(ratio, gamma, hypotheses) / self.terms_per_s

    def metadata(self) -> dict[str, Any]:
        """The budget, the threshold and what sets it (JSON-ready)."""
        bank = self.bank
        run_lengths = [
            variance_run_length(ratio, self.design.clip, self.threshold) / self.terms_per_s
            for ratio in self.design.ratios
        ]
        hypotheses = int(self.testable.sum()) * len(self.design.ratios)
        return {
            "false_alarms_per_hour": self.budget_per_s * 3600.0,
            "threshold": self.threshold,
            "design_variance_ratios": list(self.design.ratios),
            "clip": self.design.clip,
            "helmert_block": BUDGET_BLOCK,
            "terms_per_s": self.terms_per_s,
            "calibration_terms": self.calibration_terms,
            "calibration_dof": self.calibration_dof,
            "outlier_share": self.contamination,
            "scale_tau_s": self.design.scale_tau_s,
            # the threshold while the tracked variance learns: h from that many terms on
            "threshold_schedule": {
                "terms": self.schedule[0].tolist(),
                "threshold": self.schedule[1].tolist(),
            },
            "hypotheses": hypotheses,
            "run_length_s": run_lengths,
            "isolable": self.isolable.tolist(),
            # the optimal test's delay of a x3 noise growth on each sensor
            "lorden_delay_x3_s": [
                self.lorden_delay_s(j, 3.0) if self.testable[j] else None
                for j in range(self.testable.size)
            ],
            "own_variance_share": self.own_share.tolist(),
            "episodes": 0 if bank is None else bank.episodes,
            "tracked_variance": [] if bank is None else bank.variance.tolist(),
            "seconds_beyond_the_noise_model": self.check.flagged,
            "seconds_checked": self.check.windows,
        }


def budget_warning(detector: str, sensor_type: str, budget: NoiseBudget) -> str | None:
    """One line when, over a share of the processed log's seconds, most leave-one-out
    residuals were clearly more variable than calibrated (:data:`VARIANCE_WARNING`,
    :data:`WARNING_SHARE`), else None."""
    check = budget.check
    if check.flagged < max(2, WARNING_SHARE * check.windows):
        return None
    return (
        f"{detector}: {sensor_type}: on {check.flagged} s of this log"
        f" ({100 * check.share():.2g} %) most leave-one-out residuals were more than"
        f" {VARIANCE_WARNING:g}x as variable as calibrated (up to {check.worst:.3g}x): motion"
        " or sensor errors the residual model does not remove (e.g. scale factors and"
        " sampling jitter in motion); the false-alarm budget does not hold there"
    )
