"""woa-mvmd-glt under a false-alarm budget, and the check of its level in motion
(docs/algorithms/woa-mvmd-glt.md, "Under a false-alarm budget" and "In motion").

**Evidence.** Each row's GLT on u_best gives, per sensor, the signed standardized
isolation statistic ``z_i = sign(p^T v_i) sqrt(D_FI,i)`` (eq. 6 with its sign: the
whitened parity residual of sensor i over its own standard deviation, with the u_best
domain's sigma ``sigma_i ||F[t]|| sqrt(1 + L_eff / N_cal)``): N(0, 1) without fault,
shifted by a step on sensor i. A bank of CUSUM tests (:mod:`imufdi_cli.maths.sequential`)
decides on it, with the threshold of the budget. A row is decided when its window ends
(``lookahead_samples``): the bank runs on the rows in order, so its decisions carry the
same look-ahead and the pipeline counts it in the delays.

**Long-run variance.** u_best is a low-pass filter (effective length 5-25 samples) and the
rows of consecutive windows overlap: the evidence is strongly correlated, and what a
CUSUM accumulates is its long-run variance. It is computed from the filters themselves,
not estimated on 2 s of rows (a handful of independent values): for white input, the
rows a window decides sum to ``c_w . x`` with ``c_w = sum_t F_w[t] / s_w[t]`` (over its
decided rows t, ``s_w`` their row scales), and the long-run variance per row is
``(c_w . sum_k shift(c_w, k hop)) / rows`` (every window overlapping it, as if its
neighbours had its filter), averaged over the calibration windows (:func:`long_run`).

**Motion leak.** Scale-factor and misalignment errors leak the motion into the parity
vector (``s h_i^T x`` on sensor i); u_best passes the motion (it is low-pass) and
averages the noise down, so a leak of a fraction of a sigma in the raw signal is several
sigmas of the u_best domain: on conical6 the per-sample test alarmed on 88 % of the
fault-free samples (80 alpha). Under a budget the bank's motion model
(:class:`~imufdi_cli.maths.sequential.MotionModel`) learns it, on the u_best of the
weighted least-squares body-frame estimate (the same filter) in the evidence's own row
scale. The per-sample test does not model it: :class:`LeakMonitor` measures, over the
processed rows, the share of the evidence's variance the motion explains, and the detector
says so when it is large
(``calibration_warnings``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from imufdi_cli.detectors.base import DetectionBlock

if TYPE_CHECKING:
    from imufdi_cli.detectors.budget import EvidenceBudget

#: Share of the evidence's variance explained by the motion above which the per-sample
#: test warns that it does not hold its level in motion (a leak of this share raises the
#: mean GLT statistic by as much; at 5 % the 1 % level is already about 2 alpha for 45
#: degrees of freedom).
LEAK_WARNING_SHARE = 0.05
#: Rows of processed evidence below which the share is not judged.
LEAK_MIN_ROWS = 1000


def long_run(filters: np.ndarray, row_scale: np.ndarray, first_row: int, hop: int) -> float:
    """Long-run variance factor (>= 1) of rows decided by windows one ``hop`` apart.

    Parameters
    ----------
    filters : ndarray, shape (W, R, L)
        Rows ``first_row .. L - 1`` of each window's u_best filter (the rows it decides
        are its last ``hop``).
    row_scale : ndarray, shape (W, R)
        The rows' noise scales (the evidence is ``F[t] x / row_scale[t]``).
    first_row : int
        Window row of ``filters[:, 0]``.
    hop : int
    """
    n_windows, n_rows, length = filters.shape
    decided = filters[:, n_rows - hop :] / row_scale[:, n_rows - hop :, None]  # (W, hop, L)
    weights = decided.sum(axis=1)  # (W, L): c_w
    per_row = float(np.mean(np.einsum("wtl,wtl->wt", decided, decided)))  # ~1
    reach = length // hop
    total = 0.0
    for w in range(n_windows):
        c = weights[w]
        overlap = float(c @ c)
        for k in range(1, reach + 1):
            shift = k * hop
            if shift < length:
                overlap += 2.0 * float(c[shift:] @ c[: length - shift])
        total += overlap
    factor = total / n_windows / hop / max(per_row, 1e-300)
    return max(1.0, factor)


class LeakMonitor:
    """Accumulates, over processed rows, the regression of the evidence (N, n) on the
    motion regressors (N, 3) with an intercept, for the per-sample test's motion check."""

    def __init__(self, n: int) -> None:
        self.gram = np.zeros((4, 4))  # [1, x]
        self.cross = np.zeros((4, n))
        self.energy = np.zeros(n)
        self.rows = 0
        self.alarms = 0

    def add(self, evidence: np.ndarray, regressors: np.ndarray, alarm: np.ndarray) -> None:
        finite = np.all(np.isfinite(evidence), axis=1) & np.all(np.isfinite(regressors), axis=1)
        z = evidence[finite]
        x = np.concatenate([np.ones((z.shape[0], 1)), regressors[finite]], axis=1)
        self.gram += x.T @ x
        self.cross += x.T @ z
        self.energy += np.sum(z**2, axis=0)
        self.rows += int(z.shape[0])
        self.alarms += int(np.count_nonzero(alarm[finite]))

    def explained_share(self) -> float:
        """Share of the evidence's variance about its mean that the least-squares leak
        explains (0 with no motion): a constant offset (the calibration's bias error) is
        not motion."""
        if self.rows < 2:
            return 0.0
        mean = self.cross[0] / self.rows
        variance = float(np.sum(self.energy - self.rows * mean**2))
        # centred Gram and cross products of the regressors
        centre = self.gram[0, 1:] / self.rows
        gram = self.gram[1:, 1:] - self.rows * np.outer(centre, centre)
        cross = self.cross[1:] - np.outer(centre, self.cross[0])
        scale = np.trace(gram) / 3.0
        if not (variance > 0 and scale > 0):
            return 0.0
        coefficients = np.linalg.solve(gram + 1e-9 * scale * np.eye(3), cross)
        return max(0.0, float(np.sum(coefficients * cross)) / variance)


