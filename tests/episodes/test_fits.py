"""Fitting the fault models (:func:`~imufdi_cli.episodes.fits.fit_models`): class,
interval coverage, onset and end."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imufdi_cli.episodes import fit_models
from tests.episodes.helpers import SIGMA, trace

CASES = [
    ("step", np.deg2rad(0.9)),
    ("drift", np.deg2rad(10)),
    # Monte Carlos of 200 fits with a band derived from the trials (docs/testing.md rule
    # 1): the noise and spikes fits keep default tests in test_model_fits.py (a noise x2
    # fault's factor interval; the spike set against outliers), test_fits_motion.py
    # (noise x3 classified under motion) and test_episodes_identical.py (noise and
    # spikes episodes explained byte for byte as in the reference).
    pytest.param("noise", 3.0, marks=pytest.mark.slow),  # 0.6-1.1 s of CPU
    ("scale", 1.5),
    pytest.param("spikes", np.deg2rad(3), marks=pytest.mark.slow),  # 1.1-1.5 s of CPU
]


@pytest.mark.parametrize(("model", "size"), CASES)
def test_fits_classify_and_their_90_percent_intervals_cover(model: str, size: float) -> None:
    """Monte Carlo under the model's own assumptions (white Gaussian noise, known sigma):
    the class is right and the 90 % interval covers the truth 90 % of the time. With 200
    trials the coverage has a binomial standard deviation of 2.1 points; the test allows
    3.5 of them either side (a false failure once in ~2000 runs)."""
    rng = np.random.default_rng(20261122)
    trials, right, covered = 200, 0, 0
    for _ in range(trials):
        r, o, t, c = trace(model, size, rng)
        best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250))[0]
        right += best.model == model
        covered += best.model == model and best.low <= size <= best.high
    assert right / trials >= 0.97
    half = 3.5 * math.sqrt(0.9 * 0.1 / trials)
    assert 0.9 - half <= covered / right <= 0.9 + half


def test_a_frozen_output_is_stuck_with_its_value_and_onset() -> None:
    rng = np.random.default_rng(3)
    r, o, t, c = trace("stuck", 0.0, rng)
    y = r + o
    y[150:] = y[149]  # the sensor's own output, frozen exactly
    best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250), raw=y)[0]
    assert best.model == "stuck"
    assert best.onset_index == 150
    assert best.size == y[149]


def test_step_onset_is_found_to_the_sample() -> None:
    rng = np.random.default_rng(4)
    r, o, t, c = trace("step", np.deg2rad(2.0), rng)
    best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250))[0]
    assert (best.model, best.onset_index) == ("step", 150)


def test_a_fault_that_ends_before_the_window_is_fitted_up_to_its_end() -> None:
    """A detector's alarms can outlast the fault (windowed tests): a step on [150, 300) in
    a 400-sample window is a step with its end found near 300, not noise."""
    rng = np.random.default_rng(16)
    r, o, t, c = trace("step", np.deg2rad(0.9), rng)
    r[300:] -= np.deg2rad(0.9)
    best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250))[0]
    assert best.model == "step"
    assert best.end_index is not None and abs(best.end_index - 300) <= 3
    assert best.low <= np.deg2rad(0.9) <= best.high
