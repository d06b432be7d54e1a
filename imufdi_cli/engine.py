"""The detection core: one streaming pass of detectors over aligned samples.

``imufdi detect``, campaigns and the Python API run detectors through :class:`Engine`, so
that a campaign run scores exactly what ``inject | detect | report`` scores:

1. **Conditioning** (:class:`~imufdi_cli.validity.Conditioner`): the calibration mapping
   of ``detect --array``, clipped and invalid samples flagged and replaced by the
   consensus of the valid sensors (or the row held);
2. **calibration window**: its samples are collected (and the tested samples after them
   held back) until the window ends; the conditioner and every detector are fitted on it
   and the held-back samples are then tested;
3. **decisions**: each block through each detector; each output row stamped with its
   sample time and its decision time (the sample at whose arrival the decision is
   available, look-ahead counted: :func:`decision_positions`);
4. **episodes**, when explanations are asked for: the rows go through an episode builder
   per sensor type (:mod:`imufdi_cli.episodes`), which explains each closed episode;
5. **sinks**: the rows and episodes go to a :class:`Sink`: the annotated MCAP for
   ``detect`` (:mod:`imufdi_cli.detect`), in-memory scoring for campaigns
   (:mod:`imufdi_cli.campaign.run`, with the report's scoring code).

Memory is bounded by the block size and the calibration window, not by the log length.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import DetectionBlock, Detector
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock
from imufdi_cli.validity import Conditioner

if TYPE_CHECKING:
    from imufdi_cli.episodes import EpisodeBuilder

NS_PER_S = 1_000_000_000
DEFAULT_CALIBRATION = (0.0, 2.0)
#: Per sensor type, (clipped, invalid) masks of shape (N, m, 3) (imufdi_cli.validity).
Flags = dict[str, tuple[np.ndarray, np.ndarray]]


def with_budget(
    detectors: Iterable[tuple[str, Mapping[str, Any]]], false_alarms: float | None
) -> list[tuple[str, dict[str, Any]]]:
    """Detector specs with the false-alarm budget ``false_alarms`` (episodes per second) set
    on every detector that does not set its own ``false_alarms`` parameter.

    Raises DetectorConfigError for a negative budget or a detector that cannot decide
    under one."""
    from imufdi_cli.detectors import detector_class

    specs = [(name, dict(params)) for name, params in detectors]
    if false_alarms is None:
        return specs
    if not (false_alarms >= 0 and np.isfinite(false_alarms)):
        raise DetectorConfigError(
            f"--false-alarms must be a rate >= 0 such as 1/h, got {false_alarms!r}"
        )
    for name, params in specs:
        if "false_alarms" not in detector_class(name).PARAMS:
            raise DetectorConfigError(
                f"detector {name!r} has no false-alarm budget (its parameters:"
                f" {', '.join(sorted(detector_class(name).PARAMS))})"
            )
        params.setdefault("false_alarms", false_alarms)
    return specs


#: Above this many expected false alarm episodes an hour on a channel, detect warns.
NOISY_EPISODES_PER_HOUR = 60.0


def level_warning(detector: Any, rate_hz: float) -> str | None:
    """A one-line warning when a detector's settings should raise more than
    :data:`NOISY_EPISODES_PER_HOUR` false alarm episodes an hour on each of its channels
    of a fault-free log at ``rate_hz`` (the per-sample tests at their ``alpha``: about
    ``alpha^persistence`` of the samples start one), naming ``--false-alarms``; None when
    it should not, or when the detector's rate cannot be told from its settings."""
    budget = float(getattr(detector, "false_alarms", 0.0) or 0.0)
    alpha = getattr(detector, "alpha", None)
    if budget > 0 or alpha is None or not rate_hz > 0:
        return None
    persistence = max(1, int(getattr(detector, "persistence", 1) or 1))
    per_hour = float(alpha) ** persistence * rate_hz * 3600.0
    if per_hour <= NOISY_EPISODES_PER_HOUR:
        return None
    return (
        f"{detector.name}: the per-sample test at alpha={float(alpha):g} should raise about"
        f" {per_hour:,.0f} false alarm episodes an hour on each channel at {rate_hz:g} Hz;"
        " for recorded data and CI give a budget, e.g. --false-alarms 1/h (docs/guide.md)"
    )


def lookahead_of(detector: Any) -> int | None:
    """A detector's declared ``lookahead_samples`` (None when it declares none)."""
    value = getattr(detector, "lookahead_samples", None)
    return None if value is None else int(value)


