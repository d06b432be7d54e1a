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
    history: bool = True,
) -> list[tuple[np.ndarray, np.ndarray, int, bool]]:
    """Run the reduced MVMD iteration (A')-(C') for a batch of rows at once.

    A row is one (signal, K, alpha) problem: several candidates on one signal (``power`` of
    shape (F,)) or many signals of equal length, e.g. all the windows of a block (``power``
    of shape (B, F)). Rows are iterated together (arrays of shape (B, K_max, F); modes past
    a row's K are held at zero) and each stops at its own convergence, so a row's result
    does not depend on the others in the batch (the same floats: no operation mixes rows).

    Parameters
    ----------
    power : ndarray, shape (F,) or (B, F)
        Channel-summed power spectrum P(f) of the mirrored signal, shared by all rows or one
        per row.
    freqs : ndarray, shape (F,), cycles/sample
    Ks, alphas : sequences of equal length B
        Number of modes and bandwidth penalty of each row.
    history : bool
        Record the centre frequencies after every iteration (``omega_history``); without
        it the returned history holds the initial and the final values only.

    Returns
    -------
    list of B tuples ``(gains (K, F), omega_history (n_iter + 1, K), n_iter, converged)``,
    modes in the order of initialisation (not sorted).

    Notes
    -----
    Cost: each iteration is a fixed number of numpy operations on (B, F) arrays, whatever
    B is, so batching many windows amortises the Python overhead that dominates one small
    window (50 samples: F = 51). Rows that converge are saved and dropped from the arrays
    at once (each row's floats do not depend on the other rows).
    """
    power, freqs = _gains_inputs(power, freqs, Ks, alphas, init, max_iter)
    omega, used = _initial_omegas(Ks, init, freqs.shape[0], dc, rng)
    rows = _GainRows(power, freqs, alphas, omega, used, tau=tau, dc=dc)
    track = np.empty((max_iter + 1 if history else 1, len(Ks), omega.shape[1]))
    track[0] = omega
    out: list[tuple[np.ndarray, np.ndarray, int, bool] | None] = [None] * len(Ks)
    for n_iter in range(1, max_iter + 1):
        criterion = rows.iterate()
        if history:
            track[n_iter, rows.index] = rows.omega.T
        done = criterion < tol
        if n_iter == max_iter:
            done[:] = True
        if not done.any():
            continue
        for row in (int(r) for r in np.flatnonzero(done)):
            b = int(rows.index[row])
            K = int(Ks[b])
            if history:
                omega_history = track[: n_iter + 1, b, :K].copy()
            else:
                omega_history = np.empty((2, K))
                omega_history[0] = track[0, b, :K]
                omega_history[1] = rows.omega[:K, row]
            out[b] = (rows.gains[:K, row].copy(), omega_history, n_iter, bool(criterion[row] < tol))
        if done.all():
            break
        rows.keep(~done)
    return [o for o in out if o is not None]


