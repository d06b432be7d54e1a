"""Checks that need no redundancy: every sensor axis tested alone (docs/algorithms/health.md).

A one-IMU log (the commonest ROS robot) has no second sensor to compare with, so the parity
detectors cannot test it. What can still be seen on one axis, from its own output and the
calibration window:

* **stuck**: the output repeats the same value (a frozen register, a dead bus answering
  the last sample). ``r_t`` counts consecutive exact repeats; the axis alarms once
  ``r_t >= R``. If a healthy sample repeats its predecessor with probability ``p``
  (quantisation; 0 for a continuous output), a run of ``R`` repeats starts at most
  ``p^R`` times per sample, so ``R = ceil(ln(level) / ln(p))``. ``p`` is the larger of
  the calibration's repeat fraction and its repeat-after-repeat fraction (runs of a coarse
  quantiser are longer than independent repeats), each taken at its one-sided 95 % upper
  Poisson bound.
* **variance drop** and **variance growth**: the first difference
  ``z_t = (x_t - x_{t-1}) / (sqrt(2) sigma_d)`` (slow motion cancels; ``sigma_d^2`` is the
  calibration's mean of ``(x_t - x_{t-1})^2 / 2``) feeds two capped Page CUSUMs on the
  log-likelihood ratio of a variance change by the design ratios ``K = drop_factor^2``
  (0.1) and ``K = growth_factor^2`` (9) (:mod:`imufdi_cli.detectors.cusum`, Page 1954;
  Basseville & Nikiforov 1993, §2.2, with ``l_t = 1/2 (1 - 1/K) z_t^2 - 1/2 ln K``).
  Their thresholds are found by simulating the null, the larger of two: white Gaussian z
  (:func:`~imufdi_cli.detectors.cusum.cusum_threshold`) and z drawn from the
  calibration's own differences (:func:`_bootstrap_h`: a quantised or heavy-tailed
  output), both with the calibration's estimation error.
* **spikes**: ``|z_t| > Phi^-1(1 - level / 2)``.
* **clipping** and **dropouts**: samples the input conditioning flags as clipped (at the
  array's ``range``) or invalid (NaN, impossible values), and **gaps** in the sample times
  longer than 1.5 nominal periods. These are faults of the data by definition (a healthy
  log has none), so they need no threshold; they never feed the other checks (a held or
  replaced sample is not a repeat).

**False-alarm budget.** The channel of a sensor type has a per-sample false-alarm level
``L``: ``alpha`` when ``false_alarms`` is 0, else ``false_alarms / rate`` (every false
episode holds at least one alarmed sample, so an alarm probability of ``false_alarms /
rate`` per sample bounds the episode rate by ``false_alarms`` per second). ``L`` is shared
equally (Bonferroni) among the four tests with a null (stuck, drop, growth, spikes) and
the ``n`` axes: ``level = L / (4 n)`` for each.

The status row of an axis is the largest of its checks' statistic over threshold (1 is the
threshold, an alarm at or above it); the isolated sensor is the axis with the largest ratio (a
gap is not isolable). Every alarmed stretch of each check is remembered, so that an
episode of this detector is explained by the check that raised it
(:meth:`HealthDetector.explain_episode`: ``stuck`` with the value, ``noise`` with the
factor of the standard deviation, ``spikes`` with the amplitude and rate, ``clipping``
with the largest value, ``dropout`` with the missing time).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    FALSE_ALARMS,
    NO_ISOLATION,
    NOT_ISOLABLE,
    TYPES,
    DetectionBlock,
    DetectorBase,
    Param,
    parse_sensor_types,
)
from imufdi_cli.detectors.cusum import CusumDesign, cusum_threshold, run_cusum
from imufdi_cli.errors import CalibrationError, DetectorConfigError, InputDataError
from imufdi_cli.log import ImuBlock

#: the checks, in the order their statistics are stacked (and explained, for ties)
CHECKS: tuple[str, ...] = ("stuck", "drop", "growth", "spikes", "clipping", "dropout")
#: checks with a null distribution: they share the channel's false-alarm level
TESTED: tuple[str, ...] = ("stuck", "drop", "growth", "spikes")
#: default factors of the standard deviation the drop and growth CUSUMs are designed for
#: (their variance ratios K = factor^2: 0.1 and 9)
DROP_FACTOR = math.sqrt(0.1)
GROWTH_FACTOR = 3.0
#: cap of each CUSUM above its threshold (how soon an alarm ends once the variance is back)
CUSUM_MARGIN = 5.0
#: a sample-time step longer than this many nominal periods is a gap
GAP_PERIODS = 1.5
#: alarmed stretches remembered per sensor type, for the explanations
MAX_RUNS = 256
#: statistic over threshold written for a flagged (clipped, invalid) sample or a gap
FLAG_RATIO = 2.0


def _checks_problem(text: Any) -> str | None:
    items = [c.strip() for c in str(text).split(",") if c.strip()]
    unknown = [c for c in items if c not in CHECKS]
    if unknown:
        return f"unknown check {unknown[0]!r}; valid: {', '.join(CHECKS)}"
    if not items:
        return f"give at least one of {', '.join(CHECKS)}"
    return None


@functools.lru_cache(maxsize=32)
def _cusum_h(level: float, design: CusumDesign, dof: float, seed: int) -> float:
    """Threshold of one CUSUM under the Gaussian null (a function of its arguments alone:
    refits and campaign runs with the same settings simulate it once); 256 chains of
    17 408 steps, about 0.3-1 s of CPU."""
    return cusum_threshold(
        level,
        design,
        CUSUM_MARGIN,
        dof,
        np.random.default_rng([seed, 0x4EA1, int(design.ratio * 1000)]),
    )


def _rounded_dof(dof: float) -> float:
    """Degrees of freedom rounded down to two significant digits: calibrations of nearly
    the same length share their simulated thresholds (fewer degrees of freedom: a slightly
    larger estimation error, a slightly higher threshold)."""
    if dof < 10:
        return max(float(math.floor(dof)), 1.0)
    scale = 10.0 ** (math.floor(math.log10(dof)) - 1)
    return math.floor(dof / scale) * scale


def _bootstrap_h(
    level: float,
    design: CusumDesign,
    pool: np.ndarray,
    dof: float,
    seed: int,
    chains: int = 128,
    steps: int = 8192,
) -> float:
    """Threshold of one CUSUM whose null terms are drawn (i.i.d., with replacement) from
    ``pool``, the calibration's own standardised differences, each chain rescaled by the
    relative error of the calibrated variance (as :func:`cusum_threshold` does): the null
    of a quantised or heavy-tailed output, whose differences are not Gaussian (a coarse
    quantiser's many zero differences look like a variance drop to the Gaussian null).
    Independent draws leave out the -1/2 lag correlation of differences, which lowers the
    spread of the CUSUM's sums: the threshold is the larger for it (conservative). A
    function of its arguments (``pool``'s bytes included) and cached: a refit on the same
    calibration simulates once. 128 chains of 9216 steps (about 0.05 s of CPU a design):
    the Gaussian null of the same level, simulated four times longer, is the floor."""
    key = (level, design, pool.tobytes(), dof, seed, chains, steps)
    cached = _BOOTSTRAP_CACHE.get(key)
    if cached is not None:
        return cached
    from imufdi_cli.detectors.cusum import _tail_threshold, _TopValues

    rng = np.random.default_rng([seed, 0xB007, int(design.ratio * 1000)])
    burn = 1024
    scale = np.sqrt(np.maximum(1.0 + rng.normal(0.0, math.sqrt(2.0 / dof), chains), 0.05))
    z = rng.choice(pool, size=(steps + burn, chains)) / scale
    increments = design.increments(z, out=z)
    path, _ = run_cusum(increments, np.zeros(chains), math.inf)
    h = _tail_threshold(_TopValues(path[burn:], level), level)
    cap = h + CUSUM_MARGIN
    path, _ = run_cusum(increments, np.zeros(chains), cap)
    h = _tail_threshold(_TopValues(path[burn:], level), level, cap=cap)
    if len(_BOOTSTRAP_CACHE) >= 32:
        _BOOTSTRAP_CACHE.pop(next(iter(_BOOTSTRAP_CACHE)))
    _BOOTSTRAP_CACHE[key] = h
    return h


#: thresholds of :func:`_bootstrap_h` by their arguments (the 32 latest)
_BOOTSTRAP_CACHE: dict[tuple[Any, ...], float] = {}


def _poisson_upper(count: int, exposure: int) -> float:
    """One-sided 95 % upper bound of a rate from ``count`` events in ``exposure`` trials."""
    from imufdi_cli.maths.quantiles import gamma

    return float(gamma.ppf(0.95, count + 1)) / max(exposure, 1)


@dataclass
class _Run:
    """One alarmed stretch of one check on one axis (times of its first and last alarmed
    sample; the sums that size its explanation)."""

    check: str
    axis: int
    start_ns: int
    end_ns: int
    count: int = 0
    total: float = 0.0  # stuck: the value; noise: sum z^2; spikes: sum |dx|; clip: max |x|
    extra: float = 0.0  # dropout: missing time (s); noise: differences summed


@dataclass
class _Model:
    """What the fit learnt for one sensor type."""

    n: int
    sigma_d: np.ndarray  # (n,) std of first differences / sqrt 2, SI
    repeat_p: np.ndarray  # (n,) repeat probability used
    repeats: np.ndarray  # (n,) int, R
    h_drop: float
    h_growth: float
    spike_z: float
    level: float


class _State:
    """Streaming state of one sensor type."""

    def __init__(self, n: int) -> None:
        self.last: np.ndarray | None = None  # last valid value per axis (NaN: none)
        self.run = np.zeros(n, dtype=np.int64)  # current repeat count
        self.s_drop = np.zeros(n)
        self.s_growth = np.zeros(n)
        self.last_t: int | None = None
        self.open: dict[tuple[str, int], _Run] = {}
        self.runs: deque[_Run] = deque(maxlen=MAX_RUNS)


class HealthDetector(DetectorBase):
    """Per-axis checks without redundancy; CLI name ``health`` (see module docstring)."""

    name: ClassVar[str] = "health"
    lookahead_samples: ClassVar[int] = 0  # causal
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "false_alarms": FALSE_ALARMS,
        "types": TYPES,
        "checks": Param(
            "str",
            ",".join(CHECKS),
            f"checks to run, comma-separated ({', '.join(CHECKS)})",
            check=_checks_problem,
        ),
        "drop_factor": Param(
            "float",
            DROP_FACTOR,
            "std factor the variance-drop CUSUM is designed for (it alarms below about"
            " 1.6x it: 0.51 by default)",
            low=0.0,
            high=0.9,
            low_open=True,
        ),
        "growth_factor": Param(
            "float",
            GROWTH_FACTOR,
            "std factor the variance-growth CUSUM is designed for (it alarms above about"
            " half of it: 1.57 by default)",
            low=1.1,
            high=100.0,
        ),
        "seed": Param("int", 0, "seed of the simulated CUSUM null", low=0),
    }

    def __init__(
        self,
        alpha: float = 0.01,
        false_alarms: float = 0.0,
        types: str = "gyro,accel",
        checks: str = ",".join(CHECKS),
        drop_factor: float = DROP_FACTOR,
        growth_factor: float = GROWTH_FACTOR,
        seed: int = 0,
    ) -> None:
        self.alpha = alpha
        self.false_alarms = false_alarms
        self.types = parse_sensor_types(types, self.name)
        problem = _checks_problem(checks)
        if problem:
            raise DetectorConfigError(f"{self.name}.checks: {problem}")
        self.checks = tuple(c for c in CHECKS if c in {x.strip() for x in checks.split(",")})
        self.drop_factor = drop_factor
        self.growth_factor = growth_factor
        self.drop_design = CusumDesign(ratio=drop_factor**2, clip=5.0)
        self.growth_design = CusumDesign(ratio=growth_factor**2, clip=5.0)
        self.seed = seed
        self.array: ArrayConfig | None = None
        self.rate_hz = 0.0
        self.models: dict[str, _Model] = {}
        self.states: dict[str, _State] = {}
        self._flags: dict[str, tuple[np.ndarray, np.ndarray]] | None = None

    # --- fit ----------------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Difference scale, repeat probability and thresholds of every tested type.

        Raises
        ------
        CalibrationError
            No tested type in the calibration, fewer than 10 valid differences on an axis,
            or an axis whose differences are all zero (a stuck calibration).
        """
        self.array, self.models, self.states = array, {}, {}
        self.rate_hz = float(array.rate_hz)
        tested = [c for c in TESTED if c in self.checks]
        per_sample = self.alpha if self.false_alarms == 0 else self.false_alarms / self.rate_hz
        for sensor_type in self.types:
            triads = calibration.get(sensor_type)
            if triads is None or array.n_sensors(sensor_type) == 0:
                continue
            x = array.select(triads, sensor_type)
            n = x.shape[1]
            level = min(per_sample / (max(len(tested), 1) * n), 0.05)
            d = np.diff(x, axis=0)
            valid = np.isfinite(d)
            m = valid.sum(axis=0)
            fewest = int(m.min()) if m.size else 0
            if fewest < 10:
                raise CalibrationError(
                    f"{self.name}: calibration window has {fewest} valid"
                    f" {sensor_type} differences; at least 10 are needed (use --calibrate"
                    " START:END to choose a longer fault-free window)"
                )
            sigma_d, dof_share = _difference_scale(d, valid, self.rate_hz)
            ids = array.sensor_ids(sensor_type)
            if np.any(sigma_d <= 0):
                bad = ids[int(np.argmin(sigma_d))]
                raise CalibrationError(
                    f"{self.name}: {bad} does not change at all in the calibration window"
                    " (stuck, or a constant output); choose a fault-free window with"
                    " --calibrate START:END"
                )
            repeat_p = np.empty(n)
            repeats = np.empty(n, dtype=np.int64)
            for k in range(n):
                same = (d[:, k] == 0) & valid[:, k]
                c = int(same.sum())
                p = _poisson_upper(c, int(m[k]))
                if c >= 10:  # repeat after a repeat: runs of a coarse quantiser
                    both = int(np.count_nonzero(same[1:] & same[:-1]))
                    p = max(p, _poisson_upper(both, c))
                p = min(p, 0.999)
                repeat_p[k] = p
                repeats[k] = max(2, math.ceil(math.log(level) / math.log(p)))
            dof = _rounded_dof(dof_share * _successive_dof(int(m.min()) + 1))
            from imufdi_cli.maths.quantiles import norm

            # the null of the variance tests: Gaussian white differences, and the
            # calibration's own (quantised, heavy-tailed); the larger threshold of the two
            pool = (d / (math.sqrt(2.0) * sigma_d))[valid]
            if pool.size > 65536:
                pool = np.random.default_rng([self.seed, 0x9001]).choice(pool, 65536)
            h_drop, h_growth = (
                max(
                    _cusum_h(level, design, dof, self.seed),
                    _bootstrap_h(level, design, pool, dof, self.seed),
                )
                if check in tested
                else 0.0
                for design, check in ((self.drop_design, "drop"), (self.growth_design, "growth"))
            )

            self.models[sensor_type] = _Model(
                n=n,
                sigma_d=sigma_d,
                repeat_p=repeat_p,
                repeats=repeats,
                h_drop=h_drop,
                h_growth=h_growth,
                spike_z=float(norm.isf(level / 2.0)),
                level=level,
            )
            self.states[sensor_type] = _State(n)
        if not self.models:
            raise CalibrationError(
                f"{self.name}: the calibration has none of the tested types"
                f" ({', '.join(self.types)})"
            )

    # --- streaming ------------------------------------------------------------------------

    def note_flags(self, flags: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """The input conditioning's (clipped, invalid) masks, shape (N, m, 3) each, of the
        next block (before it replaced those samples); without them ``process`` flags the
        block itself (non-finite values, values at the array's range)."""
        self._flags = flags

    def _block_flags(
        self, block: ImuBlock, sensor_type: str, x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        assert self.array is not None
        if self._flags is not None and sensor_type in self._flags:
            clipped, invalid = (self.array.select(f, sensor_type) for f in self._flags[sensor_type])
            return np.asarray(clipped, bool), np.asarray(invalid, bool)
        from imufdi_cli.validity import ABSURD, CLIP_FRACTION, OUT_OF_RANGE_FACTOR

        invalid = ~np.isfinite(x)
        with np.errstate(invalid="ignore"):
            invalid |= np.abs(x) > ABSURD[sensor_type]
            full = self.array.range.get(sensor_type)
            clipped = np.zeros_like(invalid)
            if full:
                invalid |= np.abs(x) > OUT_OF_RANGE_FACTOR * full
                clipped = (np.abs(x) >= CLIP_FRACTION * full) & ~invalid
        return clipped, invalid

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """One row per sample and tested type (statistic: the largest check's statistic
        over its threshold; threshold 1)."""
        if self.array is None:
            raise CalibrationError(f"{self.name}: fit() must be called before process()")
        out = {}
        for sensor_type, model in self.models.items():
            triads = block.get(sensor_type)
            if triads is None:
                raise InputDataError(f"{self.name}: block has no {sensor_type} data")
            out[sensor_type] = self._process_type(block, sensor_type, model, triads)
        self._flags = None
        return out

    def _process_type(
        self, block: ImuBlock, sensor_type: str, model: _Model, triads: np.ndarray
    ) -> DetectionBlock:
        assert self.array is not None
        state = self.states[sensor_type]
        x = np.array(self.array.select(triads, sensor_type), dtype=np.float64)
        N, n = x.shape
        if N == 0:
            return DetectionBlock.empty(0, n)
        clipped, invalid = self._block_flags(block, sensor_type, x)
        flagged = clipped | invalid
        raw = np.abs(x)
        full = self.array.range.get(sensor_type)
        if full and self._flags is not None:  # the conditioner replaced those samples
            raw = np.where(clipped, float(full), raw)
        x[flagged] = np.nan
        ratios = np.zeros((len(CHECKS), N, n))
        # the previous valid value of each axis (flagged samples are skipped)
        prev = _previous_valid(x, state.last)
        # a row with a flagged sample may be held by the conditioning: not a repeat
        same = (x == prev) & ~flagged.any(axis=1)[:, None]
        run = _run_lengths(same, state.run)
        state.run = run[-1].copy()
        if "stuck" in self.checks:
            ratios[0] = run / model.repeats
        dx = x - prev
        # z_t: the difference with the last valid sample (the same floats whatever the
        # block boundaries); a spike enters neither CUSUM (the spike test has it)
        z = dx / (math.sqrt(2.0) * model.sigma_d)
        spike = np.abs(np.nan_to_num(z)) >= model.spike_z
        tested = np.where(spike, np.nan, z) if "spikes" in self.checks else z
        if "drop" in self.checks:
            s, state.s_drop = run_cusum(
                self.drop_design.increments(tested.copy()),
                state.s_drop,
                model.h_drop + CUSUM_MARGIN,
            )
            ratios[1] = s / model.h_drop
        if "growth" in self.checks:
            s, state.s_growth = run_cusum(
                self.growth_design.increments(tested.copy()),
                state.s_growth,
                model.h_growth + CUSUM_MARGIN,
            )
            ratios[2] = s / model.h_growth
        if "spikes" in self.checks:
            ratios[3] = np.nan_to_num(np.abs(z)) / model.spike_z
        if "clipping" in self.checks:
            ratios[4] = np.where(clipped, FLAG_RATIO, 0.0)
        gap = np.zeros(N)
        if "dropout" in self.checks:
            ratios[5] = np.where(invalid, FLAG_RATIO, 0.0)
            first = block.t_ns[0] if state.last_t is None else state.last_t
            periods = np.diff(np.concatenate([[first], block.t_ns])) * 1e-9 * self.rate_hz
            gap = np.where(periods > GAP_PERIODS, periods, 0.0)
        state.last_t = int(block.t_ns[-1])
        state.last = np.where(np.isfinite(x[-1]), x[-1], prev[-1])
        scores = ratios.max(axis=0)
        statistic = scores.max(axis=1)
        alarm = statistic >= 1.0
        isolated = np.where(alarm, scores.argmax(axis=1), NO_ISOLATION).astype(np.int32)
        is_gap = gap > 0
        if is_gap.any():
            statistic = np.maximum(statistic, np.where(is_gap, FLAG_RATIO, 0.0))
            isolated = np.where(is_gap & ~alarm, NOT_ISOLABLE, isolated).astype(np.int32)
            alarm = alarm | is_gap
        self._remember(state, block.t_ns, ratios, x, raw, tested, dx, gap)
        return DetectionBlock(
            statistic=statistic,
            threshold=np.ones(N),
            alarm=alarm,
            isolated=isolated,
            amplitude=np.full(N, np.nan),
            scores=scores,
        )

    def _remember(
        self,
        state: _State,
        t_ns: np.ndarray,
        ratios: np.ndarray,
        x: np.ndarray,
        raw: np.ndarray,
        z: np.ndarray,
        dx: np.ndarray,
        gap: np.ndarray,
    ) -> None:
        """Extend or open the alarmed stretches of every check and axis (gaps: axis -1)."""
        for c, check in enumerate(CHECKS):
            on = ratios[c] >= 1.0
            columns = [(int(k), on[:, k]) for k in range(on.shape[1])]
            if check == "dropout":
                columns.append((-1, gap > 0))
            for k, column in columns:
                key = (check, k)
                if not column.any():
                    state.open.pop(key, None)
                    continue
                rows = np.flatnonzero(column)
                # split where the previous alarmed sample was not the previous row
                pieces = np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1)
                for i, piece in enumerate(pieces):
                    run = state.open.get(key) if i == 0 and piece[0] == 0 else None
                    if run is None:
                        run = _Run(check, k, int(t_ns[piece[0]]), int(t_ns[piece[-1]]))
                        state.runs.append(run)
                    run.end_ns = int(t_ns[piece[-1]])
                    run.count += piece.size
                    _accumulate(run, piece, k, x, raw, z, dx, gap, self.rate_hz)
                    state.open[key] = run
                if not column[-1]:
                    state.open.pop(key, None)

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal: nothing held back."""
        return {t: DetectionBlock.empty(0, m.n) for t, m in self.models.items()}

    # --- explanations ---------------------------------------------------------------------

    def explain_episode(self, episode: Any) -> list[Any]:
        """The fault fits of one of this detector's episodes (best first).

        ``episode`` is an :class:`~imufdi_cli.episodes.Episode` of this detector, with the
        fits of the consensus of the other sensors when the array has one. A stuck,
        clipped or dropped-out sensor is named by the check that saw it, before those
        fits; otherwise the consensus fits stand when there are any, and the checks that
        raised the episode explain it when there are none (one IMU).
        """
        own = self._own_fits(episode)
        if own and own[0].model in ("stuck", "clipping", "dropout"):
            return own + [f for f in episode.fits if f.model not in {o.model for o in own}]
        return list(episode.fits) or own

    def _own_fits(self, episode: Any) -> list[Any]:
        """Fits from the checks that raised ``episode`` (empty when none is remembered)."""
        from imufdi_cli.episodes.fault_fit import FaultFit
        from imufdi_cli.maths.quantiles import chi2

        state = self.states.get(episode.sensor_type)
        if state is None or self.array is None:
            return []
        ids = self.array.sensor_ids(episode.sensor_type)
        axis = ids.index(episode.sensors[0]) if episode.sensors else None
        runs = [
            r
            for r in state.runs
            if r.end_ns >= episode.start_ns
            and r.start_ns <= episode.end_ns
            and (axis is None or r.axis in (axis, -1))
        ]
        if not runs:
            return []
        by_check: dict[str, list[_Run]] = {}
        for r in runs:
            by_check.setdefault(r.check, []).append(r)
        decisive = [c for c in ("stuck", "clipping", "dropout") if c in by_check]
        graded = sorted(
            (c for c in ("drop", "spikes", "growth") if c in by_check),
            key=lambda c: -sum(r.count for r in by_check[c]),
        )
        fits = []
        for check in decisive + graded:
            group = by_check[check]
            count = sum(r.count for r in group)
            if check == "stuck":
                value = group[-1].total
                fits.append(
                    FaultFit("stuck", value, value, value, 0, -math.inf, {"repeats": count})
                )
            elif check in ("drop", "growth"):
                terms = sum(r.extra for r in group)
                mean_sq = sum(r.total for r in group) / max(terms, 1.0)
                factor = math.sqrt(mean_sq)
                dof = max(terms, 1.0)
                low = math.sqrt(mean_sq * dof / float(chi2.ppf(0.95, dof)))
                high = math.sqrt(mean_sq * dof / max(float(chi2.ppf(0.05, dof)), 1e-300))
                fits.append(FaultFit("noise", factor, low, high, 0, math.nan))
            elif check == "spikes":
                amp = sum(r.total for r in group) / count
                span = max((group[-1].end_ns - group[0].start_ns) * 1e-9, 1.0 / self.rate_hz)
                fits.append(
                    FaultFit("spikes", amp, amp, amp, 0, math.nan, {"rate_hz": count / span})
                )
            elif check == "clipping":
                value = max(r.total for r in group)
                fits.append(FaultFit("clipping", value, value, value, 0, math.nan))
            else:
                missing = sum(r.extra for r in group)
                fits.append(FaultFit("dropout", missing, missing, missing, 0, math.nan))
        return fits

    def metadata(self) -> dict[str, Any]:
        return {
            "params": {
                "alpha": self.alpha,
                "false_alarms": self.false_alarms,
                "types": ",".join(self.types),
                "checks": ",".join(self.checks),
                "drop_factor": self.drop_factor,
                "growth_factor": self.growth_factor,
                "seed": self.seed,
            },
            "types": {
                t: {
                    "level_per_test": m.level,
                    "difference_sigma": m.sigma_d.tolist(),
                    "repeat_probability": m.repeat_p.tolist(),
                    "stuck_repeats": m.repeats.tolist(),
                    "cusum_drop_h": m.h_drop,
                    "cusum_growth_h": m.h_growth,
                    "spike_z": m.spike_z,
                }
                for t, m in self.models.items()
            },
        }


#: Fewest one-second blocks of differences for leaving blocks out (fewer: all are used).
MIN_BLOCKS = 5
#: A block whose mean squared difference exceeds this many times the blocks' median is
#: left out: for white Gaussian noise a 100-sample block does so with a probability of
#: about 1e-6 (chi-square of 66 degrees of freedom), a second of motion (differences
#: several times the noise) always.
OUTLIER_BLOCK = 2.0


def _difference_scale(d: np.ndarray, valid: np.ndarray, rate_hz: float) -> tuple[np.ndarray, float]:
    """``sigma_d`` (n,) of the calibration's first differences ``d`` (N, n) and the share
    of the window's degrees of freedom it rests on.

    ``mean(d^2) / 2`` over the window's one-second blocks, leaving out the blocks whose own
    mean square exceeds :data:`OUTLIER_BLOCK` times the blocks' median: a few seconds of
    motion inside the window (a quadrotor's attitude changes) inflate the mean of the
    squares and would make the steady state after them look like a variance drop. The
    blocks kept are averaged, not their median taken, so the estimate stays unbiased
    whatever the noise's distribution (a quantised output's many zero differences
    included). Fewer than :data:`MIN_BLOCKS` blocks: every difference is used."""
    m = valid.sum(axis=0)
    sq = np.where(valid, d, 0.0) ** 2
    size = max(20, round(rate_hz)) if rate_hz > 0 else 20
    blocks = d.shape[0] // size
    if blocks < MIN_BLOCKS:
        return np.sqrt(sq.sum(axis=0) / (2.0 * np.maximum(m, 1))), 1.0
    counts = valid[: blocks * size].reshape(blocks, size, -1).sum(axis=1)
    sums = sq[: blocks * size].reshape(blocks, size, -1).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_block = np.where(counts > 0, sums / counts, np.nan)
        median = np.nanmedian(per_block, axis=0)
    keep = (per_block <= OUTLIER_BLOCK * median) & (counts > 0)
    # the rows after the last whole block, and every row of an axis none of whose blocks
    # qualifies (a constant output: median 0), stay in
    tail = sq[blocks * size :].sum(axis=0), valid[blocks * size :].sum(axis=0)
    kept_sums = np.where(keep, sums, 0.0).sum(axis=0) + tail[0]
    kept_counts = np.where(keep, counts, 0).sum(axis=0) + tail[1]
    fallback = ~keep.any(axis=0)
    kept_sums = np.where(fallback, sq.sum(axis=0), kept_sums)
    kept_counts = np.where(fallback, m, kept_counts)
    sigma_d = np.sqrt(kept_sums / (2.0 * np.maximum(kept_counts, 1)))
    share = float(np.min(kept_counts / np.maximum(m, 1))) if m.size else 1.0
    return sigma_d, share


def _successive_dof(n: int) -> float:
    from imufdi_cli.episodes.white_noise import successive_difference_dof

    return successive_difference_dof(n)


def _previous_valid(x: np.ndarray, last: np.ndarray | None) -> np.ndarray:
    """(N, n): for each row, the last finite value of each column before it (``last``
    before the block; NaN where none)."""
    N, n = x.shape
    start = np.full(n, np.nan) if last is None else np.asarray(last, dtype=np.float64)
    joined = np.concatenate([start[None, :], x[:-1]]) if N else np.zeros((0, n))
    finite = np.isfinite(joined)
    index = np.where(finite, np.arange(N)[:, None], -1)
    np.maximum.accumulate(index, axis=0, out=index)
    out = np.full((N, n), np.nan)
    ok = index >= 0
    cols = np.broadcast_to(np.arange(n), (N, n))
    out[ok] = joined[index[ok], cols[ok]]
    return out


def _run_lengths(same: np.ndarray, carry: np.ndarray) -> np.ndarray:
    """(N, n) int: consecutive True values ending at each row (``carry`` before it)."""
    counts = np.cumsum(same, axis=0, dtype=np.int64)
    # the cumulative count at the last False row at or before each row
    reset = np.where(~same, counts, 0)
    np.maximum.accumulate(reset, axis=0, out=reset)
    out = counts - reset
    # rows before the first False continue the previous block's run
    never_reset = np.cumsum(~same, axis=0) == 0
    out = out + np.where(never_reset, carry[None, :], 0)
    return out


def _accumulate(
    run: _Run,
    rows: np.ndarray,
    k: int,
    x: np.ndarray,
    raw: np.ndarray,
    z: np.ndarray,
    dx: np.ndarray,
    gap: np.ndarray,
    rate_hz: float,
) -> None:
    """Add alarmed ``rows`` of axis ``k`` to the sums that size the run's explanation."""
    if k < 0:  # a gap: its missing time
        run.extra += float(np.sum(gap[rows] - 1.0) / rate_hz)
    elif run.check == "stuck":
        values = x[rows, k]
        values = values[np.isfinite(values)]
        if values.size:
            run.total = float(values[-1])
    elif run.check in ("drop", "growth"):
        values = z[rows, k]
        values = values[np.isfinite(values)]
        run.total += float(np.sum(values**2))
        run.extra += float(values.size)
    elif run.check == "spikes":
        run.total += float(np.nansum(np.abs(dx[rows, k])))
    elif run.check == "clipping":
        values = raw[rows, k]
        run.total = max(run.total, float(np.nanmax(values)) if np.isfinite(values).any() else 0.0)
    else:  # dropout: invalid samples, one period each
        run.extra += rows.size / rate_hz
