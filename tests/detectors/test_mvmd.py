"""MVMD: the paper's checks (Li et al. 2026 §2.4, Table 1), exactness, errors."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.detectors.mvmd import (
    channel_power,
    mirror_extend,
    mvmd,
    mvmd_batch,
    mvmd_gains,
    spectrum,
)
from imufdi_cli.errors import DetectorConfigError

RATE = 1000.0
T = np.arange(1000) / RATE


def tone(freq: float) -> np.ndarray:
    return np.cos(2 * np.pi * freq * T)


def two_channel() -> np.ndarray:
    # Li et al. §2.4: channel 1 = 5 Hz + 36 Hz, channel 2 = 24 Hz + 36 Hz
    return np.vstack([tone(5) + tone(36), tone(24) + tone(36)])


def direct_mvmd(x: np.ndarray, K: int, alpha: float, tau: float, n_iter: int) -> np.ndarray:
    """Unreduced ADMM (eqs. A-C of mvmd.py), per channel, fixed iteration count."""
    spec, freqs, offset = spectrum(x)
    C, F = spec.shape
    u = np.zeros((K, C, F), complex)
    lam = np.zeros((C, F), complex)
    omega = 0.5 / K * np.arange(K)
    for _ in range(n_iter):
        for k in range(K):
            others = u.sum(axis=0) - u[k]
            u[k] = (spec - others - lam / 2) / (1 + alpha * (freqs - omega[k]) ** 2)
            power = np.abs(u[k]) ** 2
            omega[k] = (power.sum(axis=0) @ freqs) / power.sum()
        lam = lam + tau * (u.sum(axis=0) - spec)
    modes = np.fft.irfft(u, n=2 * x.shape[1], axis=-1)[..., offset : offset + x.shape[1]]
    return modes[np.argsort(omega)]


def test_two_channel_signal_gives_5_24_36_hz_with_shared_36_hz_mode():
    x = two_channel()
    result = mvmd(x, 3, 2000.0)
    assert result.converged
    assert_allclose(result.omega * RATE, [5.0, 24.0, 36.0], atol=0.05)
    energy = np.linalg.norm(result.modes, axis=2)  # (K, C)
    # 5 Hz only in channel 1, 24 Hz only in channel 2, 36 Hz in both, in the same mode
    assert energy[0, 1] < 0.02 * energy[0, 0]
    assert energy[1, 0] < 0.02 * energy[1, 1]
    assert_allclose(energy[2], np.linalg.norm(tone(36)), rtol=0.01)
    inner = slice(50, -50)  # away from the mirror-extension edges
    assert_allclose(result.modes[2, 0, inner], tone(36)[inner], atol=0.05)
    assert_allclose(result.modes[2, 1, inner], tone(36)[inner], atol=0.05)


def test_sum_of_modes_reconstructs_signal():
    x = two_channel()
    result = mvmd(x, 3, 2000.0)
    relative = np.linalg.norm(result.modes.sum(axis=0) - x) / np.linalg.norm(x)
    assert relative < 5e-3  # measured 2.8e-3 with tau = 0
    with_dual = mvmd(x, 3, 2000.0, tau=0.5, tol=1e-10, max_iter=2000)
    relative_dual = np.linalg.norm(with_dual.modes.sum(axis=0) - x) / np.linalg.norm(x)
    assert relative_dual < 1e-3  # measured 4.1e-4: the dual ascent enforces reconstruction
    assert relative_dual < relative / 5


@pytest.mark.parametrize("tau", [0.0, 0.3])
def test_reduced_iteration_equals_direct_admm(tau):
    rng = np.random.default_rng(3)
    x = rng.standard_normal((5, 64)) + np.vstack([tone(40)[:64]] * 5)
    fast = mvmd(x, 3, 300.0, tau=tau, tol=0.0, max_iter=25)
    assert fast.n_iter == 25
    assert_allclose(fast.modes, direct_mvmd(x, 3, 300.0, tau, 25), atol=1e-10)


def test_convergence_is_scale_invariant():
    x = two_channel()
    small, large = mvmd(x, 3, 2000.0), mvmd(1e6 * x, 3, 2000.0)
    assert small.n_iter == large.n_iter
    assert_allclose(large.modes, 1e6 * small.modes, rtol=1e-9, atol=1e-3)


def test_batch_matches_single_runs():
    x = two_channel()
    batch = mvmd_batch(x, [2, 3, 4], [500.0, 2000.0, 800.0])
    for result, (K, alpha) in zip(batch, [(2, 500.0), (3, 2000.0), (4, 800.0)]):
        single = mvmd(x, K, alpha)
        assert result.n_iter == single.n_iter
        assert_allclose(result.modes, single.modes, atol=1e-12)


def test_windows_in_one_batch_equal_one_at_a_time():
    # many signals of one length (per-row power), as woa-mvmd-glt batches a block's windows:
    # each row converges on its own, as if alone, to the same floats (tune_signals relies on
    # it: a search's result does not depend on the searches batched with it)
    rng = np.random.default_rng(5)
    t = np.arange(50) / 100.0
    windows = 0.2 + 0.01 * rng.standard_normal((12, 6, 50)) + 0.05 * np.sin(2 * np.pi * 3 * t)
    spectra = [spectrum(w) for w in windows]
    power = np.stack([channel_power(spec) for spec, _, _ in spectra])
    freqs = spectra[0][1]
    Ks = [2, 3] * 6
    alphas = list(np.linspace(100.0, 2000.0, 12))
    batch = mvmd_gains(power, freqs, Ks, alphas, tol=1e-6, max_iter=300, history=False)
    n_iters = set()
    for row, (gains, history, n_iter, converged) in enumerate(batch):
        single = mvmd_gains(power[row], freqs, [Ks[row]], [alphas[row]], tol=1e-6, max_iter=300)
        assert n_iter == single[0][2]
        assert converged == single[0][3]
        assert_array_equal(gains, single[0][0])
        # without history: the initial and the final centre frequencies
        assert history.shape == (2, Ks[row])
        assert_array_equal(history[-1], single[0][1][-1])
        assert_allclose(history[0], single[0][1][0])
        n_iters.add(n_iter)
    assert len(n_iters) > 1  # rows left the batch at different iterations


def test_power_shape_must_match_the_rows():
    _, freqs, _ = spectrum(two_channel())
    with pytest.raises(DetectorConfigError, match="power must have shape"):
        mvmd_gains(np.ones((3, freqs.size)), freqs, [2, 2], [100.0, 100.0])


def test_dc_mode_and_inits():
    x = two_channel() + 3.0
    dc = mvmd(x, 4, 2000.0, dc=True)
    assert dc.omega[0] == 0.0
    assert_allclose(dc.modes[0].mean(axis=1), 3.0, atol=0.02)
    rand = mvmd(x, 3, 2000.0, init="random", rng=np.random.default_rng(0))
    assert rand.omega_history.shape == (rand.n_iter + 1, 3)
    zero = mvmd(x, 3, 2000.0, init="zero")
    assert_allclose(zero.omega_history[0], 0.0)


def test_mirror_extension_odd_length():
    x = np.arange(5.0)[None]
    ext, offset = mirror_extend(x)
    assert_allclose(ext[0], [1, 0, 0, 1, 2, 3, 4, 4, 3, 2])
    assert offset == 2
    result = mvmd(np.sin(np.arange(37) / 3.0), 2, 100.0)
    assert result.modes.shape == (2, 1, 37)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"K": 0, "alpha": 100.0}, "K must be"),
        ({"K": 2, "alpha": 0.0}, "alpha must be > 0"),
        ({"K": 2, "alpha": -5.0}, "alpha must be > 0"),
        ({"K": 2, "alpha": 100.0, "init": "spread"}, "valid: uniform, random, zero"),
        ({"K": 2, "alpha": 100.0, "init": "random"}, "Generator"),
    ],
)
def test_bad_parameters_raise(kwargs, match):
    with pytest.raises(DetectorConfigError, match=match) as info:
        mvmd(two_channel(), **kwargs)
    assert info.value.exit_code == 2


def test_too_short_signal_raises():
    with pytest.raises(DetectorConfigError, match="at least 4"):
        mvmd(np.ones((2, 3)), 1, 100.0)