def _gains_inputs(
    power: np.ndarray,
    freqs: np.ndarray,
    Ks: Sequence[int],
    alphas: Sequence[float],
    init: str,
    max_iter: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Check the arguments of :func:`mvmd_gains`; ``power`` as a contiguous (B, F) array
    (broadcast when one spectrum is shared) and ``freqs`` as float64 (F,)."""
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
    power = np.asarray(power, dtype=np.float64)
    freqs = np.asarray(freqs, dtype=np.float64)
    n_freqs = freqs.shape[0]
    if power.ndim == 1:
        power = np.broadcast_to(power, (n_cand, power.shape[0]))
    if freqs.ndim != 1 or power.shape != (n_cand, n_freqs):
        raise DetectorConfigError(
            f"MVMD: power must have shape (F,) or ({n_cand}, F) for freqs (F,),"
            f" got {power.shape} and {freqs.shape}"
        )
    return np.ascontiguousarray(power), freqs


def _initial_omegas(
    Ks: Sequence[int], init: str, n_freqs: int, dc: bool, rng: np.random.Generator | None
) -> tuple[np.ndarray, np.ndarray]:
    """Initial centre frequencies of every row, shape (B, K_max), and which modes a row
    uses (bool, same shape); rows of equal K share their start unless ``init='random'``."""
    k_max = max(int(K) for K in Ks)
    omega = np.zeros((len(Ks), k_max))
    used = np.zeros((len(Ks), k_max), dtype=bool)
    starts: dict[int, np.ndarray] = {}
    for b, K in enumerate(Ks):
        K = int(K)
        if init == "random" or K not in starts:
            starts[K] = _initial_omega(init, K, n_freqs, n_freqs - 1, dc, rng)
        omega[b, :K] = starts[K]
        used[b, :K] = True
    return omega, used


class _GainRows:
    """The working rows of :func:`mvmd_gains`: gains g_k(f), multipliers l(f) and centre
    frequencies of the rows still iterating (B' <= B rows; ``index`` maps a working row
    to its candidate).

    Arrays are mode-major, (K_max, B', F): mode k of every row is one contiguous block,
    so each step of the Gauss-Seidel sweep is one pass over memory. Every array an
    iteration writes is allocated once per set of rows (:meth:`_buffers`) and written with
    ``out=``; the gains alternate between two buffers (the previous sweep's values stay in
    the other one for the convergence test). Each float operation is the one of the plain
    (B, K, F) formulation (same operands, same order; the sums over f are the same dot
    products, the sum over modes runs on a (B', K_max) array as before), so the results
    do not depend on this layout.
    """

    def __init__(
        self,
        power: np.ndarray,
        freqs: np.ndarray,
        alphas: Sequence[float],
        omega: np.ndarray,
        used: np.ndarray,
        *,
        tau: float,
        dc: bool,
    ) -> None:
        n_cand, k_max = omega.shape
        n_freqs = freqs.shape[0]
        self.freqs = freqs  # (F,)
        self.tau = tau
        self.dc = dc
        self.omega = np.ascontiguousarray(omega.T)  # (K_max, B)
        self.alpha = np.asarray(alphas, dtype=np.float64)[None, :, None]  # (1, B, 1)
        self.unused_inf = np.where(used.T, 0.0, np.inf)[:, :, None]  # (K_max, B, 1)
        self.all_used = bool(used.all())
        self.moving = np.ones((k_max, 1), dtype=bool)  # centre frequencies updated by (B')
        self.moving[0] = not dc
        self.gains = np.zeros((k_max, n_cand, n_freqs))
        self.total = np.zeros((n_cand, n_freqs))
        self.lam = np.zeros((n_cand, n_freqs))
        # P(f) and f P(f) of each row, (2, B, F)
        self.spectra = np.stack(np.broadcast_arrays(power, freqs * power))
        # [sum_f du_k^2 P, sum_f du_k^2 f P], [sum_f g_k^2 P, sum_f g_k^2 f P] of the latest
        # sweep, (2, 2, K_max, B); sum_f g_k^2 P starts at 0 (zero gains)
        self.sums = np.zeros((2, 2, k_max, n_cand))
        self.index = np.arange(n_cand)  # working row -> candidate
        self._buffers()

    def _buffers(self) -> None:
        """Work arrays for the current rows."""
        k_max, rows, n_freqs = self.gains.shape
        self.spare = np.empty_like(self.gains)  # the next sweep's gains
        self.den = np.empty_like(self.gains)
        self.squares = np.empty((2, k_max, rows, n_freqs))  # du^2, g^2
        self.next_sums = np.empty_like(self.sums)
        self.others = np.empty((rows, n_freqs))
        self.base = np.empty((rows, n_freqs) if self.tau else (0,))
        self.positive = np.empty((k_max, rows), dtype=bool)
        self.ratio = np.empty((rows, k_max))
        self.ratio_modes = np.empty((k_max, rows))
        self.criterion = np.empty(rows)

    def iterate(self) -> np.ndarray:
        """One sweep of (A') (Gauss-Seidel over k), (B') and (C') on every working row.

        Returns the relative change ``sum_k |du_k|^2 / |u_k|^2`` of each working row,
        shape (B',) (inf when a mode that was zero moved); valid until the next call.
        """
        previous, gains, den = self.gains, self.spare, self.den
        numerator_base: np.ndarray | float = 1.0
        if self.tau:
            half = np.multiply(0.5, self.lam, out=self.base)
            numerator_base = np.subtract(1.0, half, out=half)
        # omega_k changes only after mode k's own update, so every denominator of this
        # sweep is known now: 1 + alpha (f - omega_k)^2, inf for a row's unused modes
        np.subtract(self.freqs, self.omega[:, :, None], out=den)
        np.multiply(den, den, out=den)
        np.multiply(den, self.alpha, out=den)
        if not self.all_used:
            np.add(den, self.unused_inf, out=den)
        np.add(den, 1.0, out=den)
        total, others = self.total, self.others
        for k in range(gains.shape[0]):  # Gauss-Seidel: mode k sees the new modes < k
            gain = gains[k]
            np.subtract(total, previous[k], out=others)
            np.subtract(numerator_base, others, out=gain)
            np.divide(gain, den[k], out=gain)
            np.add(others, gain, out=total)
        # (B') for all modes at once: they do not depend on each other within a sweep
        squares = self.squares
        delta = squares[0]
        np.subtract(gains, previous, out=delta)
        np.multiply(delta, delta, out=delta)
        np.multiply(gains, gains, out=squares[1])
        sums = np.vecdot(squares[:, None], self.spectra[None, :, None], out=self.next_sums)
        diff, energy, weighted = sums[0, 0], sums[1, 0], sums[1, 1]  # (K_max, B')
        norm = self.sums[1, 0]  # sum_f (g_k^n)^2 P: the energy of the previous sweep
        positive = np.greater(energy, 0.0, out=self.positive)
        if self.dc:
            positive &= self.moving
        np.divide(weighted, energy, out=self.omega, where=positive)
        if self.tau:
            self.lam += self.tau * (total - 1.0)
        ratio = self.ratio_modes  # (K_max, B')
        known = np.greater(norm, 0.0, out=positive)
        if known.all():  # every mode had energy: the plain ratio
            np.divide(diff, norm, out=ratio)
        else:  # a mode without energy: inf if it moved, else 0
            np.copyto(ratio, np.where(diff > 0, np.inf, 0.0))
            np.divide(diff, norm, out=ratio, where=known)
        # summed over modes on a C-ordered (B', K_max) array, as the plain formulation
        np.copyto(self.ratio, ratio.T)
        ratio = self.ratio
        # swap: the new gains and sums become the current ones
        self.gains, self.spare = gains, previous
        self.sums, self.next_sums = sums, self.sums
        return np.add.reduce(ratio, axis=1, out=self.criterion)

    def keep(self, rows: np.ndarray) -> None:
        """Drop the working rows outside ``rows`` (bool, shape (B',))."""
        self.index = self.index[rows]
        self.gains = self.gains[:, rows]
        self.total = self.total[rows]
        self.lam = self.lam[rows]
        self.omega = self.omega[:, rows]
        self.alpha = self.alpha[:, rows]
        self.unused_inf = self.unused_inf[:, rows]
        self.spectra = self.spectra[:, rows]
        self.sums = self.sums[..., rows]
        self._buffers()


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
    raw = mvmd_gains(
        channel_power(spec),
        freqs,
        Ks,
        alphas,
        tau=tau,
        tol=tol,
        max_iter=max_iter,
        init=init,
        dc=dc,
        rng=rng,
    )
    return mvmd_results(raw, spec, offset, x.shape[1])


def channel_power(spec: np.ndarray) -> np.ndarray:
    """P(f) = sum_c |X_c(f)|^2 of a spectrum (..., C, F): shape (..., F)."""
    return np.einsum("...cf,...cf->...f", spec.real, spec.real) + np.einsum(
        "...cf,...cf->...f", spec.imag, spec.imag
    )


def mvmd_results(
    raw: Sequence[tuple[np.ndarray, np.ndarray, int, bool]],
    spec: np.ndarray,
    offset: int,
    n_samples: int,
) -> list[MvmdResult]:
    """:class:`MvmdResult` of each output of :func:`mvmd_gains` on one signal's spectrum
    ``spec`` (C, n_samples + 1) (:func:`spectrum`): modes sorted by centre frequency."""
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
    "channel_power",
    "check_mvmd_params",
    "mirror_extend",
    "mvmd",
    "mvmd_batch",
    "mvmd_gains",
    "mvmd_results",
    "spectrum",
]
