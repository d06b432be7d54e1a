"""bank under a false-alarm budget: sequential decisions on the bank's residuals
(docs/algorithms/bank.md, "Under a false-alarm budget").

**Array mode.** The standardized leave-one-out residual of sensor j,
``z_j = e_j / s_j`` (``e = P (m - b)``, :func:`.array_mode.leave_one_out_matrix`; ``s_j``
its predicted standard deviation), is N(0, 1) without fault and shifted by ``f / s_j`` by
a step f on sensor j; it is the parity evidence of glt (the deleted residual of j
standardized is ``r_j / sqrt(P_jj)`` in whitened units). A bank of CUSUM tests
(:mod:`imufdi_cli.maths.sequential`) decides on it, its threshold set from the budget, with
the slow references and the motion model of the shared bank (:class:`EvidenceBudget`).

What makes the bank itself is several simultaneous faults, found by exclusion. Under a
budget the exclusion is sequential too: while the episode of the test over all sensors
is open and isolates sensor s, a second bank of CUSUM tests runs on the residuals of the
others with s excluded from every estimator (``leave_one_out_matrix(H, sigma, {s})``: a
fault on s no longer leaks into them); an episode there isolates a second sensor s', and
a third test excludes both, up to ``max_faults`` sensors. A stage lives while the episode
that started it lasts with the same isolated sensor (a change of isolation starts it
again); its reference is the first test's, frozen in that episode, carried into the
excluded estimators' residuals (the offsets and leak of the first test's evidence mapped
back to the sensors by least squares). The false alarms of the budget are those of the
first test: the others run only while a fault is being reported. ``isolated_set`` holds
every isolated sensor; ``amplitudes`` each one's residual against the sensors not
isolated, averaged since the set last changed (SI).

With the array config's per-IMU noise (what ``imufdi calibrate`` measures) the residuals
are weighted by it, as glt's ``sigma_source=auto``, and with its ``[jitter]`` the evidence
is divided by glt's motion factor ``sqrt(1 + A_t)`` (:mod:`imufdi_cli.maths.jitter`).

**Marg mode** (one IMU with accelerometer, magnetometer and gyros): the accelerometer and
magnetometer evidence is the full attitude estimator's residual linearised at its
attitude (:meth:`.marg._MargSolution.parity_evidence`), one bank of CUSUM tests over the
six components whose episodes go to the channel of the component Table 1 isolates; the
gyro evidence is each gyro's filtered residual over its white-noise sigma, whose long-run
variance is 1 by construction (:mod:`.gyro`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.detectors.bank.array_mode import _ArrayTest
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.detectors.budget import (
    BUDGET_SHARE,
    EvidenceBudget,
    MotionState,
    reference_tau,
)
from imufdi_cli.maths.jitter import MotionInflation
from imufdi_cli.maths.parity import (
    isolable_sensors,
    parity_matrix,
    sigma_estimate_variance,
    whiten,
)
from imufdi_cli.maths.sequential import CusumBank, budget_threshold


def _runs(alarm: np.ndarray, isolated: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs ``(start, stop, sensor)`` of consecutive alarm rows isolating the same sensor
    (>= 0)."""
    key = np.where(alarm & (isolated >= 0), isolated, -1)
    runs = []
    start = 0
    for row in range(1, key.size + 1):
        if row == key.size or key[row] != key[start]:
            if key[start] >= 0:
                runs.append((start, row, int(key[start])))
            start = row
    return runs


@dataclass
class _Stage:
    """A test of the residuals with the sensors ``excluded`` left out of every estimator,
    alive while the episode that started it lasts; it may start the next stage."""

    excluded: frozenset[int]
    bank: CusumBank
    child: _Stage | None = None
    child_sensor: int = -1