def decide_rows(
    budget: EvidenceBudget, n: int, parts: list[dict[str, np.ndarray] | int]
) -> DetectionBlock:
    """The stream's rows (``parts``: dicts of window rows, or counts of rows no window
    decides, which carry no evidence) decided by the budget's bank: evidence standardized
    at rest, the rows' states and motion factors; amplitude: eq. 7 of the row on the
    isolated sensor."""
    evidence, states, factors, amplitudes = [], [], [], []
    for part in parts:
        if isinstance(part, int):  # (states: 0 is the calibration's centre)
            evidence.append(np.full((part, n), np.nan))
            states.append(np.zeros((part, 3)))
            factors.append(np.ones(part))
            amplitudes.append(np.full((part, n), np.nan))
        else:
            evidence.append(part["evidence"])
            states.append(part["regressors"])
            factors.append(part["factor"])
            amplitudes.append(part["amplitude"])
    if not evidence:
        return DetectionBlock.empty(0, n)
    decided = budget.decide(
        np.concatenate(evidence), np.concatenate(states), np.concatenate(factors)
    )
    amplitude = np.concatenate(amplitudes)
    rows = np.flatnonzero(decided.isolated >= 0)
    decided.amplitude = np.full(len(decided), np.nan)
    decided.amplitude[rows] = amplitude[rows, decided.isolated[rows]]
    return decided


def motion_warning(
    detector: str, sensor_type: str, monitor: LeakMonitor | None, alpha: float
) -> str | None:
    """The per-sample test's one-line warning when its evidence followed the motion on
    the processed rows (None: not, too few rows, or no monitor: under a budget)."""
    if monitor is None or monitor.rows < LEAK_MIN_ROWS:
        return None
    share = monitor.explained_share()
    if share <= LEAK_WARNING_SHARE:
        return None
    return (
        f"{detector}: {sensor_type}: the parity residual follows the motion ({share:.0%}"
        " of its variance in the u_best domain: scale-factor or misalignment errors),"
        " which the per-sample test does not model: it alarmed on"
        f" {monitor.alarms / monitor.rows:.1%} of the samples at alpha={alpha:g}; decide"
        " under a budget (--false-alarms 1/h learns the leak) or use glt or pca-parity"
    )
