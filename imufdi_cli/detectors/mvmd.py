"""Multivariate variational mode decomposition (MVMD), fast and exact.

MVMD (ur Rehman & Aftab, "Multivariate Variational Mode Decomposition", IEEE TSP 67(23),
2019) splits a C-channel signal into K modes; mode k has one centre frequency omega_k
shared by all channels. It solves, by ADMM (their eqs. 20-23, with the frequency scaling
of the authors' MATLAB code; f in cycles/sample on the one-sided spectrum)::

    u_kc(f)  <- (x_c(f) - sum_{i != k} u_ic(f) - lambda_c(f)/2) / (1 + alpha (f - omega_k)^2)   (A)
    omega_k  <- sum_c sum_f f |u_kc(f)|^2 / sum_c sum_f |u_kc(f)|^2                            (B)
    lambda_c <- lambda_c + tau (sum_k u_kc - x_c)                                               (C)

Gauss-Seidel over k, as in the reference: mode k uses the newest values of modes < k.

Exact reduction used here (the reason this is fast)
--------------------------------------------------
With the reference initialisation u = 0, lambda = 0, every quantity in (A) and (C) is a
real, channel-independent gain times x_c(f): by induction ``u_kc(f) = g_k(f) x_c(f)`` and
``lambda_c(f) = l(f) x_c(f)``, with

    g_k(f)  <- (1 - sum_{i != k} g_i(f) - l(f)/2) / (1 + alpha (f - omega_k)^2)              (A')
    omega_k <- sum_f f g_k(f)^2 P(f) / sum_f g_k(f)^2 P(f),   P(f) = sum_c |x_c(f)|^2       (B')
    l(f)    <- l(f) + tau (sum_k g_k(f) - 1)                                                (C')

so MVMD is an adaptive filter bank shared by all channels, and the channels enter the
iteration only through their summed power spectrum P. Each iteration costs O(K F)
instead of O(K C F); the modes are formed once at the end (``irfft(g_k x_c)``). This is
the same algorithm, not an approximation (``tests/detectors/test_mvmd.py`` checks it
against the direct per-channel iteration).

Other choices (documented in docs/algorithms/woa-mvmd-glt.md)
-------------------------------------------------------------
- Mirror extension to 2T samples (half the signal mirrored on each side), real FFT
  (``rfft``: bins 0..T at f = j / 2T cycles/sample, DC and Nyquist included).
- Convergence: relative, ``sum_k ||u_k^{n+1} - u_k^n||^2 / ||u_k^n||^2 < tol`` (norms over all
  channels on the one-sided spectrum, Dragomiretskiy & Zosso 2014, §3.3). The reference code
  uses the absolute ``sum_k ||u_k^{n+1} - u_k^n||^2 / T < tol``, which makes the number of
  iterations, hence the result, depend on the signal's scale (rad/s vs deg/s).
- alpha multiplies (f - omega)^2 with f in cycles/sample, as in the authors' MATLAB code (the
  paper writes 2 alpha (omega - omega_k)^2 with omega in rad/sample): alpha values do not
  transfer between implementations that scale frequency differently (factor 2 (2 pi)^2).
- Modes are returned sorted by final centre frequency, ascending.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imufdi_cli.errors import DetectorConfigError

INIT_CHOICES: tuple[str, ...] = ("uniform", "random", "zero")

#: Shortest signal MVMD accepts (samples).
MIN_SAMPLES = 4


@dataclass
class MvmdResult:
    """One MVMD decomposition.

    Attributes
    ----------
    modes : ndarray, shape (K, C, T), float64
        Mode k of channel c, same units as the signal; sorted by centre frequency.
    omega : ndarray, shape (K,)
        Final centre frequencies, cycles/sample (multiply by the sample rate for Hz).
    omega_history : ndarray, shape (n_iter + 1, K)
        Centre frequencies at initialisation and after each iteration (same mode order as
        ``omega``).
    n_iter : int
        Iterations run.
    converged : bool
        The relative convergence test passed before ``max_iter``.
    gains : ndarray, shape (K, T + 1)
        Real spectral gains g_k(f) on the one-sided spectrum of the mirrored signal
        (``u_kc = irfft(g_k * rfft(mirror(x_c)))``): the shared filter bank.
    """

    modes: np.ndarray
    omega: np.ndarray
    omega_history: np.ndarray
    n_iter: int
    converged: bool
    gains: np.ndarray

    @property
    def K(self) -> int:
        return int(self.omega.shape[0])


def check_mvmd_params(K: int, alpha: float, n_samples: int | None = None) -> None:
    """Raise DetectorConfigError for K < 1, alpha <= 0 or a signal shorter than 4 samples."""
    if int(K) != K or K < 1:
        raise DetectorConfigError(f"MVMD: number of modes K must be an integer >= 1, got {K!r}")
    if not np.isfinite(alpha) or alpha <= 0:
        raise DetectorConfigError(f"MVMD: bandwidth penalty alpha must be > 0, got {alpha!r}")
    if n_samples is not None and n_samples < MIN_SAMPLES:
        raise DetectorConfigError(
            f"MVMD: signal has {n_samples} samples; at least {MIN_SAMPLES} are needed"
        )


def _as_channels(signal: np.ndarray) -> np.ndarray:
    x = np.asarray(signal, dtype=np.float64)
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2:
        raise DetectorConfigError(f"MVMD: signal must have shape (C, T), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise DetectorConfigError("MVMD: signal has non-finite values")
    check_mvmd_params(1, 1.0, x.shape[1])
    return x


def mirror_extend(x: np.ndarray) -> tuple[np.ndarray, int]:
    """Mirror-extend the last axis from T to 2T samples (as the reference code).

    The first ``T // 2`` samples are mirrored before the signal and the last ``T - T // 2``
    after it. Returns the extended array and the offset of the original samples.
    """
    n_samples = x.shape[-1]
    head = n_samples // 2
    tail = n_samples - head
    extended = np.concatenate(
        [x[..., head - 1 :: -1] if head else x[..., :0], x, x[..., : n_samples - tail - 1 : -1]],
        axis=-1,
    )
    return extended, head


def spectrum(signal: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """One-sided spectrum of the mirror-extended signal.

    Returns
    -------
    spec : ndarray, shape (C, T + 1), complex
    freqs : ndarray, shape (T + 1,), cycles/sample
    offset : int
        Index of the first original sample in the extended signal.
    """
    extended, offset = mirror_extend(signal)
    length = extended.shape[-1]
    return np.fft.rfft(extended, axis=-1), np.arange(length // 2 + 1) / length, offset


def _initial_omega(
    init: str, n_modes: int, n_freqs: int, n_samples: int, dc: bool, rng: np.random.Generator | None
) -> np.ndarray:
    if init == "uniform":
        omega = 0.5 / n_modes * np.arange(n_modes)
    elif init == "random":
        if rng is None:
            raise DetectorConfigError(
                "MVMD: init='random' needs an explicit numpy.random.Generator (rng=...)"
            )
        # log-uniform between one bin and Nyquist, as the reference code
        low = 1.0 / (2 * n_samples)
        omega = np.sort(np.exp(np.log(low) + (np.log(0.5) - np.log(low)) * rng.random(n_modes)))
    elif init == "zero":
        omega = np.zeros(n_modes)
    else:
        raise DetectorConfigError(
            f"MVMD: init {init!r} is not valid; valid: {', '.join(INIT_CHOICES)}"
        )
    if dc:
        omega[0] = 0.0
    return omega


def mvmd_gains(
    power: np.ndarray,
    freqs: np.ndarray,
    Ks: Sequence[int],
    alphas: Sequence[float],
    *,
    tau: float = 0.0,
    tol: float = 1e-7,
    max_iter: int = 500,
    init: str = "uniform",
    dc: bool = False,
    rng: np.random.Generator | None = None,
) -> list[tuple[np.ndarray, np.ndarray, int, bool]]:
    """Run the reduced MVMD iteration (A')-(C') for several (K, alpha) candidates at once.

    Parameters
    ----------
    power : ndarray, shape (F,)
        Channel-summed power spectrum P(f) of the mirrored signal.
    freqs : ndarray, shape (F,), cycles/sample
    Ks, alphas : sequences of equal length B
        Candidates. Candidates are iterated together (arrays of shape (B, K_max, F); modes
        past a candidate's K are held at zero) and each stops at its own convergence, so
        a candidate's result does not depend on the others in the batch.

    Returns
    -------
    list of B tuples ``(gains (K, F), omega_history (n_iter + 1, K), n_iter, converged)``,
    modes in the order of initialisation (not sorted).
    """
    n_cand = len(Ks)
    if n_cand != len(alphas) or n_cand == 0:
        raise DetectorConfigError("MVMD: give as many alphas as Ks (at least one)")
    for K, alpha in zip(Ks, alphas):
        check_mvmd_params(K, alpha)
    if init not in INIT_CHOICES:
        raise DetectorConfigError(
            f"MVMD: init {init!r} is not valid; valid: {', '.join(INIT_CHOICES)}"
        )
    if max_iter < 1:
        raise DetectorConfigError(f"MVMD: max_iter must be >= 1, got {max_iter}")
    n_freqs = freqs.shape[0]
    k_max = max(int(K) for K in Ks)
    n_samples = n_freqs - 1
    omega = np.zeros((n_cand, k_max))
    used = np.zeros((n_cand, k_max), dtype=bool)
    for b, K in enumerate(Ks):
        omega[b, :K] = _initial_omega(init, int(K), n_freqs, n_samples, dc, rng)
        used[b, :K] = True
    alpha_col = np.asarray(alphas, dtype=np.float64)[:, None]
    used_f = used.astype(np.float64)

    gains = np.zeros((n_cand, k_max, n_freqs))
    total = np.zeros((n_cand, n_freqs))
    lam = np.zeros((n_cand, n_freqs))
    history = np.empty((max_iter + 1, n_cand, k_max))
    history[0] = omega
    weighted_freqs = freqs * power  # f P(f)
    diff = np.empty((n_cand, k_max))
    norm = np.empty((n_cand, k_max))
    index = np.arange(n_cand)  # working row -> candidate
    out: list[tuple[np.ndarray, np.ndarray, int, bool] | None] = [None] * n_cand

    n_iter = 0
    for n_iter in range(1, max_iter + 1):
        numerator_base = 1.0 - 0.5 * lam  # (B, F)
        for k in range(k_max):
            old = gains[:, k]
            others = total - old
            new = (numerator_base - others) / (1.0 + alpha_col * (freqs - omega[:, k, None]) ** 2)
            new *= used_f[:, k, None]
            delta = new - old
            diff[:, k] = (delta * delta) @ power
            norm[:, k] = (old * old) @ power
            total = others + new
            gains[:, k] = new
            if not (dc and k == 0):
                energy = new * new
                denom = energy @ power
                safe = denom > 0
                omega[:, k] = np.where(
                    safe, (energy @ weighted_freqs) / np.where(safe, denom, 1.0), omega[:, k]
                )
        if tau:
            lam += tau * (total - 1.0)
        history[n_iter, index] = omega
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(
                norm > 0, diff / np.where(norm > 0, norm, 1.0), np.where(diff > 0, np.inf, 0.0)
            )
        criterion = ratio.sum(axis=1)
        done = criterion < tol
        if n_iter == max_iter:
            done[:] = True
        if done.any():
            for row in np.flatnonzero(done):
                b = int(index[row])
                K = int(Ks[b])
                out[b] = (
                    gains[row, :K].copy(),
                    history[: n_iter + 1, b, :K].copy(),
                    n_iter,
                    bool(criterion[row] < tol),
                )
            keep = ~done
            if not keep.any():
                break
            index = index[keep]
            gains = gains[keep]
            total = total[keep]
            lam = lam[keep]
            omega = omega[keep]
            alpha_col = alpha_col[keep]
            used_f = used_f[keep]
            diff = diff[keep]
            norm = norm[keep]
    return [o for o in out if o is not None]


def mvmd_batch(
    signal: np.ndarray,
    Ks: Sequence[int],
    alphas: Sequence[float],
    *,
    tau: float = 0.0,
    tol: float = 1e-7,
    max_iter: int = 500,
    init: str = "uniform",
    dc: bool = False,
    rng: np.random.Generator | None = None,
) -> list[MvmdResult]:
    """MVMD of one signal for several (K, alpha) candidates at once (see :func:`mvmd`)."""
    x = _as_channels(signal)
    spec, freqs, offset = spectrum(x)
    power = np.einsum("cf,cf->f", spec.real, spec.real) + np.einsum(
        "cf,cf->f", spec.imag, spec.imag
    )
    raw = mvmd_gains(
        power, freqs, Ks, alphas, tau=tau, tol=tol, max_iter=max_iter, init=init, dc=dc, rng=rng
    )
    n_samples = x.shape[1]
    length = 2 * n_samples
    results = []
    for gains, history, n_iter, converged in raw:
        order = np.argsort(history[-1], kind="stable")
        gains = gains[order]
        modes = np.fft.irfft(gains[:, None, :] * spec[None], n=length, axis=-1)
        results.append(
            MvmdResult(
                modes=np.ascontiguousarray(modes[..., offset : offset + n_samples]),
                omega=history[-1, order],
                omega_history=history[:, order],
                n_iter=n_iter,
                converged=converged,
                gains=gains,
            )
        )
    return results


def mvmd(
    signal: np.ndarray,
    K: int,
    alpha: float,
    *,
    tau: float = 0.0,
    tol: float = 1e-7,
    max_iter: int = 500,
    init: str = "uniform",
    dc: bool = False,
    rng: np.random.Generator | None = None,
) -> MvmdResult:
    """Multivariate variational mode decomposition (ur Rehman & Aftab 2019, eqs. 20-23).

    Parameters
    ----------
    signal : ndarray, shape (C, T) (or (T,) for one channel), float
        C channels, T >= 4 samples, any unit.
    K : int >= 1
        Number of modes.
    alpha : float > 0
        Bandwidth penalty; multiplies (f - omega_k)^2 with f in cycles/sample.
    tau : float >= 0
        Dual ascent step (0: no exact-reconstruction constraint, the usual choice for noisy
        signals and the reference default).
    tol : float
        Relative convergence tolerance (module docstring).
    max_iter : int
    init : {"uniform", "random", "zero"}
        Initial centre frequencies: ``0.5 k / K``; log-uniform random (needs ``rng``); all 0.
    dc : bool
        Hold the first mode's centre frequency at 0 (a DC/trend mode).
    rng : numpy.random.Generator, optional
        Only for ``init="random"``.

    Returns
    -------
    MvmdResult
        ``modes`` (K, C, T), ``omega`` (K,) cycles/sample, ``omega_history``, ``n_iter``,
        ``converged``, ``gains``.

    Raises
    ------
    DetectorConfigError
        K < 1, alpha <= 0, fewer than 4 samples, bad init.
    """
    check_mvmd_params(K, alpha)
    return mvmd_batch(
        signal, [K], [alpha], tau=tau, tol=tol, max_iter=max_iter, init=init, dc=dc, rng=rng
    )[0]


__all__ = [
    "INIT_CHOICES",
    "MIN_SAMPLES",
    "MvmdResult",
    "check_mvmd_params",
    "mirror_extend",
    "mvmd",
    "mvmd_batch",
    "mvmd_gains",
    "spectrum",
]
