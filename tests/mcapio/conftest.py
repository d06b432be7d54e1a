"""Shared fixtures of the mcapio tests."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.log import ImuBlock

T0_NS = 1_700_000_000_123_456_789


def make_block(n_samples: int, n_imus: int, *, seed: int = 0, mag: bool = False) -> ImuBlock:
    """Random array samples at 100 Hz (values exercise every float64 bit)."""
    rng = np.random.default_rng(seed)
    return ImuBlock(
        t_ns=T0_NS + np.arange(n_samples, dtype=np.int64) * 10_000_000,
        gyro=rng.normal(0.0, 0.3, (n_samples, n_imus, 3)),
        accel=rng.normal(0.0, 3.0, (n_samples, n_imus, 3)),
        mag=rng.normal(0.0, 5e-5, (n_samples, n_imus, 3)) if mag else None,
    )


@pytest.fixture
def block4() -> ImuBlock:
    return make_block(500, 4)


@pytest.fixture
def array4() -> ArrayConfig:
    return ArrayConfig.co_aligned(4, 100.0)
