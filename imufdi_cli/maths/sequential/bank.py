"""The streaming bank of robust CUSUM tests (:mod:`imufdi_cli.maths.sequential`): the
decisions, the slow bias reference, the motion model and :class:`CusumBank`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from imufdi_cli.maths.sequential.design import NO_ISOLATION, NOT_ISOLABLE, CusumDesign
from imufdi_cli.maths.sequential.thresholds import increments


@dataclass
class Decisions:
    """Rows of one sensor type's sequential test (N samples, n sensors).

    Attributes
    ----------
    statistic : ndarray (N,)
        Largest CUSUM statistic of the bank (log-likelihood ratio units).
    threshold : ndarray (N,)
        h.
    alarm : ndarray (N,) bool
    isolated : ndarray (N,) int32
        Sensor of the largest statistic on alarm rows; NOT_ISOLABLE where that sensor
        cannot be told from another; NO_ISOLATION elsewhere.
    amplitude : ndarray (N,)
        On alarm rows, the isolated sensor's mean evidence since the episode's estimated
        onset, in SI units (``/ g_i``); NaN elsewhere.
    scores : ndarray (N, n)
        Per sensor, its largest statistic over signs and design shifts.
    """

    statistic: np.ndarray
    threshold: np.ndarray
    alarm: np.ndarray
    isolated: np.ndarray
    amplitude: np.ndarray
    scores: np.ndarray


@dataclass
class _Episode:
    shift: int  # design index of the hypothesis that raised it
    sign: float
    sensor: int
    recovery: float = 0.0  # the "fault has ended" CUSUM
    onset: int = 0  # estimated onset, absolute sample index
    sums: np.ndarray = field(default_factory=lambda: np.zeros(0))  # z' summed from onset
    count: int = 0


class _Reference:
    """The slow reference of every column of evidence: an offset ``b`` and, with
    regressors x (the tested state: rate, specific force), a linear model ``D`` of the
    evidence on the state's deviation from its running mean ``x_bar`` (which moves with
    the offset's gains, from the calibration window's mean)::

        z'_t = (z_t - b - D^T (x_t - x_bar)) / sqrt(1 + k (x_t - x_bar)^T Sigma (x_t - x_bar))

    ``D`` is the ridge (Gaussian prior ``N(0, prior_sd^2 I)``) regression of ``z - b`` on
    ``x - x_bar`` over the calibration window and the samples since, forgotten with time
    constant ``slope_tau``; ``Sigma`` its posterior covariance per unit noise variance,
    and k (``inflation``) widens the test by ``sqrt(k)`` standard deviations of what the
    model does not know yet. Both move once per sub-block of ``stride`` samples (aligned
    on the sample count), from that sub-block's sums, and stay frozen while an episode is
    open."""

    def __init__(
        self,
        n: int,
        step: float,
        stride: int,
        gate: float,
        calibration_samples: float,
        motion: MotionModel | None = None,
        scale_step: float = 0.0,
    ) -> None:
        self.n, self.step, self.stride, self.gate = n, step, stride, gate
        self.calibration_samples = calibration_samples
        self.scale_step = scale_step
        self.offset = np.zeros(n)
        self.variance = np.ones(n)
        self.pending = np.zeros(n)
        self.pending_squares = np.zeros(n)
        self.count = 0
        self.motion = motion
        p = 0 if motion is None else motion.centre.size
        # the state's own running mean (the same gains as the offset): the slopes are
        # regressed on the state's deviation from it, so that a mean of the state the
        # offset has absorbed is not taken for a slope
        self.state_mean = np.zeros(p) if motion is None else motion.centre.copy()
        self.pending_x = np.zeros(p)
        self.pending_xx = np.zeros((p, p))
        self.pending_xz = np.zeros((p, n))

    @property
    def active(self) -> bool:
        return self.step > 0.0 or self.scale_step > 0.0 or self.motion is not None

    def snapshot(self) -> tuple[np.ndarray, ...]:
        motion = self.motion
        if motion is None:
            return (self.offset.copy(), self.variance.copy())
        return (
            self.offset.copy(),
            self.variance.copy(),
            self.state_mean.copy(),
            motion.sxx.copy(),
            motion.sxz.copy(),
        )

    def restore(self, snap: tuple[np.ndarray, ...]) -> None:
        """Back to a snapshot; the open sub-block's sums are dropped."""
        self.offset, self.variance = snap[0].copy(), snap[1].copy()
        if self.motion is not None:
            self.state_mean = snap[2].copy()
            self.motion.sxx, self.motion.sxz = snap[3].copy(), snap[4].copy()
            self.motion.solve()
        self._drop()

    def _drop(self) -> None:
        self.pending = np.zeros(self.n)
        self.pending_squares = np.zeros(self.n)
        self.count = 0
        self.pending_x = np.zeros_like(self.pending_x)
        self.pending_xx = np.zeros_like(self.pending_xx)
        self.pending_xz = np.zeros_like(self.pending_xz)

    def apply(
        self, z: np.ndarray, x: np.ndarray | None, frozen: bool, samples: int
    ) -> tuple[np.ndarray, list[tuple[int, tuple[np.ndarray, ...]]]]:
        """``z'`` for the rows of ``z`` (the rows after ``samples`` of the stream), moving
        the reference at every completed sub-block unless ``frozen``; also, for a rewind,
        the local rows from which each state held, with a snapshot of it."""
        motion = self.motion
        n_rows = z.shape[0]
        out = np.empty_like(z)
        marks = [(0, self.snapshot())]
        row = 0
        while row < n_rows:
            phase = (samples + row) % self.stride
            stop = min(n_rows, row + self.stride - phase)
            rows = slice(row, stop)
            np.subtract(z[rows], self.offset, out=out[rows])
            centred = None
            if motion is not None and x is not None:
                centred = x[rows] - self.state_mean
                if not frozen:  # the regression sees the offset-free evidence
                    self.pending_x += x[rows].sum(axis=0)
                    self.pending_xx += centred.T @ centred
                    self.pending_xz += centred.T @ out[rows]
                out[rows] -= centred @ motion.slopes
            if not frozen:
                self.pending += out[rows].sum(axis=0)
                self.count += stop - row
            if centred is not None and motion is not None:
                spread = np.einsum("ij,jk,ik->i", centred, motion.covariance, centred)
                out[rows] /= np.sqrt(1.0 + motion.inflation * spread)[:, None]
            if not frozen and self.scale_step > 0.0:
                self.pending_squares += np.minimum(np.square(out[rows]), 16.0 * self.variance).sum(
                    axis=0
                )
            if self.scale_step > 0.0:
                out[rows] /= np.sqrt(self.variance)
            if not frozen and (samples + stop) % self.stride == 0:  # sub-block complete
                self._complete(samples + stop)
                marks.append((stop, self.snapshot()))
            row = stop
        return out, marks

    def _complete(self, position: int) -> None:
        start = 1.0 / (self.calibration_samples + position)  # a running mean at first
        if self.step > 0.0 and self.count:
            gain = max(self.step, start)
            limit = self.gate * np.sqrt(self.count * self.variance)
            self.offset = self.offset + gain * np.clip(self.pending, -limit, limit)
        if self.scale_step > 0.0 and self.count:
            gain = max(self.scale_step, start)
            self.variance = self.variance + gain * (
                self.pending_squares - self.count * self.variance
            )
            np.maximum(self.variance, 0.25, out=self.variance)
        if self.motion is not None and self.count:
            gain = max(self.step, start) if self.step > 0.0 else start
            self.state_mean = self.state_mean + gain * (
                self.pending_x - self.count * self.state_mean
            )
            self.motion.update(self.pending_xx, self.pending_xz, self.count)
        self._drop()