@dataclass
class ArrayBudget:
    """The array-mode bank of one sensor type under a budget (module docstring).

    Parameters
    ----------
    test : _ArrayTest
        The calibrated leave-one-out bank (H, sigma, bias, isolability, max_faults).
    rate_hz, budget_per_s : float
    track_bias : float or None
        The reference time constant (None: 60 s).
    """

    test: _ArrayTest
    rate_hz: float
    budget_per_s: float
    track_bias: float | None
    inflation: MotionInflation | None = None  # the array config's jitter model, or None
    sigma_known: bool = False  # the test's sigma is the array config's (no estimation error)
    spatial: bool = False  # in motion, each row's own noise variance (budget.SPATIAL_TYPES)
    first: EvidenceBudget | None = None
    motion: MotionState | None = None
    stage: _Stage | None = None
    thresholds: dict[int, float] = field(default_factory=dict)
    set_sums: np.ndarray | None = None  # residual sums of the isolated set since it changed
    set_count: int = 0
    current_set: frozenset[int] = frozenset()

    def evidence(self, m: np.ndarray, excluded: frozenset[int]) -> tuple[np.ndarray, np.ndarray]:
        """z (N, n) of bias-free measurements ``m`` with ``excluded`` left out (NaN for
        them and for sensors without an estimator), and the sensitivities (n,)."""
        P, std = self.test.matrix(excluded)
        with np.errstate(invalid="ignore"):
            z = (m @ np.nan_to_num(P).T) / std
        usable = np.all(np.isfinite(P), axis=1)
        out_of_test = np.array([i in excluded for i in range(m.shape[1])]) | ~usable
        z[:, out_of_test] = np.nan
        return z, np.where(out_of_test, 0.0, 1.0 / std)

    def fit(self, values: np.ndarray) -> None:
        """Thresholds, long-run factor and leak from the calibration window (N, n)."""
        test = self.test
        m = values - test.bias
        z, sensitivity = self.evidence(m, frozenset())
        scale_variance = (
            0.0
            if self.sigma_known
            else float(np.mean(sigma_estimate_variance(test.H, test.sigma, len(values))))
        )
        self.first = EvidenceBudget(
            sensitivity,
            test.isolable,
            self.rate_hz,
            self.budget_per_s,
            reference_tau(self.track_bias),
            scale_variance=scale_variance,
            calibration_samples=values.shape[0],
            moving=self.inflation is not None and self.spatial,
        )
        self.motion = MotionState(test.H, test.sigma)
        self.first.fit(np.nan_to_num(z), self.motion(values))
        self.stage = None
        self.set_sums = None
        self.set_count = 0
        self.current_set = frozenset()

    def _threshold(self, excluded: int) -> float:
        """h of a stage with ``excluded`` sensors out (its union bound counts the rest)."""
        if excluded not in self.thresholds:
            first = self.first
            assert first is not None
            self.thresholds[excluded] = budget_threshold(
                first.design,
                max(first.n - excluded, 1),
                BUDGET_SHARE * self.budget_per_s / self.rate_hz,
                first.scale_variance,
                first.threshold_contamination,
            )
        return self.thresholds[excluded]

    def _frozen_reference(self, x: np.ndarray) -> np.ndarray:
        """The first test's reference (frozen in its episode) as sensor offsets (N, n), SI:
        the least-squares map of its z offsets (and motion model, at the rows' states
        ``x``) back through ``z = D P m``."""
        first = self.first
        assert first is not None and first.bank is not None
        bank = first.bank
        P, std = self.test.matrix(frozenset())
        usable = np.all(np.isfinite(P), axis=1)
        rows = np.nan_to_num(P)[usable] / std[usable, None]  # (k, n)
        scale = math.sqrt(bank.kappa)
        offsets_z = np.broadcast_to(bank.reference[usable] * scale, (x.shape[0], rows.shape[0]))
        model = bank.ref.motion
        if model is not None:
            centred = x - bank.ref.state_mean
            offsets_z = offsets_z + centred @ (model.slopes[:, usable] * scale)
        solution, *_ = np.linalg.lstsq(rows, np.atleast_2d(offsets_z).T, rcond=None)
        return solution.T  # type: ignore[no-any-return]

    def _new_stage(self, excluded: frozenset[int]) -> _Stage:
        first = self.first
        assert first is not None and first.bank is not None
        _, sensitivity = self.evidence(np.zeros((1, first.n)), excluded)
        rest = np.flatnonzero(sensitivity > 0)
        isolable = np.zeros(first.n, dtype=bool)
        if rest.size > self.test.H.shape[1]:
            # two of the remaining sensors may be parallel once others are excluded
            V = parity_matrix(whiten(self.test.H[rest], self.test.sigma[rest]))
            isolable[rest] = isolable_sensors(V) & self.test.isolable[rest]
        # the stages run only while an episode is open: no reference of their own
        design = dataclasses.replace(first.design, tau_s=0.0, scale_tau_s=0.0)
        bank = CusumBank(
            design,
            self._threshold(len(excluded)),
            sensitivity,
            isolable,
            self.rate_hz,
            kappa=first.bank.kappa,
            spatial=first.moving,
        )
        return _Stage(excluded, bank)

    def _children(
        self,
        stage: _Stage,
        decided: Any,
        m: np.ndarray,
        sets: np.ndarray,
        continuing: bool,
        factors: np.ndarray | None = None,
    ) -> None:
        """Start or continue the next stage over each run of ``stage``'s alarms isolating
        one isolable sensor (``decided``: its decisions on these rows)."""
        if len(stage.excluded) + 1 >= self.test.max_faults:
            return
        for start, stop, sensor in _runs(decided.alarm, decided.isolated):
            if not self.test.isolable[sensor]:
                continue
            carried = continuing and start == 0 and stage.child_sensor == sensor
            if not carried or stage.child is None:
                stage.child = self._new_stage(stage.excluded | {sensor})
                stage.child_sensor = sensor
            self._run_stage(
                stage.child,
                m[start:stop],
                sets[start:stop],
                carried,
                None if factors is None else factors[start:stop],
            )
        last = decided.alarm.size - 1
        if (
            last < 0
            or not decided.alarm[last]
            or decided.isolated[last] < 0
            or decided.isolated[last] != stage.child_sensor
        ):
            stage.child = None
            stage.child_sensor = -1

    def _run_stage(
        self,
        stage: _Stage,
        m: np.ndarray,
        sets: np.ndarray,
        continuing: bool,
        factors: np.ndarray | None = None,
    ) -> None:
        """Run ``stage`` over the rows of corrected measurements ``m`` (N, n) (``factors``:
        their motion variance factors) and mark the sensors it and its children isolate in
        ``sets`` (N, n)."""
        z, _ = self.evidence(m, stage.excluded)
        decided = stage.bank.process(z, None, factors)
        rows = np.flatnonzero(decided.alarm & (decided.isolated >= 0))
        sets[rows, decided.isolated[rows]] = True
        self._children(stage, decided, m, sets, continuing, factors)

    def process(
        self, values: np.ndarray, t_ns: np.ndarray | None = None
    ) -> tuple[DetectionBlock, np.ndarray]:
        """Decisions on a block of measurements (N, n) (``t_ns``: their times, for the
        jitter model) and the isolated sets (N, n)."""
        first, motion = self.first, self.motion
        assert first is not None and motion is not None and first.bank is not None
        m = values - self.test.bias
        n_rows, n = m.shape
        z, _ = self.evidence(m, frozenset())
        x = motion(values)
        factors = None
        if self.inflation is not None and t_ns is not None:
            # sampling-time jitter in motion (maths/jitter.py): the rows' variance factors
            factors = self.inflation.factors(values, t_ns)
        out = first.decide(z, x, factors)
        sets = np.zeros((n_rows, n), dtype=bool)
        rows = np.flatnonzero(out.alarm & (out.isolated >= 0))
        sets[rows, out.isolated[rows]] = True
        if self.stage is None:
            self.stage = _Stage(frozenset(), first.bank)
        if out.alarm.any() or self.stage.child is not None:
            # the first test's reference is frozen in its episodes: carried into the others
            corrected = m - self._frozen_reference(x) if out.alarm.any() else m
            self._children(self.stage, out, corrected, sets, True, factors)
        return out, sets

    def amplitudes(self, values: np.ndarray, sets: np.ndarray) -> np.ndarray:
        """(N, n) SI: each isolated sensor's residual against the sensors not isolated,
        averaged over the rows since the isolated set last changed; NaN elsewhere."""
        m = values - self.test.bias
        n_rows, n = m.shape
        out = np.full((n_rows, n), np.nan)
        if n_rows == 0:
            return out
        changes = np.flatnonzero(np.any(sets[1:] != sets[:-1], axis=1)) + 1
        bounds = np.concatenate([[0], changes, [n_rows]])
        for row, stop in itertools.pairwise(bounds.tolist()):
            current = frozenset(np.flatnonzero(sets[row]).tolist())
            if current != self.current_set:
                self.current_set = current
                self.set_sums = np.zeros(n)
                self.set_count = 0
            if not current:
                continue
            members = np.array(sorted(current))
            P, _ = self.test.matrix(current)
            e = m[row:stop] @ np.nan_to_num(P[members]).T  # each against the others
            sums = np.zeros(members.size) if self.set_sums is None else self.set_sums[members]
            total = sums + np.cumsum(e, axis=0)
            counts = self.set_count + np.arange(1, stop - row + 1)
            out[row:stop, members] = total / counts[:, None]
            assert self.set_sums is not None
            self.set_sums[members] = total[-1]
            self.set_count = int(counts[-1])
        return out

    def metadata(self) -> dict[str, Any]:
        return {} if self.first is None else self.first.metadata()