def decision_positions(first_row: int, rows: int, passed: int, lookahead: int | None) -> np.ndarray:
    """Index of the input sample at whose arrival each output row's decision is available.

    Rows ``first_row .. first_row + rows - 1`` were returned by a ``process``/``flush``
    call after ``passed`` input samples had been passed to the detector. The decision on
    row i is available at the newest passed sample (index ``passed - 1``) — and, since the
    detector declares that it never waits for more than ``lookahead`` later samples, no
    later than sample ``i + lookahead``. The decision time is the timestamp of
    ``min(i + lookahead, passed - 1)``: the sample time for a causal detector whatever the
    block size, and a block-size independent bound for one that looks ahead. A detector
    that declares no look-ahead (``None``) is charged the newest passed sample.

    Returns
    -------
    ndarray, shape (rows,), int64
    """
    index = np.arange(first_row, first_row + rows, dtype=np.int64)
    newest = np.full(rows, passed - 1, dtype=np.int64)
    if lookahead is None:
        return newest
    return np.minimum(index + int(lookahead), newest)


def calibration_window_ns(
    t_first: int | None, t_last: int, start_s: float, end_s: float | None
) -> list[int] | None:
    """The calibration window as absolute ``[start_ns, end_ns)`` (None for an empty log).

    A sample at time t was in the window when ``start_ns <= t < end_ns``; an open end
    (``end_s`` None) ends after the last sample.
    """
    if t_first is None:
        return None
    start = t_first + round(start_s * NS_PER_S)
    end = t_last + 1 if end_s is None else t_first + round(end_s * NS_PER_S)
    return [start, end]


class Track:
    """One detector in the pass: the timestamps of the samples passed to it whose rows it
    has not returned yet, and its episode builders (sensor type -> builder)."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector
        self.name = detector.name
        self.lookahead = lookahead_of(detector)
        self.pending: deque[np.ndarray] = deque()
        self.passed = 0  # input samples passed to the detector
        self.emitted = 0  # rows returned by it
        self.episodes: dict[str, EpisodeBuilder] = {}

    def feed(self, t_ns: np.ndarray) -> None:
        """Record the timestamps of a block about to be passed to the detector."""
        self.pending.append(t_ns)
        self.passed += int(t_ns.size)

    def take_times(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Sample times and decision times (ns) of the next ``count`` rows, in order."""
        if count > self.passed - self.emitted:
            raise DetectorConfigError(
                f"detector {self.detector.name} returned {count} rows for"
                f" {self.passed - self.emitted} samples not yet reported"
            )
        positions = decision_positions(self.emitted, count, self.passed, self.lookahead)
        # every position lies in [emitted, passed): the pending timestamps hold them
        held = np.concatenate(list(self.pending)) if self.pending else np.zeros(0, np.int64)
        decided = held[positions - self.emitted] if count else np.zeros(0, np.int64)
        times = held[:count]
        rest = held[count:]
        self.pending.clear()
        if rest.size:
            self.pending.append(rest)
        self.emitted += count
        return times, decided


class Sink(Protocol):
    """Where the engine's output goes, in order: each detector's rows of each sensor type
    as it returns them, and the episodes that closed within them."""

    def rows(
        self,
        track: Track,
        sensor_type: str,
        t_ns: np.ndarray,
        decided_ns: np.ndarray,
        out: DetectionBlock,
    ) -> None:
        """Rows of one sensor type: sample times, decision times (ns, (k,)) and the
        detector's output (k rows)."""

    def episodes(self, track: Track, episodes: Sequence[Any]) -> None:
        """Explained episodes (:class:`~imufdi_cli.episodes.Episode`) that closed."""


