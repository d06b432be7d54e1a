"""The attributes that cnn-map's parts share, declared once for the type checker.

:class:`~imufdi_cli.detectors.cnn_map.detector.CnnMapDetector` is assembled from one class
per concern, each in its own module: :class:`~.reference._ReferenceRate` (geometry and the
GLT-screened reference rate), :class:`~.input_test._InputTest` (the CUSUM input test),
:class:`~.mapping._MappingTest` (network training and the mapping test), in that order of
inheritance. The parameters and the fitted state that more than one part reads are
declared here; ``CnnMapDetector.__init__``, ``_setup`` and ``fit`` set them.
"""

from __future__ import annotations

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.cnn_map.network import MappingNetwork, _MappingReport
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.nn import Sequential
from imufdi_cli.detectors.noise_glr import NoiseGlrDetector


class _Settings:
    """Parameters (see ``CnnMapDetector.PARAMS``) and shared fitted state."""

    # parameters
    alpha: float
    false_alarms: float
    window_s: float
    input_length_s: float
    filters: int
    kernel: int
    activation: str
    epochs: int
    batch: int
    patience: int
    learning_rate: float
    holdout: float
    seed: int
    model_path: str | None
    whiten: int
    input_test: bool
    mapping_test: str
    mapping_alarms: bool
    mapping_alpha: float
    # fitted state read by more than one part
    array: ArrayConfig | None
    mapping: MappingNetwork | None
    network: Sequential | None
    mapping_report: _MappingReport
    _glt: GltDetector | None
    _input: NoiseGlrDetector | None
    input_note: str
    input_mean_window: int
    input_length: int
    tested: np.ndarray
    rotations: np.ndarray
    n_accel: int
    sensor_of: np.ndarray
    _samples_seen: int
