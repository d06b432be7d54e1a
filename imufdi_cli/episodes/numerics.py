"""Small numerical helpers of the episode fits: distribution quantiles, Gaussian
log-likelihoods, suffix sums, the median, and JSON-ready floats."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from imufdi_cli.maths import quantiles


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, recursively."""
    kind = type(value)  # the exact built-in types first (the episode JSON: 30 calls each)
    if kind is float:
        return value if math.isfinite(value) else None
    if kind is int or kind is str or value is None:
        return value
    if kind is dict:
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


# Quantiles of maths.quantiles (pure Python: no scipy import for a few hundred values a
# run), cached for the episode lengths that repeat.


@functools.lru_cache(maxsize=4096)
def _chi2_quantile(p: float, dof: float) -> float:
    """Chi-square quantile at lower tail ``p``."""
    return float(quantiles.chi2.ppf(p, dof))


@functools.lru_cache(maxsize=4096)
def _f_quantile(p: float, dof1: float, dof2: float) -> float:
    """F(dof1, dof2) quantile."""
    return float(quantiles.f.ppf(p, dof1, dof2))


@functools.lru_cache(maxsize=4096)
def _t_quantile(p: float, dof: float) -> float:
    """Student t quantile."""
    return float(quantiles.t.ppf(p, dof))


def _gaussian_nll(ss: Any, n: Any, var: Any) -> Any:
    """-log L of n samples with sum of squares ss about their model, variance var."""
    return 0.5 * (ss / var + n * np.log(2 * math.pi * var))


def _prefix(values: np.ndarray) -> np.ndarray:
    """P[j] = sum(values[:j]), shape (L + 1,)."""
    out = np.empty(values.shape[0] + 1)
    out[0] = 0.0
    values.cumsum(out=out[1:])  # np.cumsum's own method, written in place
    return out


def _suffix(values: np.ndarray) -> np.ndarray:
    """S[j] = sum(values[j:]), shape (L + 1,)."""
    out = np.zeros(values.shape[0] + 1)
    out[:-1] = values[::-1].cumsum()[::-1]  # np.cumsum's own method
    return out


def _suffixes(values: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """``_suffix(values[i])[lo:hi]`` for every row i of ``values`` (k, L), shape (k, hi -
    lo): one accumulation for all rows (sequential, as for one row: the same floats)."""
    out = np.zeros((values.shape[0], values.shape[1] + 1))
    out[:, :-1] = values[:, ::-1].cumsum(axis=1)[:, ::-1]
    return out[:, lo:hi]


def _median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D array, sorted directly (the middle value, or
    the mean of the middle two as numpy takes it: their sum halved); numpy's own for
    non-finite values."""
    n = values.shape[0]
    if n == 1 and math.isfinite(only := float(values[0])):
        return only  # (one value: itself)
    if n == 0 or not math.isfinite(float(np.add.reduce(values))):
        return float(np.median(values))
    ordered = np.sort(values)
    if n % 2:
        return float(ordered[n // 2])
    return (float(ordered[n // 2 - 1]) + float(ordered[n // 2])) / 2
