"""Alarm episodes and what they mean: which sensor, which kind of fault, how big, and why.

An **episode** is a run of alarms of one detector on one sensor type, merged across short
quiet gaps and joined with later fragments on the same isolated sensor; once it closes it
is explained on that sensor alone, against the consensus of the others, by the fault
models of ``imufdi inject`` ranked by BIC, each with the size of the fault and its
interval. docs/episodes.md describes the method and its measured coverage; the modules:

=================  ======================================================================
module             concern
=================  ======================================================================
``builder``        :class:`EpisodeBuilder` (streaming: runs, fragments, explanation as
                   they close), :func:`episode_builders` (one per sensor type)
``episode``        :class:`Episode`, :func:`find_episodes`, :func:`isolation_summary`
``fits``           :func:`fit_models`: onset and end search, BIC ranking of the models
``model_fits``     the noise, spikes and stuck fits
``reference``      :func:`leave_one_out`, :class:`Reference` (the other sensors), the
                   least-squares sizes (step, drift, scale) and their intervals, the
                   consensus matrices of a calibration
``white_noise``    :func:`white_sigma` and the spread of its calibration estimate
``variance_drop``  :class:`VarianceDropMonitor`: frozen outputs the detectors cannot see
``scoring``        :func:`match_episodes`, :class:`EpisodeTally`, :func:`score_episodes`
``fault_fit``      :class:`FaultFit`, :data:`MODELS`
``numerics``       quantiles, Gaussian log-likelihoods, suffix sums, the median
=================  ======================================================================

Every name is importable from ``imufdi_cli.episodes`` (the private helpers too, for the
tests that pin them). Coverage and false episodes are measured in ``tests/episodes/``,
``studies/episodes.py`` and docs/episodes.md.
"""

from __future__ import annotations

from imufdi_cli.episodes.builder import EpisodeBuilder, episode_builders
from imufdi_cli.episodes.episode import (
    Episode,
    find_episodes,
    isolation_summary,
)
from imufdi_cli.episodes.episode import _sensor_amplitude as _sensor_amplitude
from imufdi_cli.episodes.fault_fit import MODELS, SIZE_NAMES, FaultFit, WhiteNoise
from imufdi_cli.episodes.fits import _drift_search as _drift_search
from imufdi_cli.episodes.fits import _fault_end as _fault_end
from imufdi_cli.episodes.fits import _fit_window as _fit_window
from imufdi_cli.episodes.fits import fit_models
from imufdi_cli.episodes.model_fits import SPIKE_CUT
from imufdi_cli.episodes.model_fits import _local_level as _local_level
from imufdi_cli.episodes.model_fits import _noise_fit as _noise_fit
from imufdi_cli.episodes.model_fits import _spike_fit as _spike_fit
from imufdi_cli.episodes.model_fits import _stuck_fit as _stuck_fit
from imufdi_cli.episodes.model_fits import _white_noise_fit as _white_noise_fit
from imufdi_cli.episodes.numerics import _chi2_quantile as _chi2_quantile
from imufdi_cli.episodes.numerics import _f_quantile as _f_quantile
from imufdi_cli.episodes.numerics import _finite as _finite
from imufdi_cli.episodes.numerics import _gaussian_nll as _gaussian_nll
from imufdi_cli.episodes.numerics import _median as _median
from imufdi_cli.episodes.numerics import _suffix as _suffix
from imufdi_cli.episodes.numerics import _t_quantile as _t_quantile
from imufdi_cli.episodes.reference import DISPERSION_LEVEL, Reference, leave_one_out
from imufdi_cli.episodes.reference import _autocorrelation_factor as _autocorrelation_factor
from imufdi_cli.episodes.reference import _consensus_gain as _consensus_gain
from imufdi_cli.episodes.reference import _dispersion as _dispersion
from imufdi_cli.episodes.reference import _linear_fit as _linear_fit
from imufdi_cli.episodes.reference import _motion_fit as _motion_fit
from imufdi_cli.episodes.reference import _pinv_from_svd as _pinv_from_svd
from imufdi_cli.episodes.scoring import (
    TRUTH_SIZE_KEYS,
    EpisodeTally,
    match_episodes,
    score_episodes,
    truth_size,
)
from imufdi_cli.episodes.variance_drop import VARIANCE_DROP, VarianceDropMonitor
from imufdi_cli.episodes.variance_drop import _Rows as _Rows
from imufdi_cli.episodes.white_noise import _calibration_dof as _calibration_dof
from imufdi_cli.episodes.white_noise import (
    successive_difference_dof,
    white_sigma,
    white_sigma_covariance,
    white_sigma_excess,
    white_sigma_spread,
)

__all__ = [
    "DISPERSION_LEVEL",
    "MODELS",
    "SIZE_NAMES",
    "SPIKE_CUT",
    "TRUTH_SIZE_KEYS",
    "VARIANCE_DROP",
    "Episode",
    "EpisodeBuilder",
    "EpisodeTally",
    "FaultFit",
    "Reference",
    "VarianceDropMonitor",
    "WhiteNoise",
    "episode_builders",
    "find_episodes",
    "fit_models",
    "isolation_summary",
    "leave_one_out",
    "match_episodes",
    "score_episodes",
    "successive_difference_dof",
    "truth_size",
    "white_sigma",
    "white_sigma_covariance",
    "white_sigma_excess",
    "white_sigma_spread",
]
