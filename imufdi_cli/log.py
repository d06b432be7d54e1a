"""ImuBlock: a block of time-aligned array samples, and block iteration.

Everything in SI: timestamps in integer nanoseconds, gyro in rad/s, accel in m/s^2,
magnetometer in tesla. Triads are in each IMU's own sensor frame (as the chip reports
them); ``ArrayConfig.select`` flattens them to the used sensor axes in sensor-id order.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from imufdi_cli.array import SENSOR_TYPES


@dataclass
class ImuBlock:
    """A block of N aligned samples of an m-IMU array.

    Attributes
    ----------
    t_ns : ndarray, shape (N,), int64
        Sample timestamps, nanoseconds.
    gyro : ndarray, shape (N, m, 3), float64, or None
        Angular rate, rad/s, IMU frames.
    accel : ndarray, shape (N, m, 3), float64, or None
        Specific force, m/s^2, IMU frames.
    mag : ndarray, shape (N, m, 3), float64, or None
        Magnetic field, tesla, IMU frames.
    missing : ndarray, shape (N, m), bool, or None
        IMU k had no sample at row i (a topic that stopped or slowed while the others
        went on): its gyro and accel values there are NaN. None: every IMU has every
        sample.
    """

    t_ns: np.ndarray
    gyro: np.ndarray | None = None
    accel: np.ndarray | None = None
    mag: np.ndarray | None = None
    missing: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64)
        n = self.t_ns.shape[0]
        for name in SENSOR_TYPES:
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=np.float64)
                if value.ndim != 3 or value.shape[0] != n or value.shape[2] != 3:
                    raise ValueError(
                        f"ImuBlock.{name} must have shape (N, m, 3), got {value.shape}"
                    )
                setattr(self, name, value)
        if self.missing is not None:
            self.missing = np.asarray(self.missing, dtype=bool)
            if self.missing.ndim != 2 or self.missing.shape[0] != n:
                raise ValueError(
                    f"ImuBlock.missing must have shape (N, m), got {self.missing.shape}"
                )
            if not self.missing.any():
                self.missing = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def n_imus(self) -> int:
        for name in SENSOR_TYPES:
            value = getattr(self, name)
            if value is not None:
                return int(value.shape[1])
        return 0

    def get(self, sensor_type: str) -> np.ndarray | None:
        """The (N, m, 3) array of a sensor type, or None."""
        return getattr(self, sensor_type) if sensor_type in SENSOR_TYPES else None

    def t_s(self, t0_ns: int | None = None) -> np.ndarray:
        """Timestamps in seconds relative to ``t0_ns`` (default: the first sample)."""
        if len(self) == 0:
            return np.zeros(0)
        origin = int(self.t_ns[0]) if t0_ns is None else int(t0_ns)
        return (self.t_ns - origin).astype(np.float64) * 1e-9

    def slice(self, start: int, stop: int) -> ImuBlock:
        """Samples ``start:stop`` (views, not copies)."""
        return ImuBlock(
            t_ns=self.t_ns[start:stop],
            gyro=None if self.gyro is None else self.gyro[start:stop],
            accel=None if self.accel is None else self.accel[start:stop],
            mag=None if self.mag is None else self.mag[start:stop],
            missing=None if self.missing is None else self.missing[start:stop],
        )

    def mask(self, keep: np.ndarray) -> ImuBlock:
        """Samples where the boolean ``keep`` (N,) is true."""
        return ImuBlock(
            t_ns=self.t_ns[keep],
            gyro=None if self.gyro is None else self.gyro[keep],
            accel=None if self.accel is None else self.accel[keep],
            mag=None if self.mag is None else self.mag[keep],
            missing=None if self.missing is None else self.missing[keep],
        )

    def copy(self) -> ImuBlock:
        return replace(
            self,
            t_ns=self.t_ns.copy(),
            gyro=None if self.gyro is None else self.gyro.copy(),
            accel=None if self.accel is None else self.accel.copy(),
            mag=None if self.mag is None else self.mag.copy(),
            missing=None if self.missing is None else self.missing.copy(),
        )

    @classmethod
    def concatenate(cls, blocks: Iterable[ImuBlock]) -> ImuBlock:
        """Join blocks end to end (they must carry the same sensor types and IMU count)."""
        blocks = [b for b in blocks]
        if not blocks:
            return cls(t_ns=np.zeros(0, np.int64))
        fields: dict[str, np.ndarray | None] = {}
        for name in SENSOR_TYPES:
            values = [getattr(b, name) for b in blocks]
            if all(v is None for v in values):
                fields[name] = None
            elif any(v is None for v in values):
                raise ValueError(f"cannot concatenate blocks with and without {name}")
            else:
                fields[name] = np.concatenate(values, axis=0)  # type: ignore[arg-type]
        missing = None
        if any(b.missing is not None for b in blocks):
            m = next(b.missing.shape[1] for b in blocks if b.missing is not None)
            missing = np.concatenate(
                [np.zeros((len(b), m), bool) if b.missing is None else b.missing for b in blocks]
            )
        return cls(t_ns=np.concatenate([b.t_ns for b in blocks]), missing=missing, **fields)


def iter_blocks(block: ImuBlock, block_size: int) -> Iterator[ImuBlock]:
    """Split an in-memory block into consecutive blocks of at most ``block_size`` samples."""
    if block_size < 1:
        raise ValueError("block_size must be >= 1")
    for start in range(0, len(block), block_size):
        yield block.slice(start, start + block_size)


def rechunk(blocks: Iterable[ImuBlock], block_size: int) -> Iterator[ImuBlock]:
    """Re-cut a stream of blocks of any sizes into blocks of exactly ``block_size``
    samples (the last one may be shorter). Memory stays bounded by ``block_size``."""
    pending: list[ImuBlock] = []
    count = 0
    for block in blocks:
        if len(block) == 0:
            continue
        pending.append(block)
        count += len(block)
        while count >= block_size:
            joined = ImuBlock.concatenate(pending)
            yield joined.slice(0, block_size)
            rest = joined.slice(block_size, len(joined))
            pending = [rest] if len(rest) else []
            count = len(rest)
    if count:
        yield ImuBlock.concatenate(pending)
