"""WOA-MVMD-GLT: GLT on the MVMD mode most correlated with the raw signal.

Li, Sun, Tian, He, Zhu, "Fault Detection and Isolation of MEMS IMU Array Based on
WOA-MVMD-GLT", Micromachines 17(3):374, 2026, §2.3-2.7 and §3.

For one sensor type (n sensors, measurement matrix H, measurements m (N, n)):

1. Windows of ``window`` samples, ``hop = window - overlap`` apart, cover the log; every
   window is decomposed by MVMD (:mod:`imufdi_cli.detectors.mvmd`, all n channels jointly,
   K modes sharing their centre frequencies).
2. ``u_best``: the mode with the largest normalised inner product with the raw window,
   ``<u_k, x> / (|u_k| |x|)`` over all channels and samples (uncentred: the mean is part of
   the signal, so the mode that carries the rates and the biases is the one kept, §2.5).
   Since MVMD applies one filter to all channels (mvmd.py, "exact reduction"),
   ``V u_best`` is the same filter applied to the parity vector: the motion still cancels.
   ``u_best=lowest`` takes the mode of lowest centre frequency instead: on input without
   biases (a calibrated array) the paper's rule follows the noise of each window
   (docs/algorithms/woa-mvmd-glt.md, "On the MIMU4444 recordings").
3. GLT (§2.1, eqs. 5-7, :mod:`imufdi_cli.maths.parity`) on u_best, whitened with the
   per-sensor sigma and with the per-sensor biases estimated on u_best of the calibration
   window (sigma re-estimated in the u_best domain: the filter removes most of the noise,
   which is why the step fault is detected with a small MAR). Threshold chi2_{1-alpha}(n-3).
   When the array carries each sensor's healthy noise-variance spread kappa_i
   (``<type>_noise_spread`` from ``imufdi calibrate``), sigma_i^2 becomes kappa_i sigma_i^2:
   the level holds at the top of each chip's healthy range (``noise_spread``).
4. Each sample gets its row from the first window that contains it, where it lies in the
   last ``hop`` samples (``end``, default: causal, decided when that window ends, at most
   ``hop - 1`` samples after the sample; the first ``window - hop`` samples of the log get
   no decision), from the window where it is central (``centre``), or the smallest
   statistic of all windows containing it (``min``; ``centre`` and ``min`` use windows that
   end up to ``window - 1`` samples later, so a sample's row depends on what follows it).
   The output depends only on the sample index in the log, not on how the pipeline cuts
   blocks; :attr:`WoaMvmdGltDetector.lookahead_samples` is the longest hold-back.

Beyond the paper: accelerometers at different positions are tested on the rigid-body design
with lever-arm columns (``lever_arm``, as glt); under a false-alarm budget (``false_alarms``)
the rows are decided sequentially, the motion leak learnt online; the per-sample test says
when the motion leaks into its parity space, which it does not model (:mod:`.budget`).

(K, alpha) come from the ``params`` JSON file written by ``imufdi tune`` (:func:`tune`), from
the ``K`` and ``mvmd_alpha`` parameters, or, by default, are tuned by the whale optimization
algorithm (:mod:`imufdi_cli.detectors.woa`) on the calibration window, minimising the
composite fitness CFV (§2.6, :func:`cfv_components` for the exact definitions).

Modules, by concern: :mod:`.fitness` (CFV, the validation fault), :mod:`.tuning` (the WOA
search and its JSON result), :mod:`.windows` (per-window u_best filters and the stream of
overlapping windows), :mod:`.budget` (the long-run factor of the u_best filters, the motion
check of the per-sample test), :mod:`.detector` (parameters, construction and the GLT
decision). Every public name is importable from this package, as before the split into modules.
"""

from __future__ import annotations

from imufdi_cli.detectors.woa_mvmd_glt.detector import WoaMvmdGltDetector, clear_tuning_cache
from imufdi_cli.detectors.woa_mvmd_glt.fitness import (
    DEFAULT_WEIGHTS,
    FITNESS_CHOICES,
    OUTLIER_CHOICES,
    ValidationFault,
    cfv,
    cfv_components,
    validation_windows,
)
from imufdi_cli.detectors.woa_mvmd_glt.tuning import (
    TuneResult,
    make_validation,
    tune,
    tune_signal,
    tune_signals,
)
from imufdi_cli.detectors.woa_mvmd_glt.windows import (
    COMBINE_CHOICES,
    MODE_RULES,
    WindowSpectra,
    best_mode,
    decompose_windows,
    filter_matrices,
    filter_matrix,
)

__all__ = [
    "COMBINE_CHOICES",
    "DEFAULT_WEIGHTS",
    "FITNESS_CHOICES",
    "MODE_RULES",
    "OUTLIER_CHOICES",
    "TuneResult",
    "ValidationFault",
    "WindowSpectra",
    "WoaMvmdGltDetector",
    "best_mode",
    "cfv",
    "cfv_components",
    "clear_tuning_cache",
    "decompose_windows",
    "filter_matrices",
    "filter_matrix",
    "make_validation",
    "tune",
    "tune_signal",
    "tune_signals",
    "validation_windows",
]
