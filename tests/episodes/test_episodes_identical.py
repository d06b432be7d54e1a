"""Episode explanations are unchanged by performance work on ``imufdi_cli.episodes``.

A fixed synthetic log (seeded: 18 single-axis gyros of six rotated triads, 100 s at 100 Hz,
every fault model of ``inject`` plus chance alarms, some without an isolated sensor) goes
through :class:`~imufdi_cli.episodes.EpisodeBuilder` in blocks of random sizes; every
episode's ``to_dict()`` (class, sizes, intervals, onsets, ends, BICs, evidence) must equal
the reference recorded by the code before the fitting functions were made faster: integers,
strings and the choices (class, sensors, onsets) exactly, floats to :data:`RTOL`.

When the episodes' *classification logic* changes on purpose, record the new reference
with ``PYTHONPATH=$PWD python tests/episodes/test_episodes_identical.py --write`` in the
same commit and say so in its message; a performance-only change (or a split of the module
into a package) must pass unchanged.
"""

from __future__ import annotations

import itertools
import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from imufdi_cli.episodes import EpisodeBuilder, _local_level, _median, _pinv_from_svd
from imufdi_cli.episodes.reference import successive_variance
from tests.references import assert_tree_close

REFERENCE = Path(__file__).with_name("episodes_identical.json")
#: Relative tolerance of the episodes' floats (of their own magnitude). The fits are least
#: squares and variance ratios over windows of up to ~1000 samples (relative rounding of a
#: sum ~ n eps = 2e-13), and an interval bound ``size -/+ 1.645 se`` loses up to a factor
#: |size| / |bound| more to cancellation (~30 here): ~1e-11 at worst. Measured across
#: numpy's AVX-512, AVX2 and SSE4.2 loops, five OpenBLAS kernels and numpy 2.0 / scipy
#: 1.13 against numpy 2.4 / scipy 1.17: at most 5.8e-12 (an interval bound near zero),
#: 1.5e-13 for a BIC. A real change is far larger: the log's noise level moved by 1e-8 of
#: itself fails it.
RTOL = 1e-9
RATE = 100.0
SIGMA = np.deg2rad(0.15)


