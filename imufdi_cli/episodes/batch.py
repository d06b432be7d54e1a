"""The fits of many episodes at once: :func:`fit_models_batch`.

A window's fits (:func:`~imufdi_cli.episodes.fits.fit_models`) are a few hundred numpy
operations on arrays of a few hundred samples, so one episode costs about a millisecond of
call overhead, whatever its length. Here the windows of the episodes a block closes are
stacked, left-aligned and zero-padded, into arrays of shape (E, L), and every model's
profile likelihood, size and interval is computed for all of them by the same operations
along the rows (masked beyond each window's length): the same estimators, the same
ranking, the same intervals as the one-window functions, in a fraction of the calls. The
cumulative sums of the profile likelihoods are the same floats (zeros padded after a
window add nothing); the sums and products of the sizes are taken along rows instead of by
BLAS, so a size or a BIC can differ from the one-window fit in the last bits.

What is done one window at a time, as :func:`fit_models` does it: the spike set (its
refinement is an iteration on each window's own samples, :func:`_spike_set`), the stuck
fit of a window whose raw output repeats, and every window whose fault is found to end
before the window does, or that the batch cannot take (fewer than two healthy sensors to
check the noise model, no white-noise calibration, no candidate onset): those are passed
to :func:`fit_models` whole. ``tests/episodes/test_batch.py`` compares both on random and
recorded windows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from imufdi_cli.episodes.batch_linear import (
    LinearSizes,
    _chi2_quantiles,
    _f_quantiles,
    _nll,
    _t_quantiles,
)
from imufdi_cli.episodes.fault_fit import MODELS, FaultFit
from imufdi_cli.episodes.fits import _fault_end, _fit_window
from imufdi_cli.episodes.model_fits import (
    SPIKE_CUT,
    _refined_spike_set,
    _spike_set,
    _stuck_fit,
)
from imufdi_cli.episodes.reference import Reference
from imufdi_cli.episodes.white_noise import _calibration_dof, successive_difference_dof

#: One call of :func:`~imufdi_cli.episodes.fits.fit_models`: its positional and keyword
#: arguments.
FitProblem = tuple[tuple[Any, ...], dict[str, Any]]

#: Windows fitted together at most (their arrays are (E, L) and (E, L, m)).
BATCH = 64


def fit_models_batch(problems: Sequence[FitProblem]) -> list[list[FaultFit]]:
    """:func:`fit_models` of every problem (its arguments), the windows fitted together.

    The same steps as :func:`fit_models`, each for all the windows at once
    (:func:`fit_windows`): every model on the whole window; where the best model's fault
    ends before the window does, the refits up to the end that refine it; the windows cut
    at the ends found (the best model's and the runner-up's), each model keeping the
    variant of the lowest BIC. Returns the fits of each problem, in order."""
    count = len(problems)
    data = [_Problem(args, kwargs) for args, kwargs in problems]
    fits = fit_windows([p.window() for p in data])
    ends: list[int | None] = [
        _fault_end(f, p.r, p.var0) if f else None for f, p in zip(fits, data, strict=True)
    ]
    # the end found by the best model on the whole window, refined (at most twice) by the
    # best model of the window up to it (without the healthy sensors: fit_until(end, None))
    active = [i for i in range(count) if ends[i] is not None]
    for _ in range(2):
        if not active:
            break
        refits = fit_windows([data[i].window(ends[i], reference=False) for i in active])
        still = []
        for i, refit in zip(active, refits, strict=True):
            end = ends[i]
            assert end is not None
            refined = _fault_end(refit, data[i].r[:end], data[i].var0)
            if refined is not None and refined != end:
                ends[i] = refined
                still.append(i)
        active = still
    runner: list[int | None] = [None] * count
    for i, window_fits in enumerate(fits):
        curved = [g for g in window_fits if g.curve is not None]
        if len(curved) > 1 and window_fits[0].model != "stuck":
            runner[i] = _fault_end(window_fits, data[i].r, data[i].var0, curved[1].model)
    # the windows cut at each end found (and at the runner-up's), all together
    cuts: list[tuple[int, int]] = []
    for i in range(count):
        end, other = ends[i], runner[i]
        if end is not None:
            cuts.append((i, end))
        if other is not None and other != end:
            cuts.append((i, other))
    cut_fits = fit_windows([data[i].window(end) for i, end in cuts])
    variants: list[list[list[FaultFit]]] = [
        [f] if ends[i] is None else [] for i, f in enumerate(fits)
    ]
    for (i, end), cut in zip(cuts, cut_fits, strict=True):
        variants[i].append(data[i].cut(fits[i], end, cut))
    out = []
    for options in variants:
        if len(options) == 1:
            out.append(options[0])
            continue
        chosen: dict[str, FaultFit] = {}
        for variant in options:
            for f in variant:
                if f.model not in chosen or f.bic < chosen[f.model].bic:
                    chosen[f.model] = f
        merged = list(chosen.values())
        merged.sort(key=lambda f: (f.bic, MODELS.index(f.model)))  # stuck (-inf) stays first
        out.append(merged)
    return out


class _Problem:
    """One :func:`fit_models` call's data, and the windows it fits (whole or cut)."""

    def __init__(self, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        self.r = np.asarray(args[0], dtype=np.float64)
        self.o = np.asarray(args[1], dtype=np.float64)
        self.t = np.asarray(args[2], dtype=np.float64)
        self.sigma_k, self.consensus_sigma = float(args[3]), float(args[4])
        self.var0 = self.sigma_k**2 + self.consensus_sigma**2
        raw = kwargs.get("raw")
        self.raw = self.r + self.o if raw is None else np.asarray(raw, dtype=np.float64)
        self.onset_range = kwargs["onset_range"]
        self.reference: Reference | None = kwargs.get("reference")
        self.options = {
            "sigma_k": self.sigma_k,
            "consensus_sigma": self.consensus_sigma,
            "confidence": kwargs.get("confidence", 0.9),
            "stuck_share": kwargs.get("stuck_share", 0.9),
            "calibration_samples": kwargs.get("calibration_samples"),
            "offset_var": kwargs.get("offset_var"),
            "white": kwargs.get("white"),
        }

    def window(self, end: int | None = None, *, reference: bool = True) -> Window:
        """The arguments of ``_fit_window`` on the samples up to ``end`` (the whole window
        without one), with the healthy sensors' residuals cut the same way (or without
        them)."""
        ref = self.reference if reference else None
        if end is None:
            return Window(self.r, self.o, self.t, self.raw, self.onset_range, ref, self.options)
        lo, hi = self.onset_range
        if ref is not None:
            ref = replace(
                ref,
                residuals=ref.residuals[:end],
                motion=None if ref.motion is None else ref.motion[:end],
            )
        return Window(
            self.r[:end], self.o[:end], self.t[:end], self.raw[:end],
            (lo, min(hi, end - 2)), ref, self.options,
        )  # fmt: skip

    def cut(self, fits: list[FaultFit], end: int, cut: list[FaultFit]) -> list[FaultFit]:
        """``_cut``: the fits up to ``end`` with the healthy tail after it and the end's
        BIC penalty added; ``fits`` when nothing fits there."""
        if not cut:
            return fits
        r = self.r
        tail = float(
            2 * _nll(float(np.add.reduce(r[end:] ** 2)), float(r.shape[0] - end), self.var0)
        )
        ln_n = math.log(r.shape[0])
        out = [
            replace(f, bic=f.bic + tail + ln_n, end_index=end)
            if f.model != "none"
            else replace(f, bic=f.bic + tail)
            for f in cut
        ]
        out.sort(key=lambda f: (f.bic, MODELS.index(f.model)))
        return out


@dataclass(frozen=True)
class Window:
    """The arguments of one ``_fit_window`` call."""

    r: np.ndarray
    o: np.ndarray
    t: np.ndarray
    raw: np.ndarray
    onset_range: tuple[int, int]
    reference: Reference | None
    options: dict[str, Any]


def fit_windows(windows: Sequence[Window]) -> list[list[FaultFit]]:
    """``_fit_window`` of every window (best first), the batchable ones together."""
    results: list[list[FaultFit] | None] = [None] * len(windows)
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, window in enumerate(windows):
        key = _batch_key(window)
        if key is None:
            results[i] = _fit_window(
                window.r, window.o, window.t, window.raw, window.onset_range,
                window.reference, **window.options,
            )  # fmt: skip
        else:
            groups.setdefault(key, []).append(i)
    for members in groups.values():
        # windows of similar lengths together (each is padded to the longest of its batch)
        members.sort(key=lambda i: windows[i].r.shape[0])
        reference = windows[members[0]].reference
        width = 1 if reference is None else reference.residuals.shape[1]
        for chunk in _similar(members, [windows[i].r.shape[0] for i in members], width):
            fitted = _Windows([windows[i] for i in chunk]).fits()
            for i, fits in zip(chunk, fitted, strict=True):
                results[i] = fits
    return [r if r is not None else [] for r in results]


#: The longest window of a batch is at most this many times its shortest.
SPREAD = 1.25


#: Values of a batch's healthy-sensor residuals (E, L, m) at most (16 MB: memory linear in
#: the sensor count whatever the batch).
BATCH_VALUES = 2_000_000


def _similar(members: list[int], lengths: list[int], width: int = 1) -> list[list[int]]:
    """``members`` (sorted by ``lengths``) cut into batches of at most BATCH windows whose
    longest is at most SPREAD times the shortest, and at most BATCH_VALUES values of
    ``width`` columns each."""
    batches: list[list[int]] = []
    start = 0
    for i in range(1, len(members) + 1):
        if (
            i == len(members)
            or i - start >= BATCH
            or lengths[i] > SPREAD * lengths[start]
            or (i + 1 - start) * lengths[i] * width > BATCH_VALUES
        ):
            batches.append(members[start:i])
            start = i
    return batches


def _batch_key(window: Window) -> tuple[Any, ...] | None:
    """What windows fitted together share (None: this one is fitted alone)."""
    r, reference, options = window.r, window.reference, window.options
    white = options.get("white")
    lo, hi = window.onset_range
    if (
        r.ndim != 1
        or r.shape[0] < 4
        or white is None
        or min(r.shape[0] - 2, int(hi)) <= max(0, int(lo))
        or not np.isfinite(r).all()
    ):
        return None
    if reference is not None and (
        reference.motion is None
        or reference.residuals.shape[1] < 2
        or reference.residuals.shape[0] != r.shape[0]
    ):
        return None
    shape = None if reference is None else (reference.residuals.shape[1], reference.motion.shape[1])  # type: ignore[union-attr]
    return (
        shape,
        len(white),
        float(options.get("confidence", 0.9)),
        float(options.get("stuck_share", 0.9)),
        None if reference is None else reference.correlation_sq is None,
    )


class _Windows(LinearSizes):
    """E windows (left-aligned rows of length L, zero beyond each window's length n) and
    their sums at every candidate onset."""

    def __init__(self, windows: Sequence[Window]) -> None:
        E = len(windows)
        n = np.array([w.r.shape[0] for w in windows], dtype=np.int64)
        L = int(n.max())
        self.E, self.L, self.n = E, L, n
        self.nf = n.astype(np.float64)
        options = [w.options for w in windows]
        self.confidence = float(options[0].get("confidence", 0.9))
        self.stuck_share = float(options[0].get("stuck_share", 0.9))
        cols = np.arange(L)
        self.cols = cols
        self.valid = cols[None, :] < n[:, None]
        self.r = self._stack([w.r for w in windows])
        self.o = self._stack([w.o for w in windows])
        self.t = self._stack([w.t for w in windows])
        self.raw = self._stack([w.raw for w in windows])
        self.sigma_k = np.array([float(o["sigma_k"]) for o in options])
        self.cs = np.array([float(o["consensus_sigma"]) for o in options])
        self.var0 = self.sigma_k**2 + self.cs**2
        self.offset_var = np.array([float(o.get("offset_var") or 0.0) for o in options])
        self.white = [o["white"] for o in options]
        lo = np.array([max(0, int(w.onset_range[0])) for w in windows])
        hi = np.array([min(int(m) - 2, int(w.onset_range[1])) for m, w in zip(n, windows)])
        self.lo, self.hi = lo, hi
        self.cand = (cols[None, :] >= lo[:, None]) & (cols[None, :] < hi[:, None])
        self.taus = np.broadcast_to(cols.astype(np.float64), (E, L))
        self.n_after = np.where(self.valid, self.nf[:, None] - cols[None, :], 1.0)
        self.ln_n = np.log(self.nf)
        references = [w.reference for w in windows]
        #: the healthy sensors' residuals check each size (all windows, or none)
        self.checked = references[0] is not None
        if self.checked:
            self._references([ref for ref in references if ref is not None])
        # suffix sums from every onset (of r, r^2, t, t^2, t r, o^2, o r) and the healthy
        # prefix: the same accumulations as one window's (zeros after it add nothing)
        series = np.empty((7, E, L))
        series[0] = self.r
        np.multiply(self.r, self.r, out=series[1])
        series[2] = self.t
        np.multiply(self.t, self.t, out=series[3])
        np.multiply(self.t, self.r, out=series[4])
        np.multiply(self.o, self.o, out=series[5])
        np.multiply(self.o, self.r, out=series[6])
        suffix = series[:, :, ::-1].cumsum(axis=2)[:, :, ::-1]
        self.s_r, self.s_rr, self.s_t, self.s_tt, self.s_tr, self.s_oo, self.s_or = suffix
        self.healthy_before = self._prefix(series[1])
        self.nll_before = _nll(self.healthy_before, self.taus, self.var0[:, None])

    def _references(self, references: list[Reference]) -> None:
        """The healthy sensors' residuals (E, L, m), motion (E, L, 3), white variances,
        offset shares and correlations."""
        E, L, n = self.E, self.L, self.n
        m = references[0].residuals.shape[1]
        self.m = m
        self.ref = np.zeros((E, L, m))
        motion = references[0].motion
        assert motion is not None  # (a reference always carries the motion)
        self.motion = np.zeros((E, L, motion.shape[1]))
        for e, ref in enumerate(references):
            self.ref[e, : n[e]] = ref.residuals
            self.motion[e, : n[e]] = ref.motion  # type: ignore[index]
        # the healthy sensors' white variances over each window (successive differences)
        diff = self.ref[:, 1:] - self.ref[:, :-1]
        for e in np.flatnonzero(n < L).tolist():  # beyond the window: zero
            diff[e, n[e] - 1 :] = 0.0  # (what the valid mask's product gives: ±0, squared 0)
        self.ref_white = np.einsum("elm,elm->em", diff, diff) / (
            2 * np.maximum(self.nf - 1, 1)[:, None]
        )
        self.offset_share = np.stack(
            [
                np.where(
                    ref.variance > 0,
                    ref.offset_var / np.where(ref.variance > 0, ref.variance, 1.0),
                    0.0,
                )
                for ref in references
            ]
        )
        self.tr_r2 = np.array(
            [float(m if ref.correlation_sq is None else ref.correlation_sq) for ref in references]
        )

    # --- plumbing ------------------------------------------------------------------------

    def _stack(self, rows: Sequence[Any]) -> np.ndarray:
        out = np.zeros((self.E, self.L))
        for e, row in enumerate(rows):
            values = np.asarray(row, dtype=np.float64)
            out[e, : values.shape[0]] = values
        return out

    def _prefix(self, values: np.ndarray) -> np.ndarray:
        """P[:, j] = sum(values[:, :j]) for j < L (the healthy part before each onset)."""
        out = np.empty_like(values)
        out[:, 0] = 0.0
        np.cumsum(values[:, :-1], axis=1, out=out[:, 1:])
        return out

    #: what :meth:`_linear` and the methods it calls read, per window (first axis)
    _ROW_FIELDS = (
        "n", "nf", "valid", "r", "var0", "offset_var", "healthy_before", "ref", "ref_white",
        "offset_share", "tr_r2", "motion",
    )  # fmt: skip

    def _rows(self, index: np.ndarray) -> _Windows:
        """The windows ``index`` alone (for the linear fits of a model some windows have)."""
        sub = object.__new__(_Windows)
        sub.E, sub.L, sub.cols = int(index.size), self.L, self.cols
        sub.m = getattr(self, "m", 0)
        sub.confidence, sub.checked = self.confidence, self.checked
        for name in self._ROW_FIELDS:
            if hasattr(self, name):
                setattr(sub, name, getattr(self, name)[index])
        return sub

    def _linear_some(
        self,
        model: str,
        only: np.ndarray,
        onset: np.ndarray,
        columns: np.ndarray,
        bic: np.ndarray,
        **options: Any,
    ) -> list[FaultFit | None]:
        """:meth:`_linear` of the windows ``only`` (bool, E), None for the others."""
        out: list[FaultFit | None] = [None] * self.E
        index = np.flatnonzero(only)
        if index.size == 0:
            return out
        if index.size == self.E:
            return self._linear(model, onset, columns, bic, **options)
        fitted = self._rows(index)._linear(
            model, onset[index], columns[index], bic[index], **options
        )
        for e, fit in zip(index, fitted, strict=True):
            out[e] = fit
        return out

    def _median_steps(self) -> np.ndarray:
        """Each window's median sample interval (E,; 0 for a window of one sample): the
        middle of its sorted intervals, or the middle two's sum halved, as
        ``np.nanmedian`` of the rows with NaN beyond each window takes it (a tenth of its
        CPU: nanmedian masks each row)."""
        t = self.t
        if self.L < 2:
            return np.zeros(self.E)
        steps = np.where(self.valid[:, 1:], t[:, 1:] - t[:, :-1], np.inf)
        steps.sort(axis=1)  # each window's intervals first, the padding (inf) after
        count = self.n - 1
        rows = np.arange(self.E)
        low = steps[rows, np.maximum((count - 1) // 2, 0)]
        high = steps[rows, np.maximum(count // 2, 0)]
        return np.where(count > 0, (low + high) / 2, 0.0)

    def _argmin(self, total: np.ndarray) -> np.ndarray:
        """Per row, the first candidate onset of the smallest ``total`` (E,)."""
        return np.where(self.cand, total, np.inf).argmin(axis=1)  # type: ignore[no-any-return]

    # --- the window's fits -----------------------------------------------------------------

    def fits(self) -> list[list[FaultFit]]:
        """Every window's fits, best first."""
        E = self.E
        per: list[list[FaultFit]] = [[] for _ in range(E)]
        for model in (self._step(), self._drift(), self._noise(), self._scale()):
            for e, fit in enumerate(model):
                if fit is not None:
                    per[e].append(fit)
        nll_healthy = _nll(self.s_rr[:, 0], self.nf, self.var0)
        for e in range(E):
            per[e].append(
                FaultFit("none", math.nan, math.nan, math.nan, -1, float(2 * nll_healthy[e]))
            )
        for e, fit in enumerate(self._spikes()):
            if fit is not None:
                per[e].append(fit)
        out: list[list[FaultFit]] = []
        repeats = (self.raw[:, 1:] == self.raw[:, :-1]) & self.valid[:, 1:]
        for e in range(E):
            fits = per[e]
            fits.sort(key=lambda f: (f.bic, MODELS.index(f.model)))
            if repeats[e].any():
                stuck = _stuck_fit(
                    self.raw[e, : self.n[e]], int(self.lo[e]), int(self.hi[e]), self.stuck_share
                )
                if stuck is not None:
                    fits.insert(0, stuck)
            out.append(fits)
        return out

    def _step(self) -> list[FaultFit | None]:
        """step: r = a + e from each window's onset (the profile likelihood's argmin)."""
        a = self.s_r / self.n_after
        total = self.nll_before + _nll(
            self.s_rr - self.n_after * a**2, self.n_after, self.var0[:, None]
        )
        j = self._argmin(total)
        bic = 2 * self._pick(total, j) + 2 * self.ln_n
        columns = np.ones((self.E, self.L, 1))
        return self._linear("step", j, columns, bic, constant=True)

    def _drift(self) -> list[FaultFit | None]:
        """drift: r = b (t - t_f) + e, t_f between the onset and the sample before it
        (:func:`~imufdi_cli.episodes.fits._drift_search`)."""
        E, L = self.E, self.L
        t, n = self.t, self.n_after
        dt = self._median_steps()
        t0 = t
        s_u = self.s_t - n * t0
        s_uu = self.s_tt - 2 * t0 * self.s_t + n * t0**2
        s_ur = self.s_tr - t0 * self.s_r
        s_r, s_rr = self.s_r, self.s_rr
        det = n * s_uu - s_u**2
        with np.errstate(divide="ignore", invalid="ignore"):
            b_free = (n * s_ur - s_u * s_r) / det
            lam_free = (s_r - b_free * s_u) / n / b_free
        sse_free = s_rr - (s_r - b_free * s_u) / n * s_r - b_free * s_ur
        in_progress = (self.cols[None, :] == 0) & (det > 0)
        valid_free = ((det > 0) & (lam_free >= 0) & (lam_free <= dt[:, None])) | in_progress
        var0 = self.var0[:, None]
        fit = self.nll_before + _nll(sse_free, n, var0)
        totals = [np.where(valid_free, fit, np.inf)]
        for bound in (np.zeros(E), dt):
            off = bound[:, None]
            s_vv = s_uu + (2 * off) * s_u + n * off**2
            s_vr = s_ur + off * s_r
            with np.errstate(divide="ignore", invalid="ignore"):
                b = s_vr / s_vv
            sse = s_rr - b * s_vr
            fit = self.nll_before + _nll(sse, n, var0)
            totals.append(np.where(s_vv > 0, fit, np.inf))
        best_total = np.full(E, np.inf)
        best_j = np.zeros(E, np.int64)
        best_row = np.full(E, -1)
        for row, total in enumerate(totals):
            total = np.where(self.cand, total, np.inf)
            j = total.argmin(axis=1)
            value = total[np.arange(E), j]
            better = np.isfinite(value) & ((best_row < 0) | (value < best_total))
            best_total = np.where(better, value, best_total)
            best_j = np.where(better, j, best_j)
            best_row = np.where(better, row, best_row)
        found = best_row >= 0
        bic = 2 * best_total + 3 * self.ln_n
        out: list[FaultFit | None] = [None] * E
        onset = best_j
        u = t - self._pick(t, onset)[:, None]
        # two columns (u, 1) where the offset is free, one (u + lam) at a bound
        free = found & (best_row == 0)
        fixed = found & (best_row > 0)
        if free.any():
            columns = np.stack([u, np.ones((E, L))], axis=2)
            for e, fit in enumerate(self._linear_some("drift", free, onset, columns, bic)):
                if free[e]:
                    out[e] = fit
        if fixed.any():
            lam = np.where(best_row == 1, 0.0, dt)
            columns = (u + lam[:, None])[:, :, None]
            for e, fit in enumerate(self._linear_some("drift", fixed, onset, columns, bic)):
                if fixed[e]:
                    out[e] = fit
        return out

    def _noise(self) -> list[FaultFit | None]:
        """noise: r = gamma o + e over the window, the variance growing from the onset,
        sized from the successive differences after it (white path)."""
        r, o = self.r, self.o
        s_oo_all = self.s_oo[:, 0]
        gamma = np.where(s_oo_all > 0, self.s_or[:, 0] / np.where(s_oo_all > 0, s_oo_all, 1.0), 0.0)
        var_gamma = self.sigma_k**2 + (1 + gamma) ** 2 * self.cs**2
        sq_g = (r - gamma[:, None] * o) ** 2
        sq_g *= self.valid
        before_g = self._prefix(sq_g)
        after_g = sq_g[:, ::-1].cumsum(axis=1)[:, ::-1]
        var_hat = np.maximum(after_g / self.n_after, var_gamma[:, None])
        total_g = _nll(before_g, self.taus, var_gamma[:, None]) + _nll(
            after_g, self.n_after, var_hat
        )
        j = self._argmin(total_g)
        bic = 2 * self._pick(total_g, j) + 3 * self.ln_n
        mean = self._pick(self.s_r / self.n_after, j)
        ranking = self._pick(var_hat, j)
        # the white variance after the onset: successive differences of r from j on
        d = r[:, 1:] - r[:, :-1]
        keep = self.valid[:, 1:] & (self.cols[None, 1:] > j[:, None])
        q = np.where(keep, d * d, 0.0).sum(axis=1)
        count = self.n - j
        out: list[FaultFit | None] = [None] * self.E
        tail = (1 - self.confidence) / 2
        dof_cal = np.empty(self.E)
        extras: list[dict[str, float]] = []
        var_w = np.full(self.E, math.nan)
        dof = np.ones(self.E)
        for e in range(self.E):
            white = self.white[e]
            sigma_w, cs_w = float(white[0]), float(white[1])
            extra: dict[str, float] = {"mean": float(mean[e])}
            extras.append(extra)
            if count[e] < 3 or sigma_w <= 0:
                continue
            var_w[e] = float(q[e]) / (2 * (int(count[e]) - 1))
            dof[e] = successive_difference_dof(int(count[e]))
            dof_cal[e] = float(white[2])
            if len(white) == 4:
                dof_cal[e] = _calibration_dof(
                    float(var_w[e]), sigma_w, cs_w, white[3], float(white[2])
                )
                extra["calibration_dof"] = float(dof_cal[e])
        ok = np.isfinite(var_w)
        low_q = _f_quantiles(1 - tail, dof, np.where(ok, dof_cal, 1.0))
        high_q = _f_quantiles(tail, dof, np.where(ok, dof_cal, 1.0))
        for e in range(self.E):
            onset = int(j[e])
            if not ok[e]:
                out[e] = FaultFit(
                    "noise", math.nan, -math.inf, math.inf, onset, float(bic[e]), extras[e]
                )
                continue
            sigma_w, cs_w = float(self.white[e][0]), float(self.white[e][1])

            def factor(var: float, sigma_w: float = sigma_w, cs_w: float = cs_w) -> float:
                return math.sqrt(max(var - cs_w**2, 0.0)) / sigma_w

            curve = (np.zeros(int(count[e])), max(float(self.var0[e]), float(ranking[e])))
            out[e] = FaultFit(
                "noise",
                factor(float(var_w[e])),
                factor(float(var_w[e]) / float(low_q[e])),
                factor(float(var_w[e]) / float(high_q[e])),
                onset,
                float(bic[e]),
                extras[e],
                curve=curve,
            )
        return out

    def _scale(self) -> list[FaultFit | None]:
        """scale: r = beta o + e from the onset, ranked with beta_0 o before it."""
        s_oo, s_or = self.s_oo, self.s_or
        with np.errstate(divide="ignore", invalid="ignore"):
            beta = np.where(s_oo > 0, s_or / s_oo, 0.0)
        sse_1 = np.maximum(self.s_rr - beta * s_or, 0.0)
        motion_var = self.sigma_k[:, None] ** 2 + (1 + beta) ** 2 * self.cs[:, None] ** 2
        nll_1 = _nll(sse_1, self.n_after, motion_var)
        j = self._argmin(self.nll_before + nll_1)
        before = self.cols[None, :] < j[:, None]
        p_oo = np.where(before, self.o * self.o, 0.0).sum(axis=1)
        p_or = np.where(before, self.o * self.r, 0.0).sum(axis=1)
        beta_0 = np.where(p_oo > 0, p_or / np.where(p_oo > 0, p_oo, 1.0), 0.0)
        var_b0 = self.sigma_k**2 + (1 + beta_0) ** 2 * self.cs**2
        nll_0 = _nll(
            np.maximum(self._pick(self.healthy_before, j) - beta_0 * p_or, 0.0),
            j.astype(float),
            var_b0,
        )
        bic = 2 * (nll_0 + self._pick(nll_1, j)) + (2 + (j > 0)) * self.ln_n
        usable = self._pick(s_oo, j) > 0
        return self._linear_some("scale", usable, j, self.o[:, :, None], bic, shift=1.0)

    def _spikes(self) -> list[FaultFit | None]:
        """spikes: the spike set of r less the nuisance gamma_s o (fitted on the quiet
        samples), ranked with the quiet and spike variances, sized on r."""
        E = self.E
        r, o = self.r, self.o
        sigma_r = np.sqrt(self.var0)
        level = self._local_levels(r)
        quiet = (np.abs(r - level) <= SPIKE_CUT * sigma_r[:, None]) & self.valid
        s_oo_q = np.where(quiet, o * o, 0.0).sum(axis=1)
        s_or_q = np.where(quiet, o * r, 0.0).sum(axis=1)
        gamma_s = np.where(s_oo_q > 0, s_or_q / np.where(s_oo_q > 0, s_oo_q, 1.0), 0.0)
        r_s = (r - gamma_s[:, None] * o) * self.valid
        var_gs = self.sigma_k**2 + (1 + gamma_s) ** 2 * self.cs**2
        nll_before_s = _nll(self._prefix(r_s * r_s), self.taus, var_gs[:, None])
        # the spike sets (_spike_set of each row): the first set, the cut against the
        # running median of five, for all rows at once where _local_level takes its
        # selection network (five samples or more, no sum that could overflow), then
        # refined row by row where it holds a spike
        first = np.abs(r_s - self._local_levels(r_s)) > SPIKE_CUT * sigma_r[:, None]
        first &= self.valid
        networked = (self.n >= 5) & (np.abs(r_s).max(axis=1) < 1e300 / self.L)
        flagged = np.zeros((E, self.L), bool)
        for e in range(E):
            ne = int(self.n[e])
            if not networked[e]:
                flagged[e, :ne] = _spike_set(r_s[e, :ne], float(sigma_r[e]))
            elif first[e].any():
                flagged[e, :ne] = _refined_spike_set(r_s[e, :ne], first[e, :ne], float(sigma_r[e]))
        any_after = (flagged & (self.cols[None, :] >= self.lo[:, None])).any(axis=1)
        out: list[FaultFit | None] = [None] * E
        if not any_after.any():
            return out
        sq = r_s * r_s
        series = np.zeros((4, E, self.L))
        series[0] = flagged
        np.abs(r_s, out=series[1], where=flagged)
        np.copyto(series[2], sq, where=~flagged)
        np.copyto(series[3], sq, where=flagged)
        count_after, abs_after, sq_quiet_after, sq_spikes_after = series[:, :, ::-1].cumsum(axis=2)[
            :, :, ::-1
        ]
        n_after = self.n_after
        n_quiet = np.maximum(n_after - count_after, 1.0)
        p = (count_after / n_after).clip(1e-12, 1 - 1e-12)
        amp = np.where(count_after > 0, abs_after / np.maximum(count_after, 1), 0.0)
        ss_spikes = np.maximum(sq_spikes_after - count_after * amp**2, 0.0)
        var_r = sigma_r[:, None] ** 2
        var_quiet = np.maximum(sq_quiet_after / n_quiet, var_r)
        var_spikes = np.maximum(ss_spikes / np.maximum(count_after, 1.0), var_r)
        with np.errstate(divide="ignore", invalid="ignore"):
            nll_after = (
                _nll(sq_quiet_after, n_after - count_after, var_quiet)
                + _nll(ss_spikes, count_after, var_spikes)
                - (count_after * np.log(p / 2) + (n_after - count_after) * np.log(1 - p))
            )
        total = nll_before_s + nll_after
        j = self._argmin(total)
        bic = 2 * self._pick(total, j) + 5 * self.ln_n + self.ln_n  # + gamma_s
        tail = (1 - self.confidence) / 2
        for e in np.flatnonzero(any_after).tolist():
            onset = int(j[e])
            ne = int(self.n[e])
            spikes = np.abs(r[e, onset:ne][flagged[e, onset:ne]])
            m = spikes.shape[0]
            if m >= 2:
                se = float(spikes.std(ddof=1)) / math.sqrt(m)
                q = float(_t_quantiles(1 - tail, np.array([m - 1.0]))[0])
                low, high = float(spikes.mean() - q * se), float(spikes.mean() + q * se)
            else:
                low, high = -math.inf, math.inf
            t = self.t[e]
            duration = float(t[ne - 1] - t[onset]) + (float(t[1] - t[0]) if ne > 1 else 0.0)
            rate_low = 0.5 * float(_chi2_quantiles(tail, 2 * m)) / duration if m > 0 else 0.0
            rate_high = 0.5 * float(_chi2_quantiles(1 - tail, 2 * m + 2)) / duration
            extra = {"rate_hz": m / duration, "rate_low_hz": rate_low, "rate_high_hz": rate_high}
            size = float(spikes.mean()) if m else math.nan
            out[e] = FaultFit("spikes", size, low, high, onset, float(bic[e]), extra)
        return out

    def _local_levels(self, r: np.ndarray) -> np.ndarray:
        """Each row's running median of five (:func:`_local_level`: a min/max selection
        network inside, the ends from their three or four values)."""
        E, L = r.shape
        level = np.zeros((E, L))
        if L >= 5:
            a, b, c, d, e5 = r[:, :-4], r[:, 1:-3], r[:, 2:-2], r[:, 3:-1], r[:, 4:]
            low = np.maximum(np.minimum(a, b), np.minimum(c, d))
            high = np.minimum(np.maximum(a, b), np.maximum(c, d))
            level[:, 2:-2] = np.maximum(np.minimum(e5, low), np.minimum(np.maximum(e5, low), high))
        for e in range(E):
            n = int(self.n[e])
            row = r[e, :n].tolist()
            head, tail = row[:4], row[-4:]
            first, second = sorted(head[:3]), sorted(head)
            last, before_last = sorted(tail[1:]), sorted(tail)
            level[e, 0], level[e, n - 1] = first[1], last[1]
            level[e, 1] = (second[1] + second[2]) / 2
            level[e, n - 2] = (before_last[1] + before_last[2]) / 2
        return level
