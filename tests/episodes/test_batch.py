"""The fits of many episodes at once (:func:`~imufdi_cli.episodes.batch.fit_models_batch`)
against :func:`~imufdi_cli.episodes.fits.fit_models` one window at a time."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import imufdi_cli.episodes.builder as builder_module
from imufdi_cli.episodes import EpisodeBuilder, fit_models
from imufdi_cli.episodes.batch import fit_models_batch
from tests.episodes.test_episodes_identical import RATE, synthetic_log


@pytest.fixture(scope="module")
def problems() -> list[Any]:
    """Every fit the builder asks for on the fixed log of test_episodes_identical (every
    fault model of inject, chance alarms with and without an isolated sensor, faults the
    detector's alarms outlast), with the white-noise calibration detect gives it."""
    log = synthetic_log()
    n = log["H"].shape[0]
    captured: list[Any] = []
    inner = builder_module.fit_models_batch

    def spy(batch: list[Any]) -> list[Any]:
        captured.extend(batch)
        return inner(batch)

    builder = EpisodeBuilder(
        "glt", "gyro", log["H"], [f"s{i}" for i in range(n)], log["sigma"], RATE,
        calibration_samples=200, calibration_mean=log["calibration"].mean(0),
        white_sigma=log["sigma"],
    )  # fmt: skip
    builder_module.fit_models_batch = spy  # type: ignore[assignment]
    try:
        start, length = 0, log["m"].shape[0]
        for size in log["blocks"].tolist() * 4:
            if start >= length:
                break
            stop = min(length, start + size)
            builder.feed(log["m"][start:stop])
            status = SimpleNamespace(
                alarm=log["alarm"][start:stop],
                isolated=log["isolated"][start:stop],
                statistic=log["statistic"][start:stop],
                threshold=np.ones(stop - start),
            )
            builder.rows(log["t_ns"][start:stop], log["t_ns"][start:stop], status)
            start = stop
        builder.finish()
    finally:
        builder_module.fit_models_batch = inner  # type: ignore[assignment]
    return captured


def _agree(one: list[Any], many: list[Any]) -> None:
    """The same models ranked the same, onsets and ends and extra keys exactly; sizes,
    bounds and BICs to 1e-9 relative (the batch sums along rows where one window's fit
    uses BLAS dot products: another order of the same terms, within 1e-12 measured)."""
    assert [(f.model, f.onset_index, f.end_index) for f in one] == [
        (f.model, f.onset_index, f.end_index) for f in many
    ]
    for f, g in zip(one, many, strict=True):
        assert set(f.extra) == set(g.extra)
        pairs = [(f.size, g.size), (f.low, g.low), (f.high, g.high), (f.bic, g.bic)]
        pairs += [(f.extra[k], g.extra[k]) for k in f.extra]
        for x, y in pairs:
            if x == y or (math.isnan(x) and math.isnan(y)):
                continue
            assert abs(x - y) <= 1e-9 * max(abs(x), abs(y)), (f.model, x, y)


def test_batched_fits_are_the_one_window_fits(problems) -> None:
    models = {fits[0].model for fits in fit_models_batch(problems) if fits}
    assert {"step", "drift", "noise", "stuck", "spikes", "scale", "none"} <= models
    assert len(problems) >= 10
    serial = [fit_models(*args, **kwargs) for args, kwargs in problems]
    for one, many in zip(serial, fit_models_batch(problems), strict=True):
        _agree(one, many)
    # whatever the batch's composition: one at a time, reversed
    alone = [fit_models_batch([p])[0] for p in problems]
    reversed_batch = fit_models_batch(problems[::-1])[::-1]
    for one, a, b in zip(serial, alone, reversed_batch, strict=True):
        _agree(one, a)
        _agree(one, b)


def test_a_fault_the_alarms_outlast_is_cut_at_its_end_in_a_batch(problems) -> None:
    # the refits up to the fault's end (and the runner-up's) are batched as well
    ended = [p for p in problems if any(f.end_index is not None for f in fit_models(*p[0], **p[1]))]
    assert ended
    for (args, kwargs), many in zip(ended, fit_models_batch(ended), strict=True):
        _agree(fit_models(*args, **kwargs), many)


def test_windows_the_batch_cannot_take_are_fitted_alone(problems) -> None:
    # without a white-noise calibration, or too short for an onset: the one-window fit,
    # as it is; without the healthy sensors (as the refits up to an end are) in the batch
    args, kwargs = problems[0]
    short = (tuple(a[:3] if i < 3 else a for i, a in enumerate(args)), kwargs)
    odd = [(args, {**kwargs, "white": None}), short]
    for (a, k), many in zip(odd, fit_models_batch(odd), strict=True):
        assert [f.to_dict() for f in fit_models(*a, **k)] == [f.to_dict() for f in many]
    unchecked = [(a, {**k, "reference": None}) for a, k in problems]
    for (a, k), many in zip(unchecked, fit_models_batch(unchecked), strict=True):
        _agree(fit_models(*a, **k), many)


def test_batches_are_cut_by_spread_count_and_values() -> None:
    from imufdi_cli.episodes import batch

    lengths = [100, 110, 120, 200, 210]
    members = list(range(len(lengths)))
    # spread: 200 > 1.25 * 100 starts a new batch
    assert batch._similar(members, lengths) == [[0, 1, 2], [3, 4]]
    # values: windows of 100+ rows of 10_000 columns, at most BATCH_VALUES a batch
    wide = batch.BATCH_VALUES // (2 * 120 * 1)
    cut = batch._similar(members, lengths, width=wide)
    assert [i for chunk in cut for i in chunk] == members
    for chunk in cut:
        assert len(chunk) * max(lengths[i] for i in chunk) * wide <= batch.BATCH_VALUES
    assert len(cut) > 2


def test_median_sample_interval_is_nanmedian_of_each_window() -> None:
    # irregular times (odd and even interval counts, a window past 600 samples, where
    # nanmedian takes another path, and one of a single sample) against np.nanmedian of
    # the intervals with NaN beyond each window: the same float (a selection, no sum)
    from imufdi_cli.episodes.batch import Window, _Windows

    rng = np.random.default_rng(3)
    options = {"sigma_k": 1.0, "consensus_sigma": 0.1, "white": (1.0, 0.1, 100.0)}
    lengths = [4, 5, 8, 9, 650, 651]
    windows = []
    for n in lengths:
        t = np.cumsum(rng.choice([0.01, 0.0099, 0.0101, 0.02], size=n))
        r = rng.normal(size=n)
        windows.append(Window(r, r, t, r, (0, n), None, options))
    batch = _Windows(windows)
    steps = np.where(batch.valid[:, 1:], batch.t[:, 1:] - batch.t[:, :-1], np.nan)
    assert np.array_equal(batch._median_steps(), np.nanmedian(steps, axis=1))
    one = _Windows([Window(*(np.ones(1),) * 4, (0, 1), None, options)])
    assert one._median_steps().tolist() == [0.0]


def test_batched_spike_sets_are_each_windows_own(problems) -> None:
    # the first cut of the spike sets is taken for the whole batch, the refinement row by
    # row: the same sets as _spike_set on each window (a window of four samples, without
    # the selection network, takes _spike_set whole)
    from imufdi_cli.episodes import batch as batch_module
    from imufdi_cli.episodes.model_fits import _spike_set

    seen: list[tuple[np.ndarray, np.ndarray, float]] = []
    inner = batch_module._refined_spike_set

    def spy(r: np.ndarray, first: np.ndarray, sigma_r: float) -> np.ndarray:
        out = inner(r, first, sigma_r)
        seen.append((r.copy(), out.copy(), sigma_r))
        return out

    args, kwargs = next(p for p in problems if p[1]["reference"] is not None)
    r = np.asarray(args[0], dtype=np.float64).copy()
    r[[5, 40, 41]] += 50 * math.sqrt(args[3] ** 2 + args[4] ** 2)  # spikes, one pair
    reference = kwargs["reference"]
    four = reference.__class__(
        reference.residuals[:4], reference.variance, reference.offset_var,
        reference.motion[:4], reference.correlation_sq,
    )  # fmt: skip
    short = (
        tuple(a[:4] if i < 3 else a for i, a in enumerate(args)),
        {**kwargs, "raw": kwargs["raw"][:4], "onset_range": (0, 2), "reference": four},
    )
    cases = [*problems, ((r, *args[1:]), kwargs), short, short]
    assert batch_module._batch_key(batch_module._Problem(*short).window()) is not None
    batch_module._refined_spike_set = spy  # type: ignore[assignment]
    try:
        fitted = fit_models_batch(cases)
    finally:
        batch_module._refined_spike_set = inner  # type: ignore[assignment]
    assert len(fitted) == len(cases) and len(seen) >= 2
    for values, found, sigma_r in seen:
        assert np.array_equal(found, _spike_set(values, sigma_r))
    assert any(found.sum() >= 3 for _, found, _ in seen)
    _agree(fit_models(*short[0], **short[1]), fitted[-1])
