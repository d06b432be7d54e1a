"""WOA-MVMD-GLT tuning (paper §2.7): the whale optimization search of (K, alpha) on a
calibration segment, and its JSON result (``imufdi tune``, the ``params`` parameter).
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.mvmd import (
    MIN_SAMPLES,
    channel_power,
    check_mvmd_params,
    mvmd_gains,
    mvmd_results,
    spectrum,
)
from imufdi_cli.detectors.woa import WoaSearch
from imufdi_cli.detectors.woa_mvmd_glt.fitness import (
    DEFAULT_WEIGHTS,
    FITNESS_CHOICES,
    ValidationFault,
    cfv,
    validation_windows,
)
from imufdi_cli.detectors.woa_mvmd_glt.windows import DEFAULT_MODE_RULE, WindowSpectra
from imufdi_cli.errors import (
    CalibrationError,
    DetectorConfigError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.quantiles import chi2

# --- tuning (§2.7) ---------------------------------------------------------------------


@dataclass
class TuneResult:
    """(K, alpha) chosen by WOA for one sensor type (the ``imufdi tune`` output).

    Attributes
    ----------
    K : int
    alpha : float
        MVMD bandwidth penalty (f in cycles/sample, see mvmd.py).
    fitness : float
        CFV of the best candidate.
    curve : list of float
        Best CFV after initialisation and after each WOA iteration.
    evaluations : int
        Distinct (K, alpha) candidates decomposed.
    seconds : float
        Wall time of the search (of the joint search when several ran together,
        :func:`tune_signals`: a detector's sensor types).
    sensor_type : str
    settings : dict
        WOA and MVMD settings used (population, iterations, bounds, weights, samples).
    """

    K: int
    alpha: float
    fitness: float
    curve: list[float]
    evaluations: int
    seconds: float
    sensor_type: str = "gyro"
    settings: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps({"format": "imufdi.tune/1", **asdict(self)}, indent=2)

    @classmethod
    def from_json(cls, text: str | bytes, *, source: str = "tune result") -> TuneResult:
        from imufdi_cli.jsonin import loads

        data = loads(text, source, DetectorConfigError)
        try:
            if not isinstance(data, dict):
                raise TypeError("not an object")
            data.pop("format", None)
            result = cls(**data)
            result.K = int(result.K)
            result.alpha = float(result.alpha)
        except (ValueError, TypeError) as err:
            raise DetectorConfigError(
                f"{source}: not an imufdi tune result (JSON with K, alpha, fitness, curve, ...)"
            ) from err
        check_mvmd_params(result.K, result.alpha)
        return result

    @classmethod
    def load(cls, path: str | Path) -> TuneResult:
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as err:
            raise DetectorConfigError(
                f"cannot read tuned parameters {path}: {err.strerror}"
            ) from err
        return cls.from_json(text, source=str(path))


def _check_search(
    population: int,
    k_bounds: tuple[int, int],
    alpha_bounds: tuple[float, float],
    weights: Sequence[float],
) -> None:
    """Raise DetectorConfigError for a WOA search that cannot run."""
    if population < 2:
        raise DetectorConfigError(f"WOA population must be >= 2, got {population}")
    if not 1 <= k_bounds[0] <= k_bounds[1]:
        raise DetectorConfigError(f"K bounds must satisfy 1 <= low <= high, got {k_bounds}")
    if not 0 < alpha_bounds[0] <= alpha_bounds[1]:
        raise DetectorConfigError(f"alpha bounds must satisfy 0 < low <= high, got {alpha_bounds}")
    if len(weights) != 3:
        raise DetectorConfigError("CFV needs three weights (entropy, correlation, compactness)")


@dataclass
class _Problem:
    """One signal's WOA search and what its fitness reuses across candidates: the spectrum
    of the whole signal and those of its validation windows."""

    channels: np.ndarray  # (C, T)
    spec: np.ndarray  # (C, T + 1) complex, the mirrored signal's rfft
    freqs: np.ndarray  # (T + 1,)
    offset: int
    power: np.ndarray  # (T + 1,)
    validation: ValidationFault | None
    spectra: WindowSpectra | None  # the validation windows
    n_windows: int
    search: WoaSearch


def _gains_together(
    jobs: list[tuple[np.ndarray, np.ndarray, list[int], list[float]]], tol: float, max_iter: int
) -> list[list[tuple[np.ndarray, np.ndarray, int, bool]]]:
    """:func:`mvmd_gains` of several jobs ``(power (B, F), freqs (F,), Ks, alphas)``: the
    jobs on one frequency grid in one batched call (a row's floats do not depend on the
    other rows), the outputs split back per job."""
    out: list[list[tuple[np.ndarray, np.ndarray, int, bool]]] = [[] for _ in jobs]
    groups: dict[bytes, list[int]] = {}
    for j, (_, freqs, _, _) in enumerate(jobs):
        groups.setdefault(freqs.tobytes(), []).append(j)
    for members in groups.values():
        raw = mvmd_gains(
            np.concatenate([jobs[j][0] for j in members]),
            jobs[members[0]][1],
            [K for j in members for K in jobs[j][2]],
            [a for j in members for a in jobs[j][3]],
            tol=tol,
            max_iter=max_iter,
            history=False,
        )
        start = 0
        for j in members:
            out[j] = raw[start : start + len(jobs[j][2])]
            start += len(jobs[j][2])
    return out


def _fitness(
    problems: list[_Problem],
    requests: list[np.ndarray],
    weights: Sequence[float],
    tol: float,
    max_iter: int,
    rule: str,
) -> list[np.ndarray]:
    """Fitness (P_i,) of the candidates (P_i, 2) of each problem: CFV of the whole signal,
    plus the weighted expected missed fraction of the validation fault averaged over its
    windows (each decomposed with the candidate, its u_best filter taken, u_best chosen by
    ``rule``). Every decomposition of all the problems on one frequency grid runs in one
    batched MVMD call."""
    params = [
        ([int(k) for k in c[:, 0]], [float(a) for a in c[:, 1]]) if c.shape[0] else ([], [])
        for c in requests
    ]
    jobs: list[tuple[np.ndarray, np.ndarray, list[int], list[float]]] = []
    whole: list[int | None] = []
    windows: list[int | None] = []
    repeated: dict[int, WindowSpectra] = {}  # job -> its validation windows, repeated
    for problem, (Ks, alphas) in zip(problems, params):
        if not Ks:
            whole.append(None)
            windows.append(None)
            continue
        whole.append(len(jobs))
        jobs.append(
            (
                np.broadcast_to(problem.power, (len(Ks), problem.power.shape[0])),
                problem.freqs,
                Ks,
                alphas,
            )
        )
        if problem.validation is None or problem.spectra is None:
            windows.append(None)
            continue
        # every (validation window, candidate) pair, window-major: rows [w * P, (w + 1) * P)
        # are the P candidates on window w
        stacked = problem.spectra.repeat(len(Ks))
        windows.append(len(jobs))
        repeated[len(jobs)] = stacked
        jobs.append(
            (stacked.power, stacked.freqs, Ks * problem.n_windows, alphas * problem.n_windows)
        )
    raws = _gains_together(jobs, tol, max_iter)
    values: list[np.ndarray] = []
    for problem, (Ks, _), w, v in zip(problems, params, whole, windows):
        if w is None:
            values.append(np.empty(0))
            continue
        results = mvmd_results(raws[w], problem.spec, problem.offset, problem.channels.shape[1])
        fitness = np.array([cfv(r, weights) for r in results])
        if v is not None and problem.validation is not None:
            validation = problem.validation
            F = repeated[v].best_filters(
                raws[v], validation.window - validation.hop, rule
            )  # decided rows
            misses = validation.miss_fractions(F).reshape(problem.n_windows, len(Ks)).mean(axis=0)
            fitness = fitness + validation.weight * misses
        values.append(fitness)
    return values


def tune_signals(
    signals: Sequence[np.ndarray],
    *,
    population: int = 8,
    iterations: int = 8,
    k_bounds: tuple[int, int] = (2, 6),
    alpha_bounds: tuple[float, float] = (50.0, 5000.0),
    weights: Sequence[float] = DEFAULT_WEIGHTS,
    seed: int = 0,
    tol: float = 1e-6,
    max_iter: int = 300,
    validations: Sequence[ValidationFault | None] | None = None,
    rule: str = DEFAULT_MODE_RULE,
) -> list[TuneResult]:
    """:func:`tune_signal` of several signals at once (e.g. the sensor types of one
    calibration window), each with its own validation fault (or None).

    The searches advance together: each WOA iteration's candidates of all the signals are
    decomposed in one batched MVMD call per frequency grid, which shares the per-iteration
    cost of the MVMD loop. Each search keeps its own generator (``seed``) and cache, and a
    decomposition's floats do not depend on the rows batched with it, so every result is
    the one :func:`tune_signal` gives for that signal alone (``seconds`` is the wall time
    of the joint search).
    """
    _check_search(population, k_bounds, alpha_bounds, weights)
    checks = [None] * len(signals) if validations is None else list(validations)
    if len(checks) != len(signals):
        raise DetectorConfigError("give one validation fault (or None) per signal")
    start = time.perf_counter()
    problems = []
    for signal, validation in zip(signals, checks):
        signal = np.asarray(signal, dtype=np.float64)
        starts = validation_windows(signal.shape[-1], validation.window) if validation else []
        if validation is not None and not starts:
            raise CalibrationError(
                f"tuning segment has {signal.shape[-1]} samples; the validation fault needs one"
                f" window of {validation.window}"
            )
        channels = signal if signal.ndim == 2 else signal[None]
        spec, freqs, offset = spectrum(channels)
        spectra = None
        if validation is not None:
            spectra = WindowSpectra.of(
                np.stack([channels[:, s : s + validation.window].T for s in starts])
            )
        search = WoaSearch(
            [k_bounds[0], alpha_bounds[0]],
            [k_bounds[1], alpha_bounds[1]],
            integer=[True, False],
            population=population,
            iterations=iterations,
            rng=np.random.default_rng(seed),
        )
        problems.append(
            _Problem(
                channels,
                spec,
                freqs,
                offset,
                channel_power(spec),
                validation,
                spectra,
                len(starts),
                search,
            )
        )
    while not all(p.search.done for p in problems):
        running = [p for p in problems if not p.search.done]
        requests = [p.search.ask() for p in running]
        for problem, values in zip(
            running, _fitness(running, requests, weights, tol, max_iter, rule)
        ):
            problem.search.tell(values)
    seconds = time.perf_counter() - start
    results = []
    for signal, problem in zip(signals, problems):
        found = problem.search.result()
        shape = np.shape(signal)
        results.append(
            TuneResult(
                K=int(found.best[0]),
                alpha=float(found.best[1]),
                fitness=found.best_fitness,
                curve=[float(v) for v in found.curve],
                evaluations=found.n_evaluations,
                seconds=seconds,
                settings={
                    "population": population,
                    "iterations": iterations,
                    "k_bounds": list(k_bounds),
                    "alpha_bounds": list(alpha_bounds),
                    "weights": list(weights),
                    "seed": seed,
                    "samples": int(shape[-1]),
                    "channels": int(shape[0]) if len(shape) == 2 else 1,
                    "fitness": "cfv" if problem.validation is None else "cfv+delay",
                    "validation": None
                    if problem.validation is None
                    else asdict(problem.validation),
                },
            )
        )
    return results


def tune_signal(
    signal: np.ndarray,
    *,
    population: int = 8,
    iterations: int = 8,
    k_bounds: tuple[int, int] = (2, 6),
    alpha_bounds: tuple[float, float] = (50.0, 5000.0),
    weights: Sequence[float] = DEFAULT_WEIGHTS,
    seed: int = 0,
    tol: float = 1e-6,
    max_iter: int = 300,
    validation: ValidationFault | None = None,
    rule: str = DEFAULT_MODE_RULE,
) -> TuneResult:
    """WOA search of (K, alpha) minimising CFV for one multichannel signal (C, T).

    The whole population of each WOA iteration is decomposed in one batched MVMD call.
    With ``validation``, the fitness is ``CFV + weight * miss``, ``miss`` the expected
    missed fraction of :meth:`ValidationFault.miss_fraction` averaged over a few windows of
    the signal (each decomposed with the candidate, its u_best filter taken, u_best chosen
    by ``rule``, :data:`~imufdi_cli.detectors.woa_mvmd_glt.windows.MODE_RULES`).
    """
    return tune_signals(
        [signal],
        population=population,
        iterations=iterations,
        k_bounds=k_bounds,
        alpha_bounds=alpha_bounds,
        weights=weights,
        seed=seed,
        tol=tol,
        max_iter=max_iter,
        validations=[validation],
        rule=rule,
    )[0]


def tune(
    block: ImuBlock,
    array: ArrayConfig,
    sensor_type: str = "gyro",
    *,
    fitness: str = "cfv+delay",
    validation_step: float = 4.0,
    delay_weight: float = 100.0,
    window: int = 50,
    overlap: int = 40,
    detector_alpha: float = 0.01,
    **woa_params: Any,
) -> TuneResult:
    """Tune (K, alpha) on the measurements of one sensor type of a (fault-free) block.

    Parameters
    ----------
    block : ImuBlock
        The segment to tune on (e.g. the first 2.5 s of a log).
    array : ArrayConfig
    sensor_type : str
    fitness : {"cfv+delay", "cfv"}
        ``cfv``: the paper's CFV alone (its minimum is the alpha upper bound, see
        docs/algorithms/woa-mvmd-glt.md); ``cfv+delay`` adds ``delay_weight`` times the
        expected missed fraction of a ``validation_step``-sigma step (:class:`ValidationFault`)
        on the detector's window grid (``window``, ``overlap``) at level ``detector_alpha``.
    **woa_params
        ``population``, ``iterations``, ``k_bounds``, ``alpha_bounds``, ``weights``, ``seed``,
        ``tol``, ``max_iter`` (see :func:`tune_signal`).

    Returns
    -------
    TuneResult
    """
    triads = block.get(sensor_type)
    if triads is None or array.n_sensors(sensor_type) == 0:
        raise InputDataError(f"cannot tune: the log has no {sensor_type} data")
    values = array.select(triads, sensor_type)
    if values.shape[0] < MIN_SAMPLES:
        raise CalibrationError(
            f"tuning segment has {values.shape[0]} samples; at least {MIN_SAMPLES} are needed"
        )
    validation = None
    if fitness == "cfv+delay":
        validation = make_validation(
            values.shape[1], window, window - overlap, validation_step, delay_weight, detector_alpha
        )
    elif fitness != "cfv":
        raise DetectorConfigError(f"fitness: valid: {', '.join(FITNESS_CHOICES)}")
    result = tune_signal(values.T, validation=validation, **woa_params)
    result.sensor_type = sensor_type
    return result


def make_validation(
    n_sensors: int, window: int, hop: int, step: float, weight: float, alpha: float
) -> ValidationFault:
    """The :class:`ValidationFault` of a detector with n sensors of a type at level alpha."""
    dof = n_sensors - 3
    if dof < 1:
        raise DetectorConfigError(f"the GLT needs at least 4 sensors, got {n_sensors}")
    if window < MIN_SAMPLES or not 1 <= hop <= window:
        raise DetectorConfigError(
            f"validation fault: window must be >= {MIN_SAMPLES} and overlap in [0, window),"
            f" got window {window}, overlap {window - hop}"
        )
    if not (step > 0 and weight >= 0):
        raise DetectorConfigError(
            f"validation fault: validation_step must be > 0 and delay_weight >= 0,"
            f" got {step}, {weight}"
        )
    return ValidationFault(
        window=window,
        hop=hop,
        step=float(step),
        dof=dof,
        threshold=float(chi2.ppf(1.0 - alpha, dof)),
        projection=dof / n_sensors,
        weight=float(weight),
    )