@dataclass
class MotionModel:
    """The linear model of the evidence on the tested state (see :class:`_Reference`).

    Attributes
    ----------
    centre : ndarray (p,)
        The state's calibration mean.
    prior_sd : float
        Prior standard deviation of every slope (z units per unit of the state).
    forget : float
        Per-sample forgetting rate of the sufficient statistics (1 / (slope_tau f_s)).
    inflation : float
        k: squared standard deviations of the model's uncertainty added to the variance.
    sxx, sxz : ndarray (p, p), (p, n)
        Sufficient statistics (calibration window first).
    """

    centre: np.ndarray
    prior_sd: float
    forget: float
    inflation: float
    sxx: np.ndarray
    sxz: np.ndarray
    slopes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def __post_init__(self) -> None:
        self.solve()

    @classmethod
    def from_calibration(
        cls,
        x: np.ndarray,
        z: np.ndarray,
        prior_sd: float,
        slope_tau_samples: float,
        inflation: float = 16.0,
    ) -> MotionModel:
        """The model fitted on calibration states ``x`` (N, p) and evidence ``z`` (N, n)."""
        centre = x.mean(axis=0)
        centred = x - centre
        return cls(
            centre=centre,
            prior_sd=float(prior_sd),
            forget=0.0 if slope_tau_samples <= 0 else 1.0 / slope_tau_samples,
            inflation=float(inflation),
            sxx=centred.T @ centred,
            sxz=centred.T @ (z - z.mean(axis=0)),
        )

    def solve(self) -> None:
        p = self.centre.size
        precision = self.sxx + np.eye(p) / self.prior_sd**2
        self.covariance = np.linalg.inv(precision)
        self.slopes = self.covariance @ self.sxz

    def update(self, xx: np.ndarray, xz: np.ndarray, samples: int) -> None:
        keep = math.exp(-self.forget * samples)
        self.sxx = keep * self.sxx + xx
        self.sxz = keep * self.sxz + xz
        self.solve()


