"""Shared fixtures and helpers of the faults tests."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.log import ImuBlock

DEG = math.pi / 180.0
G = 9.80665
RATE_HZ = 100.0
T0_NS = 1_700_000_000_123_456_789  # realistic epoch stamp: checks int64 arithmetic


@pytest.fixture
def array() -> ArrayConfig:
    return ArrayConfig.co_aligned(4, RATE_HZ, sensors=("gyro", "accel", "mag"))


def make_block(n: int, n_imus: int = 4, seed: int = 0) -> ImuBlock:
    rng = np.random.default_rng(seed)
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * 10_000_000
    return ImuBlock(
        t_ns=t_ns,
        gyro=rng.normal(0.0, 0.01, (n, n_imus, 3)),
        accel=rng.normal(0.0, 0.1, (n, n_imus, 3)) + np.array([0.0, 0.0, G]),
        mag=rng.normal(0.0, 1e-7, (n, n_imus, 3)) + np.array([2e-5, 0.0, 4e-5]),
    )


def rel_s(block: ImuBlock) -> np.ndarray:
    return (block.t_ns - T0_NS) * 1e-9
