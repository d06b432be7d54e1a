"""Straightforward transcription of the MVMD algorithm (ur Rehman & Aftab 2019, Algorithm 1),
for the benchmark ratio only: full complex FFT of the mirrored signal, fftshift, one-sided
half, Gauss-Seidel loops over modes and channels as in the published algorithm. Only the
previous iterate is kept (the published code stores every iterate). Not part of the package.
"""

import numpy as np


def mvmd_reference(signal, K, alpha, tau=0.0, tol=1e-7, max_iter=500):
    C, T = signal.shape
    half = T // 2
    f = np.concatenate([signal[:, half - 1::-1], signal, signal[:, :T - (T - half) - 1:-1]], axis=1)
    M = f.shape[1]
    freqs = np.arange(1, M + 1) / M - 0.5 - 1.0 / M
    f_hat = np.fft.fftshift(np.fft.fft(f, axis=1), axes=1)
    f_hat_plus = f_hat.copy()
    f_hat_plus[:, : M // 2] = 0
    u_hat = np.zeros((K, C, M), complex)
    omega = 0.5 / K * np.arange(K)
    lam = np.zeros((C, M), complex)
    n = 0
    while n < max_iter:
        previous = u_hat.copy()
        for k in range(K):
            for c in range(C):
                sum_others = u_hat[:, c].sum(axis=0) - u_hat[k, c]
                u_hat[k, c] = (f_hat_plus[c] - sum_others - lam[c] / 2) / (
                    1 + alpha * (freqs - omega[k]) ** 2
                )
            upper = slice(M // 2, M)
            power = np.abs(u_hat[k, :, upper]) ** 2
            omega[k] = (power @ freqs[upper]).sum() / power.sum()
        lam = lam + tau * (u_hat.sum(axis=0) - f_hat_plus)
        n += 1
        diff = 0.0
        for k in range(K):
            norm = np.sum(np.abs(previous[k]) ** 2)
            if norm > 0:
                diff += np.sum(np.abs(u_hat[k] - previous[k]) ** 2) / norm
            else:
                diff = np.inf
        if diff < tol:
            break
    full = np.zeros_like(u_hat)
    full[:, :, M // 2:] = u_hat[:, :, M // 2:]
    full[:, :, 1:M // 2] = np.conj(u_hat[:, :, M - 1:M // 2:-1])
    full[:, :, 0] = np.conj(full[:, :, -1])
    u = np.real(np.fft.ifft(np.fft.ifftshift(full, axes=2), axis=2))
    return u[:, :, half:half + T], omega, n