class CusumBank:
    """Streaming bank of robust CUSUM tests over one sensor type (module docstring).

    The outputs do not depend on how the rows are split into calls (the reference moves on
    sub-blocks aligned on the sample count), up to the rounding of the cumulative sums.

    Parameters
    ----------
    design : CusumDesign
    threshold : float
        h (:func:`~imufdi_cli.maths.sequential.thresholds.budget_threshold`).
    sensitivity : ndarray, shape (n,)
        ``g_i``: z units per SI unit of a step on sensor i (before the long-run factor).
    isolable : ndarray, shape (n,), bool
        Whether sensor i's fault can be told from every other sensor's.
    rate_hz : float
        Nominal sample rate (for the reference's time constant).
    kappa : float
        Long-run variance factor (:func:`~imufdi_cli.maths.sequential.thresholds.long_run_factor`).
    history : int
        Samples of evidence kept to estimate an episode's onset.
    calibration_samples : float
        Samples the biases were estimated from: the reference starts as the running mean
        of the evidence from there (gain ``1 / (N + k)`` after k samples) until that gain
        falls to ``1 / (tau f_s)``, so that the bias estimate's own error (``1 / sqrt(N)``
        of a standard deviation, which a CUSUM of small design shift would accumulate) is
        learnt away in the first seconds.
    motion : MotionModel, optional
        The linear model of the evidence on the tested state (residual scale and
        misalignment errors): ``process`` then takes the state's rows too.
    """

    #: Rows run through the bank at once (an alarm wastes at most this much work).
    SPAN = 2048

    def __init__(
        self,
        design: CusumDesign,
        threshold: float,
        sensitivity: np.ndarray,
        isolable: np.ndarray,
        rate_hz: float,
        kappa: float = 1.0,
        history: int = 512,
        calibration_samples: float = math.inf,
        motion: MotionModel | None = None,
    ) -> None:
        self.design = design
        self.calibration_samples = float(calibration_samples)
        self.threshold = float(threshold)
        self.kappa = float(kappa)
        self.inverse_scale = 1.0 / math.sqrt(self.kappa)
        self.sensitivity = np.asarray(sensitivity, float) * self.inverse_scale
        self.isolable = np.asarray(isolable, bool)
        n = self.sensitivity.size
        self.n = n
        self.shifts = np.asarray(design.shifts, float)
        self.state = np.zeros((self.shifts.size, 2, n))  # S per shift, sign, sensor
        self.step = 0.0 if design.tau_s <= 0 else 1.0 / (design.tau_s * rate_hz)
        #: rows over which the reference stays constant (1 s, at most tau / 10)
        self.stride = max(1, round(rate_hz))
        if design.tau_s > 0:
            self.stride = max(1, min(self.stride, round(design.tau_s * rate_hz / 10)))
        self.ref = _Reference(
            n,
            self.step,
            self.stride,
            design.gate,
            self.calibration_samples,
            motion,
            0.0 if design.scale_tau_s <= 0 else 1.0 / (design.scale_tau_s * rate_hz),
        )
        self.history = np.zeros((0, n))
        self.history_length = int(history)
        self.samples = 0  # rows handled so far
        self.episode: _Episode | None = None
        self.episodes = 0

    @property
    def reference(self) -> np.ndarray:
        """Each column's tracked offset (z units after the long-run factor)."""
        return self.ref.offset

    def _referenced(
        self, z: np.ndarray, x: np.ndarray | None, frozen: bool
    ) -> tuple[np.ndarray, list[tuple[int, tuple[np.ndarray, ...]]]]:
        """``z'`` for the next rows of the stream (:class:`_Reference`)."""
        if not self.ref.active:
            return z, [(0, self.ref.snapshot())]
        return self.ref.apply(z, x, frozen, self.samples)

    def _rewind(self, marks: list[tuple[int, tuple[np.ndarray, ...]]], row: int) -> None:
        """The reference as it was on local row ``row`` (an episode opens there: from then
        on it is frozen, and the sums of the open sub-block are dropped)."""
        value = marks[0][1]
        for start, snap in marks:
            if start <= row:
                value = snap
        self.ref.restore(value)

    # --- processing --------------------------------------------------------------------

    def process(self, z: np.ndarray, x: np.ndarray | None = None) -> Decisions:
        """Decide on the rows of ``z`` (N, n): standardized signed evidence per sensor;
        ``x`` (N, p): the tested state of each row, for the motion model (if any).

        NaN evidence (a sample without a test) counts as 0."""
        z = np.asarray(z, float)
        if z.ndim != 2 or z.shape[1] != self.n:
            raise ValueError(f"evidence must be (N, {self.n}), got {z.shape}")
        if self.inverse_scale != 1.0:
            z = z * self.inverse_scale
        if not np.isfinite(z).all():
            z = np.nan_to_num(z, nan=0.0, posinf=0.0, neginf=0.0)
        n_rows = z.shape[0]
        out = Decisions(
            statistic=np.zeros(n_rows),
            threshold=np.full(n_rows, self.threshold),
            alarm=np.zeros(n_rows, bool),
            isolated=np.full(n_rows, NO_ISOLATION, np.int32),
            amplitude=np.full(n_rows, np.nan),
            scores=np.empty((n_rows, self.n)),  # every row is written
        )
        position = 0
        while position < n_rows:
            rows = z[position : position + self.SPAN]
            states = None if x is None else x[position : position + self.SPAN]
            if self.episode is None:
                position += self._watch(rows, states, position, out)
            else:
                position += self._follow(rows, states, position, out)
        return out

    def _cusums(
        self, zr: np.ndarray, best: np.ndarray | None = None
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """Every CUSUM (1)-(2) of the bank over the rows ``zr`` (M, n), from the current
        state: the statistics per (shift, sign), shift-major (list of (M, n)), and per
        sensor their maximum (M, n; written into ``best`` when given).

        With the one clip of (1), every hypothesis' cumulative log-likelihood ratio is a
        combination of one cumulative sum, ``C_t = s mu Z_t - t mu^2 / 2`` with
        ``Z_t = sum_{j<=t} clip(z'_j)``, and the walk reflected at 0 from ``S_0`` is
        ``S_t = C_t - min_{j<=t} C'_j`` where ``C'`` is C with its first value lowered to
        ``min(C_1, -S_0)``.
        """
        clip = self.design.clip
        total = np.clip(zr, -clip, clip)
        np.cumsum(total, axis=0, out=total)
        steps = np.arange(1, zr.shape[0] + 1, dtype=float)[:, None]
        stats: list[np.ndarray] = []
        if best is None:
            best = np.empty_like(zr)
        for d, mu in enumerate(self.shifts):
            drift = steps * (0.5 * mu * mu)
            for s, sign in enumerate((1.0, -1.0)):
                cumulative = np.multiply(total, sign * mu)
                cumulative -= drift
                first = cumulative[0].copy()
                np.minimum(first, -self.state[d, s], out=cumulative[0])  # seed the minimum
                statistic = np.minimum.accumulate(cumulative, axis=0)
                cumulative[0] = first
                np.subtract(cumulative, statistic, out=statistic)
                if stats:
                    np.maximum(best, statistic, out=best)
                else:
                    best[...] = statistic
                stats.append(statistic)
        return stats, best

    def _keep_state(self, stats: list[np.ndarray], row: int) -> None:
        flat = self.state.reshape(-1, self.n)
        for k, statistic in enumerate(stats):
            flat[k] = statistic[row]

    def _watch(self, z: np.ndarray, x: np.ndarray | None, position: int, out: Decisions) -> int:
        """No episode open: run the bank over the rows ``z`` (output rows from
        ``position``) up to the first alarm; returns the number of rows handled."""
        zr, marks = self._referenced(z, x, frozen=False)
        # the rows' scores are written in place; those after an alarm are written again
        stats, best = self._cusums(zr, out.scores[position : position + len(zr)])
        top = best.max(axis=1) if self.n else np.zeros(len(zr))
        over = np.flatnonzero(top > self.threshold)
        stop = len(zr) if over.size == 0 else int(over[0]) + 1
        rows = slice(position, position + stop)
        out.statistic[rows] = top[:stop]
        self._keep_state(stats, stop - 1)
        if over.size:
            self._rewind(marks, stop - 1)
            self._open(zr, stats, stop - 1, position, out)
        self._remember(zr[:stop])
        self.samples += stop
        return stop

    def _open(
        self, zr: np.ndarray, stats: list[np.ndarray], row: int, position: int, out: Decisions
    ) -> None:
        """An episode opens at local row ``row`` (output row ``position + row``)."""
        values = np.array([s[row] for s in stats])  # (2 D, n)
        k, sensor = np.unravel_index(int(np.argmax(values)), values.shape)
        shift, sign_index = divmod(int(k), 2)
        sign = 1.0 if sign_index == 0 else -1.0
        evidence = (
            np.concatenate([self.history, zr[: row + 1]]) if self.history.size else zr[: row + 1]
        )
        count = self._onset_rows(
            stats[int(k)][: row + 1, sensor], evidence[:, sensor] * sign, shift
        )
        self.episode = _Episode(
            shift=shift,
            sign=sign,
            sensor=int(sensor),
            onset=self.samples + row + 1 - count,
            sums=evidence[-count:].sum(axis=0),
            count=count,
        )
        self.episodes += 1
        self._mark(out, position + row, values.max(axis=0))

    def _onset_rows(self, statistic: np.ndarray, signed: np.ndarray, shift: int) -> int:
        """Samples from the estimated onset of a hypothesis to its alarm row: the rows after
        the last one where its statistic was 0 (Page's change-point estimate). When it was
        positive since the start of these rows, the hypothesis' CUSUM is run again over the
        kept history (``signed``: its evidence times its sign, history included, ending at
        the alarm row) from 0 at the history's start."""
        zeros = np.flatnonzero(statistic <= 0.0)
        if zeros.size:
            return int(statistic.size - 1 - zeros[-1])
        cumulative = np.cumsum(increments(self.shifts[shift], self.design.clip, signed))
        again = cumulative - np.minimum(np.minimum.accumulate(cumulative), 0.0)
        zeros = np.flatnonzero(again <= 0.0)
        return int(signed.size - 1 - zeros[-1]) if zeros.size else int(signed.size)

    def _mark(self, out: Decisions, row: int, per_sensor: np.ndarray) -> None:
        """The alarm row that opens the episode: isolation and amplitude."""
        episode = self.episode
        assert episode is not None
        out.alarm[row] = True
        sensor = int(np.argmax(per_sensor))
        out.isolated[row] = sensor if self.isolable[sensor] else NOT_ISOLABLE
        if self.isolable[sensor] and episode.count and self.sensitivity[sensor] > 0:
            out.amplitude[row] = episode.sums[sensor] / episode.count / self.sensitivity[sensor]

    def _follow(self, z: np.ndarray, x: np.ndarray | None, position: int, out: Decisions) -> int:
        """An episode is open: keep the bank running over the rows ``z`` (reference
        frozen) and test whether the fault has ended; close the episode and restart every
        statistic when it has. Returns the number of rows handled."""
        episode = self.episode
        assert episode is not None
        zr, _ = self._referenced(z, x, frozen=True)
        stats, best = self._cusums(zr, out.scores[position : position + len(zr)])
        # evidence that the fault has ended: the log-likelihood ratio of "no fault" against
        # "the fault as estimated so far" (its mean evidence since the onset, at least the
        # smallest design shift), one design per call, so that a fault between two design
        # shifts is not released while it lasts
        size = episode.sign * episode.sums[episode.sensor] / max(episode.count, 1)
        size = max(float(size), float(self.shifts[0]))
        increment = increments(size, self.design.clip, episode.sign * zr[:, episode.sensor])
        cumulative = np.cumsum(-increment)
        recovery = cumulative - np.minimum(np.minimum.accumulate(cumulative), -episode.recovery)
        ended = np.flatnonzero(recovery > self.threshold)
        stop = len(zr) if ended.size == 0 else int(ended[0]) + 1
        rows = slice(position, position + stop)
        out.statistic[rows] = best[:stop].max(axis=1)
        alarmed = stop if ended.size == 0 else stop - 1  # the row that ends it is quiet
        if alarmed:
            sums = np.cumsum(zr[:alarmed], axis=0)
            sums += episode.sums
            counts = episode.count + np.arange(1, alarmed + 1)
            sensors = np.argmax(best[:alarmed], axis=1)
            isolable = self.isolable[sensors]
            out.alarm[position : position + alarmed] = True
            out.isolated[position : position + alarmed] = np.where(isolable, sensors, NOT_ISOLABLE)
            with np.errstate(divide="ignore", invalid="ignore"):
                amplitude = sums[np.arange(alarmed), sensors] / counts / self.sensitivity[sensors]
            out.amplitude[position : position + alarmed] = np.where(isolable, amplitude, np.nan)
            episode.sums = sums[-1]
            episode.count = int(counts[-1])
        if ended.size:
            self.state[:] = 0.0
            self.episode = None
        else:
            self._keep_state(stats, stop - 1)
            episode.recovery = float(recovery[stop - 1])
        self._remember(zr[:stop])
        self.samples += stop
        return stop

    def _remember(self, zr: np.ndarray) -> None:
        """Keep the last ``history`` rows of referenced evidence (for onsets)."""
        if self.history_length <= 0 or zr.shape[0] == 0:
            return
        joined = np.concatenate([self.history, zr]) if self.history.size else zr
        self.history = joined[-self.history_length :].copy()