def _rotations(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` random proper rotations (QR of Gaussian matrices), shape (count, 3, 3)."""
    out = []
    for _ in range(count):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        if np.linalg.det(q) < 0:
            q[:, 0] = -q[:, 0]
        out.append(q)
    return np.array(out)


def synthetic_log(seed: int = 20261123) -> dict[str, Any]:
    """The fixed log: measurements (N, 18) in rad/s, times, alarm rows and block sizes.

    Faults (measurement index, onset s, duration s): step 0.9 deg/s on 2 (10, 8), drift
    1 deg/s^2 on 4 (25, 10), noise x3 on 1 (40, 8), stuck on 3 (55, 6), spikes 3 deg/s at
    5 Hz on 5 (70, 8), scale x1.05 on 0 (85, 8). Alarms follow each fault after a delay
    (2 s for the drift, 0.3 s otherwise) with 20 % dropped rows (gaps to merge across),
    5 % of alarm rows isolating another sensor; chance alarms at 1e-3 per row, a third of
    them without an isolated sensor.
    """
    rng = np.random.default_rng(seed)
    n_imus, length = 6, 10_000
    H = _rotations(rng, n_imus).reshape(n_imus * 3, 3)
    n = H.shape[0]
    sigma = SIGMA * rng.uniform(0.7, 1.4, n)
    t = np.arange(length) / RATE
    omega = np.stack(
        [np.sin(2 * np.pi * 0.1 * t), 0.5 * np.cos(2 * np.pi * 0.23 * t), 0.3 + 0 * t], axis=1
    )
    bias = rng.normal(0, np.deg2rad(0.2), n)
    m = omega @ H.T + bias + rng.normal(size=(length, n)) * sigma
    faults = [
        (2, "step", 10.0, 8.0),
        (4, "drift", 25.0, 10.0),
        (1, "noise", 40.0, 8.0),
        (3, "stuck", 55.0, 6.0),
        (5, "spikes", 70.0, 8.0),
        (0, "scale", 85.0, 8.0),
    ]
    alarm = np.zeros(length, bool)
    isolated = np.full(length, -1, np.int32)
    for k, model, onset_s, duration_s in faults:
        a, b = round(onset_s * RATE), round((onset_s + duration_s) * RATE)
        span = slice(a, b)
        if model == "step":
            m[span, k] += np.deg2rad(0.9)
        elif model == "drift":
            m[span, k] += np.deg2rad(1.0) * (t[span] - t[a])
        elif model == "noise":
            m[span, k] += rng.normal(0, sigma[k] * math.sqrt(8.0), b - a)
        elif model == "stuck":
            m[span, k] = m[a - 1, k]
        elif model == "spikes":
            hits = rng.random(b - a) < 0.05
            m[span, k] += hits * np.deg2rad(3.0) * rng.choice([-1.0, 1.0], b - a)
        elif model == "scale":
            m[span, k] += 0.05 * (omega[span] @ H[k])
        delay = round((2.0 if model == "drift" else 0.3) * RATE)
        rows = np.arange(a + delay, b + 20)
        rows = rows[rng.random(rows.size) > 0.2]
        alarm[rows] = True
        isolated[rows] = np.where(rng.random(rows.size) < 0.05, (k + 7) % n, k)
    quiet = ~alarm
    chance = quiet & (rng.random(length) < 1e-3)
    alarm |= chance
    isolated[chance] = np.where(
        rng.random(int(chance.sum())) < 1 / 3, -1, rng.integers(0, n, int(chance.sum()))
    )
    statistic = np.where(alarm, rng.uniform(1.0, 20.0, length), rng.uniform(0, 1, length))
    blocks = rng.integers(50, 700, 40)
    return {
        "H": H,
        "sigma": sigma,
        "m": m,
        "t_ns": np.arange(length, dtype=np.int64) * 10_000_000,
        "alarm": alarm,
        "isolated": isolated,
        "statistic": statistic,
        "calibration": m[:200],
        "blocks": blocks,
    }


def explained_episodes(calibrated: bool) -> list[dict[str, Any]]:
    """Every episode of the fixed log, as ``Episode.to_dict()``, block by block; with the
    calibration window's mean and size (``calibrated``) or without."""
    log = synthetic_log()
    n = log["H"].shape[0]
    options: dict[str, Any] = {}
    if calibrated:
        options = {"calibration_samples": 200, "calibration_mean": log["calibration"].mean(0)}
    builder = EpisodeBuilder(
        "glt", "gyro", log["H"], [f"s{i}" for i in range(n)], log["sigma"], RATE, **options
    )
    out = []
    start, length = 0, log["m"].shape[0]
    sizes = iter(log["blocks"].tolist())
    while start < length:
        stop = min(length, start + next(sizes, 1000))
        builder.feed(log["m"][start:stop])
        status = SimpleNamespace(
            alarm=log["alarm"][start:stop],
            isolated=log["isolated"][start:stop],
            statistic=log["statistic"][start:stop],
            threshold=np.ones(stop - start),
        )
        t_ns = log["t_ns"][start:stop]
        out += builder.rows(t_ns, t_ns + 3_000_000, status)
        start = stop
    out += builder.finish()
    return [e.to_dict() for e in out]


def _record() -> dict[str, Any]:
    return {"calibrated": explained_episodes(True), "uncalibrated": explained_episodes(False)}


def test_episode_explanations_are_identical_to_the_reference() -> None:
    expected = json.loads(REFERENCE.read_text())
    got = json.loads(json.dumps(_record()))
    for key in ("calibrated", "uncalibrated"):
        assert len(got[key]) == len(expected[key])
        for i, (mine, theirs) in enumerate(zip(got[key], expected[key])):
            assert_tree_close(mine, theirs, RTOL, f"{key}[{i}]")


def test_the_reference_covers_every_fault_model_and_the_fault_end() -> None:
    """The fixed log exercises what the fits compute: each model wins somewhere, some fault
    ends inside its window, and some episode has no isolated sensor."""
    expected = json.loads(REFERENCE.read_text())
    episodes = expected["calibrated"] + expected["uncalibrated"]
    classes = {e["fault_class"] for e in episodes}
    assert {"step", "drift", "noise", "stuck", "spikes", "none"} <= classes
    assert any(f["end_index"] is not None for e in episodes for f in e["fits"])
    assert any(e["isolated_by"] == "residual" for e in episodes)


def test_pinv_from_the_svd_is_numpys_pinv_to_the_bit() -> None:
    """_motion_fit takes the pseudo-inverse from the decomposition it tests the singular
    values of: the floats must be numpy's (a numpy that changes pinv fails here)."""
    rng = np.random.default_rng(7)
    for rows, cols in [(201, 4), (201, 5), (30, 5), (8, 4), (2500, 5)]:
        for rank_deficient in (False, True):
            a = rng.normal(size=(rows, cols)) * 10.0 ** rng.integers(-3, 3, cols)
            if rank_deficient:
                a[:, -1] = a[:, 0] * 2.0
            a = a / np.linalg.norm(a, axis=0)
            u, s, vt = np.linalg.svd(a, full_matrices=False)
            assert np.array_equal(_pinv_from_svd(u, s, vt), np.linalg.pinv(a))


def test_motion_fit_shortcuts_are_numpys_own_to_the_bit() -> None:
    """_motion_fit's column norms and successive_variance's differences skip numpy's
    wrappers (``norm(axis=0)``, ``diff``): the floats must be those of the wrappers (a
    numpy that computes them otherwise fails here)."""
    rng = np.random.default_rng(11)
    for rows, cols in [(201, 4), (201, 5), (8, 4), (2500, 5)]:
        a = rng.normal(size=(rows, cols)) * 10.0 ** rng.integers(-3, 3, cols)
        a[: rows // 2, 0] = 0.0  # a fault column, zero before its onset
        shortcut = np.sqrt(np.add.reduce(a * a, axis=0))
        assert np.array_equal(shortcut, np.linalg.norm(a, axis=0))
        d = np.diff(a, axis=0)
        expected = np.einsum("i...,i...->...", d, d) / (2 * (rows - 1))
        assert np.array_equal(successive_variance(a), expected)
        column = np.diff(a[:, 1])
        assert successive_variance(a[:, 1]) == np.einsum("i,i->", column, column) / (2 * (rows - 1))


def _windowed_median(r: np.ndarray) -> np.ndarray:
    """numpy's median (nanmedian with a NaN) of each window ``r[max(0, i - 2) : i + 3]``.

    Without NaN the full windows of five are one ``np.median`` along an axis of their
    sliding view (the same partition and middle value per row as one call per window, which
    costs 0.2 s of CPU); the ends, and every window of
    a series with a NaN (``nanmedian`` along an axis takes another route), one at a time.
    """
    n = r.size
    if np.isnan(r).any():
        return np.array([np.nanmedian(r[max(0, i - 2) : i + 3]) for i in range(n)])
    out = np.empty(n)
    ends: range | list[int] = range(n)
    if n >= 5:
        out[2 : n - 2] = np.median(np.lib.stride_tricks.sliding_window_view(r, 5), axis=1)
        ends = [0, 1, n - 2, n - 1]
    for i in ends:
        out[i] = np.median(r[max(0, i - 2) : i + 3])
    return out


@pytest.mark.filterwarnings("ignore:All-NaN slice:RuntimeWarning")
def test_local_level_is_the_running_median_of_five() -> None:
    """The selection network and the four ends against numpy's median of each window
    (values in [start, stop) of i - 2 .. i + 2), ties and non-finite values included."""
    rng = np.random.default_rng(8)
    for n in [1, 2, 4, 5, 6, 9, 201]:
        for trial in range(20):
            r = rng.normal(size=n) * 10.0 ** rng.integers(-6, 6)
            if trial % 3 == 1:
                r = np.round(r, 1)  # ties
            if trial % 5 == 4:
                r[rng.integers(n)] = np.nan
            expected = _windowed_median(r)
            expected = np.where(np.isfinite(expected), expected, 0.0)
            assert np.array_equal(_local_level(r), expected), (n, trial)


def test_median_is_numpys_median() -> None:
    """The drift search's sample step: odd and even counts, ties, non-finite values."""
    rng = np.random.default_rng(9)
    for n in range(1, 40):
        for trial in range(10):
            v = rng.normal(size=n) * 10.0 ** rng.integers(-9, 9)
            if trial % 3 == 1:
                v = np.round(np.abs(v), 2)
            if trial % 5 == 4:
                v[rng.integers(n)] = np.inf if trial % 2 else np.nan
            expected = float(np.median(v))
            got = _median(v)
            assert got == expected or (math.isnan(got) and math.isnan(expected)), (n, v)


def _plain_update(monitor: Any, state: dict[str, Any], measurements: np.ndarray) -> tuple:
    """VarianceDropMonitor.update as written before it worked in place (commit 58050f2):
    the formula step by step, each with its own temporary; ``state`` holds its last row
    and tail."""
    r = np.asarray(measurements, dtype=np.float64) @ monitor.A
    n = r.shape[0]
    last = state.get("last")
    previous = r[:1] if last is None else last[None, :]
    half_sq = 0.5 * np.diff(np.concatenate([previous, r]), axis=0) ** 2
    if last is None and n:
        half_sq = half_sq[1:]
    half_sq = np.where(np.isfinite(half_sq), half_sq, monitor.variance)
    if n:
        state["last"] = r[-1]
    tail = state.get("tail", np.zeros((0, monitor.A.shape[1])))
    held, fresh = tail.shape[0], half_sq.shape[0]
    joined = np.concatenate([tail, half_sq])
    cumulative = np.concatenate([np.zeros((1, joined.shape[1])), np.cumsum(joined, axis=0)])
    stop = np.arange(held + 1, held + fresh + 1)
    ready = stop >= monitor.window
    sums = cumulative[stop] - cumulative[np.maximum(stop - monitor.window, 0)]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = sums / monitor.window / monitor.variance * (monitor.quantile / monitor.quantiles)
    ratio = np.where(np.isfinite(ratio), ratio, np.inf)
    worst = np.argmin(ratio, axis=1) if ratio.shape[0] else np.zeros(0, np.int64)
    lowest = ratio[np.arange(ratio.shape[0]), worst]
    alarm = ready & (lowest < monitor.quantile)
    statistic = np.where(ready, -np.log(np.maximum(lowest, 1e-300)), -np.inf)
    state["tail"] = joined[-monitor.window :]
    pad = n - half_sq.shape[0]
    return (
        np.concatenate([np.zeros(pad, bool), alarm]),
        np.concatenate([np.full(pad, -1), np.where(alarm, worst, -1)]).astype(np.int64),
        np.concatenate([np.full(pad, -np.inf), statistic]),
        np.full(n, -math.log(monitor.quantile)),
    )


def test_variance_drop_monitor_is_the_plain_formula_to_the_bit() -> None:
    """The in-place monitor gives the rows of the formula step by step: blocks of odd sizes
    (empty, one row, shorter than the window), NaN and inf rows, a frozen sensor (alarms),
    a sensor without a consensus (infinite variance)."""
    from imufdi_cli.episodes.variance_drop import VarianceDropMonitor

    rng = np.random.default_rng(31)
    n = 9
    A = rng.normal(size=(n, n)) * 0.3 + np.eye(n)
    A[:, 4] = 0.0
    variance = np.full(n, 2 * 0.3**2 + 1.0)
    variance[4] = np.inf
    m = rng.normal(size=(3000, n)) + np.sin(np.arange(3000) / 50.0)[:, None]
    m[100:103, 2] = np.nan
    m[1500] = np.inf
    m[2000:2400, 6] = m[2000, 6]  # frozen: its residual keeps only the others' noise
    cuts = [0, 0, 1, 2, 3, 40, 41, 100, 101, 102, 400, 1990, 1991, 2500, 2597, 3000]
    monitor = VarianceDropMonitor(A, variance, window=100, alpha=1e-3, calibration_dof=130.0)
    state: dict[str, Any] = {}
    alarms = 0
    with np.errstate(invalid="ignore"):
        for lo, hi in itertools.pairwise(cuts):
            got = monitor.update(m[lo:hi])
            expected = _plain_update(monitor, state, m[lo:hi])
            for field, value in zip(("alarm", "isolated", "statistic", "threshold"), expected):
                mine = getattr(got, field)
                assert mine.dtype == value.dtype and mine.tobytes() == value.tobytes(), (lo, field)
            alarms += int(got.alarm.sum())
    assert alarms > 0


def test_stacked_suffix_sums_are_the_one_row_sums_to_the_bit() -> None:
    """_fit_window's seven suffix sums in one accumulation equal _suffix row by row."""
    from imufdi_cli.episodes.numerics import _suffix, _suffixes

    rng = np.random.default_rng(12)
    for length in (4, 5, 76, 201, 3000):
        rows = rng.normal(size=(7, length)) * 10.0 ** rng.integers(-6, 6, size=(7, 1))
        lo, hi = 0, length - 2
        got = _suffixes(rows, lo, hi)
        for i in range(7):
            assert got[i].tobytes() == _suffix(rows[i])[np.arange(lo, hi)].tobytes()


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    REFERENCE.write_text(json.dumps(_record(), indent=0, sort_keys=True) + "\n")
    print(f"wrote {REFERENCE}")
