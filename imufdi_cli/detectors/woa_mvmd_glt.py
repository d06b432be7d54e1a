"""WOA-MVMD-GLT: GLT on the MVMD mode most correlated with the raw signal.

Li, Sun, Tian, He, Zhu, "Fault Detection and Isolation of MEMS IMU Array Based on
WOA-MVMD-GLT", Micromachines 17(3):374, 2026, §2.3-2.7 and §3.

For one sensor type (n sensors, measurement matrix H, measurements m (N, n)):

1. Windows of ``window`` samples, ``hop = window - overlap`` apart, cover the log; every
   window is decomposed by MVMD (:mod:`imufdi_cli.detectors.mvmd`, all n channels jointly,
   K modes sharing their centre frequencies).
2. ``u_best``: the mode with the largest normalised inner product with the raw window,
   ``<u_k, x> / (|u_k| |x|)`` over all channels and samples (uncentred: the mean is part of
   the signal, so the mode that carries the rates and the biases is the one kept, §2.5).
   Since MVMD applies one filter to all channels (mvmd.py, "exact reduction"),
   ``V u_best`` is the same filter applied to the parity vector: the motion still cancels.
3. GLT (§2.1, eqs. 5-7, :mod:`imufdi_cli.detectors.parity`) on u_best, whitened with the
   per-sensor sigma and with the per-sensor biases estimated on u_best of the calibration
   window (sigma re-estimated in the u_best domain: the filter removes most of the noise,
   which is why the step fault is detected with a small MAR). Threshold chi2_{1-alpha}(n-3).
4. Each sample gets its row from the first window that contains it, where it lies in the
   last ``hop`` samples (``end``, default: causal, decided when that window ends, at most
   ``hop - 1`` samples after the sample; the first ``window - hop`` samples of the log get
   no decision), from the window where it is central (``centre``), or the smallest
   statistic of all windows containing it (``min``; ``centre`` and ``min`` use windows that
   end up to ``window - 1`` samples later, so a sample's row depends on what follows it).
   The output depends only on the sample index in the log, not on how the pipeline cuts
   blocks; :attr:`WoaMvmdGltDetector.lookahead_samples` is the longest hold-back.

(K, alpha) come from the ``params`` JSON file written by ``imufdi tune`` (:func:`tune`), from
the ``K`` and ``mvmd_alpha`` parameters, or, by default, are tuned by the whale optimization
algorithm (:mod:`imufdi_cli.detectors.woa`) on the calibration window, minimising the
composite fitness CFV (§2.6, :func:`cfv_components` for the exact definitions).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from scipy.signal import hilbert
from scipy.stats import chi2

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    NO_ISOLATION,
    NOT_ISOLABLE,
    TYPES,
    DetectionBlock,
    DetectorBase,
    Param,
    parse_sensor_types,
)
from imufdi_cli.detectors.mvmd import (
    MIN_SAMPLES,
    MvmdResult,
    channel_power,
    check_mvmd_params,
    mirror_extend,
    mvmd_gains,
    mvmd_results,
    spectrum,
)
from imufdi_cli.detectors.parity import (
    isolable_sensors,
    isolation_statistics,
    parity_matrix,
    residual_sigma,
    residuals,
    whiten,
)
from imufdi_cli.detectors.woa import woa
from imufdi_cli.errors import (
    ArrayTooSmallError,
    CalibrationError,
    DetectorConfigError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock

DEFAULT_WEIGHTS: tuple[float, float, float] = (1.0, 1.0, 1.0)
COMBINE_CHOICES: tuple[str, ...] = ("end", "centre", "min")


# --- fitness (§2.6) --------------------------------------------------------------------


def cfv_components(result: MvmdResult) -> tuple[float, float, float]:
    """The three terms of the composite fitness value of one decomposition (§2.6).

    - envelope entropy: per mode k and channel c, the Hilbert envelope e = |hilbert(u_kc)|
      normalised to a distribution p = e / sum(e); ``H = -sum p ln p / ln T`` (in [0, 1]; 1
      for a flat envelope). Mean over modes and channels.
    - inter-mode correlation: ``|rho(u_kc, u_jc)|`` (Pearson) averaged over mode pairs
      k < j and channels (0 when K = 1). In [0, 1].
    - spectral compactness: per mode, the power-weighted spread of its spectrum around its
      own mean frequency, ``sqrt(sum (f - fbar_k)^2 P_k(f) / sum P_k(f)) / 0.5`` with
      ``P_k(f) = sum_c |U_kc(f)|^2`` on the rfft grid of the mode (f in cycles/sample);
      mean over modes. In [0, 1]; small for narrow-band modes.

    Returns
    -------
    (entropy, correlation, compactness) : floats
    """
    modes = result.modes
    n_modes, _, n_samples = modes.shape
    envelope = np.abs(hilbert(modes, axis=-1))
    total = envelope.sum(axis=-1, keepdims=True)
    prob = envelope / np.where(total > 0, total, 1.0)
    logp = np.log(np.where(prob > 0, prob, 1.0))
    entropy = float((-(prob * logp).sum(axis=-1) / np.log(n_samples)).mean())
    if n_modes > 1:
        centred = modes - modes.mean(axis=-1, keepdims=True)
        norms = np.linalg.norm(centred, axis=-1, keepdims=True)
        unit = centred / np.where(norms > 0, norms, 1.0)
        corr = np.abs(np.einsum("kct,jct->ckj", unit, unit))
        upper = np.triu_indices(n_modes, 1)
        correlation = float(corr[:, upper[0], upper[1]].mean())
    else:
        correlation = 0.0
    spec = np.fft.rfft(modes, axis=-1)
    power = (spec.real**2 + spec.imag**2).sum(axis=1)  # (K, F)
    freqs = np.arange(power.shape[1]) / n_samples
    mass = power.sum(axis=1)
    safe = np.where(mass > 0, mass, 1.0)
    mean_f = power @ freqs / safe
    spread = np.sqrt((power * (freqs[None, :] - mean_f[:, None]) ** 2).sum(axis=1) / safe)
    compactness = float(np.where(mass > 0, spread / 0.5, 1.0).mean())
    return entropy, correlation, compactness


def cfv(result: MvmdResult, weights: Sequence[float] = DEFAULT_WEIGHTS) -> float:
    """CFV = w1 * envelope entropy + w2 * inter-mode correlation + w3 * compactness (§2.6)."""
    terms = cfv_components(result)
    return float(sum(w * t for w, t in zip(weights, terms)))


# --- validation fault (beyond the paper) -----------------------------------------------

FITNESS_CHOICES: tuple[str, ...] = ("cfv+delay", "cfv")
OUTLIER_CHOICES: tuple[str, ...] = ("clip", "variance", "ignore")


@dataclass(frozen=True)
class ValidationFault:
    """A step on one sensor, used to score how a candidate (K, alpha) delays detection.

    CFV alone decreases monotonically as alpha grows (narrower modes have flatter envelopes
    and smaller spectral spread), so WOA returns the alpha upper bound whatever it is. The
    detection statistic pays for that smoothing in delay: this fault measures it.

    Attributes
    ----------
    window, hop : int
        The detector's window grid (rows are decided in the last ``hop`` of a window).
    step : float
        Step amplitude in units of the sensor's noise sigma.
    dof : int
        n - 3, degrees of freedom of the GLT statistic.
    threshold : float
        chi2_{1-alpha}(n - 3).
    projection : float
        Mean diagonal of the whitened parity projector, (n - 3) / n: the share of a
        one-sensor step that reaches the parity space.
    weight : float
        Weight of the expected missed fraction in the fitness.
    horizon : int
        Samples after the onset over which misses are counted (default 4 windows).
    """

    window: int
    hop: int
    step: float
    dof: int
    threshold: float
    projection: float
    weight: float = 1.0
    horizon: int = 0

    def miss_fraction(self, F: np.ndarray) -> float:
        """Expected fraction of missed fault samples over the horizon, for filter F (L, L).

        A sample k samples after the onset is decided on row t of a window (t uniformly in
        the last ``hop`` rows); the step covers columns ``c = max(t - k, 0)`` .. L - 1, so the
        GLT statistic (eq. 5) is noncentral chi2(n - 3) with noncentrality
        ``step^2 * projection * (sum_{tau >= c} F[t, tau])^2 / |F[t]|^2`` (the whitened step
        through the filter, against the filtered noise). Detection probability
        ``P(chi2'(n - 3, lambda) > threshold)``; the result is the mean of 1 - P over t and
        over k = 0 .. horizon - 1 (k >= t: the whole window carries the step).
        """
        return float(self.miss_fractions(np.asarray(F)[None])[0])

    def miss_fractions(self, F: np.ndarray) -> np.ndarray:
        """:meth:`miss_fraction` of a stack of filters F (R, L, L), one value per filter
        (or of their last ``hop`` rows, (R, hop, L): the only rows it reads).

        Offsets ``k >= L - 1`` all see the step on every column (c = 0), so the
        probabilities are computed for ``k < L`` only and the last one weighted by the
        offsets it stands for; one vectorised call of the noncentral chi2 distribution
        function ``1 - P = chndtr(threshold, n - 3, lambda)`` covers the whole stack.
        """
        from scipy.special import chndtr  # imported when used (start-up time)

        F = np.asarray(F, dtype=np.float64)
        L = F.shape[-1]
        horizon = self.horizon or 4 * self.window
        rows = np.arange(L - self.hop, L)
        kept = F[:, -self.hop :]  # (R, hop, L): the rows decided (or only those given)
        tails = np.cumsum(kept[..., ::-1], axis=-1)[..., ::-1]  # tails[., r, c] = sum_{tau>=c}
        norms = np.sqrt(np.einsum("rij,rij->ri", kept, kept))
        distinct = min(horizon, L)
        k = np.arange(distinct)
        weights = np.ones(distinct)
        if horizon > distinct:
            weights[-1] += horizon - distinct  # k >= L - 1: columns all 0, as k = L - 1
        columns = np.maximum(rows[:, None] - k[None, :], 0)  # (hop, distinct)
        signal = tails[:, np.arange(rows.size)[:, None], columns] / norms[:, :, None]
        noncentrality = self.step**2 * self.projection * signal**2
        missed = chndtr(self.threshold, self.dof, noncentrality)  # (R, hop, distinct)
        return np.asarray((missed @ weights).sum(axis=1) / (rows.size * horizon))


def validation_windows(n_samples: int, window: int, count: int = 4) -> list[int]:
    """Start indices of ``count`` windows spread over a tuning segment of ``n_samples``."""
    if n_samples < window:
        return []
    return sorted({int(v) for v in np.linspace(0, n_samples - window, count).round()})


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
) -> TuneResult:
    """WOA search of (K, alpha) minimising CFV for one multichannel signal (C, T).

    The whole population of each WOA iteration is decomposed in one batched MVMD call.
    With ``validation``, the fitness is ``CFV + weight * miss``, ``miss`` the expected
    missed fraction of :meth:`ValidationFault.miss_fraction` averaged over a few windows of
    the signal (each decomposed with the candidate, its u_best filter taken).
    """
    if population < 2:
        raise DetectorConfigError(f"WOA population must be >= 2, got {population}")
    if not 1 <= k_bounds[0] <= k_bounds[1]:
        raise DetectorConfigError(f"K bounds must satisfy 1 <= low <= high, got {k_bounds}")
    if not 0 < alpha_bounds[0] <= alpha_bounds[1]:
        raise DetectorConfigError(f"alpha bounds must satisfy 0 < low <= high, got {alpha_bounds}")
    if len(weights) != 3:
        raise DetectorConfigError("CFV needs three weights (entropy, correlation, compactness)")
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
        # every (validation window, candidate) pair in one batched decomposition,
        # window-major: rows [w * P, (w + 1) * P) are the P candidates on window w
        stacked = spectra.repeat(len(Ks))
        raw = mvmd_gains(
            stacked.power,
            stacked.freqs,
            Ks * len(starts),
            alphas * len(starts),
            tol=tol,
            max_iter=max_iter,
            history=False,
        )
        _, F = stacked.u_best(raw, validation.window - validation.hop)  # decided rows
        misses = validation.miss_fractions(F).reshape(len(starts), len(Ks)).mean(axis=0)
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


# --- windowed decomposition ------------------------------------------------------------


def best_mode(result: MvmdResult, window: np.ndarray) -> int:
    """Index of u_best: the mode with the largest uncentred normalised inner product
    ``<u_k, x> / (|u_k| |x|)`` with the raw window (over all channels and samples).

    Parameters
    ----------
    result : MvmdResult of ``window.T``
    window : ndarray, shape (L, n)
    """
    modes = result.modes  # (K, n, L)
    inner = np.einsum("kct,ct->k", modes, window.T)
    norms = np.linalg.norm(modes.reshape(modes.shape[0], -1), axis=1)
    score = inner / np.where(norms > 0, norms, np.inf)
    return int(np.argmax(score))


def filter_matrix(gains: np.ndarray, n_samples: int) -> np.ndarray:
    """The linear map x -> u of one MVMD mode on a window: ``u = F x`` (per channel).

    ``F = crop . irfft . diag(g) . rfft . mirror`` (mvmd.py), built by filtering the
    identity. Row t gives the weights of output sample t: its noise variance is
    ``sigma^2 sum_tau F[t, tau]^2`` and a constant bias b appears as ``b sum_tau F[t, tau]``.

    Parameters
    ----------
    gains : ndarray, shape (n_samples + 1,)
    n_samples : int

    Returns
    -------
    F : ndarray, shape (n_samples, n_samples)
    """
    extended, offset = mirror_extend(np.eye(n_samples))  # (L, 2L): row tau = impulse at tau
    response = np.fft.irfft(np.fft.rfft(extended, axis=-1) * gains, n=2 * n_samples, axis=-1)
    return np.ascontiguousarray(response[:, offset : offset + n_samples].T)


_IMPULSE_SPECTRA: dict[int, np.ndarray] = {}


def _impulse_spectra(n_samples: int) -> np.ndarray:
    """rfft of the mirror-extended unit impulses of a window of n samples, (n, n + 1)."""
    cached = _IMPULSE_SPECTRA.get(n_samples)
    if cached is None:
        extended, _ = mirror_extend(np.eye(n_samples))
        cached = np.fft.rfft(extended, axis=-1)
        if len(_IMPULSE_SPECTRA) < 16:
            _IMPULSE_SPECTRA[n_samples] = cached
    return cached


_FILTER_BASES: dict[int, np.ndarray] = {}


def filter_matrices(gains: np.ndarray, n_samples: int, first_row: int = 0) -> np.ndarray:
    """:func:`filter_matrix` of a stack of gains (W, L + 1), rows ``first_row`` .. L - 1.

    F is linear in the gains, ``F = sum_f g(f) B_f`` with ``B_f`` the filter of a unit
    gain at bin f (built once per window length with the FFTs of :func:`filter_matrix`),
    so a stack is one matrix product; equal to :func:`filter_matrix` up to rounding
    (about 1e-15 of the largest weight).

    Returns
    -------
    F : ndarray, shape (W, L - first_row, L)
    """
    gains = np.asarray(gains, dtype=np.float64)
    basis = _FILTER_BASES.get(n_samples)
    if basis is None:
        offset = n_samples // 2
        unit = np.fft.irfft(
            _impulse_spectra(n_samples)[None] * np.eye(n_samples + 1)[:, None, :],
            n=2 * n_samples,
            axis=-1,
        )
        basis = np.ascontiguousarray(np.swapaxes(unit[..., offset : offset + n_samples], 1, 2))
        if len(_FILTER_BASES) < 16:
            _FILTER_BASES[n_samples] = basis  # (L + 1, L, L)
    kept = basis[:, first_row:, :]
    flat = gains @ kept.reshape(n_samples + 1, -1)
    return flat.reshape(gains.shape[0], n_samples - first_row, n_samples)


@dataclass
class WindowSpectra:
    """Spectra of a stack of windows, ready for a batched MVMD (:func:`decompose_windows`).

    Attributes
    ----------
    x : ndarray, shape (W, n, L)
        The windows, channels first.
    spec : ndarray, shape (W, n, L + 1), complex
        rfft of the mirror-extended windows.
    power : ndarray, shape (W, L + 1)
        Channel-summed power spectra.
    freqs : ndarray, shape (L + 1,), cycles/sample
    offset : int
        First original sample in the mirror extension.
    """

    x: np.ndarray
    spec: np.ndarray
    power: np.ndarray
    freqs: np.ndarray
    offset: int

    @classmethod
    def of(cls, windows: np.ndarray) -> WindowSpectra:
        """Spectra of windows (W, L, n) (non-finite values: DetectorConfigError)."""
        windows = np.asarray(windows, dtype=np.float64)
        if not np.all(np.isfinite(windows)):
            raise DetectorConfigError("MVMD: signal has non-finite values")
        n_samples = windows.shape[1]
        x = np.swapaxes(windows, 1, 2)  # (W, n, L)
        extended, offset = mirror_extend(x)
        spec = np.fft.rfft(extended, axis=-1)
        freqs = np.arange(n_samples + 1) / (2 * n_samples)
        return cls(x, spec, channel_power(spec), freqs, offset)

    def repeat(self, count: int) -> WindowSpectra:
        """Each window repeated ``count`` times in a row (window-major)."""
        return WindowSpectra(
            np.repeat(self.x, count, axis=0),
            np.repeat(self.spec, count, axis=0),
            np.repeat(self.power, count, axis=0),
            self.freqs,
            self.offset,
        )

    def u_best(
        self, raw: Sequence[tuple[np.ndarray, np.ndarray, int, bool]], first_row: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """u_best (W, L, n) and rows ``first_row`` .. L - 1 of its filter (W, L - first_row,
        L) from the outputs of :func:`mvmd_gains` (one per window), chosen as
        :func:`best_mode` does (modes sorted by centre frequency), the filter as
        :func:`filter_matrices`."""
        n_windows, _, n_samples = self.x.shape
        k_max = max(g.shape[0] for g, _, _, _ in raw)
        gains = np.zeros((n_windows, k_max, n_samples + 1))
        omega = np.full((n_windows, k_max), np.inf)  # unused modes sort last
        for w, (g, history, _, _) in enumerate(raw):
            gains[w, : g.shape[0]] = g
            omega[w, : g.shape[0]] = history[-1]
        order = np.argsort(omega, axis=1, kind="stable")
        gains = np.take_along_axis(gains, order[..., None], axis=1)
        unused = ~np.isfinite(np.take_along_axis(omega, order, axis=1))
        modes = np.fft.irfft(gains[:, :, None, :] * self.spec[:, None], n=2 * n_samples, axis=-1)
        modes = modes[..., self.offset : self.offset + n_samples]  # (W, K, n, L)
        inner = np.einsum("wkct,wct->wk", modes, self.x)
        norms = np.linalg.norm(modes.reshape(n_windows, k_max, -1), axis=2)
        score = inner / np.where(norms > 0, norms, np.inf)
        score[unused] = -np.inf
        best = np.argmax(score, axis=1)
        rows = np.arange(n_windows)
        u = np.ascontiguousarray(np.swapaxes(modes[rows, best], 1, 2))
        return u, filter_matrices(gains[rows, best], n_samples, first_row)


def decompose_windows(
    windows: np.ndarray,
    Ks: Sequence[int],
    alphas: Sequence[float],
    *,
    tol: float,
    max_iter: int,
    first_row: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """u_best of each window of a stack and its filter matrix, by one batched MVMD.

    Window w is decomposed with ``Ks[w]`` modes and penalty ``alphas[w]`` (the iteration
    of :func:`~imufdi_cli.detectors.mvmd.mvmd_gains`, all windows together), u_best is
    chosen as :func:`best_mode` does and its filter built as :func:`filter_matrix`: the
    same values as one window at a time.

    Parameters
    ----------
    windows : ndarray, shape (W, L, n)
        W windows of L samples of n channels.
    Ks, alphas : sequences of W
    tol, max_iter : MVMD convergence settings
    first_row : int
        First row of the filter returned (the rows a caller uses).

    Returns
    -------
    u : ndarray, shape (W, L, n)
        u_best of each window (same units).
    F : ndarray, shape (W, L - first_row, L)
        Rows of its filter: ``u[w, first_row:] = F[w] @ windows[w]``.
    """
    spectra = WindowSpectra.of(windows)
    raw = mvmd_gains(
        spectra.power,
        spectra.freqs,
        list(Ks),
        list(alphas),
        tol=tol,
        max_iter=max_iter,
        history=False,
    )
    return spectra.u_best(raw, first_row)


class _WindowStream:
    """Overlapping windows on a stream of (N, n) rows; emits per-sample rows in order.

    Windows start at ``j * hop`` (global sample index) and hold ``window`` samples. A
    row's value is taken from the window that has it in its last ``hop`` samples (``end``;
    rows before ``window - hop`` are emitted at once as quiet, undecided rows), from the
    window that has it in its central ``hop`` samples (``centre``) or is the row-wise
    minimum of the statistic over all windows containing it (``min``), exactly as if the
    whole log were processed at once.
    """

    #: Most windows evaluated in one call (bounds the memory of a large block).
    BATCH: ClassVar[int] = 512

    def __init__(self, window: int, hop: int, combine: str) -> None:
        self.window = window
        self.hop = hop
        self.pad = (window - hop) // 2
        self.combine = combine
        self.buffer: np.ndarray | None = None
        self.buffer_start = 0  # global index of buffer[0]
        self.received = 0
        self.emitted = 0  # rows returned so far
        self.next_window = 0  # index j of the next window to evaluate
        self.pending: dict[str, np.ndarray] | None = None  # rows [emitted, ...) being combined
        self.pending_count = 0  # rows of pending filled by at least one window

    def _store(self, start: int, rows: dict[str, np.ndarray]) -> None:
        """Combine a window's rows (global indices start..) into the pending rows."""
        offset = start - self.emitted
        length = rows["statistic"].shape[0]
        need = offset + length
        if self.pending is None:
            self.pending = {key: value[:0].copy() for key, value in rows.items()}
        have = self.pending["statistic"].shape[0]
        if need > have:
            for key, value in rows.items():
                extra = np.empty((need - have, *value.shape[1:]), dtype=value.dtype)
                if key == "statistic":
                    extra.fill(np.inf)
                self.pending[key] = np.concatenate([self.pending[key], extra])
        stat = self.pending["statistic"][offset:need]
        if self.combine == "min":
            better = rows["statistic"] < stat
        else:
            better = np.ones(length, dtype=bool)
        for key, value in rows.items():
            target = self.pending[key][offset:need]
            target[better] = value[better]

    def _take(self, upto: int) -> dict[str, np.ndarray] | None:
        """Emit pending rows up to global index ``upto`` (exclusive)."""
        count = upto - self.emitted
        if count <= 0 or self.pending is None:
            return None
        out = {key: value[:count] for key, value in self.pending.items()}
        self.pending = {key: value[count:] for key, value in self.pending.items()}
        self.emitted = upto
        return out

    def _window_rows(self, start: int, length: int) -> tuple[int, int]:
        """Global rows [lo, hi) a window starting at ``start`` contributes."""
        if self.combine == "min":
            return start, start + length
        if self.combine == "end":
            return start + length - self.hop, start + length
        lo = 0 if start == 0 else start + self.pad
        return lo, start + self.pad + self.hop

    def push(
        self, values: np.ndarray, evaluate: Callable[[np.ndarray, int], dict[str, np.ndarray]]
    ) -> list[dict[str, np.ndarray] | int]:
        """Rows decided by the samples ``values`` (N, columns), oldest first.

        ``evaluate(windows (W, L, columns), first_row)`` gives, for rows ``first_row .. L - 1``
        of each window, a dict of (W, L - first_row, ...) arrays, ``"statistic"`` first. Each
        returned part is such a dict of rows, or an int: that many rows no window decides
        (the first ``window - hop`` rows with ``combine=end``, a tail too short to test).
        """
        if self.buffer is None:
            self.buffer = values.copy()
        else:
            self.buffer = np.concatenate([self.buffer, values])
        self.received += values.shape[0]
        outputs: list[dict[str, np.ndarray] | int] = []
        if self.combine == "end":
            # rows before the first window's last hop are never decided: emit them now
            quiet = min(self.received, self.window - self.hop) - self.emitted
            if quiet > 0:
                outputs.append(quiet)
                self.emitted += quiet
        count = max((self.received - self.window) // self.hop + 1 - self.next_window, 0)
        for first in range(0, count, self.BATCH):
            # all complete windows of the push (at most BATCH at a time) in one evaluation
            starts = (self.next_window + np.arange(min(self.BATCH, count - first))) * self.hop
            local = starts - self.buffer_start
            stack = self.buffer[local[:, None] + np.arange(self.window)]  # (W, L, columns)
            if self.combine == "end":
                rows = evaluate(stack, self.window - self.hop)  # the last hop rows
                # contributions are consecutive, disjoint and final at once: the last hop
                # rows of each window, in order (pending is empty between pushes)
                outputs.append(
                    {
                        key: value.reshape(starts.size * self.hop, *value.shape[2:])
                        for key, value in rows.items()
                    }
                )
                self.emitted = int(starts[-1]) + self.window
                self.next_window += starts.size
                continue
            rows = evaluate(stack, 0)
            for i, start in enumerate(int(s) for s in starts):
                lo, hi = self._window_rows(start, self.window)
                self._store(lo, {k: v[i, lo - start : hi - start] for k, v in rows.items()})
                self.next_window += 1
                # rows before the next window's start (min) / contribution (centre) are final
                final = self.next_window * self.hop
                if self.combine == "centre":
                    final = self.next_window * self.hop + self.pad
                taken = self._take(final)
                if taken is not None:
                    outputs.append(taken)
        # drop buffered samples no window needs any more
        keep_from = self.next_window * self.hop
        if keep_from > self.buffer_start:
            self.buffer = self.buffer[keep_from - self.buffer_start :]
            self.buffer_start = keep_from
        return outputs

    def flush(
        self, evaluate: Callable[[np.ndarray, int], dict[str, np.ndarray]]
    ) -> list[dict[str, np.ndarray] | int]:
        """Cover the tail with one last window ending at the last sample (see :meth:`push`)."""
        if self.emitted >= self.received or self.buffer is None:
            return []
        total = self.received
        length = min(self.window, total)
        start = total - length
        if length < MIN_SAMPLES:
            return [total - self.emitted]
        # the tail window may start before buffer_start: keep the buffer long enough
        if start < self.buffer_start:
            start = self.buffer_start
            length = total - start
            if length < MIN_SAMPLES:
                return [total - self.emitted]
        lo = max(start, self.emitted)
        rows = evaluate(self.buffer[None, start - self.buffer_start :], lo - start)
        self._store(lo, {k: v[0] for k, v in rows.items()})
        out = self._take(total)
        return [out] if out is not None else []


# --- the detector ----------------------------------------------------------------------

#: WOA results of this process, keyed by the tuning segment's bytes and every setting that
#: enters the search (the search is deterministic given them): a campaign's runs of one
#: seed share their calibration window, and so their tuning.
_TUNING_CACHE: dict[tuple[Any, ...], TuneResult] = {}
_TUNING_CACHE_SIZE = 64


def clear_tuning_cache() -> None:
    """Forget the WOA results reused across fits in this process (benchmarks, tests)."""
    _TUNING_CACHE.clear()


def _weights_check(value: Any) -> str | None:
    try:
        parts = [float(v) for v in str(value).split(",")]
    except ValueError:
        return "weights must be three comma-separated numbers, e.g. 1,1,1"
    if len(parts) != 3 or any(not np.isfinite(p) or p < 0 for p in parts):
        return "weights must be three comma-separated non-negative numbers, e.g. 1,1,1"
    return None


@dataclass
class _TypeState:
    sensor_type: str
    n: int
    K: int
    alpha: float
    tuned: dict[str, Any] | None
    sigma: np.ndarray
    bias: np.ndarray
    V: np.ndarray  # whitened parity matrix (n-3, n)
    isolable: np.ndarray
    threshold: float
    stream: _WindowStream
    n_calibration: int = 0  # samples the biases were averaged over
    outlier_variance: float = (
        0.0  # variance added for outliers (variance: SI^2; clip: sigma^2 units)
    )
    outlier_cut: float | None = None  # outliers=clip: level of the standardised residual
    clipped: int = 0  # residual entries clipped so far

    @staticmethod
    def clip_probe(
        values: np.ndarray, bias: np.ndarray, sigma: np.ndarray, V: np.ndarray, cut: float
    ) -> np.ndarray:
        """(N, n) bool: the residuals :meth:`clip` cuts."""
        return _TypeState._clip_shift(values, bias, sigma, V, cut)[1]

    @staticmethod
    def _clip_shift(
        values: np.ndarray, bias: np.ndarray, sigma: np.ndarray, V: np.ndarray, cut: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The move of each sensor by :meth:`clip`, (N, n) in the units of ``values``, and
        which entries were cut, (N, n) bool."""
        projector = V.T @ V
        scale = np.sqrt(np.diag(projector))
        current = np.array(values, dtype=np.float64)
        shift = np.zeros_like(current)
        cut_mask = np.zeros(current.shape, dtype=bool)
        active = np.arange(current.shape[0])
        for _ in range(current.shape[1]):  # one sensor per sample and round
            z = (((current[active] - bias) / sigma) @ projector) / scale
            largest = np.argmax(np.abs(z), axis=1)
            top = z[np.arange(active.size), largest]
            over = np.abs(top) > cut
            if not over.any():
                break
            rows, cols, top = active[over], largest[over], top[over]
            delta = np.sign(top) * (np.abs(top) - cut) * sigma[cols] / scale[cols]
            current[rows, cols] -= delta
            shift[rows, cols] += delta
            cut_mask[rows, cols] = True
            active = rows
        return shift, cut_mask

    def clip(self, values: np.ndarray) -> np.ndarray:
        """Clip each sample's standardised parity residuals at ``outlier_cut``, (N, n).

        Whitened residual ``r = P x_w`` (``P = V^T V``, ``x_w = (x - bias) / sigma``),
        standardised ``z_i = r_i / sqrt(P_ii)`` (``z_i^2`` is the GLT isolation statistic
        of sensor i, eq. 6, since V V^T = I). Per sample, the sensor with the largest
        ``|z_i|``, when it exceeds c, is moved by ``(|z_i| - c) sigma_i / sqrt(P_ii)``
        toward the others, so that ``|z_i| = c``; the residuals are computed again and the
        next largest is cut if still beyond c, until none is (two spikes in one sample are
        both cut). A one-sample spike on one sensor is cut to c; a step larger than c sigma
        is cut too, sample by sample, but stays far above the threshold once u_best
        averages it (the amplitude is estimated on the unclipped signal). Gaussian noise is
        left alone but with probability about 2 n Phi(-c) per sample (3e-3 at c = 4, n = 48).

        One at a time: a fault of hundreds of sigma on one sensor also pushes every other
        sensor's residual past c (by about 1/n of it); cutting them all at once moved the
        healthy sensors toward the faulty one and erased the fault (a 10 deg/s^2 drift went
        undetected from about 1.5 s after its onset). Once the faulty sensor is cut, the
        others' residuals are back under c.
        """
        if self.outlier_cut is None:
            return values
        shift, cut_mask = self._clip_shift(values, self.bias, self.sigma, self.V, self.outlier_cut)
        self.clipped += int(np.count_nonzero(cut_mask))
        return np.asarray(values - shift)


class WoaMvmdGltDetector(DetectorBase):
    """WOA-tuned MVMD + GLT detector (module docstring), CLI name ``woa-mvmd-glt``."""

    name: ClassVar[str] = "woa-mvmd-glt"
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "window": Param("int", 50, "MVMD window length, samples", low=MIN_SAMPLES),
        "overlap": Param("int", 40, "overlap of consecutive windows, samples", low=0),
        "combine": Param(
            "choice",
            "end",
            "per-sample row: from the first window that ends after the sample (causal,"
            " look-ahead hop - 1), the window where it is central, or the min over all"
            " windows containing it (look-ahead window - 1)",
            choices=COMBINE_CHOICES,
        ),
        "outliers": Param(
            "choice",
            "clip",
            "sparse spikes: clip each sample's largest standardised parity residual at"
            " outlier_cut before the decomposition (clip), add their calibration variance to sigma"
            " (variance), or nothing (ignore)",
            choices=OUTLIER_CHOICES,
        ),
        "outlier_cut": Param(
            "float",
            4.0,
            "clip level of outliers=clip, standardised residual",
            low=0.0,
            low_open=True,
        ),
        "fitness": Param(
            "choice",
            "cfv+delay",
            "WOA fitness: the paper's CFV plus the expected missed fraction of a validation"
            " step (cfv+delay), or CFV alone (cfv: picks the alpha upper bound)",
            choices=FITNESS_CHOICES,
        ),
        "validation_step": Param(
            "float", 4.0, "validation step of cfv+delay, in noise sigmas", low=0.0, low_open=True
        ),
        "delay_weight": Param(
            "float", 100.0, "weight of the validation miss fraction in cfv+delay", low=0.0
        ),
        "params": Param("path", None, "JSON file of tuned (K, alpha) from `imufdi tune`"),
        "K": Param("int", None, "number of MVMD modes (skips tuning, with mvmd_alpha)", low=1),
        "mvmd_alpha": Param(
            "float", None, "MVMD bandwidth penalty (f in cycles/sample)", low=0, low_open=True
        ),
        "population": Param("int", 8, "WOA population", low=2),
        "iterations": Param("int", 6, "WOA iterations", low=0),
        "k_min": Param("int", 2, "smallest K searched", low=1),
        "k_max": Param("int", 5, "largest K searched", low=1),
        "alpha_min": Param("float", 50.0, "smallest MVMD alpha searched", low=0, low_open=True),
        "alpha_max": Param("float", 5000.0, "largest MVMD alpha searched", low=0, low_open=True),
        "weights": Param(
            "str",
            "1,1,1",
            "CFV weights w1,w2,w3 (entropy, correlation, compactness)",
            check=_weights_check,
        ),
        "tune_samples": Param("int", 250, "calibration samples used for tuning", low=MIN_SAMPLES),
        "seed": Param("int", 0, "seed of the WOA search", low=0),
        "types": TYPES,
        "tol": Param("float", 1e-6, "MVMD relative convergence tolerance", low=0, low_open=True),
        "max_iter": Param("int", 300, "MVMD iteration cap", low=1),
    }

    def __init__(
        self,
        alpha: float = 0.01,
        window: int = 50,
        overlap: int = 40,
        combine: str = "end",
        outliers: str = "clip",
        outlier_cut: float = 4.0,
        fitness: str = "cfv+delay",
        validation_step: float = 4.0,
        delay_weight: float = 100.0,
        params: str | None = None,
        K: int | None = None,
        mvmd_alpha: float | None = None,
        population: int = 8,
        iterations: int = 6,
        k_min: int = 2,
        k_max: int = 5,
        alpha_min: float = 50.0,
        alpha_max: float = 5000.0,
        weights: str = "1,1,1",
        tune_samples: int = 250,
        seed: int = 0,
        types: str = "gyro,accel",
        tol: float = 1e-6,
        max_iter: int = 300,
    ) -> None:
        arguments = locals()
        values = {key: arguments[key] for key in self.PARAMS}  # each PARAMS name, typed
        self.params = values
        window = int(values["window"])
        overlap = int(values["overlap"])
        if not 0 <= overlap < window:
            raise DetectorConfigError(
                f"{self.name}.overlap: must be >= 0 and < window ({window}), got {overlap}"
            )
        if values["k_min"] > values["k_max"]:
            raise DetectorConfigError(f"{self.name}: k_min must be <= k_max")
        if values["alpha_min"] > values["alpha_max"]:
            raise DetectorConfigError(f"{self.name}: alpha_min must be <= alpha_max")
        if (values["K"] is None) != (values["mvmd_alpha"] is None):
            raise DetectorConfigError(f"{self.name}: give both K and mvmd_alpha, or neither")
        if values["K"] is not None:
            check_mvmd_params(values["K"], values["mvmd_alpha"])
        self.window = window
        self.hop = window - overlap
        self.weights = tuple(float(v) for v in str(values["weights"]).split(","))
        self.types = list(parse_sensor_types(types, self.name))
        self.tuned_file = TuneResult.load(values["params"]) if values["params"] else None
        self._states: dict[str, _TypeState] = {}
        #: Per sensor type: the window evaluation its stream is pushed with (see _evaluator).
        self._evaluators: dict[str, Callable[[np.ndarray, int], dict[str, np.ndarray]]] = {}
        self._array: ArrayConfig | None = None

    @property
    def lookahead_samples(self) -> int:
        """Most samples a row is held back: its decision waits for a window's last sample.

        ``end``: a sample in the last ``hop`` samples of a window is decided when that window
        ends, ``hop - 1`` samples later at most. ``centre`` and ``min``: up to ``window - 1``
        (the first window decides its first sample ``window - 1`` samples late; ``min`` waits
        for the last window containing the sample).
        """
        if self.params["combine"] == "end":
            return self.hop - 1
        return self.window - 1

    def decision_index(self, sample: np.ndarray, n_samples: int) -> np.ndarray:
        """Index of the input sample at which each row's decision is available, (N,).

        Exact for the window grid (``end``: the end of the first window that has the sample
        in its last ``hop``; ``centre``: the end of the window where it is central; ``min``:
        the end of the last window that contains it), capped at the last sample of the log
        (the tail window of ``flush``).
        """
        sample = np.asarray(sample, dtype=np.int64)
        window, hop = self.window, self.hop
        combine = self.params["combine"]
        if combine == "end":
            first = np.maximum(-(-(sample - window + 1) // hop), 0)
            decided = first * hop + window - 1
            decided = np.where(sample < window - hop, sample, decided)  # quiet rows
        elif combine == "centre":
            pad = (window - hop) // 2
            j = np.maximum((sample - pad) // hop, 0)
            decided = j * hop + window - 1
        else:
            decided = (sample // hop) * hop + window - 1
        return np.asarray(np.minimum(decided, n_samples - 1))

    # -- calibration ----------------------------------------------------------------

    def _choose(self, sensor_type: str, values: np.ndarray) -> tuple[int, float, dict | None]:
        p = self.params
        if p["K"] is not None:
            return int(p["K"]), float(p["mvmd_alpha"]), None
        if self.tuned_file is not None:
            return self.tuned_file.K, self.tuned_file.alpha, {"source": "params file"}
        segment = values[: int(p["tune_samples"])]
        validation = None
        if p["fitness"] == "cfv+delay":
            validation = make_validation(
                values.shape[1],
                self.window,
                self.hop,
                float(p["validation_step"]),
                float(p["delay_weight"]),
                float(p["alpha"]),
            )
        settings: dict[str, Any] = {
            "population": int(p["population"]),
            "iterations": int(p["iterations"]),
            "k_bounds": (int(p["k_min"]), int(p["k_max"])),
            "alpha_bounds": (float(p["alpha_min"]), float(p["alpha_max"])),
            "weights": self.weights,
            "seed": int(p["seed"]),
            "tol": float(p["tol"]),
            "max_iter": int(p["max_iter"]),
        }
        segment = np.ascontiguousarray(segment, dtype=np.float64)
        key = (
            hashlib.sha256(segment.tobytes()).hexdigest(),
            segment.shape,
            repr(sorted(settings.items())),
            repr(validation),
        )
        cached = _TUNING_CACHE.get(key)
        if cached is None:
            cached = tune_signal(segment.T, validation=validation, **settings)
            if len(_TUNING_CACHE) >= _TUNING_CACHE_SIZE:
                _TUNING_CACHE.pop(next(iter(_TUNING_CACHE)))
            _TUNING_CACHE[key] = cached
            reused = False
        else:
            reused = True
        record = asdict(cached)
        record["sensor_type"] = sensor_type
        record["reused"] = reused
        return cached.K, cached.alpha, record

    def _decompose(self, K: int, alpha: float) -> Any:
        tol = float(self.params["tol"])
        max_iter = int(self.params["max_iter"])

        def u_best(windows: np.ndarray, first_row: int) -> tuple[np.ndarray, np.ndarray]:
            count = windows.shape[0]
            u, F = decompose_windows(
                windows,
                [K] * count,
                [alpha] * count,
                tol=tol,
                max_iter=max_iter,
                first_row=first_row,
            )
            return u[:, first_row:], F

        return u_best

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        self._array = array
        self._states = {}
        self._evaluators = {}
        for sensor_type in self.types:
            triads = calibration.get(sensor_type)
            n = array.n_sensors(sensor_type)
            if triads is None or n == 0:
                continue
            if n < 4:
                raise ArrayTooSmallError(
                    f"{self.name}: {sensor_type} has {n} sensors; the GLT needs at least 4"
                )
            values = array.select(triads, sensor_type)
            if values.shape[0] < max(self.window, 10):
                raise CalibrationError(
                    f"calibration window has {values.shape[0]} samples; {self.name} needs at"
                    f" least {max(self.window, 10)} (one MVMD window); use --calibrate"
                )
            K, alpha, tuned = self._choose(sensor_type, values)
            decompose = self._decompose(K, alpha)
            # sigma and biases of the raw sensors (many degrees of freedom), carried into the
            # u_best domain exactly through each window's filter matrix (filter_matrix)
            H = array.measurement_matrix(sensor_type)
            sigma = residual_sigma(H, values)
            if np.any(~np.isfinite(sigma)) or np.any(sigma <= 0):
                raise CalibrationError(
                    f"{self.name}: {sensor_type} noise sigma is zero or not finite;"
                    " the calibration window is degenerate"
                )
            outlier_variance = 0.0
            outlier_cut = None
            if self.params["outliers"] == "clip":
                outlier_cut = float(self.params["outlier_cut"])
            if self.params["outliers"] == "variance":
                # sparse spikes, smoothed by u_best, act as extra white noise: their variance
                # (all samples minus the spike-free fit), pooled over the sensors of the type
                plain = residual_sigma(H, values, outlier_cut=None)
                outlier_variance = float(np.mean(np.maximum(plain**2 - sigma**2, 0.0)))
                sigma = np.sqrt(sigma**2 + outlier_variance)
            bias = residuals(H, values).mean(axis=0)
            V = parity_matrix(whiten(H, sigma))
            if outlier_cut is not None:
                # a clipped spike still carries c standardised sigmas: its variance, at the
                # rate spikes were clipped in the calibration window, joins the noise
                probe = _TypeState.clip_probe(values, bias, sigma, V, outlier_cut)
                rate = float(np.mean(probe))
                diagonal = np.einsum("ki,ki->i", V, V)
                outlier_variance = rate * outlier_cut**2
                sigma = sigma * np.sqrt(1.0 + outlier_variance / diagonal)
                V = parity_matrix(whiten(H, sigma))
            state = _TypeState(
                sensor_type=sensor_type,
                n=n,
                K=K,
                alpha=alpha,
                tuned=tuned,
                sigma=sigma,
                bias=bias,
                V=V,
                isolable=isolable_sensors(V),
                threshold=float(chi2.ppf(1.0 - float(self.params["alpha"]), n - 3)),
                stream=_WindowStream(self.window, self.hop, self.params["combine"]),
                n_calibration=int(values.shape[0]),
                outlier_variance=outlier_variance,
                outlier_cut=outlier_cut,
            )
            self._states[sensor_type] = state
            self._evaluators[sensor_type] = self._evaluator(state, decompose)
        if not self._states:
            raise CalibrationError(
                f"{self.name}: no tested sensor type ({', '.join(self.types)}) in the log"
            )

    def _evaluator(self, state: _TypeState, decompose: Any) -> Any:
        def evaluate(windows: np.ndarray, first_row: int) -> dict[str, np.ndarray]:
            # windows (W, L, 2n); the stream carries [clipped | raw] side by side (process);
            # rows first_row .. L - 1 of each window: R = L - first_row
            raw = windows[..., state.n :]
            u, F = decompose(windows[..., : state.n], first_row)  # (W, R, n), (W, R, L)
            noise_gain = np.sqrt(np.einsum("wij,wij->wi", F, F))  # sigma_u = sigma * gain
            dc_gain = F.sum(axis=-1)  # (W, L): bias_u = bias * dc_gain
            # the calibration bias (mean of n_cal samples) is off by N(0, sigma^2 / n_cal),
            # carried as dc_gain * error: its variance against the filtered noise is
            # dc_gain^2 / (gain^2 n_cal) (the filter's effective length over n_cal), not
            # negligible once u_best has averaged the noise down
            inflation = 1.0 + (dc_gain / noise_gain) ** 2 / max(state.n_calibration, 1)
            row_scale = noise_gain * np.sqrt(inflation)
            whitened = (u - dc_gain[..., None] * state.bias) / (
                state.sigma[None, :] * row_scale[..., None]
            )
            p = whitened @ state.V.T
            statistic = np.einsum("...j,...j->...", p, p)  # eq. 5, V V^T = I
            d_fi, _ = isolation_statistics(p, state.V)  # eq. 6
            if state.outlier_cut is not None:  # eq. 7 on the unclipped signal
                raw_white = (F @ raw - dc_gain[..., None] * state.bias) / (
                    state.sigma[None, :] * row_scale[..., None]
                )
                _, amplitude = isolation_statistics(raw_white @ state.V.T, state.V)
            else:
                _, amplitude = isolation_statistics(p, state.V)
            # amplitude of a step in the raw signal: undo whitening and the filter's DC gain
            scale = (
                state.sigma[None, :]
                * (row_scale / np.where(dc_gain != 0, dc_gain, np.nan))[..., None]
            )
            return {"statistic": statistic, "scores": d_fi, "amplitude": amplitude * scale}

        return evaluate

    # -- streaming ------------------------------------------------------------------

    def _rows(self, state: _TypeState, parts: list[dict[str, np.ndarray] | int]) -> DetectionBlock:
        blocks = []
        for part in parts:
            if isinstance(part, int):  # rows no window decides
                blocks.append(DetectionBlock.empty(part, state.n))
                continue
            statistic = part["statistic"]
            count = statistic.shape[0]
            alarm = statistic > state.threshold
            scores = part["scores"]
            safe_scores = np.where(np.isfinite(scores), scores, -np.inf)
            best = np.argmax(safe_scores, axis=1).astype(np.int32)
            isolated = np.where(
                alarm, np.where(state.isolable[best], best, NOT_ISOLABLE), NO_ISOLATION
            ).astype(np.int32)
            amplitude = np.where(isolated >= 0, part["amplitude"][np.arange(count), best], np.nan)
            blocks.append(
                DetectionBlock(
                    statistic=statistic,
                    threshold=np.full(count, state.threshold),
                    alarm=alarm,
                    isolated=isolated,
                    amplitude=amplitude,
                    scores=scores,
                )
            )
        if not blocks:
            return DetectionBlock.empty(0, state.n)
        return DetectionBlock.concatenate(blocks)

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        if not self._states or self._array is None:
            raise CalibrationError(f"{self.name}: fit() must be called before process()")
        out = {}
        for sensor_type, state in self._states.items():
            triads = block.get(sensor_type)
            if triads is None:
                raise InputDataError(f"{self.name}: block has no {sensor_type} data")
            values = self._array.select(triads, sensor_type)
            carried = np.concatenate([state.clip(values), values], axis=1)
            evaluate = self._evaluators[sensor_type]
            out[sensor_type] = self._rows(state, state.stream.push(carried, evaluate))
        return out

    def flush(self) -> dict[str, DetectionBlock]:
        return {
            t: self._rows(s, s.stream.flush(self._evaluators[t])) for t, s in self._states.items()
        }

    def metadata(self) -> dict[str, Any]:
        params = {k: v for k, v in self.params.items()}
        return {
            "params": params,
            "types": {
                t: {
                    "K": s.K,
                    "mvmd_alpha": s.alpha,
                    "tuning": s.tuned,
                    "sigma_u_best": s.sigma.tolist(),
                    "bias_u_best": s.bias.tolist(),
                    "threshold": s.threshold,
                    "window": self.window,
                    "hop": self.hop,
                    "lookahead_samples": self.lookahead_samples,
                    "outlier_variance": s.outlier_variance,
                    "clipped_residuals": s.clipped,
                }
                for t, s in self._states.items()
            },
        }


__all__ = [
    "COMBINE_CHOICES",
    "DEFAULT_WEIGHTS",
    "FITNESS_CHOICES",
    "TuneResult",
    "ValidationFault",
    "WoaMvmdGltDetector",
    "best_mode",
    "cfv",
    "cfv_components",
    "clear_tuning_cache",
    "decompose_windows",
    "filter_matrices",
    "make_validation",
    "tune",
    "tune_signal",
]
