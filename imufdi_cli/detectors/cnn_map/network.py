"""cnn-map's mapping network (paper §2): architecture, standardisation, weights and their
saved file format; and the running report of the mapping test.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.detectors.cnn_map.signals import MODEL_FORMAT
from imufdi_cli.detectors.nn import ACTIVATIONS, Conv1d, Dense, Sequential
from imufdi_cli.errors import (
    DetectorConfigError,
)


@dataclass
class _MappingReport:
    """Running account of the mapping test when it only reports (``mapping_test=report``):
    samples and episodes over its threshold, per isolated accelerometer axis."""

    samples: int = 0
    over: int = 0
    episodes: int = 0
    first_over: int = -1
    max_ratio: float = 0.0
    by_sensor: dict[int, int] = field(default_factory=dict)
    _was_over: bool = False

    def add(self, ratio: np.ndarray, isolated: np.ndarray) -> None:
        """Account one block.

        Parameters
        ----------
        ratio : ndarray, shape (N,)
            Mapping statistic over its threshold (> 1: over).
        isolated : ndarray, shape (N,), int
            The mapping test's isolated accelerometer (valid where over).
        """
        over = ratio > 1.0
        if over.any():
            rows = np.flatnonzero(over)
            if self.first_over < 0:
                self.first_over = self.samples + int(rows[0])
            previous = np.concatenate([[self._was_over], over[:-1]])
            self.episodes += int(np.sum(over & ~previous))
            for sensor, count in zip(*np.unique(isolated[rows], return_counts=True)):
                self.by_sensor[int(sensor)] = self.by_sensor.get(int(sensor), 0) + int(count)
            self.max_ratio = max(self.max_ratio, float(ratio.max()))
        self.over += int(over.sum())
        self.samples += int(ratio.size)
        if ratio.size:
            self._was_over = bool(over[-1])


@dataclass
class MappingNetwork:
    """The trained mapping: architecture, standardisation and weights.

    Attributes
    ----------
    input_length : int
        Samples per input window (L).
    filters, kernel : int
        Channels and taps of both convolutions (the second has stride 2).
    activation : str
        ``relu`` or ``tanh``.
    rate_hz : float
        Sample rate the network was trained at.
    input_mean, input_std : ndarray, shape (3,)
        Body-frame specific-force standardisation, m/s^2.
    output_mean, output_std : ndarray, shape (3,)
        Body-rate standardisation, rad/s.
    weights : list of ndarray
        Conv1 W, b, conv2 W, b, dense W, b.
    training : dict
        Training figures (loss curves, best epoch, mean absolute errors).
    """

    input_length: int
    filters: int
    kernel: int
    activation: str
    rate_hz: float
    input_mean: np.ndarray
    input_std: np.ndarray
    output_mean: np.ndarray
    output_std: np.ndarray
    weights: list[np.ndarray] = field(default_factory=list)
    training: dict[str, Any] = field(default_factory=dict)

    def build(self, rng: np.random.Generator | None = None) -> Sequential:
        """The Sequential network; with ``weights`` set, those are loaded."""
        rng = np.random.default_rng(0) if rng is None else rng
        act = ACTIVATIONS[self.activation]
        conv1 = Conv1d(3, self.filters, self.kernel, 1, rng)
        conv2 = Conv1d(self.filters, self.filters, self.kernel, 2, rng)
        shape = conv2.output_shape(conv1.output_shape((self.input_length, 3)))
        if shape[0] < 1:
            raise DetectorConfigError(
                f"cnn-map: input window of {self.input_length} samples is too short for two"
                f" convolutions of kernel {self.kernel}; use a longer input_length"
            )
        network = Sequential([conv1, act(), conv2, act(), Dense(shape[0] * shape[1], 3, rng)])
        if self.weights:
            for param, value in zip(network.params, self.weights):
                if param.shape != value.shape:
                    raise DetectorConfigError("cnn-map: model weights do not fit the architecture")
                param[...] = value
        return network

    def to_npz_bytes(self) -> bytes:
        header = {
            "format": MODEL_FORMAT,
            "input_length": self.input_length,
            "filters": self.filters,
            "kernel": self.kernel,
            "activation": self.activation,
            "rate_hz": self.rate_hz,
            "training": self.training,
        }
        arrays: dict[str, Any] = {f"weight{i}": w for i, w in enumerate(self.weights)}
        arrays.update(
            header=np.array(json.dumps(header)),
            input_mean=self.input_mean,
            input_std=self.input_std,
            output_mean=self.output_mean,
            output_std=self.output_std,
        )
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        return buffer.getvalue()

    @classmethod
    def from_npz_bytes(cls, data: bytes, where: str) -> MappingNetwork:
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                from imufdi_cli.jsonin import loads

                header = loads(str(npz["header"]), f"{where}: header", DetectorConfigError)
                if not isinstance(header, dict) or header.get("format") != MODEL_FORMAT:
                    raise DetectorConfigError(
                        f"{where}: not a cnn-map model (format {header.get('format')!r},"
                        f" expected {MODEL_FORMAT})"
                    )
                n_weights = sum(1 for key in npz.files if key.startswith("weight"))
                return cls(
                    input_length=int(header["input_length"]),
                    filters=int(header["filters"]),
                    kernel=int(header["kernel"]),
                    activation=str(header["activation"]),
                    rate_hz=float(header["rate_hz"]),
                    input_mean=npz["input_mean"],
                    input_std=npz["input_std"],
                    output_mean=npz["output_mean"],
                    output_std=npz["output_std"],
                    weights=[npz[f"weight{i}"] for i in range(n_weights)],
                    training=dict(header.get("training", {})),
                )
        except DetectorConfigError:
            raise
        except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as err:
            raise DetectorConfigError(
                f"{where}: not a readable cnn-map model file ({err})"
            ) from err
