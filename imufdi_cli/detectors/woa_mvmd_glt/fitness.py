"""WOA-MVMD-GLT fitness: the composite fitness value CFV (paper §2.6) and the validation fault
(beyond the paper) whose expected missed fraction joins it in ``fitness=cfv+delay``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imufdi_cli.detectors.mvmd import (
    MvmdResult,
)

DEFAULT_WEIGHTS: tuple[float, float, float] = (1.0, 1.0, 1.0)


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
    from scipy.signal import hilbert  # imported when a fitness is computed, not on import

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
        function ``1 - P = chndtr(threshold, n - 3, lambda)`` covers the whole stack, once
        per distinct (row, column) pair (row t reads column 0 for every k >= t).
        """
        from scipy.special import chndtr

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
        # the offsets k >= t of row t all read column 0: chndtr once per distinct (row,
        # column) pair, spread back into an array of signal's memory order (that of the
        # plain elementwise evaluation, in which the product below sums)
        _, first, inverse = np.unique(
            np.arange(rows.size)[:, None] * L + columns, return_index=True, return_inverse=True
        )
        picked = signal.reshape(signal.shape[0], -1)[:, first]
        noncentrality = self.step**2 * self.projection * picked**2
        missed = np.empty_like(signal)  # (R, hop, distinct)
        missed[...] = chndtr(self.threshold, self.dof, noncentrality)[:, inverse]
        return np.asarray((missed @ weights).sum(axis=1) / (rows.size * horizon))


def validation_windows(n_samples: int, window: int, count: int = 4) -> list[int]:
    """Start indices of ``count`` windows spread over a tuning segment of ``n_samples``."""
    if n_samples < window:
        return []
    return sorted({int(v) for v in np.linspace(0, n_samples - window, count).round()})
