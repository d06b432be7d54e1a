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
tests that pin them), from its submodule on first use (PEP 562). Coverage and false
episodes are measured in ``tests/episodes/``, ``studies/episodes.py`` and docs/episodes.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from imufdi_cli.lazy import lazy_exports

if TYPE_CHECKING:
    from imufdi_cli.episodes.builder import EpisodeBuilder, episode_builders
    from imufdi_cli.episodes.episode import (
        FITS_EXPLANATION,
        SAMPLE_EXPLANATION,
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

#: name -> the submodule defining it (imported on first use: ``report`` needs only the
#: scoring, not the fits; start-up time, docs/performance.md)
_WHERE: dict[str, str] = {
    "DISPERSION_LEVEL": "imufdi_cli.episodes.reference",
    "Episode": "imufdi_cli.episodes.episode",
    "FITS_EXPLANATION": "imufdi_cli.episodes.episode",
    "SAMPLE_EXPLANATION": "imufdi_cli.episodes.episode",
    "EpisodeBuilder": "imufdi_cli.episodes.builder",
    "EpisodeTally": "imufdi_cli.episodes.scoring",
    "FaultFit": "imufdi_cli.episodes.fault_fit",
    "MODELS": "imufdi_cli.episodes.fault_fit",
    "Reference": "imufdi_cli.episodes.reference",
    "SIZE_NAMES": "imufdi_cli.episodes.fault_fit",
    "SPIKE_CUT": "imufdi_cli.episodes.model_fits",
    "TRUTH_SIZE_KEYS": "imufdi_cli.episodes.scoring",
    "VARIANCE_DROP": "imufdi_cli.episodes.variance_drop",
    "VarianceDropMonitor": "imufdi_cli.episodes.variance_drop",
    "WhiteNoise": "imufdi_cli.episodes.fault_fit",
    "_Rows": "imufdi_cli.episodes.variance_drop",
    "_autocorrelation_factor": "imufdi_cli.episodes.reference",
    "_calibration_dof": "imufdi_cli.episodes.white_noise",
    "_chi2_quantile": "imufdi_cli.episodes.numerics",
    "_consensus_gain": "imufdi_cli.episodes.reference",
    "_dispersion": "imufdi_cli.episodes.reference",
    "_drift_search": "imufdi_cli.episodes.fits",
    "_f_quantile": "imufdi_cli.episodes.numerics",
    "_fault_end": "imufdi_cli.episodes.fits",
    "_finite": "imufdi_cli.episodes.numerics",
    "_fit_window": "imufdi_cli.episodes.fits",
    "_gaussian_nll": "imufdi_cli.episodes.numerics",
    "_linear_fit": "imufdi_cli.episodes.reference",
    "_local_level": "imufdi_cli.episodes.model_fits",
    "_median": "imufdi_cli.episodes.numerics",
    "_motion_fit": "imufdi_cli.episodes.reference",
    "_noise_fit": "imufdi_cli.episodes.model_fits",
    "_pinv_from_svd": "imufdi_cli.episodes.reference",
    "_sensor_amplitude": "imufdi_cli.episodes.episode",
    "_spike_fit": "imufdi_cli.episodes.model_fits",
    "_stuck_fit": "imufdi_cli.episodes.model_fits",
    "_suffix": "imufdi_cli.episodes.numerics",
    "_t_quantile": "imufdi_cli.episodes.numerics",
    "_white_noise_fit": "imufdi_cli.episodes.model_fits",
    "episode_builders": "imufdi_cli.episodes.builder",
    "find_episodes": "imufdi_cli.episodes.episode",
    "fit_models": "imufdi_cli.episodes.fits",
    "isolation_summary": "imufdi_cli.episodes.episode",
    "leave_one_out": "imufdi_cli.episodes.reference",
    "match_episodes": "imufdi_cli.episodes.scoring",
    "score_episodes": "imufdi_cli.episodes.scoring",
    "successive_difference_dof": "imufdi_cli.episodes.white_noise",
    "truth_size": "imufdi_cli.episodes.scoring",
    "white_sigma": "imufdi_cli.episodes.white_noise",
    "white_sigma_covariance": "imufdi_cli.episodes.white_noise",
    "white_sigma_excess": "imufdi_cli.episodes.white_noise",
    "white_sigma_spread": "imufdi_cli.episodes.white_noise",
}


__getattr__ = lazy_exports(__name__, _WHERE, globals())


__all__ = [
    "DISPERSION_LEVEL",
    "FITS_EXPLANATION",
    "MODELS",
    "SAMPLE_EXPLANATION",
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
