"""What an episode is explained by: the fault models and one model's fit
(:class:`FaultFit`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.episodes.numerics import _finite

#: ``(sigma_k, consensus_sigma, dof)`` or ``(sigma_k, consensus_sigma, dof, (A, B, D))``:
#: the white noise of a sensor and its consensus, and how well the calibration knows them
#: (:func:`fit_models`, :func:`white_sigma_spread`)
WhiteNoise = tuple[float, float, float] | tuple[float, float, float, tuple[float, float, float]]

#: fault models an episode is explained by, in tie-break order (``clipping`` and
#: ``dropout`` are faults of the data that only the health detector's checks name)
MODELS = ("none", "step", "drift", "noise", "scale", "spikes", "stuck", "clipping", "dropout")
#: what the size of each model is
SIZE_NAMES = {
    "none": "",
    "step": "amp",
    "drift": "rate",
    "noise": "factor",
    "scale": "factor",
    "spikes": "amp",
    "stuck": "value",
    "clipping": "value",
    "dropout": "duration",
}


@dataclass(frozen=True)
class FaultFit:
    """One fault model fitted to an episode's residual.

    Attributes
    ----------
    model : str
        One of :data:`MODELS`.
    size : float
        Step amplitude, drift rate (per second), noise or scale factor, spike amplitude, or
        stuck value; SI units of the sensor type (factors are dimensionless).
    low, high : float
        Confidence interval of ``size`` at the fit's confidence level.
    onset_index : int
        Index in the analysis window where the fitted fault starts.
    bic : float
        Schwarz criterion ``-2 log L + k ln n`` (lower is better; ``-inf`` for stuck).
    extra : dict
        Model-specific figures (spikes: ``rate_hz`` with its interval).
    """

    model: str
    size: float
    low: float
    high: float
    onset_index: int
    bic: float
    extra: dict[str, float] = field(default_factory=dict)
    #: index in the analysis window where the fitted fault ends (exclusive; None: it lasts
    #: to the window's end)
    end_index: int | None = None
    #: fitted mean and variance of the residual from the onset on (for the end search; not
    #: serialised)
    curve: tuple[np.ndarray, float] | None = field(default=None, repr=False, compare=False)

    @property
    def size_name(self) -> str:
        return SIZE_NAMES[self.model]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        out = _finite(
            {
                "model": self.model,
                "size": self.size,
                "low": self.low,
                "high": self.high,
                "onset_index": self.onset_index,
                "end_index": self.end_index,
                "bic": self.bic,
                "extra": dict(self.extra),
            }
        )
        out["size_name"] = self.size_name
        return out
