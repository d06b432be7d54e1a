"""Shared helpers of the capture tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imufdi_cli.log import ImuBlock

LAYOUTS = Path(__file__).resolve().parents[2] / "docs" / "layouts"


def random_block(
    n_samples: int,
    n_imus: int,
    *,
    rate_hz: float = 100.0,
    t0_ns: int = 0,
    seed: int = 0,
    mag: bool = False,
) -> ImuBlock:
    """Gyro within +-3 rad/s, accel within +-20 m/s^2 (inside 500 dps / 4 g... mostly)."""
    rng = np.random.default_rng(seed)
    t_ns = t0_ns + np.round(np.arange(n_samples) * 1e9 / rate_hz).astype(np.int64)
    return ImuBlock(
        t_ns=t_ns,
        gyro=rng.uniform(-8.0, 8.0, (n_samples, n_imus, 3)),
        accel=rng.uniform(-39.0, 39.0, (n_samples, n_imus, 3)),
        mag=rng.uniform(-4e-3, 4e-3, (n_samples, n_imus, 3)) if mag else None,
    )
