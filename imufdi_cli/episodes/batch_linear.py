"""The linear sizes of many windows at once (the least-squares fits, their intervals, the
healthy sensors' check and the motion refit), for :mod:`imufdi_cli.episodes.batch`: the
one-window functions of :mod:`imufdi_cli.episodes.reference` along the rows of (E, L)
arrays, masked beyond each window's length."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imufdi_cli.episodes.fault_fit import FaultFit
from imufdi_cli.episodes.reference import DISPERSION_LEVEL
from imufdi_cli.maths import quantiles


def _t_quantiles(p: float, dof: np.ndarray) -> np.ndarray:
    return np.asarray(quantiles.t.ppf(p, dof), dtype=np.float64)


def _f_quantiles(p: float, dof1: Any, dof2: Any) -> np.ndarray:
    return np.asarray(quantiles.f.ppf(p, dof1, dof2), dtype=np.float64)


def _chi2_quantiles(p: float, dof: Any) -> np.ndarray:
    return np.asarray(quantiles.chi2.ppf(p, dof), dtype=np.float64)


def _nll(ss: Any, n: Any, var: Any) -> Any:
    """-log L of n samples with sum of squares ss about their model, variance var (the
    one-window ``_gaussian_nll``)."""
    return 0.5 * (ss / var + n * np.log(2 * math.pi * var))


class LinearSizes:
    """The linear fits of E stacked windows: the arrays they read are set by the batch
    (:class:`~imufdi_cli.episodes.batch._Windows`)."""

    E: int
    m: int
    n: np.ndarray  # (E,) samples of each window
    nf: np.ndarray  # (E,) the same as floats
    cols: np.ndarray  # (L,)
    valid: np.ndarray  # (E, L) inside each window
    r: np.ndarray  # (E, L) residuals
    var0: np.ndarray  # (E,) calibrated residual variance
    offset_var: np.ndarray  # (E,) variance of the calibrated bias
    healthy_before: np.ndarray  # (E, L) sum of r^2 before each onset
    confidence: float
    checked: bool  # the healthy sensors' residuals are there
    ref: np.ndarray  # (E, L, m) healthy sensors' residuals
    ref_white: np.ndarray  # (E, m) their white variances
    offset_share: np.ndarray  # (E, m)
    tr_r2: np.ndarray  # (E,)
    motion: np.ndarray  # (E, L, 3)

    def _pick(self, values: np.ndarray, j: np.ndarray) -> np.ndarray:
        return values[np.arange(self.E), j]

    # --- the linear sizes ------------------------------------------------------------------

    def _linear(
        self,
        model: str,
        onset: np.ndarray,
        columns: np.ndarray,
        bic: np.ndarray,
        *,
        shift: float = 0.0,
        constant: bool = False,
    ) -> list[FaultFit | None]:
        """:func:`~imufdi_cli.episodes.reference._linear_fit` of every window: least
        squares of r on ``columns`` (E, L, p) over its samples from ``onset`` (E,); the
        size ``c[0] + shift``, its interval from the noise (with its autocorrelation) and
        the calibrated bias, checked by the healthy sensors, refitted with the motion
        alongside when they spread too much or the sensor's own residual carries it."""
        E = self.E
        p = columns.shape[2]
        rows = np.ones(E, bool)
        after = (self.cols[None, :] >= onset[:, None]) & self.valid  # the fit's samples
        nfit = (self.n - onset).astype(np.float64)
        X = columns * after[:, :, None]
        y = self.r * after
        out: list[FaultFit | None] = [None] * E
        if constant:
            weights = (after / np.maximum(nfit, 1)[:, None])[:, None, :]  # (E, 1, L)
            good = rows.copy()
        else:
            gram = np.einsum("elp,elq->epq", X, X)
            det = np.linalg.det(gram)
            good = rows & np.isfinite(gram).all(axis=(1, 2)) & (np.abs(det) > 1e-300)
            safe = np.where(good[:, None, None], gram, np.eye(p)[None])
            weights = np.linalg.solve(safe, np.swapaxes(X, 1, 2))  # (E, p, L)
        coef = np.einsum("epl,el->ep", weights, y)
        w = weights[:, 0, :]
        size = coef[:, 0] + shift
        dof = nfit - p
        for e in np.flatnonzero(rows & ~good):
            out[e] = FaultFit(model, math.nan, -math.inf, math.inf, int(onset[e]), float(bic[e]))
        for e in np.flatnonzero(good & (dof < 1)):
            out[e] = FaultFit(
                model, float(size[e]), -math.inf, math.inf, int(onset[e]), float(bic[e])
            )
        todo = good & (dof >= 1)
        if not todo.any():
            return out
        fitted = np.einsum("elp,ep->el", X, coef)
        resid = (y - fitted) * after
        sw2 = np.einsum("el,el->e", w, w)
        sw = w.sum(axis=1)
        quantile = _t_quantiles(0.5 + self.confidence / 2, np.where(todo, dof, 1.0))
        # the sensor's own white variance: successive differences of the window before the
        # onset and of the fit's residuals after it
        before = self.valid & ~after
        d_pre = self.r[:, 1:] - self.r[:, :-1]
        pre_sum = np.where(before[:, 1:], d_pre * d_pre, 0.0).sum(axis=1) / 2
        d_e = resid[:, 1:] - resid[:, :-1]
        e_sum = np.where(after[:, 1:] & after[:, :-1], d_e * d_e, 0.0).sum(axis=1) / 2
        n_pre = onset.astype(np.float64)
        white_var = (
            np.where(n_pre >= 2, pre_sum, 0.0) + np.where(nfit >= 2, e_sum, 0.0)
        ) / np.maximum(n_pre + nfit - 2, 1)
        offset_ratio = np.where(self.var0 > 0, self.offset_var / self.var0, 0.0)
        if self.checked:
            dispersion, widened_var, widened_q = self._dispersion(
                w, white_var, offset_ratio, sw2, sw, after
            )
            healthy = self._pick(self.healthy_before, onset)
            sse_without = healthy + np.einsum("el,el->e", resid, resid)
            motion = self._motion(
                columns, after, onset, offset_ratio, sse_without, widened_var, todo
            )
        else:  # without the healthy sensors: no check, no motion fit
            dispersion = widened_var = widened_q = np.full(E, np.nan)
            motion = [None] * E
        s2 = np.einsum("el,el->e", resid, resid) / np.maximum(dof, 1)
        auto = self._autocorrelation(resid, after, w, sw2, nfit)
        variance = s2 * auto * sw2 + self.offset_var * sw**2
        for e in np.flatnonzero(todo):
            extra: dict[str, float] = {}
            if self.checked:
                extra["dispersion"] = float(dispersion[e])
            curve = (fitted[e, int(onset[e]) : int(self.n[e])], float(self.var0[e]))
            found = motion[e]
            if found is not None:
                value, half, extra["motion_dispersion"] = found
                value += shift
                out[e] = FaultFit(
                    model, value, value - half, value + half, int(onset[e]), float(bic[e]),
                    extra, curve=curve,
                )  # fmt: skip
                continue
            var, q = float(variance[e]), float(quantile[e])
            if np.isfinite(widened_var[e]) and widened_var[e] > var:
                var, q = float(widened_var[e]), float(widened_q[e])
            half = q * math.sqrt(max(var, 0.0))
            value = float(size[e])
            out[e] = FaultFit(
                model, value, value - half, value + half, int(onset[e]), float(bic[e]), extra,
                curve=curve,
            )  # fmt: skip
        return out

    def _dispersion(
        self,
        w: np.ndarray,
        white_var: np.ndarray,
        offset_ratio: np.ndarray,
        sw2: np.ndarray,
        sw: np.ndarray,
        after: np.ndarray,
        windows: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The healthy sensors' check of the noise model for the estimates ``w`` (E, L)
        (:func:`~imufdi_cli.episodes.reference._dispersion`): Q / m, and the widened
        variance and quantile where Q exceeds its quantile (NaN elsewhere)."""
        ref = self.ref if windows is None else windows
        estimates = (w[:, None, :] @ ref)[:, 0, :]  # (E, m)
        predicted = self.ref_white * (sw2[:, None] + self.offset_share * sw[:, None] ** 2)
        m = self.m
        with np.errstate(divide="ignore", invalid="ignore"):
            q = (estimates**2 / predicted).sum(axis=1)
        dof = m * m / self.tr_r2
        limit = self.tr_r2 / m * _chi2_quantiles(DISPERSION_LEVEL, dof)
        wide = q > limit
        white = q / m * white_var * (sw2 + offset_ratio * sw**2)
        quantile = _t_quantiles(0.5 + self.confidence / 2, dof)
        return q / m, np.where(wide, white, np.nan), np.where(wide, quantile, np.nan)

    def _autocorrelation(
        self, e: np.ndarray, after: np.ndarray, w: np.ndarray, sw2: np.ndarray, nfit: np.ndarray
    ) -> np.ndarray:
        """:func:`~imufdi_cli.episodes.reference._autocorrelation_factor` of each row's
        residuals ``e`` over its fit's samples (``after``), for its weights ``w``."""
        n = nfit
        lags = np.minimum(n - 2, np.floor(4 * (n / 100) ** (2 / 9))).astype(np.int64)
        mean = np.where(after, e, 0.0).sum(axis=1) / np.maximum(n, 1)
        e0 = (e - mean[:, None]) * after
        c0 = np.einsum("el,el->e", e0, e0)
        total = np.ones(self.E)
        ok = (lags >= 1) & (c0 > 0) & (sw2 > 0)
        top = int(lags[ok].max()) if ok.any() else 0
        for k in range(1, top + 1):
            use = ok & (lags >= k)
            rho = np.einsum("el,el->e", e0[:, :-k], e0[:, k:]) / np.where(c0 > 0, c0, 1.0)
            ww = np.einsum("el,el->e", w[:, :-k], w[:, k:]) / np.where(sw2 > 0, sw2, 1.0)
            step = 2 * (1 - k / (lags + 1)) * rho * ww
            total = np.where(use, total + step, total)
        return np.where(ok, np.maximum(total, 0.1), 1.0)

    def _motion(
        self,
        columns: np.ndarray,
        after: np.ndarray,
        onset: np.ndarray,
        offset_ratio: np.ndarray,
        sse_without: np.ndarray,
        widened_var: np.ndarray,
        todo: np.ndarray,
    ) -> list[tuple[float, float, float] | None]:
        """:func:`~imufdi_cli.episodes.reference._motion_fit` of every window: the fault
        columns (zero before the onset) with the motion alongside over the whole window;
        used where the healthy sensors spread too much (``widened_var`` finite) or a
        partial F test finds the motion in the sensor's own residual."""
        E = self.E
        p = columns.shape[2]
        M = self.motion
        k = M.shape[2]
        out: list[tuple[float, float, float] | None] = [None] * E
        dof = self.nf - p - k
        usable = todo & (dof >= 2)
        if not usable.any():
            return out
        design = np.concatenate([columns * after[:, :, None], M], axis=2)  # (E, L, p + k)
        design *= self.valid[:, :, None]
        scale = np.sqrt(np.einsum("elq,elq->eq", design, design))
        usable &= np.isfinite(design).all(axis=(1, 2)) & (scale > 0).all(axis=1)
        if not usable.any():
            return out
        normalised = design / np.where(scale > 0, scale, 1.0)[:, None, :]
        u, singular, vt = np.linalg.svd(normalised, full_matrices=False)
        usable &= singular[:, -1] > 1e-6 * singular[:, 0]
        cut = np.abs(singular[:, -1] - 1e-6 * singular[:, 0]) <= 1e-10 * singular[:, 0]
        for e in np.flatnonzero(usable & cut):  # at the cut: the values alone decide
            alone = np.linalg.svd(normalised[e, : self.n[e]], compute_uv=False)
            usable[e] = bool(alone[-1] > 1e-6 * alone[0])
        if not usable.any():
            return out
        large = singular > 1e-15 * singular[:, :1]
        inverse = np.where(large, 1.0 / np.where(large, singular, 1.0), 0.0)
        # pinv = V diag(1 / s) U^T, each row over the column's scale (E, p + k, L)
        pinv = (np.swapaxes(vt, 1, 2) * inverse[:, None, :]) @ np.swapaxes(u, 1, 2)
        pinv /= scale[:, :, None]
        w = pinv[:, 0, :]
        coef = np.einsum("eql,el->eq", pinv, self.r)
        e_res = (self.r - np.einsum("elq,eq->el", design, coef)) * self.valid
        sse = np.einsum("el,el->e", e_res, e_res)
        with np.errstate(divide="ignore", invalid="ignore"):
            f_stat = np.where(
                sse > 0, (sse_without - sse) / k / (sse / np.where(dof > 0, dof, 1.0)), np.inf
            )
        force = np.isfinite(widened_var)
        f_limit = _f_quantiles(DISPERSION_LEVEL, k, np.where(usable, dof, 2.0))
        usable &= force | (f_stat > f_limit)
        if not usable.any():
            return out
        sw2 = np.einsum("el,el->e", w, w)
        sw = w.sum(axis=1)
        d = e_res[:, 1:] - e_res[:, :-1]
        d *= self.valid[:, 1:]
        white = np.einsum("el,el->e", d, d) / (2 * np.maximum(self.nf - 1, 1))
        offset = np.where(self.var0 > 0, offset_ratio * white, self.offset_var)
        auto = self._autocorrelation(e_res, self.valid, w, sw2, self.nf)
        variance = sse / np.where(dof > 0, dof, 1.0) * auto * sw2 + offset * sw**2
        quantile = _t_quantiles(0.5 + self.confidence / 2, np.where(usable, dof, 1.0))
        dispersion, wide_var, wide_q = self._dispersion(w, white, offset_ratio, sw2, sw, self.valid)
        for e in np.flatnonzero(usable):
            var, q = float(variance[e]), float(quantile[e])
            if np.isfinite(wide_var[e]) and wide_var[e] > var:
                var, q = float(wide_var[e]), float(wide_q[e])
            out[e] = (float(coef[e, 0]), q * math.sqrt(max(var, 0.0)), float(dispersion[e]))
        return out
