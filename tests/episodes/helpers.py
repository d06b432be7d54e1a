"""Synthetic residuals and status rows shared by the episodes tests."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

RATE = 100.0
SIGMA = np.deg2rad(0.15)


def trace(model: str, size: float, rng: np.random.Generator, length: int = 400, onset: int = 150):
    """Residual, consensus prediction, times (s) and consensus sigma of one sensor with
    ``model`` of ``size`` from sample ``onset`` on (white noise SIGMA, a swinging truth)."""
    t = np.arange(length) / RATE
    truth = np.deg2rad(10) + np.deg2rad(5) * np.sin(2 * np.pi * 0.5 * t)
    consensus_sigma = SIGMA / math.sqrt(15)
    y = truth + rng.normal(0, SIGMA, length)
    if model == "step":
        y[onset:] += size
    elif model == "drift":
        y[onset:] += size * (t[onset:] - t[onset])
    elif model == "noise":
        y[onset:] += rng.normal(0, SIGMA * math.sqrt(size**2 - 1), length - onset)
    elif model == "scale":
        y[onset:] = truth[onset:] * size + (y[onset:] - truth[onset:])
    elif model == "spikes":
        events = rng.random(length - onset) < 0.05
        y[onset:] += events * size * rng.choice([-1.0, 1.0], length - onset)
    elif model == "stuck":
        y[onset:] = y[onset - 1]
    prediction = truth + rng.normal(0, consensus_sigma, length)
    return y - prediction, prediction, t, consensus_sigma


def status_rows(alarm: np.ndarray, isolated: np.ndarray) -> SimpleNamespace:
    """Status rows in the shape :meth:`EpisodeBuilder.rows` reads."""
    n = alarm.size
    return SimpleNamespace(
        alarm=alarm, isolated=isolated, statistic=np.where(alarm, 3.0, 0.5), threshold=np.ones(n)
    )


def coverage_band(trials: int, level: float = 0.9, z: float = 3.5) -> tuple[float, float]:
    """Binomial band of the coverage of a calibrated ``level`` interval over ``trials``
    (z standard deviations: a false failure about once in 2000 runs)."""
    half = z * math.sqrt(level * (1 - level) / trials)
    return level - half, level + half


def slow_error(length: int, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """A slowly varying error (0.3-0.5 Hz, random phase) like the scale and misalignment
    errors of a sensor under motion."""
    t = np.arange(length) / RATE
    f, phase = rng.uniform(0.3, 0.5), rng.uniform(0, 2 * np.pi)
    return amplitude * np.sin(2 * np.pi * f * t + phase)
