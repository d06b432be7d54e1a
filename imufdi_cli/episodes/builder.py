"""Streaming: episodes of one detector on one sensor type, explained as they close.

An **episode** is a run of alarms of one detector on one sensor type. Alarms are merged
across gaps of at most ``merge_gap`` quiet samples (0.1 s: a detector at its nominal
false-alarm level flickers inside a fault; a gap that short is not a recovery), whatever
they isolate. Such a run is then joined to the previous episode of the **same isolated
sensor** when at most ``join_gap`` (1 s) separates them: a fault that a detector sees in
fragments (noise growth, spikes) is one fault, and is explained over its whole span,
quiet gaps included, instead of over the fragments where the statistic happened to be
highest. Its start and end are the first and last alarmed samples; the decision times are
those of the status rows.

A closed episode is explained on its isolated sensor against the consensus of the others
(:mod:`~imufdi_cli.episodes.reference`) by the fault models of
:mod:`~imufdi_cli.episodes.fits`. :func:`episode_builders` makes one builder per sensor
type from the calibration window.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np

from imufdi_cli.episodes.batch import FitProblem, fit_models_batch
from imufdi_cli.episodes.block_alarms import BlockAlarms
from imufdi_cli.episodes.episode import (
    FITS_EXPLANATION,
    Episode,
    _sensor_amplitude,
)
from imufdi_cli.episodes.fault_fit import WhiteNoise
from imufdi_cli.episodes.reference import (
    Reference,
    correlation_sq,
    downdated_gain,
    estimator_without,
    leave_two_out,
)
from imufdi_cli.episodes.sample_explanation import SampleExplanations
from imufdi_cli.episodes.variance_drop import VARIANCE_DROP, VarianceDropMonitor
from imufdi_cli.episodes.white_noise import (
    successive_difference_dof,
    white_sigma,
    white_sigma_covariance,
    white_sigma_excess,
    white_sigma_spread,
    white_variance_dof,
)
from imufdi_cli.maths.parity import check_measurement_matrix

#: Fitted windows explained together (:func:`fit_models_batch`), at most: what waits.
FIT_BATCH = 64
#: Episodes waiting to be explained, at most (one-sample ones keep only their sample).
SAMPLE_BATCH = 512
#: ... and the bytes their windows hold (memory linear in the sensor count: a fit's window
#: holds the healthy sensors' residuals).
FIT_BYTES = 8 << 20
#: Bytes of leave-two-out consensus matrices kept (an (n, n - 1) matrix per sensor).
REFERENCE_CACHE_BYTES = 8 << 20


class _Cache:
    """Values computed from a key on demand, the least recently used dropped once the
    arrays they hold pass ``limit`` bytes (shared by the builders of one calibration)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.values: OrderedDict[int, Any] = OrderedDict()
        self.size = 0

    def get(self, key: int, make: Any) -> Any:
        if key in self.values:
            self.values.move_to_end(key)
            return self.values[key]
        value = make(key)
        self.values[key] = value
        self.size += _nbytes(value)
        while self.size > self.limit and len(self.values) > 1:
            _, dropped = self.values.popitem(last=False)
            self.size -= _nbytes(dropped)
        return value


def _nbytes(value: Any) -> int:
    if value is None:
        return 0
    return sum(int(getattr(item, "nbytes", 0)) for item in value)


