"""The streaming accumulator of the metrics (:class:`MetricsAccumulator`) and its one-call
form (:func:`compute_metrics`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from imufdi_cli.metrics.figures import (
    AmplitudeFigure,
    FaultFigures,
    FaultWindow,
    Metrics,
    _ratio,
)
from imufdi_cli.metrics.rows import (
    apply_budget_match,
    episode_rate,
    faulty_matrix,
    judged_isolation,
)
from imufdi_cli.tested_time import SamplePeriod, fault_free_tested_hours  # per-hour denominator

NS_PER_S = 1_000_000_000


class _FaultState:
    """Streaming per-fault bookkeeping (see :class:`MetricsAccumulator`)."""

    def __init__(self, window: FaultWindow, episode_end_ns: int | None) -> None:
        self.window = window
        self.episode_end_ns = episode_end_ns
        self.samples = 0
        self.run = 0  # consecutive alarms inside the fault so far
        self.detected_ns: int | None = None
        self.isolated_ns: int | None = None
        self.alarmed = 0
        self.isolated_ok = 0
        self.after_first = 0  # faulty samples from the first alarm on
        self.alarmed_after_first = 0
        self.first_alarm = False
        self.quiet_from_ns: int | None = None  # decision time of the candidate quiet sample
        self.quiet_from_t: int | None = None  # its sample time
        self.quiet = 0  # quiet samples since then
        self.recovered_ns: int | None = None  # decision time of the recovery sample, once known
        #: per faulty sensor: its estimated amplitudes while isolated (AmplitudeFigure)
        self.amplitudes = {s: _AmplitudeTrack() for s in window.sensors}


#: Amplitude samples kept per faulty sensor for the median (evenly decimated beyond).
AMPLITUDE_POINTS = 20_000


class _AmplitudeTrack:
    """A faulty sensor's estimated amplitudes, in bounded memory: least-squares sums for
    the slope against time, and an evenly decimated copy (every ``stride``-th value, at
    most 2 x AMPLITUDE_POINTS) for the median."""

    def __init__(self) -> None:
        self.count = 0
        self.sums = np.zeros(4)  # sum of t, a, t^2 and t a over every sample
        self.kept: list[np.ndarray] = []
        self.n_kept = 0
        self.stride = 1
        self.seen = 0

    def add(self, t_s: np.ndarray, values: np.ndarray) -> None:
        if values.size == 0:
            return
        self.count += int(values.size)
        self.sums += [t_s.sum(), values.sum(), (t_s * t_s).sum(), (t_s * values).sum()]
        first = (-self.seen) % self.stride
        self.seen += int(values.size)
        picked = values[first :: self.stride]
        self.kept.append(picked)
        self.n_kept += int(picked.size)
        if self.n_kept > 2 * AMPLITUDE_POINTS:
            self.kept = [np.concatenate(self.kept)[::2]]
            self.n_kept = int(self.kept[0].size)
            self.stride *= 2

    def median(self) -> float:
        return _median(np.concatenate(self.kept))

    def slope(self) -> float | None:
        n = self.count
        st, sa, stt, sta = self.sums
        spread = n * stt - st * st
        if n < 2 or spread <= 0:
            return None
        return float((n * sta - st * sa) / spread)


def _run_lengths(on: np.ndarray, carried: int) -> np.ndarray:
    """The length of the run of True ending at each element of ``on`` (k,) bool (0 where
    False), the first run continuing ``carried`` True before it."""
    k = int(on.size)
    index = np.arange(k, dtype=np.int64)
    last_off = np.maximum.accumulate(np.where(on, -1, index)) if k else index
    return np.where(last_off >= 0, index - last_off, carried + index + 1)


def _among(column: np.ndarray, sensors: tuple[int, ...]) -> np.ndarray:
    """``np.isin(column, sensors)`` for a few sensor indices (one comparison each: the
    generic isin costs 20 times more on these sizes)."""
    out = np.zeros(column.shape, dtype=bool)
    for sensor in sensors:
        out |= column == sensor
    return out


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D float array (NaN if it holds a NaN or nothing), the same
    float: the middle element, or the mean of the two middle ones, of a partition. numpy's
    own checks the NaNs through ``numpy.ma``, whose import (about 15 ms) ``report`` would
    otherwise pay for this one call."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    n = values.shape[0]
    if n == 0 or bool(np.isnan(values).any()):
        return float("nan")
    k = n // 2
    if n % 2:
        return float(np.partition(values, k)[k])
    part = np.partition(values, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2.0)


class MetricsAccumulator:
    """Streaming metrics of one detector on one sensor type (module docstring).

    Feed the rows in time order with :meth:`update`, any number of rows at a time, then
    call :meth:`result`. Memory does not depend on the number of rows.

    Parameters
    ----------
    n_sensors : int
    faults : sequence of FaultWindow
        The faults of this sensor type.
    calibration_ns : (start_ns, end_ns) or None
        Samples with ``start <= t < end`` are in-sample and excluded from the figures
        (counted in ``far_calibration``); None: every sample counts.
    persist : int
        Detection delay: the first run of this many consecutive alarms; recovery: at least
        this many quiet samples after the last alarm.
    sweep : bool
        Also fill the matched-FAR histograms (:mod:`imufdi_cli.sweep`).
    merge_gap_s : float
        Recovery: an alarm that comes back within this time of the candidate recovery
        sample belongs to the same alarm episode (flicker), s.
    sensor_ids : sequence of str, optional
        Names of the sensors in the per-fault amplitude figures (default: their indices).
    episode_gaps : (merge_gap, join_gap), optional
        The episodes' joining rule in rows (:func:`~imufdi_cli.sweep.episode_gap_rows`):
        with it, the false alarm episodes are counted (and, with ``sweep`` and
        ``budget_levels``, at every level of the matched budget); without (no sample rate
        known), they are undefined.
    budget_levels : bool
        Count the episodes at the matched budget's levels (:meth:`budget_curve`): the
        joining rule on every row above 0.63 x the threshold, at 65 levels.
    """

    def __init__(
        self,
        n_sensors: int,
        faults: Sequence[FaultWindow] = (),
        *,
        calibration_ns: tuple[int, int] | None = None,
        persist: int = 1,
        sweep: bool = True,
        merge_gap_s: float = 0.1,
        sensor_ids: Sequence[str] | None = None,
        episode_gaps: tuple[int, int] | None = None,
        budget_levels: bool = True,
    ) -> None:
        from imufdi_cli.sweep import BUDGET_LEVELS, AlarmEpisodes, FaultRuns, SweepAccumulator

        self.sensor_ids = None if sensor_ids is None else list(sensor_ids)

        self.merge_gap_ns = round(merge_gap_s * NS_PER_S)
        self.n_sensors = int(n_sensors)
        self.windows = list(faults)
        self.calibration_ns = calibration_ns
        self.persist = max(int(persist), 1)
        onsets = sorted(w.start_ns for w in self.windows)
        self.states = []
        for w in self.windows:
            later = [s for s in onsets if w.end_ns is not None and s >= w.end_ns]
            self.states.append(_FaultState(w, min(later) if later else None))
        self.sweep = SweepAccumulator([w.start_ns for w in self.windows]) if sweep else None
        self.episodes = None if episode_gaps is None else AlarmEpisodes(1, n_sensors, *episode_gaps)
        self.budget = (
            AlarmEpisodes(BUDGET_LEVELS.size, n_sensors, *episode_gaps)
            if episode_gaps is not None and sweep and budget_levels
            else None
        )
        #: the detector's own runs that began in a fault (their rows: the fault's, at any scale)
        self.fault_runs = (
            None if self.budget is None or episode_gaps is None else FaultRuns(episode_gaps[0])
        )
        self.period = SamplePeriod()
        self.n = 0
        self.n_cal = 0
        self.n_eval = 0
        self.n_free = 0
        self.n_free_cal = 0
        self.false_alarms = 0
        self.false_alarms_cal = 0
        self.n_faulty = 0
        self.missed = 0
        self.detected = 0
        self.false_iso = 0
        self.unisolated = 0
        self.alarms_eval = 0
        self.events = 0
        self.false_events = 0
        self.latency_sum = 0.0
        self.t_first: int | None = None
        self.t_last = 0
        self.previous_alarm = False

    def update(
        self,
        t_ns: np.ndarray,
        alarm: np.ndarray,
        isolated: np.ndarray,
        *,
        decided_ns: np.ndarray | None = None,
        isolated_set: np.ndarray | None = None,
        statistic: np.ndarray | None = None,
        threshold: np.ndarray | None = None,
        scores: np.ndarray | None = None,
        faulty: np.ndarray | None = None,
        amplitudes: np.ndarray | None = None,
        scored: np.ndarray | None = None,
        amplitude: np.ndarray | None = None,
        best_score: np.ndarray | None = None,
    ) -> None:
        """Add k consecutive rows.

        Parameters
        ----------
        t_ns : (k,) int64, sample times, ns
        alarm : (k,) bool
        isolated : (k,) int, isolated sensor (negative: none / not isolable)
        decided_ns : (k,) int64, decision times (default: the sample times)
        isolated_set : (k, n) bool, every sensor isolated (default: one-hot of ``isolated``)
        statistic, threshold : (k,) float64, for the matched-FAR and matched-budget sweeps
        scores : (k, n) float64, isolation scores; the sweeps judge the isolation of rows
            the detector left unisolated by their largest score
        faulty : (k, n) bool, optional
            Ground truth per row and sensor; default: from the fault windows
        amplitudes : (k, n) float64, optional
            Estimated amplitude of every sensor, SI, NaN where none (the status'
            ``amplitudes``), for the per-fault :class:`AmplitudeFigure`
        amplitude : (k,) float64, optional
            Without ``amplitudes``: the estimated amplitude on the isolated sensor of
            each row (the status' ``amplitude``), the same as ``amplitudes`` holding it
            on the column of ``isolated`` and NaN elsewhere (what a single-isolation
            detector records), without making that (k, n) array
        best_score : (k,) int64, optional
            In place of ``scores``: the column of each row's first largest finite score,
            -1 where none is finite (:func:`imufdi_cli.sweep.best_columns`), all the
            sweeps read of the scores
        scored : (k,) bool, optional
            The rows scored (default: all). The others (samples ``detect`` excluded as
            clipped or invalid, rows outside ``report --start/--end``) count in no figure,
            but are part of the alarm episodes: an episode is counted where it starts.
        """
        t_ns = np.asarray(t_ns, dtype=np.int64)
        k = int(t_ns.size)
        if k == 0:
            return
        alarm = np.asarray(alarm, dtype=bool)
        isolated = np.asarray(isolated, dtype=np.int64)
        decided = t_ns if decided_ns is None else np.asarray(decided_ns, dtype=np.int64)
        n_s = self.n_sensors
        if faulty is None:
            faulty = faulty_matrix(t_ns, self.windows, n_s)
        else:
            faulty = np.asarray(faulty, dtype=bool).reshape(k, n_s)
        any_fault = np.asarray(faulty.any(axis=1), dtype=bool)
        if self.calibration_ns is not None:
            in_cal = (t_ns >= self.calibration_ns[0]) & (t_ns < self.calibration_ns[1])
        else:
            in_cal = np.zeros(k, dtype=bool)
        keep = np.ones(k, bool) if scored is None else np.asarray(scored, bool)
        sweeping = self.sweep is not None and statistic is not None and threshold is not None
        bins = judged = column = None
        if sweeping:
            from imufdi_cli.sweep import ratio_bins

            bins = ratio_bins(statistic, threshold)  # type: ignore[arg-type]
            judged, column = judged_isolation(isolated, scores, n_s, best_score)
        eligible = keep & ~any_fault & ~in_cal
        if self.episodes is not None:
            self.episodes.update(alarm, isolated, eligible)
        if self.budget is not None and bins is not None:
            assert self.fault_runs is not None
            in_fault_run = self.fault_runs.update(alarm, any_fault)
            self._budget_levels(bins, np.where(judged, column, -1), eligible & ~in_fault_run)  # type: ignore[arg-type]
        if not keep.all():
            rows = np.flatnonzero(keep)
            k = int(rows.size)
            if k == 0:
                return
            t_ns, alarm, isolated, decided = t_ns[rows], alarm[rows], isolated[rows], decided[rows]
            faulty, any_fault, in_cal = faulty[rows], any_fault[rows], in_cal[rows]
            if isolated_set is not None:
                isolated_set = np.asarray(isolated_set, dtype=bool).reshape(-1, n_s)[rows]
            if amplitudes is not None:
                amplitudes = np.asarray(amplitudes, dtype=np.float64).reshape(-1, n_s)[rows]
            elif amplitude is not None:
                amplitude = np.asarray(amplitude, dtype=np.float64).reshape(-1)[rows]
            if bins is not None:
                bins, judged, column = bins[rows], judged[rows], column[rows]  # type: ignore[index]
        evaluated = ~in_cal
        free = ~any_fault & evaluated
        free_cal = ~any_fault & in_cal
        faulty_eval = any_fault & evaluated

        if self.t_first is None:
            self.t_first = int(t_ns[0])
        self.t_last = int(t_ns[-1])
        self.period.add(t_ns)
        self.n += k
        self.n_cal += int(np.count_nonzero(in_cal))
        self.n_eval += int(np.count_nonzero(evaluated))
        self.n_free += int(np.count_nonzero(free))
        self.n_free_cal += int(np.count_nonzero(free_cal))
        self.false_alarms += int(np.count_nonzero(alarm & free))
        self.false_alarms_cal += int(np.count_nonzero(alarm & free_cal))
        self.n_faulty += int(np.count_nonzero(faulty_eval))
        self.missed += int(np.count_nonzero(faulty_eval & ~alarm))
        detected = faulty_eval & alarm
        self.detected += int(np.count_nonzero(detected))
        self.alarms_eval += int(np.count_nonzero(alarm & evaluated))
        self.latency_sum += float(np.sum(decided[evaluated] - t_ns[evaluated])) / NS_PER_S

        has_iso = isolated >= 0
        iso_column = np.clip(np.where(has_iso, isolated, 0), 0, max(n_s - 1, 0))
        rows = np.arange(k)
        correct = has_iso & faulty[rows, iso_column] if n_s else np.zeros(k, dtype=bool)
        self.false_iso += int(np.count_nonzero(detected & has_iso & ~correct))
        self.unisolated += int(np.count_nonzero(detected & ~has_iso))

        previous = np.concatenate([[self.previous_alarm], alarm[:-1]])
        rising = alarm & ~previous & evaluated
        self.events += int(np.count_nonzero(rising))
        self.false_events += int(np.count_nonzero(rising & ~any_fault))
        self.previous_alarm = bool(alarm[-1])

        if isolated_set is None:
            iso_set = np.zeros((k, n_s), dtype=bool)
            iso_set[rows[has_iso], isolated[has_iso]] = True
        else:
            iso_set = np.asarray(isolated_set, dtype=bool).reshape(k, n_s)
        in_faults = [self._update_fault(st, t_ns, decided, alarm, iso_set) for st in self.states]
        if amplitudes is not None or amplitude is not None:
            if amplitudes is not None:
                values = np.asarray(amplitudes, dtype=np.float64).reshape(k, n_s)
            else:
                one = np.asarray(amplitude, dtype=np.float64).reshape(k)
            for st, inside in zip(self.states, in_faults):
                for sensor, track in st.amplitudes.items():
                    if amplitudes is not None:
                        estimate = values[:, sensor]
                    else:
                        estimate = np.where(isolated == sensor, one, np.nan)
                    use = inside & alarm & iso_set[:, sensor] & np.isfinite(estimate)
                    t_s = (t_ns[use] - st.window.start_ns).astype(np.float64) * 1e-9
                    track.add(t_s, estimate[use])

        if sweeping and self.sweep is not None:
            assert bins is not None and judged is not None and column is not None
            right = judged & faulty[rows, column] if n_s else np.zeros(k, dtype=bool)
            iso_class = np.zeros(k, dtype=np.int8)
            iso_class[faulty_eval & right] = 1
            iso_class[faulty_eval & judged & ~right] = 2
            iso_class[faulty_eval & ~judged] = 3
            isolated_to = [
                inside & judged & _among(column, st.window.sensors)
                for st, inside in zip(self.states, in_faults)
            ]
            self.sweep.update(bins, decided, free, iso_class, in_faults, isolated_to)

    def _budget_levels(self, bins: np.ndarray, isolated: np.ndarray, eligible: np.ndarray) -> None:
        """The alarm episodes of these rows at every level of the matched budget: only the
        rows above the lowest level take part (the others alarm at none)."""
        from imufdi_cli.sweep import BUDGET_LEVELS

        assert self.budget is not None
        rows = np.flatnonzero(bins > BUDGET_LEVELS[0])
        level, column = np.nonzero(bins[rows][None, :] > BUDGET_LEVELS[:, None])
        # columns index the candidate rows: map them back to rows of the block
        self.budget.update_sparse(level, rows[column], isolated, eligible, int(bins.size))

    def _update_fault(
        self,
        st: _FaultState,
        t_ns: np.ndarray,
        decided: np.ndarray,
        alarm: np.ndarray,
        iso_set: np.ndarray,
    ) -> np.ndarray:
        w = st.window
        inside = t_ns >= w.start_ns
        if w.end_ns is not None:
            inside &= t_ns < w.end_ns
        idx = np.flatnonzero(inside)
        if idx.size:
            st.samples += int(idx.size)
            on = alarm[idx]
            hit = iso_set[np.ix_(idx, np.asarray(w.sensors, dtype=np.intp))].any(axis=1) & on
            st.alarmed += int(np.count_nonzero(on))
            st.isolated_ok += int(np.count_nonzero(hit))
            if st.isolated_ns is None and hit.any():
                st.isolated_ns = int(decided[idx[np.argmax(hit)]])
            if not st.first_alarm and on.any():
                st.first_alarm = True
                first = int(np.argmax(on))
                st.after_first += int(idx.size - first)
                st.alarmed_after_first += int(np.count_nonzero(on[first:]))
            elif st.first_alarm:
                st.after_first += int(idx.size)
                st.alarmed_after_first += int(np.count_nonzero(on))
            if st.detected_ns is None:
                # run length ending at each row, carried over from the previous rows: the
                # first row where it reaches persist detects the fault
                runs = _run_lengths(on, st.run)
                reached = np.flatnonzero(runs >= self.persist)
                if reached.size:
                    j = int(reached[0])
                    st.detected_ns = int(decided[idx[j]])
                    st.run = int(runs[j])
                else:
                    st.run = int(runs[-1])
        if w.end_ns is not None and st.recovered_ns is None:
            after = t_ns >= w.end_ns
            if st.episode_end_ns is not None:
                after &= t_ns < st.episode_end_ns
            rows = np.flatnonzero(after)
            if rows.size:
                self._update_recovery(st, t_ns[rows], decided[rows], alarm[rows])
        return inside

    def _update_recovery(
        self, st: _FaultState, t_ns: np.ndarray, decided: np.ndarray, alarm: np.ndarray
    ) -> None:
        """Recovery bookkeeping on rows of the fault's recovery episode (module docstring):
        a candidate quiet sample r is confirmed when an alarm comes back more than
        ``merge_gap_s`` after it with at least ``persist`` quiet samples in between, or when
        the episode ends quiet after at least ``persist`` samples."""
        size = int(t_ns.size)
        alarms = np.flatnonzero(alarm)
        first = int(alarms[0]) if alarms.size else size
        if first > 0:  # the quiet rows before the first alarm continue the carried run
            if st.quiet_from_ns is None:
                st.quiet_from_ns = int(decided[0])
                st.quiet_from_t = int(t_ns[0])
                st.quiet = 0
            st.quiet += first
        if first == size:
            return
        if (
            st.quiet_from_t is not None
            and st.quiet >= self.persist
            and t_ns[first] - st.quiet_from_t > self.merge_gap_ns
        ):
            st.recovered_ns = st.quiet_from_ns  # the alarm is a new episode
            return
        # each later alarm: the quiet run before it starts right after the alarm before
        # it (a candidate only when it holds persist rows: persist >= 1)
        start = alarms[:-1] + 1
        quiet = alarms[1:] - start
        new = (quiet >= self.persist) & (t_ns[alarms[1:]] - t_ns[start] > self.merge_gap_ns)
        hit = np.flatnonzero(new)
        if hit.size:
            i = int(hit[0])
            st.quiet_from_ns = st.recovered_ns = int(decided[start[i]])
            st.quiet_from_t = int(t_ns[start[i]])
            st.quiet = int(quiet[i])
            return
        last = int(alarms[-1])
        st.quiet_from_ns = st.quiet_from_t = None
        st.quiet = 0
        if last + 1 < size:  # quiet rows after the last alarm: a run carried on
            st.quiet_from_ns = int(decided[last + 1])
            st.quiet_from_t = int(t_ns[last + 1])
            st.quiet = size - last - 1

    def result(self) -> Metrics:
        """The figures of every row fed so far."""
        n = self.n
        far = _ratio(self.false_alarms, self.n_free)
        mar = _ratio(self.missed, self.n_faulty)
        fir = _ratio(self.false_iso, self.detected)
        accuracy = None if far is None or mar is None else 1.0 - far - mar
        duration_s = 0.0
        if n > 1 and self.t_first is not None:
            span = float(self.t_last - self.t_first) / NS_PER_S
            duration_s = span * n / (n - 1)  # count the last sample's period too
        period_s = self.period.seconds
        free_hours = fault_free_tested_hours(self.n_free, period_s)
        figures: list[FaultFigures] = []
        delays: list[float] = []
        isolations: list[float] = []
        recoveries: list[float] = []
        after_first = 0
        alarmed_after_first = 0
        for st in self.states:
            w = st.window
            delay = None if st.detected_ns is None else (st.detected_ns - w.start_ns) / NS_PER_S
            iso_delay = None if st.isolated_ns is None else (st.isolated_ns - w.start_ns) / NS_PER_S
            recovered = st.recovered_ns
            if recovered is None and st.quiet_from_ns is not None and st.quiet >= self.persist:
                recovered = st.quiet_from_ns  # quiet to the end of the episode
            recovery = None
            if w.end_ns is not None and delay is not None and recovered is not None:
                recovery = (recovered - w.end_ns) / NS_PER_S
            figures.append(
                FaultFigures(
                    fault_id=w.fault_id,
                    detected=delay is not None,
                    detection_delay_s=delay,
                    isolation_delay_s=iso_delay,
                    recovery_delay_s=recovery,
                    isolated_correctly=_ratio(st.isolated_ok, st.alarmed),
                    faulty_samples=st.samples,
                    rate_after_first_detection=_ratio(st.alarmed_after_first, st.after_first),
                    amplitudes=self._amplitude_figures(st),
                )
            )
            after_first += st.after_first
            alarmed_after_first += st.alarmed_after_first
            for value, bucket in ((delay, delays), (iso_delay, isolations), (recovery, recoveries)):
                if value is not None:
                    bucket.append(value)
        return Metrics(
            samples=n,
            fault_free_samples=self.n_free,
            faulty_samples=self.n_faulty,
            false_alarms=self.false_alarms,
            missed=self.missed,
            detected_faulty=self.detected,
            false_isolations=self.false_iso,
            unisolated=self.unisolated,
            far=far,
            mar=mar,
            accuracy=None if self.n_faulty == 0 else accuracy,
            fir=fir,
            isolation_accuracy=None if fir is None else 1.0 - fir,
            detection_delay_s=float(np.mean(delays)) if delays else None,
            recovery_delay_s=float(np.mean(recoveries)) if recoveries else None,
            alarm_rate=_ratio(self.alarms_eval, self.n_eval),
            alarm_events=self.events,
            false_alarm_events_per_hour=(self.false_events / free_hours)
            if free_hours > 0
            else None,
            duration_s=duration_s,
            faults=figures,
            calibration_samples=self.n_cal,
            far_calibration=_ratio(self.false_alarms_cal, self.n_free_cal),
            isolation_delay_s=float(np.mean(isolations)) if isolations else None,
            decision_latency_s=(self.latency_sum / self.n_eval) if self.n_eval else None,
            rate_after_first_detection=_ratio(alarmed_after_first, after_first),
            fault_free_hours=free_hours,
            sample_period_s=period_s,
            **self._episode_figures(free_hours),
        )

    def _episode_figures(self, hours: float) -> dict[str, Any]:
        """False alarm episodes, their rate per hour of ``hours`` with its exact Poisson
        95 % upper bound, and the mean time between them with its lower bound."""
        if self.episodes is None:
            return {}
        count = int(self.episodes.finished().false_episodes[0])
        return {"false_episodes": count, **episode_rate(count, hours)}

    def budget_curve(self) -> Any:
        """The :class:`~imufdi_cli.sweep.BudgetCurve` of the rows fed so far (None without
        the sweep or the joining rule's gaps)."""
        from imufdi_cli.sweep import BUDGET_FIGURES, BUDGET_LEVELS, BudgetCurve

        if self.budget is None or self.sweep is None or not self.sweep.sweepable:
            return None
        curve = self.sweep.curve()
        hours = fault_free_tested_hours(self.n_free, self.period.seconds)
        figures = {name: np.asarray(curve[name])[BUDGET_LEVELS] for name in BUDGET_FIGURES}
        return BudgetCurve(hours, self.budget.finished().false_episodes, figures)

    def matched_budget(self, metrics: Metrics, target_per_hour: float) -> str | None:
        """Fill the ``*_at_budget`` figures of ``metrics`` at ``target_per_hour`` false
        episodes per hour; returns a note (why they are undefined, or where the match
        sits) or None."""
        from imufdi_cli.sweep import match_budget

        metrics.target_budget_per_hour = target_per_hour
        curve = self.budget_curve()
        if curve is None:
            return "matched budget: no sweepable statistic or no sample rate"
        match = match_budget(curve.false_episodes, curve.hours, target_per_hour)
        apply_budget_match(metrics, curve, match)
        return match.note

    def _amplitude_figures(self, st: _FaultState) -> list[AmplitudeFigure]:
        """One :class:`AmplitudeFigure` per faulty sensor with estimated amplitudes."""
        w = st.window
        figures = []
        for sensor, track in st.amplitudes.items():
            if track.count == 0:
                continue
            size_name = "rate" if w.model == "drift" else "amp"
            estimate = track.slope() if size_name == "rate" else track.median()
            if estimate is None:
                continue
            true = w.size if w.model in ("step", "drift") else None
            name = self.sensor_ids[sensor] if self.sensor_ids is not None else str(sensor)
            figures.append(
                AmplitudeFigure(
                    sensor=name,
                    size_name=size_name,
                    estimate=estimate,
                    true=true,
                    ratio=estimate / true if true else None,
                    samples=track.count,
                )
            )
        return figures

    def matched(self, metrics: Metrics, target_far: float) -> str | None:
        """Fill the ``*_at_far`` figures of ``metrics`` at ``target_far``; returns a note
        (why a figure is undefined, or where the match sits) or None."""
        if self.sweep is None:
            return "matched FAR: no sweep data"
        match = self.sweep.match(target_far)
        metrics.target_far = target_far
        metrics.mar_at_far = match.mar
        metrics.fir_at_far = match.fir
        metrics.detection_delay_at_far_s = match.detection_delay_s
        metrics.threshold_scale_at_far = match.threshold_scale
        return match.note


def compute_metrics(
    t_ns: np.ndarray,
    alarm: np.ndarray,
    isolated: np.ndarray,
    faulty: np.ndarray | None = None,
    faults: Sequence[FaultWindow] = (),
    *,
    persist: int = 1,
    isolated_set: np.ndarray | None = None,
    decided_ns: np.ndarray | None = None,
    calibration_ns: tuple[int, int] | None = None,
    statistic: np.ndarray | None = None,
    threshold: np.ndarray | None = None,
    scores: np.ndarray | None = None,
    match_far: float | None = None,
    n_sensors: int | None = None,
    amplitudes: np.ndarray | None = None,
    episode_gaps: tuple[int, int] | None = None,
    match_budget: float | None = None,
) -> Metrics:
    """Per-sample metrics of one detector on one sensor type, in one call.

    Parameters
    ----------
    t_ns : ndarray, shape (N,), int64
        Sample timestamps, ns.
    alarm : ndarray, shape (N,), bool
        Detector alarm per sample.
    isolated : ndarray, shape (N,), int
        Isolated sensor index per sample (negative: none / not isolable).
    faulty : ndarray, shape (N, n_s), bool, optional
        Ground truth: sensor j has an active fault at sample i (default: from ``faults``,
        see :func:`faulty_matrix`, with ``n_sensors`` columns).
    faults : sequence of FaultWindow
        The faults of this sensor type.
    persist : int
        See :class:`MetricsAccumulator`.
    isolated_set : ndarray, shape (N, n_s), bool, optional
        Every sensor the detector isolated at each sample.
    decided_ns : ndarray, shape (N,), int64, optional
        Decision times (default: the sample times).
    calibration_ns : (start_ns, end_ns), optional
        Calibration window, excluded from the figures.
    statistic, threshold, scores : optional
        For the matched-FAR sweep (``match_far``).
    match_far : float, optional
        Target FAR for the ``*_at_far`` figures.
    amplitudes : ndarray, shape (N, n_s), float64, optional
        Estimated amplitude of every sensor (per-fault :class:`AmplitudeFigure`).
    episode_gaps : (merge_gap, join_gap), optional
        The episodes' joining rule in rows, for the false alarm episodes.
    match_budget : float, optional
        Target false episodes per hour for the ``*_at_budget`` figures (needs
        ``episode_gaps``, ``statistic`` and ``threshold``).

    Returns
    -------
    Metrics
    """
    if n_sensors is None:
        if faulty is None:
            raise ValueError("give faulty or n_sensors")
        n_sensors = int(np.asarray(faulty).reshape(len(t_ns), -1).shape[1])
    acc = MetricsAccumulator(
        n_sensors,
        faults,
        calibration_ns=calibration_ns,
        persist=persist,
        sweep=True,
        episode_gaps=episode_gaps,
    )
    acc.update(
        t_ns,
        alarm,
        isolated,
        decided_ns=decided_ns,
        isolated_set=isolated_set,
        statistic=statistic,
        threshold=threshold,
        scores=scores,
        faulty=faulty,
        amplitudes=amplitudes,
    )
    metrics = acc.result()
    if match_far is not None:
        acc.matched(metrics, match_far)
    if match_budget is not None:
        acc.matched_budget(metrics, match_budget)
    return metrics