class Engine:
    """One streaming detection pass (module docstring).

    Feed the aligned blocks in time order with :meth:`add_block`, then call
    :meth:`finish`.

    Parameters
    ----------
    detectors : sequence of Detector
        Constructed, not fitted.
    array : ArrayConfig
        The array to test with.
    conditioner : Conditioner
        Calibration mapping and validity flags (its counts are what ``detect`` records).
    sink : Sink
    calibrate : (start_s, end_s or None)
        Calibration window, seconds from the first sample (an open end: the whole log).
    window : (start_s, end_s or None)
        Samples tested, seconds from the first sample (the others get no row).
    explain : bool
        Build and explain episodes (:mod:`imufdi_cli.episodes`).
    copy : bool
        Copy the blocks held back until the calibration window ends (a reader may reuse
        its buffers); False when the caller's blocks are never modified (a campaign run's
        log in memory).
    imu_topics : sequence of str, optional
        The IMUs' topics, to name an IMU missing from the calibration window.
    """

    def __init__(
        self,
        detectors: Sequence[Detector],
        array: ArrayConfig,
        conditioner: Conditioner,
        sink: Sink,
        *,
        calibrate: tuple[float, float | None] = DEFAULT_CALIBRATION,
        window: tuple[float, float | None] = (0.0, None),
        explain: bool = False,
        copy: bool = True,
        imu_topics: Sequence[str] | None = None,
    ) -> None:
        self.array = array
        self.copy = copy
        self.imu_topics = list(imu_topics or [])
        self.conditioner = conditioner
        self.sink = sink
        self.cal_start_s, self.cal_end_s = calibrate
        self.test_start_s, self.test_end_s = window
        self.explain = explain
        self.tracks = [Track(det) for det in detectors]
        self.warnings: list[str] = []
        self.n_samples = 0  # tested samples
        self.t_first: int | None = None
        self.t_last = 0
        self.calibration: list[tuple[ImuBlock, Flags]] = []
        self.backlog: list[tuple[ImuBlock, Flags]] = []
        self.fitted = False
        self.cal_samples = 0

    def calibration_window(self) -> list[int] | None:
        """The calibration window, absolute ``[start_ns, end_ns)`` (None before a sample)."""
        return calibration_window_ns(self.t_first, self.t_last, self.cal_start_s, self.cal_end_s)

    def add_block(self, block: ImuBlock) -> None:
        """An aligned block: into the calibration window and backlog until the detectors
        are fitted, then straight through them."""
        if self.t_first is None:
            from imufdi_cli.units import window_from_log_start

            self.t_first = int(block.t_ns[0])
            # ISO 8601 / Unix times of --start/--end, now that the log start is known
            self.test_start_s, self.test_end_s = window_from_log_start(
                (self.test_start_s, self.test_end_s), self.t_first
            )
        self.t_last = int(block.t_ns[-1])
        block, flags = self.conditioner.prepare(block)
        rel = (block.t_ns - self.t_first) / NS_PER_S
        tested = rel >= self.test_start_s
        if self.test_end_s is not None:
            tested &= rel < self.test_end_s
        test_block, test_flags = block, flags
        if not tested.all():
            test_block, test_flags = block.mask(tested), _mask_flags(flags, tested)
        self.n_samples += len(test_block)
        if self.fitted:
            if len(test_block):
                self._process(test_block, test_flags)
            return
        cal_window = self.calibration_window()
        assert cal_window is not None
        inside = block.t_ns >= cal_window[0]
        if self.cal_end_s is not None:
            inside &= block.t_ns < cal_window[1]
        if inside.any():  # (a boolean mask makes new arrays: nothing to copy)
            self.calibration.append((block.mask(inside), _mask_flags(flags, inside)))
        if len(test_block):
            self.backlog.append((test_block.copy() if self.copy else test_block, test_flags))
        if self.cal_end_s is not None and block.t_ns[-1] >= cal_window[1]:
            self._fit()

    def _process(self, block: ImuBlock, flags: Flags) -> None:
        block = self.conditioner.sanitize(block, flags)
        for track in self.tracks:
            track.feed(block.t_ns)
            note_flags = getattr(track.detector, "note_flags", None)
            if note_flags is not None:  # a detector that tests flagged samples itself
                note_flags(flags)
            for sensor_type, builder in track.episodes.items():
                triads = block.get(sensor_type)
                assert triads is not None  # builders exist only for types in the log
                builder.feed(self.array.select(triads, sensor_type))
            self._emit(track, track.detector.process(block))

    def _fit(self) -> None:
        whole = ImuBlock.concatenate(b for b, _ in self.calibration)
        whole_flags = _concat_flags([f for _, f in self.calibration])
        if whole.missing is not None:  # an IMU without samples in the window
            from imufdi_cli.validity import complete_rows

            cal = (self.cal_start_s, self.cal_end_s)
            names = self.imu_topics or [f"imu{k}" for k in range(whole.n_imus)]
            whole, whole_flags, kept = complete_rows(whole, whole_flags, names, cal)
            self.warnings.append(kept)
        self.cal_samples = len(whole)
        if self.cal_samples == 0:
            end = "" if self.cal_end_s is None else f"{self.cal_end_s:g}s"
            raise CalibrationError(
                f"calibration window {self.cal_start_s:g}s:{end}"
                " holds no samples; choose one inside the log with --calibrate START:END"
            )
        self.conditioner.fit(whole, whole_flags)
        whole = self.conditioner.sanitize(whole, whole_flags, count=False)
        for track in self.tracks:
            track.detector.fit(whole, self.array)
            note = level_warning(track.detector, self.array.rate_hz)
            if note is not None:
                self.warnings.append(note)
        builders: dict[str, EpisodeBuilder] = {}
        if self.explain:
            # imported when used: --no-explain runs do not load (or compile) it
            from imufdi_cli.episodes import episode_builders

            builders = episode_builders(whole, self.array)
        for track in self.tracks:
            # a per-sample test's one-sample episodes (chance alarms, most of them) may be
            # explained by their sample alone; under a false-alarm budget all are fitted
            budgeted = float(getattr(track.detector, "false_alarms", 0.0) or 0.0) > 0
            track.episodes = {
                t: b.for_detector(track.detector.name, sample_explanations=not budgeted)
                for t, b in builders.items()
            }
        self.fitted = True
        self.calibration.clear()
        for pending, pending_flags in self.backlog:
            self._process(pending, pending_flags)
        self.backlog.clear()

    def _emit(self, track: Track, outputs: Mapping[str, DetectionBlock]) -> None:
        """Rows (with their times) and the episodes that closed in them, to the sink."""
        rows = {len(v) for v in outputs.values()}
        if not rows:
            return
        if len(rows) != 1:
            raise DetectorConfigError(
                f"detector {track.detector.name} returned blocks of different lengths"
            )
        t_ns, decided_ns = track.take_times(rows.pop())
        if t_ns.size == 0:
            return
        for sensor_type, out in outputs.items():
            self.sink.rows(track, sensor_type, t_ns, decided_ns, out)
            builder = track.episodes.get(sensor_type)
            if builder is not None:
                self._episodes(track, builder.rows(t_ns, decided_ns, out))
        for sensor_type in set(track.episodes) - set(outputs):
            del track.episodes[sensor_type]  # a type this detector does not test

    def _episodes(self, track: Track, episodes: Sequence[Any]) -> None:
        if not episodes:
            return
        explain = getattr(track.detector, "explain_episode", None)
        if explain is not None:  # a detector that knows what raised its episodes
            for episode in episodes:
                if episode.detector == track.detector.name:
                    episode.fits = explain(episode)
        self.sink.episodes(track, episodes)

    def finish(self, strict: bool = False) -> None:
        """Fit if the log ended inside the calibration window, flush the detectors and the
        episode builders, and judge each detector's calibration (``strict``: a problem is
        a CalibrationError)."""
        if not self.fitted:
            if self.t_first is not None and self.cal_end_s is not None:
                self.warnings.append(
                    f"the log ({(self.t_last - self.t_first) / NS_PER_S:.3g} s) is shorter"
                    f" than the calibration window end ({self.cal_end_s:g} s); calibrated on"
                    " what there is"
                )
            self._fit()
        for track in self.tracks:
            self._emit(track, track.detector.flush())
            for builder in track.episodes.values():
                self._episodes(track, builder.finish())
            if track.pending and sum(p.size for p in track.pending):
                raise DetectorConfigError(
                    f"detector {track.detector.name} left samples without output"
                )
        for track in self.tracks:
            # A detector may judge its calibration window from what it processed (e.g.
            # pca-parity: motion beyond the calibrated range); --strict makes that fatal.
            judge = getattr(track.detector, "calibration_warnings", None)
            found = list(judge()) if judge is not None else []
            if strict and found:
                raise CalibrationError(f"{found[0]} (--strict)")
            self.warnings.extend(found)


def _mask_flags(flags: Flags, keep: np.ndarray) -> Flags:
    return {s: (c[keep], i[keep]) for s, (c, i) in flags.items()}


def _concat_flags(parts: Sequence[Flags]) -> Flags:
    if not parts:
        return {}
    return {
        s: (
            np.concatenate([p[s][0] for p in parts]),
            np.concatenate([p[s][1] for p in parts]),
        )
        for s in parts[0]
    }
