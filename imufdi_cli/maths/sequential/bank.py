"""The streaming bank of robust CUSUM tests (:mod:`imufdi_cli.maths.sequential`).

Per sensor type, the bank takes per sample t and sensor i the evidence ``z_t,i``,
standardized *at rest* (N(0, 1) without fault), the state of the array (rate or specific
force, for the motion model) and the motion variance factor ``v_t >= 1`` of the detector's
noise model (1 at rest). It keeps, per column, a slow reference (offset, slopes on the
state, variance) and per sensor, sign and design shift the CUSUM

    u_t = clip(z'_t / s_t, -c, c) / s_t,          s_t^2 = v_t (1 + k q_t)
    l_t = mu s u_t - mu^2 / (2 s_t^2)                                         (1)
    S_t = max(0, S_{t-1} + l_t)                                               (2)

(z' the evidence less its reference; ``q_t`` the motion model's uncertainty). (1) is the
log-likelihood ratio of a step of ``mu`` rest standard deviations when the noise standard
deviation is ``s_t``: at rest the designs 2 and 4 run, in motion the larger designs'
effective shift ``mu / s_t`` comes into range. With ``W1 = cumsum(u)`` and
``W2 = cumsum(1 / s^2)`` every hypothesis' cumulative sum is ``s mu W1 - mu^2 W2 / 2``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from imufdi_cli.maths.sequential.design import NO_ISOLATION, NOT_ISOLABLE, CusumDesign
from imufdi_cli.maths.sequential.spatial import MIN_SPATIAL_COLUMNS, spatial_variance
from imufdi_cli.maths.sequential.walk import _Chunk, _Feed, _History, _Running, _Walk


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
        On alarm rows the sensor whose evidence since the onset is largest (the step's
        GLR); NOT_ISOLABLE where that sensor cannot be told from another; NO_ISOLATION
        elsewhere.
    amplitude : ndarray (N,)
        On alarm rows, the isolated sensor's mean evidence since the episode's estimated
        onset (weighted by the inverse noise variance, at the evidence's scale: times the
        sd its variance reference divided by), in SI units; NaN elsewhere.
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
        self._prior_precision = np.eye(self.centre.size) / self.prior_sd**2
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
        precision = self.sxx + self._prior_precision
        self.covariance = np.linalg.inv(precision)
        self.slopes = self.covariance @ self.sxz

    def update(self, xx: np.ndarray, xz: np.ndarray, samples: int) -> None:
        keep = math.exp(-self.forget * samples)
        self.sxx = keep * self.sxx + xx
        self.sxz = keep * self.sxz + xz
        self.solve()


class _Reference:
    """The slow reference of every column of evidence::

        z'_t = (z_t - b - D^T (x_t - x_bar)) / sqrt(w)

    ``b`` an offset, ``w`` a variance (both learnt at rest only: a running mean from the
    calibration window on, then exponential averages of time constants ``tau`` and
    ``scale_tau``; innovations clipped), ``D`` the ridge regression (prior ``N(0,
    prior_sd^2)``) of ``z - b`` on the state's deviation from its running mean
    ``x_bar``, weighted by the inverse motion variance and forgotten with time constant
    ``slope_tau``, whose posterior covariance ``Sigma`` widens the test by
    ``1 + k (x - x_bar)^T Sigma (x - x_bar)``. Everything moves once per sub-block of
    ``stride`` samples (aligned on the sample count) and stays frozen while an episode is
    open, for at most ``hold`` samples of it."""

    def __init__(
        self,
        n: int,
        design: CusumDesign,
        rate_hz: float,
        calibration_samples: float,
        motion: MotionModel | None,
    ) -> None:
        self.n = n
        self.step = 0.0 if design.tau_s <= 0 else 1.0 / (design.tau_s * rate_hz)
        self.scale_step = 0.0 if design.scale_tau_s <= 0 else 1.0 / (design.scale_tau_s * rate_hz)
        self.stride = max(1, round(rate_hz))
        if design.tau_s > 0:
            self.stride = max(1, min(self.stride, round(design.tau_s * rate_hz / 10)))
        self.gate = design.gate
        self.rest_factor = design.rest_factor
        self.calibration_samples = calibration_samples
        self.offset = np.zeros(n)
        self.variance = np.ones(n)
        self.motion = motion
        p = 0 if motion is None else motion.centre.size
        self.state_mean = np.zeros(p) if motion is None else motion.centre.copy()
        self.rest_samples = 0  # rows at rest that taught the references so far
        self._drop()

    def _drop(self) -> None:
        p = self.state_mean.size
        self.pending = np.zeros(self.n)
        self.pending_squares = np.zeros(self.n)
        self.count = 0  # rest rows in the open sub-block
        self.pending_x = np.zeros(p)
        self.motion_count = 0.0  # weighted rows in the open sub-block (slopes)
        self.pending_xx = np.zeros((p, p))
        self.pending_xz = np.zeros((p, self.n))

    def snapshot(self) -> tuple[np.ndarray, ...]:
        items = [self.offset.copy(), self.variance.copy(), np.array([self.rest_samples])]
        if self.motion is not None:
            items += [self.state_mean.copy(), self.motion.sxx.copy(), self.motion.sxz.copy()]
        return tuple(items)

    def restore(self, snap: tuple[np.ndarray, ...]) -> None:
        """Back to a snapshot; the open sub-block's sums are dropped."""
        self.offset, self.variance = snap[0].copy(), snap[1].copy()
        self.rest_samples = int(snap[2][0])
        if self.motion is not None:
            self.state_mean = snap[3].copy()
            self.motion.sxx, self.motion.sxz = snap[4].copy(), snap[5].copy()
            self.motion.solve()
        self._drop()

    def apply(
        self,
        z: np.ndarray,
        x: np.ndarray | None,
        factors: np.ndarray,
        frozen: bool,
        samples: int,
        out: np.ndarray | None = None,
        variance: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, tuple[np.ndarray, ...]]]]:
        """``z'`` and the rows' noise variance factors ``s^2`` for the next rows of the
        stream (after ``samples`` rows), learning at every completed sub-block unless
        ``frozen``; also, for a rewind, the local rows from which each state held, with a
        snapshot of it. ``out`` and ``variance``: arrays to write them into (None: new).

        What does not depend on the references (the rows at rest, the weights and the
        weighted states) is computed once for all the rows, in the same floats as per
        sub-block; rows all at rest with unit factors (no motion term) skip the masks and
        the weights, which change nothing there."""
        motion = self.motion
        n_rows = z.shape[0]
        if out is None:
            out = np.empty_like(z)
        if variance is None:
            variance = factors.copy()
        else:
            variance[...] = factors
        marks = [(0, self.snapshot())]
        learn = not frozen
        rest = factors <= self.rest_factor
        all_rest = bool(rest.all())
        unit = bool((factors == 1.0).all())
        weight = weighted_x = factors  # (replaced where used)
        if motion is not None and x is not None and learn:
            if unit:  # rows laid out as the products by the weights would be
                x = np.ascontiguousarray(x)
            else:
                weight = 1.0 / factors
                weighted_x = weight[:, None] * x
        stride = self.stride
        row = 0
        while row < n_rows:
            stop = min(n_rows, row + stride - (samples + row) % stride)
            rows = slice(row, stop)
            part = np.subtract(z[rows], self.offset, out=out[rows])
            if motion is not None and x is not None:
                centred = x[rows] - self.state_mean
                if learn:
                    if unit:  # weights 1: the weighted sums are the plain ones
                        self.pending_x += x[rows].sum(axis=0)
                        self.motion_count += float(stop - row)
                        weighted = centred
                    else:
                        self.pending_x += weighted_x[rows].sum(axis=0)
                        self.motion_count += float(weight[rows].sum())
                        weighted = centred * weight[rows, None]
                    self.pending_xx += weighted.T @ centred
                    self.pending_xz += weighted.T @ part
                part -= centred @ motion.slopes
                spread = np.einsum("ij,jk,ik->i", centred, motion.covariance, centred)
                variance[rows] *= 1.0 + motion.inflation * spread
            if learn:
                at_rest = part if all_rest else part[rest[rows]]
                self.pending += at_rest.sum(axis=0)
                self.pending_squares += np.minimum(np.square(at_rest), 16.0 * self.variance).sum(
                    axis=0
                )
                self.count += stop - row if all_rest else int(np.count_nonzero(rest[rows]))
            part /= np.sqrt(self.variance)
            if learn and (samples + stop) % stride == 0:  # the sub-block is complete
                self._complete()
                marks.append((stop, self.snapshot()))
            row = stop
        return out, variance, marks

    def _complete(self) -> None:
        if self.count:
            start = 1.0 / (self.calibration_samples + self.rest_samples + self.count)
            if self.step > 0.0:
                gain = max(self.step, start)
                limit = self.gate * np.sqrt(self.count * self.variance)
                clipped = np.minimum(np.maximum(self.pending, -limit), limit)  # np.clip's floats
                self.offset = self.offset + gain * clipped
            if self.scale_step > 0.0:
                gain = max(self.scale_step, start)
                change = self.pending_squares - self.count * self.variance
                self.variance = np.maximum(self.variance + gain * change, 0.25)
            self.rest_samples += self.count
        if self.motion is not None and self.motion_count > 0:
            gain = max(self.step, 1.0 / (self.calibration_samples + self.rest_samples))
            mean = self.pending_x / self.motion_count
            self.state_mean = self.state_mean + min(1.0, gain * self.motion_count) * (
                mean - self.state_mean
            )
            self.motion.update(self.pending_xx, self.pending_xz, self.stride)
        self._drop()


