"""bank's gyro test in marg mode (the paper's Table 2): calibration of the gyro residuals,
the attitude increments of the intact estimators, residual filtering, the decision,
isolation and amplitude of every gyro.
"""

from __future__ import annotations

import math

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.attitude import (
    body_rate_from_quaternions,
    make_continuous,
)
from imufdi_cli.detectors.bank.marg import (
    FULL_ESTIMATOR,
    GYRO_BLIND_STD_RATIO,
    GYRO_MAX_GAP_S,
    _MargSolution,
)
from imufdi_cli.detectors.bank.thresholds import SIGMA_FLOOR, bonferroni_threshold, robust_std
from imufdi_cli.detectors.base import (
    NO_ISOLATION,
    DetectionBlock,
)
from imufdi_cli.detectors.budget import REFERENCE_TAU_S, EvidenceBudget
from imufdi_cli.errors import CalibrationError
from imufdi_cli.log import ImuBlock


class _GyroTest:
    """The gyro test of :class:`~imufdi_cli.detectors.bank.detector.BankDetector` in marg mode."""

    # shared with BankDetector, which sets them (__init__, fit, _reset_stream)
    alpha: float
    tau: float
    _gyro_bias: np.ndarray | None
    _gyro_variance: np.ndarray | None
    _gyro_H: np.ndarray | None
    _t_last: int | None
    _filter_state: np.ndarray | None
    _variance_state: np.ndarray | None
    _episode_counts: np.ndarray
    false_alarms: float
    _gyro_budget: EvidenceBudget | None

    def _fit_gyro(self, calibration: ImuBlock, array: ArrayConfig, q_full: np.ndarray) -> None:
        """Gyro residual bias and white-noise variance (Table 2 residuals)."""
        assert calibration.gyro is not None
        n = len(calibration)
        if n < 12:
            raise CalibrationError(f"bank: calibration window has {n} samples; need >= 12")
        H_gyro = array.measurement_matrix("gyro")
        dt = np.diff(calibration.t_ns).astype(float) * 1e-9
        if np.any(dt <= 0):
            raise CalibrationError("bank: calibration timestamps are not increasing")
        self._sample_period = float(np.median(dt))
        self._filter_pole = math.exp(-self._sample_period / self.tau)
        q = make_continuous(q_full)
        rate = body_rate_from_quaternions(q[:-1], q[1:], dt) @ H_gyro.T  # (n-1, n_g)
        gyro = array.select(calibration.gyro, "gyro")
        gyro_mid = 0.5 * (gyro[1:] + gyro[:-1])
        raw = gyro_mid - rate
        # Bias: Hann-weighted mean of the raw residual. The finite-difference rate noise
        # telescopes (sum w_k (n_k - n_{k-1}) = -sum n_k (w_{k+1} - w_k), tiny for a smooth
        # window), so the estimate's error is mainly the gyro noise, sigma_g^2 sum w_k^2;
        # that variance is added to the residual's (the bias is not known exactly).
        taper = np.hanning(raw.shape[0] + 2)[1:-1]
        taper /= taper.sum()
        self._gyro_bias = taper @ raw
        self._bias_weight_energy = float(taper @ taper)
        if "gyro" in array.noise:
            self._gyro_variance = np.full(H_gyro.shape[0], array.noise["gyro"] ** 2)
        else:
            # white noise: Var(D^2 g) = 6 sigma_g^2; smooth motion cancels to O(Te^2)
            self._gyro_variance = robust_std(np.diff(gyro, n=2, axis=0)) ** 2 / 6.0
        if not np.all(np.isfinite(self._gyro_variance)) or np.any(self._gyro_variance <= 0):
            raise CalibrationError(
                "bank: gyro noise from the calibration window is not positive (constant data?);"
                " give noise.gyro in the array config or choose another --calibrate window"
            )
        self._gyro_threshold = bonferroni_threshold(self.alpha, H_gyro.shape[0])
        self._gyro_H = H_gyro
        self._gyro_budget = None
        if self.false_alarms > 0:
            # under a budget the evidence is the filtered residual over the gyro's white
            # noise sigma: the attitude's finite-difference noise telescopes in its sums, so
            # its long-run variance is sigma_g^2 (the filter keeps sums) and the long-run
            # factor is 1 by construction (a window of 2 s is too short to measure it for a
            # filter of time constant tau)
            self._gyro_budget = EvidenceBudget(
                1.0 / np.sqrt(self._gyro_variance),
                np.ones(H_gyro.shape[0], dtype=bool),
                array.rate_hz,
                self.false_alarms,
                REFERENCE_TAU_S,
                calibration_samples=n,
            )
            self._gyro_budget.fit(np.zeros((0, H_gyro.shape[0])), long_run=1.0)

    def _gyro_candidates(
        self, solution: _MargSolution, noise: np.ndarray, alarm: np.ndarray, best: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which estimators' attitudes the gyro test may use: ``clean`` (N, 7), the
        ``candidates`` (N, 7) it chooses among, and where it ``abstain``s (N,).

        An estimator is clean at a sample when it converged, observes the attitude and
        does not use the component isolated there. During an accel/mag alarm, every
        component isolated since the alarm began is a candidate for the faulty one (the
        isolation hesitates at an onset while the faulty component's blind estimator drops
        in and out of observability). Only the series of the estimator blind to the faulty
        component is fault-free; a gyro fault shows in every series. The gyro test takes,
        per sample, the clean candidate series with the smallest largest z^2
        (``_gyro_decision``), and abstains where any candidate is not clean (its series
        could be the only fault-free one).
        """
        well_conditioned = np.ones_like(solution.usable)
        well_conditioned[:, :6] = solution.blind_std <= GYRO_BLIND_STD_RATIO * noise
        clean = solution.usable & well_conditioned & ~alarm[:, None]
        seen = self._episode_components(alarm, best)  # (N, 6)
        usable = (solution.usable & well_conditioned)[:, :6]
        candidates = np.zeros_like(clean)
        candidates[:, :6] = seen & usable
        candidates[:, FULL_ESTIMATOR] = ~alarm
        clean[:, :6] |= candidates[:, :6]
        abstain = ~candidates.any(axis=1) | np.any(seen & ~usable, axis=1)
        return clean, candidates, abstain

    def _episode_components(self, alarm: np.ndarray, best: np.ndarray) -> np.ndarray:
        """Accel/mag components isolated at least once since the current alarm began,
        (N, 6) bool (all False where no alarm). State carries over blocks."""
        n = alarm.shape[0]
        if n == 0:
            return np.zeros((0, 6), dtype=bool)
        onehot = np.zeros((n, 6))
        onehot[np.flatnonzero(alarm), best[alarm]] = 1.0
        previous = np.concatenate([[self._episode_counts.sum() > 0], alarm[:-1]])
        starts = alarm & ~previous
        segment = np.cumsum(starts)  # 0: the episode carried over from the last block
        cumulative = np.cumsum(onehot, axis=0)
        start_rows = np.flatnonzero(starts)
        base = np.empty((start_rows.size + 1, 6))
        base[0] = -self._episode_counts
        base[1:] = np.where((start_rows > 0)[:, None], cumulative[np.maximum(start_rows - 1, 0)], 0)
        counts = cumulative - base[segment]
        self._episode_counts = counts[-1].copy() if alarm[-1] else np.zeros(6)
        return (counts > 0) & alarm[:, None]  # type: ignore[no-any-return]

    def _gyro_test(
        self,
        block: ImuBlock,
        array: ArrayConfig,
        q: np.ndarray,
        clean: np.ndarray,
        candidates: np.ndarray,
        covariance: np.ndarray,
        abstain: np.ndarray,
    ) -> tuple[DetectionBlock, np.ndarray, np.ndarray]:
        """Table 2 residuals: filtered ``gyro - H_g w(attitude of a fault-free estimator)``.

        One filtered residual series per estimator (7 x n_g channels), each built from its
        own attitude only, so that choosing another estimator never inserts a jump; an
        interval where the estimator is not clean at both ends contributes 0. The output
        takes, per sample, the candidate series with the smallest largest z^2. Steps:
        :meth:`_gyro_integral_of` (gyro integral), :meth:`_raw_gyro_residuals` (per series,
        against its attitude change), :meth:`_filtered_gyro_residuals` (first-order filter
        and noise model), :meth:`_gyro_decision` (series choice, alarm, isolation).

        Parameters
        ----------
        q : ndarray, shape (7, N, 4)
            Sign-continuous attitudes of the estimators.
        clean : ndarray, shape (N, 7), bool
        candidates : ndarray, shape (N, 7), bool
            Series the output may take per sample (the full one without an accel/mag
            alarm); the one with the smallest largest z^2 is taken.
        covariance : ndarray, shape (7, N, 3, 3)
        abstain : ndarray, shape (N,), bool
            Samples without a clean candidate: no gyro decision (statistic 0; the
            residual shown is the full estimator's).

        Returns
        -------
        detection : DetectionBlock
        isolated_set : ndarray, shape (N, n_g), bool
        residual : ndarray, shape (N, n_g)
            The chosen series' filtered residual, rad/s.
        """
        assert block.gyro is not None and self._gyro_H is not None
        gyro = array.select(block.gyro, "gyro")
        dt, integral, t_s = self._gyro_integral_of(block, gyro, q.shape[0])
        raw, valid = self._raw_gyro_residuals(q, clean, integral, t_s)
        self._gyro_integral = integral[-1].copy()
        filtered, variances = self._filtered_gyro_residuals(raw, valid, covariance, dt)
        self._gyro_last = gyro[-1].copy()
        self._t_last = int(block.t_ns[-1])
        return self._gyro_decision(filtered, variances, candidates, abstain)

    def _gyro_integral_of(
        self, block: ImuBlock, gyro: np.ndarray, n_est: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample intervals dt (N,) s, the running trapezoid integral (N, n_g) of the
        bias-corrected gyro, rad, and sample times (N,) s from the stream's origin; starts
        the stream state on the first block."""
        assert self._gyro_bias is not None
        if self._gyro_last is None or self._t_last is None:
            self._t_origin = int(block.t_ns[0])
            self._gyro_integral = np.zeros(gyro.shape[1])
            self._clean_integral = np.zeros((n_est, gyro.shape[1]))
            self._clean_q = np.tile([1.0, 0.0, 0.0, 0.0], (n_est, 1))
            self._clean_t = np.full(n_est, np.nan)
            gyro_prev = np.concatenate([gyro[:1], gyro[:-1]])
            t_prev = np.concatenate([block.t_ns[:1], block.t_ns[:-1]])
            integral_start = np.zeros(gyro.shape[1])
        else:
            gyro_prev = np.concatenate([self._gyro_last[None], gyro[:-1]])
            t_prev = np.concatenate([[self._t_last], block.t_ns[:-1]])
            integral_start = self._gyro_integral
        dt = (block.t_ns - t_prev).astype(float) * 1e-9
        dt = np.where(dt > 0, dt, 0.0)
        integral = integral_start + np.cumsum(
            (0.5 * (gyro + gyro_prev) - self._gyro_bias) * dt[:, None], axis=0
        )
        t_s = (block.t_ns - self._t_origin).astype(float) * 1e-9
        return dt, integral, t_s

    def _raw_gyro_residuals(
        self, q: np.ndarray, clean: np.ndarray, integral: np.ndarray, t_s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Unfiltered residual of every series (7, N, n_g), rad/s, and where it is valid
        (7, N); remembers each series' last clean sample for the next block.

        Each series compares the gyro integral with the attitude change since its last
        clean sample L (L = k - 1 normally): x_k = (int_L^k g - H w (t_k - t_L)) / Te with
        w the least-squares rate of q_dot = 1/2 Xi(q) w between q_L and q_k. Unclean
        samples give x = 0 and the next clean one takes the whole gap, so the filtered sum
        still telescopes (no spike when estimators drop out).
        """
        assert self._gyro_H is not None
        n_est, n_samples = q.shape[0], q.shape[1]
        index = np.arange(n_samples)
        marker = np.where(clean.T, index[None, :], -1)  # (7, N)
        last_clean = np.concatenate(
            [np.full((n_est, 1), -1), np.maximum.accumulate(marker, axis=1)[:, :-1]], axis=1
        )
        from_block = last_clean >= 0
        safe = np.maximum(last_clean, 0)
        est = np.arange(n_est)[:, None]
        q_from = np.where(from_block[..., None], q[est, safe], self._clean_q[:, None])
        integral_from = np.where(
            from_block[..., None], integral[safe], self._clean_integral[:, None]
        )
        t_from = np.where(from_block, t_s[safe], self._clean_t[:, None])
        span = t_s[None, :] - t_from  # (7, N), inf/nan where there is no clean sample yet
        # A series idle for longer than GYRO_MAX_GAP_S restarts instead of taking the gap:
        # its attitude change over a long gap is not a constant-rate rotation (an a_y step
        # made the long-unobservable a_y-blind estimator clean again after seconds, and its
        # first sample raised gyro alarms on healthy gyros for 0.5 s).
        valid = clean.T & np.isfinite(span) & (span > 0) & (span <= GYRO_MAX_GAP_S)
        span = np.where(valid, span, self._sample_period)
        q_from = np.where(valid[..., None], q_from, q)
        rate = body_rate_from_quaternions(q_from, q, span)  # (7, N, 3)
        raw = (
            integral[None] - integral_from - (rate @ self._gyro_H.T) * span[..., None]
        ) / self._sample_period
        raw[~valid] = 0.0
        has_clean = np.asarray(clean.any(axis=0), dtype=bool)
        last_index = n_samples - 1 - np.argmax(clean[::-1], axis=0)
        self._clean_q = np.where(has_clean[:, None], q[np.arange(n_est), last_index], self._clean_q)
        self._clean_integral = np.where(
            has_clean[:, None], integral[last_index], self._clean_integral
        )
        self._clean_t = np.where(has_clean, t_s[last_index], self._clean_t)
        return raw, valid

    def _filtered_gyro_residuals(
        self, raw: np.ndarray, valid: np.ndarray, covariance: np.ndarray, dt: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """First-order filtered residuals (7, N, n_g), rad/s, and their variances, (rad/s)^2.

        Noise of the filtered residual ``y = (1-a) sum_i a^i x_{k-i}``: the trapezoid gyro
        average of white noise sigma_g gives ``sigma_g^2 (1-a)/2``; the finite-difference
        rate ``(n_k - n_{k-1}) / Te`` of white attitude noise n (covariance P from the
        estimator, ``s^2 = h^T P h / Te^2``, smoothed by the same filter) gives
        ``2 s^2 (1-a)^2 / (1+a)``; the calibrated bias adds ``sigma_g^2 sum w^2``.
        """
        assert self._gyro_H is not None and self._gyro_variance is not None
        H = self._gyro_H
        dt = np.where(dt > 0, dt, self._sample_period)
        rate_variance = np.einsum("gi,enij,gj->eng", H, covariance, H) / dt[None, :, None] ** 2
        rate_variance[~valid] = 0.0
        raw = np.nan_to_num(raw)
        a = self._filter_pole
        if self._filter_state is None or self._variance_state is None:
            self._filter_state = np.zeros((raw.shape[0], 1, raw.shape[2]))
            self._variance_state = np.zeros((raw.shape[0], 1, raw.shape[2]))
        from scipy.signal import lfilter  # imported when the gyro test runs, not on import

        filtered, self._filter_state = lfilter(
            [1.0 - a], [1.0, -a], raw, axis=1, zi=self._filter_state
        )
        smoothed_rate_variance, self._variance_state = lfilter(
            [1.0 - a], [1.0, -a], rate_variance, axis=1, zi=self._variance_state
        )
        variances = self._gyro_variance * (
            (1 - a) / 2 + self._bias_weight_energy
        ) + 2 * smoothed_rate_variance * (1 - a) ** 2 / (1 + a)  # (7, N, n_g)
        return filtered, variances

    def _gyro_decision(
        self,
        filtered: np.ndarray,
        variances: np.ndarray,
        candidates: np.ndarray,
        abstain: np.ndarray,
    ) -> tuple[DetectionBlock, np.ndarray, np.ndarray]:
        """Per sample, the candidate series with the smallest largest z^2; alarm when its
        largest z^2 exceeds the threshold; every gyro above it is isolated and gets its
        filtered residual as amplitude (several simultaneous gyro faults)."""
        n_samples = filtered.shape[1]
        rows = np.arange(n_samples)
        z2_all = filtered**2 / np.maximum(variances, SIGMA_FLOOR**2)
        peak = np.where(candidates.T, z2_all.max(axis=2), np.inf)  # (7, N)
        chosen = np.where(abstain, FULL_ESTIMATOR, np.argmin(peak, axis=0))
        self._gyro_chosen = chosen
        residual = filtered[chosen, rows]  # (N, n_g)
        z2 = z2_all[chosen, rows]
        z2[abstain] = 0.0
        if self._gyro_budget is not None:
            assert self._gyro_variance is not None
            evidence = residual / np.sqrt(self._gyro_variance)
            evidence[abstain] = np.nan
            decided = self._gyro_budget.decide(evidence)
            # a gyro fault shows in its own residual only (Table 2): every gyro whose own
            # CUSUM is over the threshold during an episode is isolated
            isolated_set = decided.alarm[:, None] & (decided.scores > decided.threshold[:, None])
            on = np.flatnonzero(decided.isolated >= 0)
            isolated_set[on, decided.isolated[on]] = True
            decided.isolated_set = isolated_set
            decided.amplitudes = np.where(isolated_set, residual, np.nan)
            return decided, isolated_set, residual
        statistic = z2.max(axis=1)
        alarm = statistic > self._gyro_threshold
        best = np.argmax(z2, axis=1)
        isolated = np.where(alarm, best, NO_ISOLATION).astype(np.int32)
        amplitude = np.where(alarm, residual[rows, best], np.nan)
        isolated_set = z2 > self._gyro_threshold
        detection = DetectionBlock(
            statistic=statistic,
            threshold=np.full(n_samples, self._gyro_threshold),
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=z2,
            amplitudes=np.where(isolated_set, residual, np.nan),
        )
        return detection, isolated_set, residual
