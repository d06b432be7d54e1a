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
from imufdi_cli.detectors.woa import woa
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
from imufdi_cli.quantiles import chi2  # scipy.stats' floats without its import

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
        Wall time of the search.
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
        try:
            data = json.loads(text)
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


def _validation_misses(
    validation: ValidationFault,
    spectra: WindowSpectra,
    n_windows: int,
    Ks: list[int],
    alphas: list[float],
    tol: float,
    max_iter: int,
    rule: str = DEFAULT_MODE_RULE,
) -> np.ndarray:
    """(P,) expected missed fraction of the validation fault for each of P candidates,
    averaged over the ``n_windows`` validation windows of ``spectra``."""
    # every (validation window, candidate) pair in one batched decomposition,
    # window-major: rows [w * P, (w + 1) * P) are the P candidates on window w
    stacked = spectra.repeat(len(Ks))
    raw = mvmd_gains(
        stacked.power,
        stacked.freqs,
        Ks * n_windows,
        alphas * n_windows,
        tol=tol,
        max_iter=max_iter,
        history=False,
    )
    F = stacked.best_filters(raw, validation.window - validation.hop, rule)  # decided rows
    return validation.miss_fractions(F).reshape(n_windows, len(Ks)).mean(axis=0)


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
    _check_search(population, k_bounds, alpha_bounds, weights)
    signal = np.asarray(signal, dtype=np.float64)
    start = time.perf_counter()

    starts = validation_windows(signal.shape[-1], validation.window) if validation else []
    if validation is not None and not starts:
        raise CalibrationError(
            f"tuning segment has {signal.shape[-1]} samples; the validation fault needs one"
            f" window of {validation.window}"
        )

    channels = signal if signal.ndim == 2 else signal[None]
    spec, freqs, offset = spectrum(channels)
    power = channel_power(spec)
    spectra = None
    if validation is not None:
        spectra = WindowSpectra.of(
            np.stack([channels[:, s : s + validation.window].T for s in starts])
        )

    def fitness(candidates: np.ndarray) -> np.ndarray:
        Ks = [int(k) for k in candidates[:, 0]]
        alphas = [float(a) for a in candidates[:, 1]]
        raw = mvmd_gains(power, freqs, Ks, alphas, tol=tol, max_iter=max_iter, history=False)
        results = mvmd_results(raw, spec, offset, channels.shape[1])
        values = np.array([cfv(r, weights) for r in results])
        if validation is None or spectra is None:
            return values
        misses = _validation_misses(
            validation, spectra, len(starts), Ks, alphas, tol, max_iter, rule
        )
        return values + validation.weight * misses

    found = woa(
        fitness,
        [k_bounds[0], alpha_bounds[0]],
        [k_bounds[1], alpha_bounds[1]],
        integer=[True, False],
        population=population,
        iterations=iterations,
        rng=np.random.default_rng(seed),
    )
    return TuneResult(
        K=int(found.best[0]),
        alpha=float(found.best[1]),
        fitness=found.best_fitness,
        curve=[float(v) for v in found.curve],
        evaluations=found.n_evaluations,
        seconds=time.perf_counter() - start,
        settings={
            "population": population,
            "iterations": iterations,
            "k_bounds": list(k_bounds),
            "alpha_bounds": list(alpha_bounds),
            "weights": list(weights),
            "seed": seed,
            "samples": int(signal.shape[-1]),
            "channels": int(signal.shape[0]) if signal.ndim == 2 else 1,
            "fitness": "cfv" if validation is None else "cfv+delay",
            "validation": None if validation is None else asdict(validation),
        },
    )


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