@dataclass
class _Episode:
    shift: float  # the fault's estimated size (rest standard deviations) for its end test
    sign: float
    sensor: int
    onset: int = 0  # estimated onset, absolute sample index
    sums: np.ndarray = field(default_factory=lambda: np.zeros(0))  # sum of z'/s^2 since it
    weight: float = 0.0  # sum of 1/s^2 since the onset
    recovery: float = 0.0  # the "fault has ended" CUSUM
    started: int = 0  # absolute sample index of the alarm


class CusumBank:
    """Streaming bank of robust CUSUM tests over one sensor type (module docstring).

    The outputs do not depend on how the rows are split into calls (the references move
    on sub-blocks aligned on the sample count), up to the rounding of cumulative sums.

    Parameters
    ----------
    design : CusumDesign
    threshold : float
        h (:func:`~imufdi_cli.maths.sequential.budget_threshold`).
    sensitivity : ndarray, shape (n,)
        ``g_i``: z units (at rest) per SI unit of a step on sensor i (before kappa).
    isolable : ndarray, shape (n,), bool
        Whether sensor i's fault can be told from every other sensor's.
    rate_hz : float
        Nominal sample rate (the references' time constants).
    kappa : float
        Long-run variance factor (:func:`~imufdi_cli.maths.sequential.long_run_factor`).
    history : int
        Samples of evidence kept to estimate an episode's onset.
    calibration_samples : float
        Samples the biases were estimated from: the references start as running means of
        the evidence from there (gain ``1 / (N + k)`` after k samples at rest) until that
        gain falls to ``1 / (tau f_s)``: the calibration's own errors (``1 / sqrt(N)`` of
        a standard deviation in the offset, ``sqrt(2 / N)`` in the variance) are learnt
        away in the first seconds.
    motion : MotionModel, optional
        The linear model of the evidence on the tested state (residual scale and
        misalignment errors): ``process`` then takes the state's rows too.
    spatial : bool
        In motion (rows whose ``v_t`` exceeds ``design.rest_factor``), each row's noise
        variance from the row's own evidence (:mod:`.spatial`) instead of ``v_t``.
    """

    #: Longest run of the cumulative sums (a span; see the span walker below).
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
        spatial: bool = False,
    ) -> None:
        self.design = design
        self.threshold = float(threshold)
        self.kappa = float(kappa)
        self.inverse_scale = 1.0 / math.sqrt(self.kappa)
        self.sensitivity = np.asarray(sensitivity, float) * self.inverse_scale
        self.isolable = np.asarray(isolable, bool)
        n = self.sensitivity.size
        self.n = n
        self.shifts = np.asarray(design.shifts, float)
        self.state = np.zeros((self.shifts.size, 2, n))  # S per shift, sign, sensor
        # an infinite hold (latched episodes): frozen until the episode ends
        self.hold = (
            sys.maxsize if math.isinf(design.hold_s) else max(0, round(design.hold_s * rate_hz))
        )
        self.ref = _Reference(n, design, rate_hz, float(calibration_samples), motion)
        # the last `history` rows of u of (1), z' / s^2 and 1 / s^2
        self.history = _History(int(history), n)
        self.samples = 0  # rows handled so far
        self.episode: _Episode | None = None
        self.episodes = 0
        self._event: int | None = None  # the sample of the last alarm or episode end
        self._spatial_columns = self.sensitivity > 0
        columns = int(np.count_nonzero(self._spatial_columns))
        self.spatial = bool(spatial) and columns >= MIN_SPATIAL_COLUMNS

    @property
    def reference(self) -> np.ndarray:
        """Each column's tracked offset (z units at rest, after the long-run factor)."""
        return self.ref.offset

    # --- processing --------------------------------------------------------------------

    def process(
        self, z: np.ndarray, x: np.ndarray | None = None, factors: np.ndarray | None = None
    ) -> Decisions:
        """Decide on the rows of ``z`` (N, n): evidence per sensor standardized at rest;
        ``x`` (N, p): the tested state of each row, for the motion model (if any);
        ``factors`` (N,): the detector's motion variance factors ``v_t >= 1`` (None: 1).

        NaN evidence (a sample without a test) counts as 0."""
        z = np.asarray(z, float)
        if z.ndim != 2 or z.shape[1] != self.n:
            raise ValueError(f"evidence must be (N, {self.n}), got {z.shape}")
        if self.inverse_scale != 1.0:
            z = z * self.inverse_scale
        n_rows = z.shape[0]
        v = np.ones(n_rows) if factors is None else np.maximum(np.asarray(factors, float), 1.0)
        if self.spatial and factors is not None:  # over the sensors with evidence on the row
            v = spatial_variance(
                z, v, self._spatial_columns, self.design.clip, self.design.rest_factor
            )
        if not np.isfinite(z).all():
            z = np.nan_to_num(z, nan=0.0, posinf=0.0, neginf=0.0)
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
            span = slice(position, position + self.SPAN)
            states = None if x is None else x[span]
            if self.episode is None:
                position += self._watch(z[span], states, v[span], position, out)
            else:
                position += self._follow(z[span], states, v[span], position, out)
        return out

    def _frozen(self) -> bool:
        episode = self.episode
        return episode is not None and self.samples - episode.started < self.hold

    def _terms(self, zr: np.ndarray, variance: np.ndarray) -> tuple[np.ndarray, ...]:
        """u of (1), z'/s^2 and 1/s^2 of the rows."""
        scale = np.sqrt(variance)[:, None]
        clip = self.design.clip
        u = np.divide(zr, scale)
        np.clip(u, -clip, clip, out=u)
        u /= scale
        inverse = 1.0 / variance
        return u, zr * inverse[:, None], inverse

    # --- the span walker ------------------------------------------------------------
    #
    # A span (at most SPAN rows from the start of a call, an alarm or an episode's end) is
    # one run of the cumulative sums of (1)-(2). It goes through in sub-chunks with the
    # sums, minima and statistics carried across them (:class:`_Walk`): the same floats as
    # one pass over the span, in working arrays that stay in the CPU's cache, and the span
    # stops at the sub-chunk of its first alarm (or of the episode's end) instead of
    # computing every row and discarding those after it. The references are applied ahead
    # of the sub-chunks in pieces that end on their sub-block boundaries (:class:`_Feed`),
    # which gives them the same sums. A design runs on a sub-chunk when some row's
    # effective shift is in range or its statistic is not 0 (out of range on every row,
    # from 0, it stays 0).

    #: Rows of a span's first sub-chunk, doubling up to SUB_ROWS: after an alarm the next
    #: may be near, and rows past it are work thrown away.
    FIRST_ROWS = 8
    SUB_ROWS = 512

    def _chunks(self, n_rows: int) -> Iterator[tuple[int, int]]:
        """(lo, hi) sub-chunks of the next ``n_rows`` rows."""
        size, lo = self.FIRST_ROWS, 0
        while lo < n_rows:
            hi = min(n_rows, lo + size)
            yield lo, hi
            lo = hi
            size = min(2 * size, self.SUB_ROWS)

    def _groups(
        self, walk: _Walk, feed: _Feed, n_rows: int
    ) -> Iterator[tuple[int, int, list[bool] | None]]:
        """The sub-chunks of the next ``n_rows`` rows, those that would run the same
        designs taken together (at most SUB_ROWS rows) when the last alarm or episode end
        is at least SUB_ROWS rows back (the short sub-chunks after one are kept: the next
        may be near): (lo, hi, the designs run, or None for one sub-chunk, which decides
        them itself). Consecutive sub-chunks run the same designs when every design is in
        range on all of them, or out of range on all of them from a statistic of 0 (it
        stays 0): the walk carries the sums across sub-chunks, so one pass over their rows
        gives the same floats. Lazy: each group is decided from the walk's state after the
        previous one."""
        bounds = list(self._chunks(n_rows))
        event = self._event
        if event is not None and self.samples - event < self.SUB_ROWS:
            for lo, hi in bounds:
                yield lo, hi, None
            return
        clip, least = self.design.clip, self.design.min_shift
        low_edge, high_edge = self.shifts / (2.0 * clip), self.shifts / least
        index = 0
        while index < len(bounds):
            lo = bounds[index][0]
            last = index
            while last + 1 < len(bounds) and bounds[last + 1][1] - lo <= self.SUB_ROWS:
                last += 1
            if last == index:
                yield lo, bounds[index][1], None
                index += 1
                continue
            _, variance = feed.rows(lo, bounds[last][1])
            starts = [b[0] - lo for b in bounds[index : last + 1]]
            largest = np.sqrt(np.maximum.reduceat(variance, starts))
            smallest = np.sqrt(np.minimum.reduceat(variance, starts))
            # as _cusums decides per sub-chunk: some row's effective shift in range
            in_range = (largest[:, None] > low_edge) & (smallest[:, None] <= high_edge)
            first = in_range[0]
            held = walk.state.reshape(self.shifts.size, -1).any(axis=1)
            if (held & ~first).any():  # a design out of range runs on from its statistic
                yield lo, bounds[index][1], None
                index += 1
                continue
            same = 1
            while same < in_range.shape[0] and (in_range[same] == first).all():
                same += 1
            yield lo, bounds[index + same - 1][1], [bool(on) for on in first]
            index += same

    def _cusums(
        self,
        walk: _Walk,
        u: np.ndarray,
        inverse: np.ndarray,
        variance: np.ndarray,
        best: np.ndarray,
        ran: list[bool] | None = None,
    ) -> list[bool]:
        """Every running CUSUM (1)-(2) over the next rows of a span, from the walk's
        state, and per sensor their maximum (written into ``best``; 0 where no design
        runs). Advances ``walk`` to the last row; returns which designs ran (``ran``:
        decided by the caller)."""
        w1 = walk.carried_sum(u)
        w2 = walk.carried_drift(inverse)
        if ran is None:
            largest = float(np.sqrt(variance.max()))
            smallest = float(np.sqrt(variance.min()))
            clip, least = self.design.clip, self.design.min_shift
            # run where some row's effective shift mu / s is in [min_shift, 2 c)
            ran = [
                (largest > mu / (2.0 * clip) and smallest <= mu / least)
                or bool(walk.state[2 * d : 2 * d + 2].any())
                for d, mu in enumerate(self.shifts)
            ]
        # fmin skips NaN checks: the same floats as minimum on these sums, since a NaN in
        # the evidence stays in them (every statistic after it is NaN either way)
        finite = bool(np.isfinite(walk.state).all())
        accumulate = np.fmin.accumulate if finite else np.minimum.accumulate
        best[...] = 0.0
        cumulative, low = np.empty_like(w1), np.empty_like(w1)
        drift = w2[:, None]
        for d, mu in enumerate(self.shifts):
            if not ran[d]:
                walk.rest(2 * d)
                walk.rest(2 * d + 1)
                continue
            half = drift * (0.5 * mu * mu)
            for s, sign in enumerate((1.0, -1.0)):
                k = 2 * d + s
                np.multiply(w1, sign * mu, out=cumulative)
                cumulative -= half
                first = cumulative[0].copy()
                np.minimum(first, walk.minimum(k, sign * mu, 0.5 * mu * mu), out=cumulative[0])
                accumulate(cumulative, axis=0, out=low)
                cumulative[0] = first
                minimum = low[-1].copy()
                np.subtract(cumulative, low, out=low)
                np.maximum(best, low, out=best)
                walk.keep(k, low[-1], minimum)
        walk.advance(w1[-1], float(w2[-1]), u.shape[0])
        return ran

    def _column(self, origin: np.ndarray, chunks: list[_Chunk], k: int, sensor: int) -> np.ndarray:
        """The statistic of hypothesis ``k`` on ``sensor`` over the span's rows so far
        (``chunks``) from the span's ``origin`` state, as :meth:`_cusums` computed it."""
        walk = _Walk.start(origin[:, :, sensor : sensor + 1])
        d, s = divmod(k, 2)
        mu = float(self.shifts[d])
        factor, half = (1.0 if s == 0 else -1.0) * mu, 0.5 * mu * mu
        pieces = []
        for chunk in chunks:
            w1 = walk.carried_sum(chunk.u[:, sensor : sensor + 1])
            w2 = walk.carried_drift(chunk.inverse)
            if chunk.ran[d]:
                cumulative = np.multiply(w1, factor)
                cumulative -= w2[:, None] * half
                first = cumulative[0].copy()
                np.minimum(first, walk.minimum(k, factor, half), out=cumulative[0])
                low = np.minimum.accumulate(cumulative, axis=0)
                cumulative[0] = first
                statistic = cumulative - low
                walk.keep(k, statistic[-1], low[-1])
            else:
                statistic = np.zeros_like(w1)
                walk.rest(k)
            walk.advance(w1[-1], float(w2[-1]), w1.shape[0])
            pieces.append(statistic[:, 0])
        return np.concatenate(pieces)

    def _watch(
        self, z: np.ndarray, x: np.ndarray | None, factors: np.ndarray, position: int,
        out: Decisions,
    ) -> int:  # fmt: skip
        """No episode open: run the bank over the rows up to the first alarm; returns the
        number of rows handled."""
        origin = self.state.copy()  # the span's starting state
        walk = _Walk.start(origin)
        feed = _Feed(self.ref, z, x, factors, self.samples, frozen=False)
        chunks: list[_Chunk] = []
        for lo, hi, decided in self._groups(walk, feed, z.shape[0]):
            zr, variance = feed.rows(lo, hi)
            u, q, inverse = self._terms(zr, variance)
            # the rows' scores are written in place; those after an alarm are written again
            best = out.scores[position + lo : position + hi]
            before = walk.copy()
            ran = self._cusums(walk, u, inverse, variance, best, decided)
            top = best.max(axis=1) if self.n else np.zeros(hi - lo)
            over = np.flatnonzero(top > self.threshold)
            if over.size == 0:
                out.statistic[position + lo : position + hi] = top
                chunks.append(_Chunk(u, q, inverse, ran))
                continue
            row = int(over[0])  # the alarm, on local row `row` of this sub-chunk
            out.statistic[position + lo : position + lo + row + 1] = top[: row + 1]
            # every hypothesis on the alarm row: the sub-chunk again up to it
            walk = before
            cut = slice(0, row + 1)
            scratch = np.empty((row + 1, self.n))
            self._cusums(walk, u[cut], inverse[cut], variance[cut], scratch, ran)
            self.state[...] = walk.state.reshape(self.state.shape)
            feed.rewind(lo + row)
            chunks.append(_Chunk(u[cut], q[cut], inverse[cut], ran))
            self._open(origin, chunks, lo + row, position + lo + row, out)
            self._remember(chunks)
            self.samples += lo + row + 1
            return lo + row + 1
        self.state[...] = walk.state.reshape(self.state.shape)
        self._remember(chunks)
        self.samples += z.shape[0]
        return z.shape[0]

    def _open(
        self, origin: np.ndarray, chunks: list[_Chunk], row: int, row_out: int, out: Decisions
    ) -> None:
        """An episode opens at the span's row ``row`` (output row ``row_out``; ``chunks``:
        the span's rows up to it, from the ``origin`` state)."""
        values = self.state.reshape(-1, self.n)  # (hypotheses, n) on the alarm row
        k, sensor = np.unravel_index(int(np.argmax(values)), values.shape)
        shift, sign_index = divmod(int(k), 2)
        sign = 1.0 if sign_index == 0 else -1.0
        column = self._column(origin, chunks, int(k), int(sensor))
        span_w = [c.inverse for c in chunks]
        zeros = np.flatnonzero(column <= 0.0)
        if zeros.size:  # the onset inside the span (Page's estimate: after its last 0)
            count = int(column.size - 1 - zeros[-1])
            hist_w = np.concatenate(span_w)
        else:  # the hypothesis run again over the kept history too
            history = self.history
            hist_w = np.concatenate([history.last_inverse(), *span_w])
            hist_u = np.concatenate(
                [history.last_column(int(sensor)), *(c.u[:, sensor] for c in chunks)]
            )
            count = self._onset_rows(column, hist_u * sign, hist_w, float(self.shifts[shift]))
        span_rows = column.size
        tail = self.history.last_q(max(0, count - span_rows))
        sums = np.concatenate([tail, *(c.q for c in chunks)])[-count:].sum(axis=0)
        weight = float(hist_w[-count:].sum())
        # isolation by the unclipped evidence since the onset (the step's GLR): the clip
        # saturates a large fault's evidence on every sensor correlated with it, so the
        # CUSUMs of two such sensors tie
        chosen = int(np.argmax(np.abs(sums)))
        size = abs(float(sums[chosen])) / weight if weight > 0 else float(self.shifts[0])
        self.episode = _Episode(
            shift=max(size, float(self.shifts[0]) / 2.0),
            sign=1.0 if sums[chosen] >= 0 else -1.0,
            sensor=chosen,
            onset=self.samples + row + 1 - count,
            sums=sums,
            weight=weight,
            started=self.samples + row,
        )
        self.episodes += 1
        self._event = self.samples + row
        out.alarm[row_out] = True
        out.isolated[row_out] = chosen if self.isolable[chosen] else NOT_ISOLABLE
        if self.isolable[chosen] and weight > 0 and self.sensitivity[chosen] > 0:
            # z' is over the column's tracked sd: back to the evidence's scale, then SI
            scale = math.sqrt(self.ref.variance[chosen])
            out.amplitude[row_out] = sums[chosen] / weight * scale / self.sensitivity[chosen]

    def _onset_rows(
        self, statistic: np.ndarray, signed_u: np.ndarray, inverse: np.ndarray, mu: float
    ) -> int:
        """Samples from the estimated onset of a hypothesis to its alarm row: the rows after
        the last one where its statistic was 0 (Page's change-point estimate). When it was
        positive since the start of these rows, the hypothesis' CUSUM is run again over the
        kept history (``signed_u``: its u times its sign, history included, ending at the
        alarm row; ``inverse`` the matching 1/s^2) from 0 at the history's start."""
        zeros = np.flatnonzero(statistic <= 0.0)
        if zeros.size:
            return int(statistic.size - 1 - zeros[-1])
        cumulative = np.cumsum(mu * signed_u - 0.5 * mu * mu * inverse)
        again = cumulative - np.minimum(np.minimum.accumulate(cumulative), 0.0)
        zeros = np.flatnonzero(again <= 0.0)
        return int(signed_u.size - 1 - zeros[-1]) if zeros.size else int(signed_u.size)

    def _follow(
        self, z: np.ndarray, x: np.ndarray | None, factors: np.ndarray, position: int,
        out: Decisions,
    ) -> int:  # fmt: skip
        """An episode is open: keep the bank running over the rows (references frozen for
        the first ``hold_s`` of it) and test whether the fault has ended; close the episode
        and restart every statistic when it has. Returns the number of rows handled."""
        episode = self.episode
        assert episode is not None
        frozen = self._frozen()
        if frozen:  # at most up to the end of the hold
            z = z[: max(1, episode.started + self.hold - self.samples)]
            factors = factors[: z.shape[0]]
            x = None if x is None else x[: z.shape[0]]
        walk = _Walk.start(self.state)
        # the references learn up to the sub-block boundaries the sub-chunks reach; at the
        # episode's end they go back to the open sub-block's start (as at an alarm), so
        # that no row is learnt twice and the rows' partition into calls changes nothing
        feed = _Feed(self.ref, z, x, factors, self.samples, frozen=frozen)
        chunks: list[_Chunk] = []
        # evidence that the fault has ended: the log-likelihood ratio of "no fault" against
        # "the fault as estimated" (its size since the onset), on its sensor and sign; its
        # cumulative sum and running minimum (from -recovery) carried across sub-chunks,
        # as are the evidence's sums since the span's start. The size at most c s_t on each
        # row: beyond 2 c s_t the clipped increment of a fault that lasts,
        # mu c / s - mu^2 / (2 s^2), is negative, and a fault larger than the clip would be
        # released at once and raised again, sample after sample
        recovered = _Running(np.zeros(1), -episode.recovery)
        evidence = _Running(np.zeros(self.n), 0.0)
        weight = _Running(np.zeros(1), 0.0)
        sums_before, weight_before = episode.sums, episode.weight
        last_sums: np.ndarray | None = None
        last_weight = 0.0
        for lo, hi, decided in self._groups(walk, feed, z.shape[0]):
            zr, variance = feed.rows(lo, hi)
            u, q, inverse = self._terms(zr, variance)
            best = out.scores[position + lo : position + hi]
            ran = self._cusums(walk, u, inverse, variance, best, decided)
            mu = np.minimum(episode.shift, self.design.clip / np.sqrt(inverse))
            column = episode.sign * u[:, episode.sensor]
            increments = -(mu * column - 0.5 * mu * mu * inverse)
            cumulative = recovered.sum(increments[:, None])[:, 0]
            recovery = cumulative - recovered.minimum(cumulative)
            ended = np.flatnonzero(recovery > self.threshold)
            stop = hi - lo if ended.size == 0 else int(ended[0]) + 1
            out.statistic[position + lo : position + lo + stop] = best[:stop].max(axis=1)
            alarmed = stop if ended.size == 0 else stop - 1  # the row that ends it is quiet
            if alarmed:
                sums = evidence.sum(q[:alarmed])
                sums += sums_before
                weights = weight_before + weight.sum(inverse[:alarmed, None])[:, 0]
                sensors = np.argmax(np.abs(sums), axis=1)  # the step's GLR, as at the opening
                isolable = self.isolable[sensors]
                span = slice(position + lo, position + lo + alarmed)
                out.alarm[span] = True
                out.isolated[span] = np.where(isolable, sensors, NOT_ISOLABLE)
                with np.errstate(divide="ignore", invalid="ignore"):
                    rows = np.arange(alarmed)
                    picked = sums[rows, sensors] / weights
                    scale = np.sqrt(feed.reference_variance(lo, lo + alarmed)[rows, sensors])
                    amplitude = picked * scale / self.sensitivity[sensors]
                out.amplitude[span] = np.where(isolable, amplitude, np.nan)
                last_sums, last_weight = sums[-1], float(weights[-1])
            chunks.append(_Chunk(u[:stop], q[:stop], inverse[:stop], ran))
            if ended.size:
                if last_sums is not None:
                    episode.sums, episode.weight = last_sums, last_weight
                if not frozen:
                    feed.rewind(lo + stop)
                self.state[:] = 0.0
                self.episode = None
                self._event = self.samples + lo + stop
                self._remember(chunks)
                self.samples += lo + stop
                return lo + stop
            episode.recovery = float(recovery[-1])
        if last_sums is not None:
            episode.sums, episode.weight = last_sums, last_weight
        self.state[...] = walk.state.reshape(self.state.shape)
        self._remember(chunks)
        self.samples += z.shape[0]
        return z.shape[0]

    def _remember(self, chunks: list[_Chunk]) -> None:
        """Keep the last ``history`` rows (for onsets): only the chunks that reach into
        them are copied into the ring."""
        first, rows = len(chunks), 0
        while first > 0 and rows < self.history.length:
            first -= 1
            rows += chunks[first].u.shape[0]
        for chunk in chunks[first:]:
            self.history.add(chunk.u, chunk.q, chunk.inverse)
