"""PCA of parity vectors: moving-mean pattern test (Hao & Wang), with isolation by direction.

Hao & Wang, "PCA with parity vectors for redundant IMU fault detection in vehicle
navigation" (§2-4). For one sensor type with measurement matrix H (n, 3) and parity matrix
V ((n-3), n), V H = 0 (:mod:`imufdi_cli.maths.parity`):

1. Training on a fault-free window (§3): parity vectors ``p = V m`` (the motion cancels),
   their mean ``mu`` (the per-sensor biases of a real array end up here, so they raise no
   alarm) and covariance ``C = W Lambda W^T``; the ``components`` leading eigenvectors W_k
   are the principal components, the pattern is ``y = W_k^T (p - mu)`` (§3, PCA).
2. Online (§4): the moving mean ``ybar_t`` of y over ``window`` samples is compared with the
   region learned in training. We use the Mahalanobis norm of the moving mean,

   ``T_t = sum_i ybar_{t,i}^2 / s_i^2``,  ``s_i^2 = lambda_i (g(rho_i, L) / L + g(rho_i, N) / N)``

   where ``g(rho, L) = 1 + 2 sum_{l=1}^{L-1} (1 - l/L) rho^l`` is the variance inflation of
   the mean of L samples of an AR(1) sequence with lag-one autocorrelation ``rho_i``
   (estimated per component in training; 1 for white noise) and the ``1/N`` term is the
   error of the training mean ``mu`` itself. The moving mean of a linear function of the
   noise is Gaussian (exactly for Gaussian noise, by the central limit theorem otherwise),
   so ``T ~ chi2(k)`` when there is no fault, and the threshold is ``chi2_{1-alpha}(k)``.
   An empirical quantile of the training moving-mean statistic was rejected: a 2 s window
   at 100 Hz holds only N / L (about 10) independent windows, far too few to estimate a 1 %
   quantile.

Beyond the paper:

- ``residual_test`` (default on): PCA keeps the directions of largest training variance,
  which, for white sensor noise, are arbitrary; a fault whose parity direction is nearly
  orthogonal to them would go unseen. The discarded components are tested as well (the
  Q statistic of PCA monitoring, whitened, ``chi2(n-3-k)``); each test runs at alpha/2
  (Bonferroni) and the reported statistic is the larger of ``T / c_T`` and ``Q / c_Q``
  (threshold 1).
- ``leak`` (default ``regress``): scale-factor and misalignment errors make the parity
  vector depend on the motion, ``p = V (S H) x + ...``. When the training window contains
  motion, the leak matrix K ((n-3), 3) of ``p = mu + K xhat`` (xhat the least-squares
  body-frame estimate) is fitted on the excited directions of xhat only (directions whose
  variance exceeds ``100 x`` the noise variance of xhat), kept only for parity components
  where a regression F test finds it significant (p < 1e-3 / (n-3): a leak fitted on noise would
  extrapolate badly once the motion leaves the training range), and subtracted online.
- Prediction variance (threshold out of sample): the fitted mean mu and leak K are
  estimates; at a sample whose moving-mean motion estimate is xbar_t (centred on the
  training mean, in the excited basis) their error adds ``h_t = 1/N + xbar_t^T G xbar_t``
  (G the inverse Gram matrix of the training motion) to the moving-mean variance, in
  units of the noise variance: ``s_i^2 = lambda_i (g(rho_i, L)/L + g(rho_i, N) h_t)``, the
  regression prediction variance instead of the training-mean variance alone. At the
  training centre h_t = 1/N (the earlier formula); where the motion leaves the training
  range the threshold widens instead of raising false alarms (the leak error then grows
  with |xbar|). The same factor multiplies the Q threshold. The leak-error term is
  multiplied by e, the number of excited directions (``SCHEFFE_LEAK``): for one
  calibration the leak error at the worst motion is chi2(e) times its average-case
  variance (Scheffe), and e is that ratio's mean.
- Calibration of the variances (docs/algorithms/pca-parity.md): the principal directions come from the whole
  window; the kept components keep their sample eigenvalues and the discarded ones get
  out-of-fold variances (``principal_components``, ``cross_validated_components``: the
  smallest eigenvalues of a sample covariance are biased low, Lawley 1956; taking the
  directions from one half of the window, ``cross_fitted_components``, held the level but
  cost power at a matched false-alarm rate); the thresholds are F
  quantiles for a statistic standardised by an estimated variance (``plug_in_quantile``);
  a negative lag-one autocorrelation estimate is floored at 0 (``RHO_FLOOR``); and once the
  leak of one parity component is significant, every component's fitted leak is kept
  (``KEEP_LEAKS_IF_ANY``), its error carried by the prediction variance.
- Calibration coverage: the same leverage over all three directions, with the noise
  covariance of xhat as a floor (``coverage_inverse``), measures how far the motion goes
  beyond what the calibration window covered. When more than 5 % of the processed
  samples are beyond 20x the training-centre leverage, ``calibration_warnings`` reports
  it with the measured share (`imufdi detect` prints it; ``--strict`` makes it exit 3).
- Isolation by fault direction: a fault f on sensor j moves the parity vector by ``f v_j``
  (v_j = column j of V). The mean parity deviation ``dp_t`` (moving mean of p minus mu) is
  compared to every v_j; the isolated sensor has the smallest angle
  ``theta_j = arccos(|v_j . dp| / (|v_j| |dp|))`` (``scores`` holds theta_j in radians),
  and the amplitude is the least-squares ``f = v_j . dp / |v_j|^2`` (SI). Sensors whose
  directions are zero or parallel to another's are not isolable (NOT_ISOLABLE).
- ``space=raw``: the same moving-mean PCA test on the raw measurements instead of the
  parity vectors (a "traditional" PCA monitor). Motion is not cancelled, so it alarms as
  soon as the motion departs from the training window: use it to see why the parity space
  matters. No isolation in that mode (NOT_ISOLABLE).
- ``false_alarms`` (a budget, ``imufdi detect --false-alarms 1/h``): sequential decisions
  on the GLR evidence of each sensor under the parity covariance learnt in training (a
  spiked model of the correlated noise), with the motion leak learnt online
  (:mod:`.budget`); the moving-mean test's own options do not apply then.
"""

from imufdi_cli.detectors.moving import MovingWindow
from imufdi_cli.detectors.pca_parity import choices
from imufdi_cli.detectors.pca_parity.components import (
    _lag_one_autocorrelation,
    cross_fit_split,
    cross_fitted_components,
    cross_validated_components,
    fold_labels,
    mean_variance_inflation,
    plug_in_quantile,
    principal_components,
)
from imufdi_cli.detectors.pca_parity.detector import PcaParityDetector
from imufdi_cli.detectors.pca_parity.model import lever_arm_spread

__all__ = [
    "MovingWindow",
    "PcaParityDetector",
    "_lag_one_autocorrelation",
    "choices",
    "cross_fit_split",
    "cross_fitted_components",
    "cross_validated_components",
    "fold_labels",
    "lever_arm_spread",
    "mean_variance_inflation",
    "plug_in_quantile",
    "principal_components",
]