class EpisodeBuilder(SampleExplanations):
    """Builds explained episodes from a detector's status rows while a log streams by.

    The builder keeps the last ``margin`` samples of the sensor type's measurements (the
    fault usually starts before its first alarm: a drift is detected late) and, while an
    episode is open, its samples up to ``max_window``; an episode closes once ``merge_gap``
    quiet rows follow it, and is then explained (:func:`fit_models` on the isolated
    sensor). Memory is bounded by ``margin + max_window`` samples whatever the log length.

    Parameters
    ----------
    detector, sensor_type : str
    H : ndarray, shape (n, 3)
        Measurement matrix of the sensor type.
    sensor_ids : sequence of str, length n
    sigma : ndarray, shape (n,)
        Calibrated per-sensor white-noise standard deviation (SI), e.g. from
        :func:`imufdi_cli.maths.parity.residual_sigma` on the calibration window.
    rate_hz : float
        Nominal sample rate.
    merge_gap_s, join_gap_s, margin_s, max_window_s : float
        Quiet time that does not end an episode; longer quiet time (at least
        ``merge_gap_s``) across which an alarm run that isolates the same sensor as the
        episode is joined to it as a fragment of the same fault; analysis margin before the
        first alarm (onset candidates); longest stretch of an episode kept for the fit.
    confidence : float
        Level of the size intervals.
    explain : bool
        Fit the fault models; False (too few sensors for a consensus, or no calibrated
        sigma) gives the episodes with their evidence but no fault class.
    calibration_samples : int, optional
        Samples ``sigma`` was estimated from (widens the noise factor's interval).
    calibration_mean : ndarray, shape (n,), optional
        Mean measurements of the calibration window: each sensor's bias against the
        consensus is taken out of its residual (a fault is what changed since).
    white_sigma : ndarray, shape (n,), optional
        The white part of each sensor's noise (:func:`white_sigma`, SI), estimated from
        ``calibration_samples`` samples; the noise factor is then sized against it from
        successive differences (:func:`_white_noise_fit`).
    white_excess : float
        How much more the white variances spread than Gaussian white noise says
        (:func:`white_sigma_excess`: outliers that pass the cut, heavy tails); it scales
        :func:`white_sigma_covariance` and so lowers the calibration's degrees of freedom
        in the noise factor's interval.
    variance_drop : bool
        Also run the :class:`VarianceDropMonitor` on the measurements and return its
        explained episodes (``detector`` :data:`VARIANCE_DROP`) with this builder's: a
        detection of its own, for frozen outputs the detectors cannot see. Needs
        ``white_sigma`` and ``calibration_samples``.
    variance_drop_window_s, variance_drop_alpha : float
        The monitor's window and the probability that one healthy sensor's window falls
        below its threshold.
    sample_explanations : bool
        Explain an episode of one alarmed sample by that sample alone
        (:meth:`_explain_samples`: ``spikes`` or ``none``) instead of the fits: what
        ``detect`` does for a per-sample test, whose chance alarms are most of its episodes
        and carry nothing a fit over a margin could tell apart from chance.
    """

    def __init__(
        self,
        detector: str,
        sensor_type: str,
        H: np.ndarray,
        sensor_ids: Sequence[str],
        sigma: np.ndarray,
        rate_hz: float,
        *,
        merge_gap_s: float = 0.1,
        join_gap_s: float = 1.0,
        margin_s: float = 2.0,
        max_window_s: float = 30.0,
        confidence: float = 0.9,
        explain: bool = True,
        calibration_samples: int | None = None,
        calibration_mean: np.ndarray | None = None,
        white_sigma: np.ndarray | None = None,
        white_excess: float = 1.0,
        variance_drop: bool = False,
        variance_drop_window_s: float = 1.0,
        variance_drop_alpha: float = 1e-7,
        sample_explanations: bool = False,
    ) -> None:
        self.detector = detector
        self.sensor_type = sensor_type
        self.H = check_measurement_matrix(H)
        self.sensor_ids = list(sensor_ids)
        self.sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (self.H.shape[0],))
        self.merge_gap = max(0, round(merge_gap_s * rate_hz))
        self.join_gap = max(self.merge_gap, round(join_gap_s * rate_hz))
        self.margin = max(2, round(margin_s * rate_hz))
        self.max_window = max(4, round(max_window_s * rate_hz))
        self.confidence = confidence
        self.explain = explain
        #: one-sample episodes explained by their sample alone (:meth:`_explain_samples`)
        self.sample_explanations = sample_explanations
        #: episodes closed and waiting to be explained, in order; of them, the one-sample
        #: episodes explained by their sample (its row) and those fitted (their problems)
        self._waiting_episodes: list[Episode] = []
        self._samples: list[tuple[Episode, np.ndarray, int]] = []
        self._fits: list[tuple[Episode, FitProblem]] = []
        self._fit_bytes = 0  # what the waiting fits hold
        self.calibration_samples = calibration_samples
        self.calibration_mean = (
            None if calibration_mean is None else np.asarray(calibration_mean, np.float64)
        )
        # what another detector's builder is made from (for_detector)
        self._arguments = (sensor_type, H, sensor_ids, sigma, rate_hz)
        self._options: dict[str, Any] = {
            "merge_gap_s": merge_gap_s,
            "join_gap_s": join_gap_s,
            "margin_s": margin_s,
            "max_window_s": max_window_s,
            "confidence": confidence,
            "explain": explain,
            "calibration_samples": calibration_samples,
            "calibration_mean": calibration_mean,
            "white_sigma": white_sigma,
            "white_excess": white_excess,
            "variance_drop_window_s": variance_drop_window_s,
            "variance_drop_alpha": variance_drop_alpha,
            "sample_explanations": sample_explanations,
        }
        self.white_sigma = (
            None
            if white_sigma is None
            else np.broadcast_to(np.asarray(white_sigma, np.float64), (self.H.shape[0],))
        )
        self._gains: dict[int, tuple[np.ndarray, float]] = {}
        #: (residual matrix (n, n), calibrated bias (n,), sigma_r (n,)) of every sensor
        self._sample_matrix: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # k -> _reference_matrix(k): (n, n - 1) each, so a bounded cache (memory linear
        # in the sensor count, not cubic)
        self._references: _Cache = _Cache(REFERENCE_CACHE_BYTES)
        self.white_excess = float(white_excess)
        self._white_cov: np.ndarray | None = None  # white_sigma_covariance, once
        self._estimators: dict[int, np.ndarray] = {}  # k -> _estimator(k)
        # per-sensor values that depend only on the calibration, computed once per k:
        # k -> (correlation_sq of its leave-two-out A, calibration mean @ _estimator(k))
        self._reference_constants: dict[int, tuple[float, np.ndarray | None]] = {}
        self._whites: dict[int, WhiteNoise | None] = {}  # k -> _white(k, gain of k)
        self._biases: dict[int, Any] = {}  # k -> calibrated bias against the consensus
        self._pending: list[np.ndarray] = []  # measurements fed but not yet paired with rows
        #: the block :meth:`rows` is appending (measurements, times), while it does
        self._block: tuple[np.ndarray, np.ndarray] | None = None
        self._history: np.ndarray = np.zeros((0, self.H.shape[0]))  # last `margin` rows
        self._history_t: np.ndarray = np.zeros(0, np.int64)
        self._open: dict[str, Any] | None = None  # the alarm run under way
        self._waiting: dict[int, dict[str, Any]] = {}  # sensor -> episode awaiting fragments
        self._pos = 0
        self._monitor_issued = False  # for_detector: the first builder gets the monitor
        self._drop: tuple[VarianceDropMonitor, EpisodeBuilder] | None = None
        if variance_drop and self.white_sigma is not None and calibration_samples and explain:
            window = max(2, round(variance_drop_window_s * rate_hz))
            self._drop = (
                self._variance_monitor(window, variance_drop_alpha),
                EpisodeBuilder(
                    VARIANCE_DROP,
                    *self._arguments,
                    **{**self._options, "sample_explanations": False},
                ),
            )

    # measurements arrive with the input blocks, rows when the detector emits them
    def feed(self, measurements: np.ndarray) -> None:
        """Measurements (N, n) of the next N input samples, SI."""
        self._pending.append(np.asarray(measurements, dtype=np.float64))

    def _take(self, count: int) -> np.ndarray:
        parts, need = [], count
        while need > 0:
            head = self._pending[0]
            if head.shape[0] <= need:
                parts.append(self._pending.pop(0))
                need -= head.shape[0]
            else:
                parts.append(head[:need])
                self._pending[0] = head[need:]
                need = 0
        return np.concatenate(parts) if parts else np.zeros((0, self.H.shape[0]))

    def rows(self, t_ns: np.ndarray, decided_ns: np.ndarray, out: Any) -> list[Episode]:
        """Status rows (a DetectionBlock ``out`` with sample and decision times, in order);
        returns episodes closed within them or before, explained (a batch of them at a
        time, :meth:`_explain_jobs`; the rest by :meth:`finish`), ordered by their decision
        time."""
        n = len(t_ns)
        t_ns = np.asarray(t_ns, dtype=np.int64)
        m = self._take(n)
        alarm = np.asarray(out.alarm, dtype=bool)
        isolated_rows = np.asarray(out.isolated)
        amplitudes = out.amplitude_set() if hasattr(out, "amplitude_set") else None
        idx = np.flatnonzero(alarm)
        groups = np.split(idx, np.flatnonzero(np.diff(idx) - 1 > self.merge_gap) + 1)
        closed: list[Episode] = []
        self._pos = 0  # next row of this block not yet appended to the open states
        ratios = None
        if idx.size:
            # the statistic ratio of the alarmed rows, elementwise as per group
            with np.errstate(divide="ignore", invalid="ignore"):
                ratios = np.asarray(out.statistic)[idx] / np.asarray(out.threshold)[idx]
        self._block = (m, t_ns)
        if idx.size:
            assert ratios is not None
            alarms = BlockAlarms(
                groups, isolated_rows[idx], ratios, amplitudes, len(self.sensor_ids)
            )
        for g, group in enumerate(groups if idx.size else []):
            first, last = int(group[0]), int(group[-1])
            self._advance(m, t_ns, first, closed)
            self._end_quiet_run(closed)
            state = self._open
            if state is None:
                state = self._open = self._new_run(m, t_ns, int(decided_ns[first]), first)
            self._advance(m, t_ns, last + 1, closed, alarmed=True)
            state["end_ns"] = int(t_ns[last])
            state["decided_end_ns"] = int(decided_ns[last])
            alarms.add(state, g)
        self._advance(m, t_ns, n, closed)
        self._end_quiet_run(closed)
        # the rows the open run and the waiting episodes keep of this block, copied (a
        # view would keep the whole block alive while they wait)
        for state in (self._open, *self._waiting.values()):
            if state is not None:
                self._keep(state)
        self._block = None
        tail = max(0, n - self.margin)
        self._history = np.concatenate([self._history, m[tail:]])[-self.margin :]
        self._history_t = np.concatenate([self._history_t, t_ns[tail:]])[-self.margin :]
        done = self._explain_jobs()
        if self._drop is not None:
            monitor, builder = self._drop
            builder._gains, builder._references = self._gains, self._references
            builder.feed(m)
            done.extend(builder.rows(t_ns, t_ns, monitor.update(m)))
        done.sort(key=lambda e: e.decided_end_ns)
        return done

    def _end_quiet_run(self, closed: list[Episode]) -> None:
        """Close the open alarm run once more than ``merge_gap`` quiet rows follow it."""
        state = self._open
        if state is not None and state["quiet"] > self.merge_gap:
            self._run_closed(state, closed)
            self._open = None

    def _new_run(
        self, m: np.ndarray, t_ns: np.ndarray, decided_ns: int, first: int
    ) -> dict[str, Any]:
        """The state of an alarm run starting at row ``first`` of the block (decided at
        ``decided_ns``), with the last ``margin`` rows before it."""
        # only the last `margin` rows before the alarm are kept: copy no more
        if first >= self.margin:  # all inside the block: one copy (C order, as joined)
            history = m[first - self.margin : first].copy()
            history_t = t_ns[first - self.margin : first].copy()
        else:
            history = np.concatenate([self._history, m[:first]])[-self.margin :]
            history_t = np.concatenate([self._history_t, t_ns[:first]])[-self.margin :]
        return {
            "start_ns": int(t_ns[first]),
            "decided_start_ns": decided_ns,
            "window": [history],
            "window_t": [history_t],
            "kept": history.shape[0],
            "span": None,  # rows [lo, hi) of the block not yet copied into "window"
            "alarm_index": history.shape[0],
            "alarms": 0,
            # alarmed rows that isolated a sensor (negative: none); those isolating one
            # of the sensors are counted per sensor in "counts"
            "isolated_rows": 0,
            "amplitudes": [],  # (sensor, amplitude) of alarms with an estimate
            "counts": np.zeros(len(self.sensor_ids), np.int64),
            "fragments": 1,
            "peak": -math.inf,
            "quiet": 0,
            # episodes this run may still join: they wait until it has ended
            "may_join": set(self._waiting),
        }

    def _variance_monitor(self, window: int, alpha: float) -> VarianceDropMonitor:
        """The :class:`VarianceDropMonitor` of this sensor type (white sigma, leave-one-out
        gains of every sensor with a consensus)."""
        assert self.white_sigma is not None and self.calibration_samples
        n = self.H.shape[0]
        A = np.zeros((n, n))
        variance = np.full(n, np.inf)
        dof = np.full(n, successive_difference_dof(self.calibration_samples))
        covariance = self._white_covariance()
        for k in range(n):
            try:
                gain, _ = self._gain(k)
            except ValueError:
                continue
            A[:, k] = -gain
            A[k, k] += 1.0
            variance[k] = self.white_sigma[k] ** 2 + float(np.sum((gain * self.white_sigma) ** 2))
            if covariance.size:
                dof[k] = white_variance_dof(covariance, gain, k, variance[k], dof[k])
        return VarianceDropMonitor(A, variance, window=window, alpha=alpha, calibration_dof=dof)

    def _white_covariance(self) -> np.ndarray:
        """Covariance of the calibrated white variances (:func:`white_sigma_covariance`
        times the measured excess of outliers, :func:`white_sigma_excess`), computed once;
        shape (0, 0) when they are not identifiable one by one."""
        assert self.white_sigma is not None and self.calibration_samples
        if self._white_cov is None:
            self._white_cov = self.white_excess * white_sigma_covariance(
                self.H, self.white_sigma, self.calibration_samples
            )
        return self._white_cov

    def _advance(
        self,
        m: np.ndarray,
        t_ns: np.ndarray,
        stop: int,
        closed: list[Episode],
        alarmed: bool = False,
    ) -> None:
        """Append rows ``[pos, stop)`` of the block to the open run and to every episode
        waiting for a fragment; count them as quiet (unless they are the open run's
        alarms); explain the waiting episodes that have waited ``join_gap`` in vain."""
        lo = self._pos
        if stop <= lo:
            return
        self._pos = stop
        if self._open is not None:
            self._append(self._open, m, t_ns, lo, stop)
            if not alarmed:
                self._open["quiet"] += stop - lo
        held = set() if self._open is None else self._open["may_join"]
        for sensor, waiting in list(self._waiting.items()):
            self._append(waiting, m, t_ns, lo, stop)
            waiting["quiet"] += stop - lo
            if sensor not in held:
                self._expire(sensor, closed)

    def _expire(self, sensor: int, closed: list[Episode]) -> None:
        """Explain the episode waiting on ``sensor`` if it has waited ``join_gap`` in vain."""
        waiting = self._waiting[sensor]
        if waiting["quiet"] > self.join_gap:
            del self._waiting[sensor]
            closed.append(self._close(waiting))

    def _run_closed(self, run: dict[str, Any], closed: list[Episode]) -> None:
        """An alarm run has ended (``merge_gap`` quiet rows follow it). With an isolated
        sensor it joins that sensor's waiting episode when one ended at most ``join_gap``
        rows before it (the waiting episode already holds every row since), or starts to
        wait itself; without one it is explained at once."""
        if not run["counts"].any():
            closed.append(self._close(run))
            for other in list(self._waiting):  # no longer held by this run
                self._expire(other, closed)
            return
        sensor = int(run["counts"].argmax())  # (the array method: what np.argmax calls)
        waiting = self._waiting.get(sensor)
        if waiting is not None:
            # the rows of the run, and its quiet rows since, are in the waiting window
            waiting["end_ns"] = run["end_ns"]
            waiting["decided_end_ns"] = run["decided_end_ns"]
            waiting["quiet"] = run["quiet"]
            waiting["alarms"] += run["alarms"]
            waiting["isolated_rows"] += run["isolated_rows"]
            waiting["amplitudes"].extend(run["amplitudes"])
            waiting["counts"] += run["counts"]
            waiting["fragments"] += run["fragments"]
            waiting["peak"] = max(waiting["peak"], run["peak"])
        else:
            self._waiting[sensor] = run
        for other in list(self._waiting):  # no longer held by this run
            self._expire(other, closed)

    def _append(
        self, state: dict[str, Any], m: np.ndarray, t_ns: np.ndarray, lo: int, hi: int
    ) -> None:
        """Rows ``[lo, hi)`` of the block (``m``, ``t_ns``) into the state's window, up to
        ``max_window`` rows: noted as a span of the block, copied by :meth:`_keep` once
        the block's rows are appended or the state closes (the spans a state gets in a
        block are consecutive: one copy)."""
        hi = min(hi, lo + max(0, self.max_window - state["kept"]))
        if hi > lo:
            span = state["span"]
            if span is not None and span[1] == lo:
                state["span"] = (span[0], hi)
            else:
                if span is not None:
                    self._keep(state)
                state["span"] = (lo, hi)
            state["kept"] += hi - lo

    def _keep(self, state: dict[str, Any]) -> None:
        """The state's span of the current block, copied into its window: a view would
        keep the whole block alive while the episode waits (6 MB a block at 64 IMUs, per
        builder)."""
        span = state["span"]
        if span is not None:
            assert self._block is not None
            m, t_ns = self._block
            lo, hi = span
            state["window"].append(m[lo:hi].copy())
            state["window_t"].append(t_ns[lo:hi].copy())
            state["span"] = None

    def finish(self) -> list[Episode]:
        """The episodes still open or waiting at the end of the log, explained."""
        closed: list[Episode] = []
        if self._open is not None:
            self._run_closed(self._open, closed)
            self._open = None
        for waiting in self._waiting.values():
            closed.append(self._close(waiting))
        self._waiting.clear()
        done = self._explain_jobs(flush=True)
        if self._drop is not None:
            done.extend(self._drop[1].finish())
        done.sort(key=lambda e: e.decided_end_ns)
        return done

    def _close(self, state: dict[str, Any]) -> Episode:
        self._keep(state)
        window_t = np.concatenate(state["window_t"])
        # drop the quiet rows after the last alarm (they are not part of the fault): only
        # the pieces before them are joined (the same C-ordered rows as joining all)
        last = int(window_t.searchsorted(state["end_ns"], side="right"))
        window_t = window_t[:last]
        pieces, need = [], last
        for piece in state["window"]:
            if need <= 0:
                break
            pieces.append(piece[:need])
            need -= piece.shape[0]
        window = np.concatenate(pieces) if pieces else state["window"][0][:0]
        names, runner_up, share = self._isolation_summary(state)
        episode = Episode(
            detector=self.detector,
            sensor_type=self.sensor_type,
            start_ns=state["start_ns"],
            end_ns=state["end_ns"],
            decided_start_ns=state["decided_start_ns"],
            decided_end_ns=state["decided_end_ns"],
            alarms=state["alarms"],
            sensors=names,
            peak_ratio=state["peak"],
            runner_up=runner_up,
            runner_up_share=share,
            fragments=state["fragments"],
            amplitude=_sensor_amplitude(state["amplitudes"], self.sensor_ids, names),
        )
        self._waiting_episodes.append(episode)
        if self.explain and window.shape[0] >= 4:
            single = state["alarms"] == 1 and state["fragments"] == 1
            alarm_index = state["alarm_index"]
            if single and self.sample_explanations and self._sample_explains(episode, window):
                # (only its alarmed sample is kept)
                self._samples.append((episode, window[alarm_index].copy(), alarm_index))
            else:
                problem = self._fit_problem(episode, window, window_t, alarm_index)
                if problem is not None:
                    self._fits.append((episode, problem))
                    reference = problem[1]["reference"]
                    self._fit_bytes += window.nbytes + (
                        0 if reference is None else reference.residuals.nbytes
                    )
        return episode

    def _explain_jobs(self, flush: bool = False) -> list[Episode]:
        """The episodes closed so far, explained, once enough wait (or with ``flush``):
        their fits are found together, up to :data:`FIT_BATCH` windows at a time
        (:func:`~imufdi_cli.episodes.batch.fit_models_batch`), the one-sample episodes of
        a per-sample test by their sample (:meth:`_explain_samples`). At most
        :data:`FIT_BATCH` windows wait, whatever the log length."""
        waiting = len(self._waiting_episodes)
        held = self._fit_bytes
        if (
            not flush
            and len(self._fits) < FIT_BATCH
            and waiting < SAMPLE_BATCH
            and held < FIT_BYTES
        ):
            return []
        if self._samples:
            self._explain_samples(self._samples)
        if self._fits:
            fitted = fit_models_batch([problem for _, problem in self._fits])
            for (episode, _), fits in zip(self._fits, fitted, strict=True):
                episode.fits = fits
                if fits:
                    episode.explained_by = FITS_EXPLANATION
        done, self._waiting_episodes = self._waiting_episodes, []
        self._samples, self._fits, self._fit_bytes = [], [], 0
        return done

    def _isolation_summary(
        self, state: dict[str, Any]
    ) -> tuple[list[str], str | None, float | None]:
        """:func:`~imufdi_cli.episodes.episode.isolation_summary` of the run ``state``'s alarmed rows, from the counts
        per sensor kept while they arrived (the same order, stable, and share)."""
        counts = state["counts"].tolist()
        total = state["isolated_rows"]
        if total != sum(counts):
            # an index past the sensors: isolation_summary says what is wrong with it
            raise IndexError(f"isolated sensor index out of range ({len(counts)} sensors)")
        if total == 0:
            return [], None, None
        isolated = state["counts"].nonzero()[0].tolist()
        order = sorted(isolated, key=lambda i: -counts[i]) if len(isolated) > 1 else isolated
        names = [self.sensor_ids[i] for i in order]
        if len(order) < 2:
            return names, None, 0.0
        return names, names[1], float(counts[order[1]] / total)

    def _fit_problem(
        self, episode: Episode, window: np.ndarray, window_t: np.ndarray, alarm_index: int
    ) -> FitProblem | None:
        """The arguments of :func:`~imufdi_cli.episodes.fits.fit_models` on the episode's
        isolated sensor (or, when none was isolated, the loudest, named in the episode)
        over ``window`` (L, n) with times ``window_t`` (L,) ns, its first alarm at
        ``alarm_index``; None when the other sensors give no consensus."""
        names = episode.sensors
        k = self.sensor_ids.index(names[0]) if names else self._loudest(window)
        if not names:
            episode.sensors = [self.sensor_ids[k]]
            episode.isolated_by = "residual"
        try:
            gain, consensus_sigma = self._gain(k)
        except ValueError:
            return None
        prediction = window @ gain
        residual = window[:, k] - prediction
        offset_var = None
        if self.calibration_mean is not None:
            # the sensor's own bias against the consensus, as calibrated: a fault is what
            # changed since (its estimate's variance widens the step interval)
            bias = self._biases.get(k)
            if bias is None:  # once per sensor
                bias = self._biases[k] = self.calibration_mean[k] - self.calibration_mean @ gain
            residual = residual - bias
            if self.calibration_samples:
                offset_var = (self.sigma[k] ** 2 + consensus_sigma**2) / self.calibration_samples
        t_s = (window_t - window_t[0]).astype(np.float64) * 1e-9
        alarm_index = min(alarm_index, max(len(window_t) - 2, 0))
        args = (residual, prediction, t_s, float(self.sigma[k]), consensus_sigma)
        kwargs = {
            # the onset may precede the first alarm (a drift is detected late) or follow
            # it (a chance alarm just before the fault merges into its episode)
            "onset_range": (0, alarm_index + 1 + (len(window_t) - alarm_index) // 2),
            "confidence": self.confidence,
            "raw": window[:, k].copy(),
            "calibration_samples": self.calibration_samples,
            "offset_var": offset_var,
            "reference": self._reference(k, window),
            "white": self._white_of(k, gain),
        }
        return args, kwargs

    def _white_of(self, k: int, gain: np.ndarray) -> WhiteNoise | None:
        """:meth:`_white` of sensor k (``gain`` its :meth:`_gain`), computed once."""
        if k not in self._whites:
            self._whites[k] = self._white(k, gain)
        return self._whites[k]

    def _white(self, k: int, gain: np.ndarray) -> WhiteNoise | None:
        """(sigma_k, consensus sigma, dof, spread) of the white noise for
        :func:`fit_models` (spread: :func:`white_sigma_spread`, left out when the
        calibration's variances are not identifiable one by one)."""
        if self.white_sigma is None or not self.calibration_samples:
            return None
        consensus = float(np.sqrt(np.sum((gain * self.white_sigma) ** 2)))
        dof = successive_difference_dof(self.calibration_samples)
        covariance = self._white_covariance()
        if covariance.size == 0:
            return float(self.white_sigma[k]), consensus, dof
        spread = white_sigma_spread(covariance, gain, k)
        return float(self.white_sigma[k]), consensus, dof, spread

    def _reference(self, k: int, window: np.ndarray) -> Reference | None:
        """The other sensors' residuals over ``window`` (:class:`Reference`), each against
        the consensus of the sensors other than itself and ``k``."""
        cached = self._references.get(k, self._reference_matrix)
        if cached is None:
            return None
        A, offset, variance, offset_var = cached
        constants = self._reference_constants.get(k)
        if constants is None:
            mean_motion = (
                None
                if self.calibration_mean is None
                else self.calibration_mean @ self._estimator(k)
            )
            constants = self._reference_constants[k] = (
                correlation_sq(A, self.sigma),
                mean_motion,
            )
        correlation, mean_motion = constants
        # the sensed vector relative to its calibration mean: the calibrated offsets taken
        # out of the residuals hold the motion errors of the calibration window too
        motion = window @ self._estimator(k)
        if mean_motion is not None:
            motion = motion - mean_motion
        return Reference(window @ A - offset, variance, offset_var, motion, correlation)

    def _reference_matrix(
        self, k: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """:func:`~imufdi_cli.episodes.reference.leave_two_out` of sensor k with this
        builder's calibration."""
        return leave_two_out(self.H, self.sigma, k, self.calibration_mean, self.calibration_samples)

    def _estimator(self, k: int) -> np.ndarray:
        """:func:`~imufdi_cli.episodes.reference.estimator_without` sensor k (cached)."""
        found = self._estimators.get(k)
        if found is None:
            found = self._estimators[k] = estimator_without(self.H, self.sigma, k)
        return found

    def _gain(self, k: int) -> tuple[np.ndarray, float]:
        """:func:`~imufdi_cli.episodes.reference.downdated_gain` of sensor k (cached)."""
        found = self._gains.get(k)
        if found is None:
            found = self._gains[k] = downdated_gain(self.H, self.sigma, k)
        return found

    def for_detector(
        self, detector: str, *, sample_explanations: bool | None = None
    ) -> EpisodeBuilder:
        """A fresh builder with the same calibration, for another detector (it shares the
        consensus gains, which depend only on the calibration); ``sample_explanations``:
        whether its one-sample episodes are explained by their sample alone (a per-sample
        test's chance alarms) or by the fits like the others (a detector under a
        false-alarm budget, whose episodes are rare; default: this builder's choice)."""
        # the variance-drop monitor is a detection of its own: one builder runs it
        monitor = not self._monitor_issued
        self._monitor_issued = True
        options = dict(self._options)
        if sample_explanations is not None:
            options["sample_explanations"] = sample_explanations
        builder = EpisodeBuilder(detector, *self._arguments, **options, variance_drop=monitor)
        builder._gains = self._gains
        builder._references = self._references
        return builder

    def _loudest(self, window: np.ndarray) -> int:
        """For detectors that do not isolate: the sensor with the largest normalised
        leave-one-out residual energy over the episode."""
        energies = []
        for k in range(self.H.shape[0]):
            try:
                gain, c = self._gain(k)
            except ValueError:
                energies.append(-math.inf)
                continue
            r = window[:, k] - window @ gain
            energies.append(float(np.sum(r**2)) / (self.sigma[k] ** 2 + c**2))
        return int(np.argmax(energies))


def episode_builders(calibration: Any, array: Any, **options: Any) -> dict[str, EpisodeBuilder]:
    """One builder per sensor type of ``array`` present in the calibration block (an
    :class:`~imufdi_cli.log.ImuBlock`), with per-sensor sigma from its parity residuals
    (:func:`~imufdi_cli.maths.parity.residual_sigma`). Types with fewer than 4 sensors
    (no leave-one-out consensus) get episodes without explanation. Use
    :meth:`EpisodeBuilder.for_detector` to get each detector its own builder."""
    from imufdi_cli.errors import ArrayConfigError, CalibrationError
    from imufdi_cli.maths.parity import residual_sigma

    builders = {}
    for sensor_type in array.sensor_types():
        triads = calibration.get(sensor_type)
        if triads is None:
            continue
        H = array.measurement_matrix(sensor_type)
        try:
            check_measurement_matrix(H)
        except ArrayConfigError:
            continue  # the detectors say what is wrong with such a geometry; no episodes
        explain = H.shape[0] >= 4
        sigma = np.ones(H.shape[0])
        n_cal: int | None = None
        mean: np.ndarray | None = None
        white: np.ndarray | None = None
        excess = 1.0
        if explain:
            measurements = array.select(triads, sensor_type)
            finite = np.all(np.isfinite(measurements), axis=1)
            n_cal = int(np.count_nonzero(finite))
            mean = measurements[finite].mean(axis=0) if n_cal else None
            try:
                sigma = residual_sigma(H, measurements[finite])
                white = white_sigma(H, measurements[finite])
                excess = white_sigma_excess(H, measurements[finite])
            except CalibrationError:
                explain = False
            explain = explain and bool(np.all(np.isfinite(sigma)) and np.all(sigma > 0))
        builders[sensor_type] = EpisodeBuilder(
            "",
            sensor_type,
            H,
            array.sensor_ids(sensor_type),
            sigma,
            array.rate_hz,
            explain=explain,
            calibration_samples=n_cal if explain else None,
            calibration_mean=mean if explain else None,
            white_sigma=white if explain else None,
            white_excess=excess,
            **options,
        )
    return builders
