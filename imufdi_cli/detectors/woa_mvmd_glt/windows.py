"""WOA-MVMD-GLT windowed decomposition: u_best of every window (paper §2.5) as one linear
filter per window, and the stream that turns overlapping windows into one row per sample
(``combine``: end, centre, min).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from imufdi_cli.detectors.mvmd import (
    MIN_SAMPLES,
    MvmdResult,
    channel_power,
    mirror_extend,
    mvmd_gains,
)
from imufdi_cli.errors import (
    DetectorConfigError,
)

COMBINE_CHOICES: tuple[str, ...] = ("end", "centre", "min")
#: How u_best is chosen among a window's modes: the paper's largest uncentred inner product
#: with the raw window (``inner``), or the mode of lowest centre frequency (``lowest``).
MODE_RULES: tuple[str, ...] = ("inner", "lowest")
#: u_best rule by default: the lowest-frequency mode (the paper's "inner" follows the noise
#: on bias-free input; identical figures on the paper's scenario, docs/algorithms/woa-mvmd-glt.md)
DEFAULT_MODE_RULE = "lowest"
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
        self,
        raw: Sequence[tuple[np.ndarray, np.ndarray, int, bool]],
        first_row: int = 0,
        rule: str = DEFAULT_MODE_RULE,
    ) -> tuple[np.ndarray, np.ndarray]:
        """u_best (W, L, n) and rows ``first_row`` .. L - 1 of its filter (W, L - first_row,
        L) from the outputs of :func:`mvmd_gains` (one per window), chosen as
        :func:`best_mode` does (modes sorted by centre frequency; ``rule="lowest"``: the
        first of them, whatever the window holds), the filter as :func:`filter_matrices`.

        Only the modes the rule reads are transformed back: all of them for ``inner``
        (their scores), u_best alone for ``lowest`` (each mode is its own inverse FFT, so
        u_best has the same floats either way)."""
        n_samples = self.x.shape[2]
        gains, best, modes = self._best(raw, rule)
        rows = np.arange(gains.shape[0])
        u = self._modes(gains[:, :1])[:, 0] if modes is None else modes[rows, best]
        u = np.ascontiguousarray(np.swapaxes(u, 1, 2))
        return u, filter_matrices(gains[rows, best], n_samples, first_row)

    def best_filters(
        self,
        raw: Sequence[tuple[np.ndarray, np.ndarray, int, bool]],
        first_row: int = 0,
        rule: str = DEFAULT_MODE_RULE,
    ) -> np.ndarray:
        """The filter rows of :meth:`u_best` alone (W, L - first_row, L), the same floats;
        with ``rule="lowest"`` no mode is transformed back."""
        gains, best, _ = self._best(raw, rule)
        return filter_matrices(gains[np.arange(gains.shape[0]), best], self.x.shape[2], first_row)

    def _best(
        self, raw: Sequence[tuple[np.ndarray, np.ndarray, int, bool]], rule: str
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Gains of every window sorted by centre frequency (W, K_max, L + 1), the index
        of u_best among them (W,) under ``rule`` and, for ``inner``, the modes it scored
        (W, K_max, n, L) (None for ``lowest``)."""
        n_windows, _, n_samples = self.x.shape
        k_max = max(g.shape[0] for g, _, _, _ in raw)
        gains = np.zeros((n_windows, k_max, n_samples + 1))
        omega = np.full((n_windows, k_max), np.inf)  # unused modes sort last
        for w, (g, history, _, _) in enumerate(raw):
            gains[w, : g.shape[0]] = g
            omega[w, : g.shape[0]] = history[-1]
        order = np.argsort(omega, axis=1, kind="stable")
        gains = np.take_along_axis(gains, order[..., None], axis=1)
        if rule != "inner":
            return gains, np.zeros(n_windows, dtype=np.intp), None
        unused = ~np.isfinite(np.take_along_axis(omega, order, axis=1))
        modes = self._modes(gains)
        inner = np.einsum("wkct,wct->wk", modes, self.x)
        norms = np.linalg.norm(modes.reshape(n_windows, k_max, -1), axis=2)
        score = inner / np.where(norms > 0, norms, np.inf)
        score[unused] = -np.inf
        return gains, np.argmax(score, axis=1), modes

    def _modes(self, gains: np.ndarray) -> np.ndarray:
        """Modes (W, K, n, L) of the windows for gains (W, K, L + 1): cropped inverse FFTs."""
        n_samples = self.x.shape[2]
        modes = np.fft.irfft(gains[:, :, None, :] * self.spec[:, None], n=2 * n_samples, axis=-1)
        return modes[..., self.offset : self.offset + n_samples]


def decompose_windows(
    windows: np.ndarray,
    Ks: Sequence[int],
    alphas: Sequence[float],
    *,
    tol: float,
    max_iter: int,
    first_row: int = 0,
    rule: str = DEFAULT_MODE_RULE,
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
    rule : str
        :data:`MODE_RULES`: ``inner`` (:func:`best_mode`, the paper) or ``lowest`` (the
        mode of lowest centre frequency).

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
    return spectra.u_best(raw, first_row, rule)


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
