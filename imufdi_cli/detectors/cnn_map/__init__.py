"""cnn-map: a 1-D CNN maps each IMU's accelerometer window to the screened gyro body rate;
the mapping residual grows when that IMU's accelerometer noise grows.

Chen, Su, Xu, fault detection for wearable positioning systems built on arrays of inertial
devices (§2-3): accelerometer noise increase in a 12-IMU array. The paper's method:

1. Reference rate (§2): the array gyros are screened by the GLT (faulty gyros excluded) and
   the remaining ones give the body rate by least squares, ``w_ref = (H_a^T H_a)^-1 H_a^T m_a``
   (:class:`~imufdi_cli.detectors.glt.GltDetector`, ``types=gyro``; a gyro is excluded
   while the GLT isolates it and re-admitted ``READMIT_S`` = 0.5 s after its last
   isolation, so a GLT false alarm does not remove a healthy gyro for good; every
   exclusion and re-admission is logged in the metadata, ``excluded_gyros``). The
   calibration window must contain motion: rotation and specific-force change of at least
   10x their noise on one body axis (``check_motion``), else fit refuses it; the noise is
   the smaller of a second-difference estimate and the sensors' disagreement (parity
   residuals, which no motion reaches), so jerky motion sampled slowly is not taken for
   noise.
2. Mapping network (§2): two 1-D convolution layers and a fully connected layer (numpy,
   :mod:`imufdi_cli.detectors.nn`) map a window of ``L`` samples of one IMU's specific force, rotated to the body
   frame and standardised, to the reference rate at the window's last sample. One network
   is shared by every IMU (12x the training windows of one network per IMU; the IMUs'
   lever arms change their inputs only slightly, and step 4 compares IMUs). Training
   on the fault-free calibration window: MSE loss, Adam, shuffled mini-batches from a seeded
   Generator, early stopping on the last ``holdout`` fraction of the window (a time-ordered
   split with a gap of ``L`` samples, so no training window overlaps a held-out one); the
   weights of the best held-out epoch are kept.
3. Residuals (§3): ``e_k(t) = CNN(a_k[t-L+1..t]) - w_ref(t)`` (rad/s, 3 components).
   Beyond the paper (see docs/algorithms/cnn-map.md for the measurements behind each step):
   the plain residual is dominated by the smooth mapping error, so it is prewhitened by an
   autoregressive filter of order ``p = whiten`` fitted by least squares on the calibration
   residuals (per component, pooled over IMUs)::

       z_kc(t) = e_kc(t) - sum_{i=1..p} phi_ci e_kc(t - i)

   This removes the predictable mapping error and leaves the accelerometer noise the
   network passes through (broadband, independent between IMUs). ``whiten=0`` keeps the
   plain residual.
4. Energy ratio: per IMU, ``s_k(t) = 1/3 sum_c (z_kc - mu_kc)^2 / v_c`` with mu_kc the
   calibration mean and v_c the calibration variance of component c averaged over the
   IMUs; ``E_k(t)`` = mean of s_k over the last ``w`` samples. The network's noise gain
   changes with the motion phase, by a factor of 2-3 over a swing, and every IMU sees the
   same motion. The test therefore compares each IMU with the others at the same time::

       R_k(t) = E_k(t) / mean_{j != k} E_j(t)        (about 1 when fault-free)

5. Threshold: the windowed energies are sums of coloured terms, so the chi2 law of white
   residuals does not hold. Every IMU's R_k over the calibration window is pooled and
   fitted with a gamma law by the method of moments (shape ``kappa = mean^2 / var``, scale
   ``mean / kappa``). Threshold ``T = Gamma^-1(1 - a)`` with the Šidák level
   ``a = 1 - (1 - alpha)^(1/m)`` over the m tested IMUs. While the window fills (c < w
   samples at the start of the log) the shape is ``kappa c / w``.
6. Isolation: the IMU with the largest R_k. Which of its accelerometer axes: by the
   network's linearised sensitivity. White noise of added variance delta on IMU axis a
   (body direction d_a = R_k[:, a]) raises the expected energy of component c by
   ``delta S_k[a, c]`` with ``S_k[a, c] = sum_lags ((K * J_c) . d_a)^2 / v_c``. Here
   J = d CNN / d input of the current window (from backpropagation) and K is the
   whitening kernel ``[1, -phi_1, .., -phi_p]`` convolved along the lags (J is taken as
   constant over p consecutive windows). With the observed excess of each component's
   energy ratio against the other IMUs, ``x_c``, each axis is fitted alone by least
   squares: ``delta_a = x . S_a / |S_a|^2``. The isolated sensor is the axis with the best
   fit ``(sum x . S_a)^2 / sum |S_a|^2`` (positive sum), the sums running over the alarm
   episode on that IMU so far (:meth:`CnnMapDetector._episode_axes`). ``scores`` =
   sqrt(max(delta_a, 0)), the estimated added noise standard deviation of every
   accelerometer axis, m/s^2.
7. ``statistic`` = max_k R_k; ``amplitude`` = R_k of the isolated IMU, the residual energy
   ratio against the other IMUs (dimensionless; 1 = nominal, ~1 + delta S for a noise
   growth).

8. Input test (beyond the paper; ``input_test``, default on). The mapping passes an
   accelerometer axis's noise to its output only as far as the network uses that axis: on
   wearable12 the linearised gain ``sum_c S_k[a, c]`` is 9x (y) and 16x (z) smaller than
   for x, so a noise growth on y or z hardly moves R_k (detection 10-14 % at x3). Every
   axis is therefore also tested on its own: the leave-one-out residual of each
   accelerometer against the rigid-body consensus of the others (lever arms modelled; the
   residual model of :class:`~imufdi_cli.detectors.noise_glr.NoiseGlrDetector`), minus
   the mean of its ``INPUT_MEAN_S`` (8) previous samples and standardized by the
   calibrated variance of that quantity (``z``, :func:`imufdi_cli.detectors.cusum.local_mean_residual`),
   feeds a capped variance CUSUM (:mod:`imufdi_cli.detectors.cusum`, design ratio ``K = 9``, ``z^2`` clipped
   at 25, cap ``INPUT_RELEASE_S`` of null drift above h). The threshold h is the
   per-channel Šidák share of ``alpha``, from a seeded simulation of the null
   (:func:`imufdi_cli.detectors.cusum.cusum_threshold`).
9. Output. By default (``mapping_test=off``) no network is trained and the input test
   alone decides; the mapping test (steps 1-7), with ``mapping_test=report``, is trained
   and computed but does not alarm: its threshold, fitted in-sample on the calibration
   window, does not hold its level out of sample (alone at alpha: 5.05 alpha mean, 24.5
   alpha worst of 10 fresh seeds; see docs/algorithms/cnn-map.md), so the samples over its
   threshold are counted in the metadata (``mapping_report``). The output is the input
   test's:
   ``statistic = max_j S_j / h``, threshold 1, an alarm isolates its channel (the axis
   itself) with ``amplitude`` = the variance ratio of its recent residuals (mean z^2 over
   ``window``). With ``mapping_test=alarm`` both tests alarm, each at ``alpha / 2``
   (Bonferroni): ``statistic = max(max_k R_k / T_map, max_j S_j / h)``, the mapping's
   isolation and amplitude where only it alarms (refused under a false-alarm budget).
   ``off`` and ``report`` give the same output. ``scores`` = the added noise standard
   deviation of every axis, ``sqrt(max(mean z^2 - 1, 0) s^2)`` with s^2 the nominal
   residual variance, m/s^2.

10. Under a false-alarm budget (``false_alarms`` > 0) the input test is noise-glr's
    sequential test of the accelerometers
    (:class:`~imufdi_cli.detectors.noise_glr.NoiseBudget`: Helmert contrasts of the same
    residuals, a bank of variance-growth CUSUMs whose threshold holds half the budget).

Only ``accel`` is reported (the gyros are the reference; their screening is in
:meth:`CnnMapDetector.metadata`). The first ``L - 1 + p`` samples of the log have no
whitened residual: their energy counts as the calibrated mean (R = 1, no alarm possible).
At least two IMUs with accelerometer triads are needed (step 4 compares them).

Modules, by concern: :mod:`.signals` (constants, input windows, AR prewhitening, motion
check), :mod:`.network` (the mapping network and its file format), :mod:`.reference` (the
GLT-screened reference rate), :mod:`.input_test` (the CUSUM input test), :mod:`.mapping`
(training and the mapping test), :mod:`.detector` (parameters, fit, the per-block decision,
metadata); :mod:`.settings` declares the attributes they share. Every public name is
importable from this package, as before the split into modules.
"""

from __future__ import annotations

from imufdi_cli.detectors.cnn_map.detector import CnnMapDetector
from imufdi_cli.detectors.cnn_map.network import MappingNetwork
from imufdi_cli.detectors.cnn_map.signals import (
    INPUT_DESIGN,
    INPUT_MEAN_S,
    INPUT_RELEASE_S,
    MAD_TO_STD,
    MAPPING_MODES,
    MIN_MOTION_RATIO,
    MIN_TRAINING_WINDOWS,
    MODEL_FORMAT,
    READMIT_S,
    check_motion,
    fit_autoregression,
    gamma_shape,
    input_windows,
    noise_across_accels,
    noise_across_gyros,
    whiten,
)

__all__ = [
    "INPUT_DESIGN",
    "INPUT_MEAN_S",
    "INPUT_RELEASE_S",
    "MAD_TO_STD",
    "MAPPING_MODES",
    "MIN_MOTION_RATIO",
    "MIN_TRAINING_WINDOWS",
    "MODEL_FORMAT",
    "READMIT_S",
    "CnnMapDetector",
    "MappingNetwork",
    "check_motion",
    "fit_autoregression",
    "gamma_shape",
    "input_windows",
    "noise_across_accels",
    "noise_across_gyros",
    "whiten",
]
