"""PCA of parity vectors: moving-mean pattern test (Hao & Wang), with isolation by direction.

Hao & Wang, "PCA with parity vectors for redundant IMU fault detection in vehicle
navigation" (§2-4). For one sensor type with measurement matrix H (n, 3) and parity matrix
V ((n-3), n), V H = 0 (:mod:`imufdi_cli.detectors.parity`):

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
- Calibration of the variances (issue 16): the principal directions come from the whole
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
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from scipy.stats import chi2
from scipy.stats import f as f_distribution

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    NO_ISOLATION,
    NOT_ISOLABLE,
    TYPES,
    DetectionBlock,
    DetectorBase,
    Param,
    calibration_stats,
    parse_sensor_types,
)
from imufdi_cli.detectors.jitter import MotionInflation, array_inflation
from imufdi_cli.detectors.parity import isolable_sensors, parity_matrix
from imufdi_cli.detectors.rigid import accel_design
from imufdi_cli.detectors.tracking import TRACK_BIAS, BiasTracker
from imufdi_cli.errors import ArrayTooSmallError, CalibrationError
from imufdi_cli.log import ImuBlock

#: Excitation test of the leak regression: a direction of xhat counts as excited when its
#: training variance exceeds this multiple of the noise variance of xhat.
EXCITATION_RATIO = 100.0
#: A sample's motion counts as outside the calibrated range when its prediction leverage
#: is this many times the leverage at the training centre (1/N): the fitted leak's error
#: then weighs as much as 20 training-mean errors.
COVERAGE_LEVERAGE = 20.0
#: Share of the processed samples beyond the calibrated range above which the detector
#: warns that its calibration window lacked the motion the leak model needs.
COVERAGE_WARNING = 0.05
#: Accelerometers of IMUs further apart than this (m) are tested on the rigid-body design
#: with lever-arm columns (detectors/rigid.py) instead of H alone.
MAX_LEVER_ARM = 1e-3
#: Significance level (Bonferroni over the parity components) of the F test that keeps a
#: parity component's fitted leak.
LEAK_SIGNIFICANCE = 1e-3
#: How the variance of each principal direction is estimated from the calibration window:
#: ``"folds"`` (directions from the whole window, variances out of fold,
#: ``cross_validated_components``), ``"halves"`` (directions from one half, variances from
#: the other, ``cross_fitted_components``; the issue-16 choice, which cost power) or
#: ``"sample"`` (the eigenvalues of one eigendecomposition, the paper's).
VARIANCE_ESTIMATE = "mixed"
#: Number of interleaved folds of ``cross_validated_components``.
FOLDS = 10
#: When the leak of some parity component is significant, keep the fitted leak of every
#: component (see ``_fit_leak``); False: only the significant ones.
KEEP_LEAKS_IF_ANY = True
#: Allowance for the leak error of one calibration: the leak-error term ``xbar^T G xbar`` of
#: the prediction variance is multiplied by e, the number of excited directions. For one
#: calibration the leak error at the worst motion is ``chi2(e)`` times that term (Scheffe),
#: and e is that ratio's mean; without it (False) the variance is right only on average over
#: calibrations, and one calibration in 20 raised 7-9 alpha (see docs/algorithms/pca-parity.md).
SCHEFFE_LEAK = True
#: Thresholds from the F distribution of a statistic with an estimated scale.
USE_F_THRESHOLD = True
#: Floor of the estimated lag-one autocorrelation (see ``_lag_one_autocorrelation``).
RHO_FLOOR = 0.0


class MovingWindow:
    """Streaming moving sums over the last ``length`` rows, across consecutive blocks.

    ``push(values)`` returns, for every new row, the sum of the rows of the window ending at
    it and the number of rows in that window (fewer than ``length`` at the start of the log).
    """

    def __init__(self, length: int, width: int) -> None:
        if length < 1:
            raise ValueError("window length must be >= 1")
        self.length = length
        self.tail = np.zeros((0, width))
        self.seen = 0

    def push(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Moving sums (N, width) and window counts (N,) for a block of rows (N, width)."""
        values = np.asarray(values, dtype=np.float64)
        n_new = values.shape[0]
        joined = np.concatenate([self.tail, values], axis=0)
        cumulative = np.concatenate([np.zeros((1, joined.shape[1])), np.cumsum(joined, axis=0)])
        end = np.arange(self.tail.shape[0], joined.shape[0]) + 1  # exclusive end in joined
        start = np.maximum(end - self.length, 0)
        sums = cumulative[end] - cumulative[start]
        counts = np.minimum(self.seen + np.arange(1, n_new + 1), self.length)
        self.seen += n_new
        keep = self.length - 1
        self.tail = joined[max(joined.shape[0] - keep, 0) :] if keep > 0 else joined[:0]
        return sums, counts


def mean_variance_inflation(rho: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``g(rho, L) = 1 + 2 sum_{l=1}^{L-1} (1 - l/L) rho^l``: Var(mean of L) = g sigma^2 / L.

    Closed form of the AR(1) sum, for every pair of ``rho`` (k,) and ``lengths`` (M,).

    Returns
    -------
    g : ndarray, shape (M, k)
    """
    rho = np.asarray(rho, dtype=np.float64)[None, :]
    length = np.asarray(lengths, dtype=np.float64)[:, None]
    one_minus = 1.0 - rho
    with np.errstate(divide="ignore", invalid="ignore"):
        # sum_{l=1}^{L-1} (1 - l/L) rho^l = rho/(1-rho) - rho (1 - rho^L) / (L (1-rho)^2)
        tail = rho / one_minus - rho * (1.0 - rho**length) / (length * one_minus**2)
    g = 1.0 + 2.0 * tail
    return np.where(np.abs(one_minus) < 1e-12, length, g)


def _lag_one_autocorrelation(y: np.ndarray) -> np.ndarray:
    """Per-column lag-one autocorrelation of centred rows (N, k), clipped to [RHO_FLOOR, 0.99].

    The floor (0 by default) keeps a chance negative estimate from shrinking the moving-mean
    variance: for white noise the estimate has a standard error of about 1/sqrt(N) (0.07 for
    a 2 s window at 100 Hz), and ``g(-0.15, 20) = 0.74`` would understate the moving-mean
    variance by a quarter (measured on tuning seed 104 of conical6, where all three parity
    components came out near -0.15). A truly negative autocorrelation is then treated as
    white, which only makes the test conservative.
    """
    energy = np.einsum("ij,ij->j", y, y)
    lagged = np.einsum("ij,ij->j", y[1:], y[:-1])
    rho = np.where(energy > 0, lagged / np.where(energy > 0, energy, 1.0), 0.0)
    return np.clip(rho, RHO_FLOOR, 0.99)


def plug_in_quantile(level: float, dof: np.ndarray, estimate_dof: float) -> np.ndarray:
    """Upper ``level`` quantile of a chi2(dof) statistic whose scale was estimated.

    With the variance estimated on ``estimate_dof`` degrees of freedom independent of the
    tested data (the cross-fitted half, out of sample), ``X / dof`` with
    ``X = sum z_i^2 / s_i^2`` follows ``F(dof, estimate_dof)`` instead of ``chi2(dof)/dof``
    (the plug-in correction of Student's t; Hotelling's T^2 for a diagonal scale), so the
    threshold is ``dof F^-1(1 - level; dof, estimate_dof)``. An infinite ``estimate_dof``
    gives ``chi2^-1(1 - level; dof)``.

    Parameters
    ----------
    level : float
    dof : ndarray, shape (M,)
    estimate_dof : float

    Returns
    -------
    ndarray, shape (M,)
    """
    dof = np.asarray(dof, dtype=np.float64)
    if not np.isfinite(estimate_dof) or not USE_F_THRESHOLD:
        return np.asarray(chi2.ppf(1.0 - level, dof), dtype=np.float64)
    return np.asarray(dof * f_distribution.ppf(1.0 - level, dof, estimate_dof), dtype=np.float64)


def _half_a(n_rows: int, block: int) -> np.ndarray:
    """Rows (n_rows,) bool of half A: the even blocks of ``block`` rows (at most n_rows/4)."""
    block = max(1, min(int(block), n_rows // 4))
    return np.asarray((np.arange(n_rows) // block) % 2 == 0)


def cross_fit_split(n_rows: int, block: int) -> int:
    """Number of rows in half A of ``cross_fitted_components`` (half B has the rest)."""
    return int(np.count_nonzero(_half_a(n_rows, block)))


def cross_fitted_components(centred: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Principal directions from one half of the window, their variances from the other.

    The rows are split into alternating blocks of ``block`` samples (half A: even blocks,
    half B: odd blocks, so both halves span the whole window and its motion). The
    eigenvectors W of the covariance of half A give the directions and their order
    (descending eigenvalue of A); the variance of each direction is ``w_i^T C_B w_i``, C_B
    the covariance of half B about the full-window mean (divisor: its row count).

    Why: the eigenvalues of a sample covariance are biased (Lawley 1956): the smallest is
    too small, because its direction is chosen to minimise the variance of the same data
    (on conical6, q = 3, N = 500: the out-of-sample variance along the last direction was
    1.13x its eigenvalue). For directions fixed by half A, ``w^T C_B w`` is an unbiased
    variance estimate (the halves' noise is independent for white noise, up to the block
    boundaries).

    Parameters
    ----------
    centred : ndarray, shape (N, q)
        Training parity deviations about their mean (SI).
    block : int
        Block length in samples (the moving-mean window).

    Returns
    -------
    variances : ndarray, shape (q,)
        ``w_i^T C_B w_i`` in the order of half A's eigenvalues (SI squared).
    directions : ndarray, shape (q, q)
        Columns w_i (orthonormal).
    """
    n_rows = centred.shape[0]
    half_a = _half_a(n_rows, block)
    first, second = centred[half_a], centred[~half_a]
    covariance_a = first.T @ first / max(first.shape[0] - 1, 1)
    eigenvalues, directions = np.linalg.eigh(covariance_a)
    directions = directions[:, np.argsort(eigenvalues)[::-1]]
    projected = second @ directions
    variances = np.einsum("ij,ij->j", projected, projected) / max(second.shape[0], 1)
    return variances, directions


def fold_labels(n_rows: int, block: int, folds: int) -> np.ndarray:
    """Fold (N,) int of every row: blocks of ``block`` rows dealt to ``folds`` folds in turn.

    The block is shortened (to at least one row) so that every fold gets at least one
    block; the folds are interleaved, so each spans the whole window and its motion.
    """
    folds = max(2, min(int(folds), n_rows))
    block = max(1, min(int(block), n_rows // folds))
    return np.asarray((np.arange(n_rows) // block) % folds)


def cross_validated_components(
    centred: np.ndarray, block: int, folds: int
) -> tuple[np.ndarray, np.ndarray]:
    """Principal directions of the whole window, each with its out-of-fold variance.

    The directions W (columns, descending eigenvalue) come from the covariance of all N
    rows. The variance of the i-th direction is estimated out of sample by K-fold
    cross-validation: the rows are dealt to ``folds`` interleaved folds of ``block``-row
    blocks (``fold_labels``); for each fold, the eigenvectors of the covariance of the other
    folds give its i-th direction ``w_i^(-f)``, and the fold's rows are projected on it.
    The estimate is the mean over all N rows of these squared out-of-fold projections.

    Why: the eigenvalues of a sample covariance are biased (Lawley 1956; the smallest too
    small, in high dimension the largest too large), because each direction is chosen on
    the data that measure its variance. A held-out row is independent of the direction it
    is projected on (white noise, up to the block edges), so each term is unbiased for the
    variance along a direction chosen by PCA on ``(K-1)/K`` of the window, which is the
    full-window direction up to an O(1/N) difference (where eigenvalues are distinct) or a
    direction of the same variance (where they are equal, e.g. isotropic noise). Unlike
    ``cross_fitted_components`` the directions use the whole window and every row counts in
    the variance (about N degrees of freedom instead of N/2): the halves' directions from
    N/2 rows cost power at a matched false-alarm rate (docs/algorithms/pca-parity.md).

    Parameters
    ----------
    centred : ndarray, shape (N, q)
        Training parity deviations about their mean (SI).
    block : int
        Block length in samples (the moving-mean window).
    folds : int
        Number of folds K (at least 2; capped at N).

    Returns
    -------
    variances : ndarray, shape (q,)
        Out-of-fold variance of the i-th principal direction (SI squared).
    directions : ndarray, shape (q, q)
        Columns w_i of the whole window (orthonormal), descending eigenvalue.
    """
    n_rows, q = centred.shape
    eigenvalues, directions = np.linalg.eigh(centred.T @ centred)
    directions = directions[:, np.argsort(eigenvalues)[::-1]]
    labels = fold_labels(n_rows, block, folds)
    energy = np.zeros(q)
    for fold in np.unique(labels):
        held = labels == fold
        rest = centred[~held]
        fold_values, fold_directions = np.linalg.eigh(rest.T @ rest)
        projected = centred[held] @ fold_directions[:, np.argsort(fold_values)[::-1]]
        energy += np.einsum("ij,ij->j", projected, projected)
    return energy / max(n_rows - 1, 1), directions


def principal_components(
    centred: np.ndarray, n_components: int, block: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Principal directions of the training deviations and the variance of each, as
    ``VARIANCE_ESTIMATE`` says (default ``"mixed"``).

    ``"mixed"``: the directions of the whole window; the ``n_components`` kept ones keep
    their sample eigenvalues (N - 1 degrees of freedom; biased high where eigenvalues are
    close, which only makes the T test conservative), the discarded ones get their
    out-of-fold variances (``cross_validated_components``; the smallest sample eigenvalues
    are biased low, which made the Q test liberal), counted with N/2 degrees of freedom
    (the spread measured for isotropic noise, tests/detectors/test_pca_parity.py).
    ``"folds"``: out-of-fold variances for every direction. ``"halves"``: the issue-16
    ``cross_fitted_components``. ``"sample"``: the eigenvalues (the paper's).

    Parameters
    ----------
    centred : ndarray, shape (N, q)
        Training parity deviations about their mean (SI).
    n_components : int
        Components kept by the T test (k).
    block : int
        Fold block length in samples (the moving-mean window).

    Returns
    -------
    variances : ndarray, shape (q,)
        Variance of each direction (SI squared).
    directions : ndarray, shape (q, q)
        Columns, in the order of the kept/discarded split.
    rows : ndarray, shape (q,)
        Equivalent rows behind each variance (degrees of freedom before autocorrelation).
    """
    n_rows, q = centred.shape
    rows = np.full(q, float(n_rows - 1))
    if VARIANCE_ESTIMATE == "halves":
        variances, directions = cross_fitted_components(centred, block)
        return variances, directions, np.full(q, float(n_rows - cross_fit_split(n_rows, block)))
    if VARIANCE_ESTIMATE in ("folds", "mixed"):
        variances, directions = cross_validated_components(centred, block, FOLDS)
        rows[:] = n_rows / 2.0
        if VARIANCE_ESTIMATE == "mixed":
            kept = directions[:, :n_components]
            variances[:n_components] = np.einsum("ij,ij->j", centred @ kept, centred @ kept) / max(
                n_rows - 1, 1
            )
            rows[:n_components] = n_rows - 1
        return variances, directions, rows
    eigenvalues, directions = np.linalg.eigh(centred.T @ centred / max(n_rows - 1, 1))
    order = np.argsort(eigenvalues)[::-1]
    return eigenvalues[order], directions[:, order], rows


def lever_arm_spread(array: ArrayConfig, sensor_type: str) -> float:
    """Largest distance (m) between the positions of the IMUs carrying ``sensor_type``."""
    imu_idx, _ = array.sensor_index(sensor_type)
    positions = array.positions()[np.unique(imu_idx)]
    if positions.shape[0] < 2:
        return 0.0
    return float(np.max(np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)))


class _MotionDesign:
    """The training motion as a regression design for the leak model.

    Attributes
    ----------
    centre : ndarray, shape (3,)
        Training mean of the body-frame estimate xhat (SI).
    basis : ndarray, shape (3, e)
        Excited directions of xhat (those the leak was fitted on; e = 0 without motion).
    inverse_gram : ndarray, shape (e, e)
        ``(X^T X)^-1`` of the centred training xhat in that basis.
    rms : ndarray, shape (e,)
        RMS of the training motion along each excited direction (SI).
    coverage_inverse : ndarray, shape (3, 3)
        ``(X^T X + N S)^-1`` over all three directions, S the noise covariance of xhat:
        the leverage of a motion along a direction the training did not excite is large.
        Zero when coverage is not tracked (``space=raw``, ``leak=none``).
    """

    def __init__(
        self,
        centre: np.ndarray,
        basis: np.ndarray,
        inverse_gram: np.ndarray,
        rms: np.ndarray,
        coverage_inverse: np.ndarray,
    ) -> None:
        self.centre = centre
        self.basis = basis
        self.inverse_gram = inverse_gram
        self.rms = rms
        self.coverage_inverse = coverage_inverse

    @classmethod
    def static(
        cls, coverage_inverse: np.ndarray | None = None, centre: np.ndarray | None = None
    ) -> _MotionDesign:
        """No excited direction (no leak fitted); coverage tracked if given."""
        coverage = np.zeros((3, 3)) if coverage_inverse is None else coverage_inverse
        middle = np.zeros(3) if centre is None else centre
        return cls(middle, np.zeros((3, 0)), np.zeros((0, 0)), np.zeros(0), coverage)


class _TypeModel:
    """Everything learned in training for one sensor type."""

    def __init__(
        self,
        projection: np.ndarray,
        estimator: np.ndarray,
        leak: np.ndarray,
        mean: np.ndarray,
        eigenvalues: np.ndarray,
        eigenvectors: np.ndarray,
        rho: np.ndarray,
        n_train: int,
        window: int,
        n_components: int,
        isolable: np.ndarray,
        motion: _MotionDesign | None = None,
        variance_rows: float | np.ndarray = np.inf,
    ) -> None:
        self.projection = projection  # (q, n): V (parity) or I (raw)
        self.estimator = estimator  # (3, n): H^+ (least-squares body-frame estimate)
        self.leak = leak  # (q, 3): K
        self.mean = mean  # (q,)
        self.eigenvalues = eigenvalues  # (q,), descending
        self.eigenvectors = eigenvectors  # (q, q), columns
        self.rho = rho  # (q,)
        self.n_components = n_components
        self.n_train = n_train
        # Equivalent degrees of freedom of each component's variance estimate (rows of the
        # half it was measured on, less for autocorrelated rows); inf: treated as known.
        self.variance_dof = variance_rows * (1.0 - rho**2) / (1.0 + rho**2)  # (q,)
        self.isolable = isolable  # (n,) bool
        lengths = np.arange(1, window + 1)
        # Variance of the moving-mean deviation of each component, per window fill (L, q).
        self.mean_variance = eigenvalues[None, :] * (
            mean_variance_inflation(rho, lengths) / lengths[:, None]
            + mean_variance_inflation(rho, np.array([n_train]))[0][None, :] / n_train
        )
        self.window = MovingWindow(window, projection.shape[0])
        self.window_length = window
        self._residual_thresholds: dict[float, np.ndarray] = {}
        norms = np.linalg.norm(projection, axis=0)
        self.direction_norms = norms  # |v_j|, (n,)
        self.motion = motion if motion is not None else _MotionDesign.static()
        # Scheffe allowance on the leak error (``SCHEFFE_LEAK``): e, the mean of chi2(e).
        excited = self.motion.basis.shape[1]
        self.leak_tolerance = float(excited) if excited and SCHEFFE_LEAK else 1.0
        self.motion_window = MovingWindow(window, 3)
        self.inflation_n = mean_variance_inflation(rho, np.array([n_train]))[0]  # g(rho_i, N)
        self.inflation_l = mean_variance_inflation(rho, lengths) / lengths[:, None]  # (L, q)
        tail = eigenvalues[n_components:]
        pooled = float(np.sum(tail * rho[n_components:]) / np.sum(tail)) if tail.size else 0.0
        self.pooled_rho = np.array([pooled])
        # Share of each principal component in the parity components whose leak was fitted:
        # only those carry the leak-estimate error (the others carry the mean error only).
        fitted = np.any(leak != 0.0, axis=1).astype(np.float64)  # (q,)
        self.leak_weight = (eigenvectors**2).T @ fitted  # (q,)
        self.leak_fitted = bool(fitted.any())
        tail_weight = self.leak_weight[n_components:]
        self.leak_weight_q = float(np.sum(tail * tail_weight) / np.sum(tail)) if tail.size else 0.0
        # Online extrapolation of the leak model, accumulated for the coverage report.
        self.samples_seen = 0
        self.samples_beyond = 0
        self.max_leverage_ratio = 0.0

    def leverage(self, estimates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Prediction leverage ``h_t`` of the moving mean of the motion, per sample.

        ``h_t = 1/N + xbar_t^T G xbar_t`` where xbar_t is the moving mean of the motion
        estimate (centred on the training mean, in the excited basis) and G the inverse Gram
        matrix of the training motion: the variance of the fitted mean and leak at xbar_t
        in units of the noise variance (the regression prediction variance). 1/N at the
        training centre; it grows as the motion leaves the training range.

        Returns
        -------
        extra : ndarray, shape (N,)
            ``xbar_t^T G xbar_t`` (the leverage is ``1/N + extra``).
        coverage : ndarray, shape (N,)
            The same ratio ``N h_t`` over all three directions (``coverage_inverse``): 1 at
            the training centre, large where the motion leaves what training covered.
        """
        design = self.motion
        sums, counts = self.motion_window.push(estimates - design.centre)
        means = sums / counts[:, None]  # (N, 3)
        excited = means @ design.basis  # (N, e)
        extra = np.einsum("ij,jk,ik->i", excited, design.inverse_gram, excited)
        coverage = 1.0 + self.n_train * np.einsum(
            "ij,jk,ik->i", means, design.coverage_inverse, means
        )
        return extra, coverage

    def residual_threshold(self, level: float) -> np.ndarray:
        """Threshold of Q = |discarded components of the mean deviation|^2, per window fill,
        for a deviation at the training centre (leverage 1/N); see ``residual_scale``.

        Q is a weighted sum of chi2(1) variables with weights v_i (the moving-mean variances
        of the discarded components); Box's approximation Q ~ g chi2(h), g = sum v^2 / sum v,
        h = (sum v)^2 / sum v^2 (Box 1954; Jackson & Mudholkar 1979). It uses only sums of
        eigenvalues, which are far less biased than the individual small eigenvalues of a
        sample covariance (in high dimension the smallest ones are grossly underestimated),
        and one pooled autocorrelation for the discarded components.

        Returns
        -------
        ndarray, shape (window,)
        """
        if level not in self._residual_thresholds:
            k = self.n_components
            tail = self.eigenvalues[k:]
            rho = np.array([float(np.sum(tail * self.rho[k:]) / np.sum(tail))])
            lengths = np.arange(1, self.window_length + 1)
            factor = (
                mean_variance_inflation(rho, lengths)[:, 0] / lengths
                + mean_variance_inflation(rho, np.array([self.n_train]))[0, 0] / self.n_train
            )
            weights = tail[None, :] * factor[:, None]  # (L, q-k)
            scale = (weights**2).sum(axis=1) / weights.sum(axis=1)
            dof = weights.sum(axis=1) ** 2 / (weights**2).sum(axis=1)
            tail_dof = self.variance_dof[k:]
            estimate_dof = float(np.sum(tail) ** 2 / np.sum(tail**2 / tail_dof))
            self._residual_thresholds[level] = scale * plug_in_quantile(level, dof, estimate_dof)
        return self._residual_thresholds[level]

    def residual_scale(self, counts: np.ndarray, leverage: np.ndarray) -> np.ndarray:
        """Factor (N,) on ``residual_threshold`` for the prediction leverage of each sample.

        The discarded components share one pooled autocorrelation, so their moving-mean
        variances are ``tail_i f_t`` with a common factor
        ``f_t = g(rho, L)/L + g(rho, N) h_t``; Box's dof does not depend on a common factor
        and the threshold scales with it.
        """
        rho = self.pooled_rho
        lengths = np.arange(1, self.window_length + 1)
        per_length = mean_variance_inflation(rho, lengths)[:, 0] / lengths  # (L,)
        g_n = mean_variance_inflation(rho, np.array([self.n_train]))[0, 0]
        at_centre = per_length[counts - 1] + g_n / self.n_train
        return (per_length[counts - 1] + g_n * leverage) / at_centre

    def transform(self, measurements: np.ndarray) -> np.ndarray:
        """Leak-compensated deviations ``p - K xhat - mu``, shape (N, q)."""
        parity = measurements @ self.projection.T
        if np.any(self.leak):
            parity = parity - (measurements @ self.estimator.T) @ self.leak.T
        return parity - self.mean


class PcaParityDetector(DetectorBase):
    """PCA of parity vectors with a moving-mean test (Hao & Wang); see the module docstring.

    Parameters
    ----------
    alpha : float
        False-alarm level per sample.
    components : int
        Number of principal components kept (capped at n - 3, or n with ``space=raw``).
    window : float
        Moving-mean window, seconds.
    space : {"parity", "raw"}
        Test the parity vectors (default) or the raw measurements (demonstration).
    residual_test : bool
        Also test the discarded components (Q statistic).
    leak : {"regress", "none"}
        Fit and remove the motion leaking into the parity space through scale-factor and
        misalignment errors (needs motion in the training window to have any effect).
    types : str
        Comma-separated sensor types to test (those present with enough sensors are used);
        ``sensors``, its old name, is still accepted with a warning.
    """

    name: ClassVar[str] = "pca-parity"
    RENAMED_PARAMS: ClassVar[dict[str, str]] = {"sensors": "types"}
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "components": Param("int", 2, "number of principal components kept", low=1, high=64),
        "window": Param(
            "time", 0.2, "moving-mean window (e.g. 0.2s)", low=0.0, high=60.0, low_open=True
        ),
        "space": Param(
            "choice", "parity", "test parity vectors or raw measurements", choices=("parity", "raw")
        ),
        "residual_test": Param("bool", True, "also test the discarded components (Q statistic)"),
        "leak": Param(
            "choice",
            "regress",
            "remove motion leaking into the parity space (scale/misalignment errors)",
            choices=("regress", "none"),
        ),
        "types": TYPES,
        "track_bias": TRACK_BIAS,
    }

    def __init__(
        self,
        alpha: float = 0.01,
        components: int = 2,
        window: float = 0.2,
        space: str = "parity",
        residual_test: bool = True,
        leak: str = "regress",
        types: str = "gyro,accel",
        track_bias: float = 0.0,
    ) -> None:
        self.alpha = float(alpha)
        self.components = int(components)
        self.window_s = float(window)
        self.space = space
        self.residual_test = bool(residual_test)
        self.leak = leak
        self.sensor_types = parse_sensor_types(types, self.name)
        self.tracker = BiasTracker(track_bias)
        self.array: ArrayConfig | None = None
        self.models: dict[str, _TypeModel] = {}
        self.untested: dict[str, str] = {}
        self.window_samples = 0
        self.inflations: dict[str, MotionInflation | None] = {}  # jitter model (detectors/jitter)

    # --- training ----------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Learn mean, principal components, autocorrelation and leak per sensor type.

        Raises
        ------
        ArrayTooSmallError
            No sensor type with enough sensors to test (exit 3, with a hint).
        CalibrationError
            Window too short, or degenerate (zero-variance) data.
        """
        self.array = array
        designs = {s: self._design(array, s) for s in array.sensor_types()}
        self.tracker.fit(calibration, array, designs)
        self.window_samples = max(1, round(self.window_s * array.rate_hz))
        self.models = {}
        self.untested = {}
        self.inflations = {}
        minimum = 3 if self.space == "parity" else 0
        for sensor_type in self.sensor_types:
            triads = calibration.get(sensor_type)
            if triads is None or array.n_sensors(sensor_type) <= minimum:
                continue
            design = designs[sensor_type]
            if self.space == "parity" and design.shape[0] <= design.shape[1]:
                self.untested[sensor_type] = (
                    f"{design.shape[0]} sensors: with the lever-arm terms of these IMU"
                    f" positions the parity space needs at least {design.shape[1] + 1}"
                )
                continue
            measurements = array.select(triads, sensor_type)
            self.models[sensor_type] = self._fit_type(measurements, design, sensor_type)
            inflation = array_inflation(array, sensor_type, design, self.window_samples)
            self.inflations[sensor_type] = inflation if self.space == "parity" else None
        if not self.models:
            need = "at least 4 sensors of a type" if self.space == "parity" else "sensors"
            if self.untested:
                need += " (" + "; ".join(f"{k}: {v}" for k, v in self.untested.items()) + ")"
            raise ArrayTooSmallError(
                f"{self.name}: nothing to test: the calibration block has no "
                f"{'/'.join(self.sensor_types)} data with {need}"
            )

    @staticmethod
    def _design(array: ArrayConfig, sensor_type: str) -> np.ndarray:
        """H (n, 3); for accelerometers of IMUs more than MAX_LEVER_ARM apart, the rigid-body
        design [H | lever-arm columns] (n, 3 + q) of :mod:`.rigid`, so the parity space
        cancels w x (w x r) and dw/dt x r."""
        if sensor_type == "accel" and lever_arm_spread(array, sensor_type) > MAX_LEVER_ARM:
            return accel_design(array, sensor_type)
        return array.measurement_matrix(sensor_type)

    def _fit_type(self, measurements: np.ndarray, H: np.ndarray, sensor_type: str) -> _TypeModel:
        n_train = measurements.shape[0]
        minimum = max(10, 2 * self.window_samples)
        calibration_stats(measurements, min_samples=minimum)
        n = H.shape[0]
        estimator = np.linalg.pinv(H)[:3]  # (3, n): the body-frame quantity (f_0 with levers)
        if self.space == "parity":
            projection = parity_matrix(H)  # (n-3, n), Potter's V
            isolable = isolable_sensors(projection)
        else:
            projection = np.eye(n)
            isolable = np.zeros(n, dtype=bool)
        parity = measurements @ projection.T  # (N, q)
        q = projection.shape[0]
        leak = np.zeros((q, 3))
        motion = _MotionDesign.static()
        if self.space == "parity" and self.leak == "regress":
            leak, motion = self._fit_leak(parity, measurements @ estimator.T, estimator)
        compensated = parity - (measurements @ estimator.T) @ leak.T
        mean = compensated.mean(axis=0)
        centred = compensated - mean
        n_components = min(self.components, q)
        eigenvalues, eigenvectors, variance_rows = principal_components(
            centred, n_components, self.window_samples
        )
        if not np.all(np.isfinite(eigenvalues)) or float(np.min(eigenvalues)) <= 1e-30 * max(
            float(np.max(eigenvalues)), 1e-300
        ):
            raise CalibrationError(
                f"{self.name}: {sensor_type} training data is degenerate (a zero-variance"
                " direction); check the calibration window"
            )
        rho = _lag_one_autocorrelation(centred @ eigenvectors)
        return _TypeModel(
            projection=projection,
            estimator=estimator,
            leak=leak,
            mean=mean,
            eigenvalues=eigenvalues,
            eigenvectors=eigenvectors,
            rho=rho,
            n_train=n_train,
            window=self.window_samples,
            n_components=n_components,
            isolable=isolable,
            motion=motion,
            variance_rows=variance_rows,
        )

    @staticmethod
    def _fit_leak(
        parity: np.ndarray, estimate: np.ndarray, estimator: np.ndarray
    ) -> tuple[np.ndarray, _MotionDesign]:
        """Least-squares leak matrix K ((q, 3)) of ``p = mu + K xhat`` on excited directions,
        and the training motion as a regression design (for the prediction variance)."""
        q = parity.shape[1]
        n_train = parity.shape[0]
        if q == 0:
            return np.zeros((0, 3)), _MotionDesign.static()
        parity_c = parity - parity.mean(axis=0)
        estimate_c = estimate - estimate.mean(axis=0)
        # Noise scale: with V V^T = I the parity covariance trace is sum of noise variances
        # (for equal sigmas q sigma^2); xhat noise covariance = sigma^2 (H^T H)^-1.
        noise_variance = float(np.trace(parity_c.T @ parity_c)) / (parity.shape[0] - 1) / q
        xhat_noise = noise_variance * (estimator @ estimator.T)  # (3, 3)
        covariance = estimate_c.T @ estimate_c / (estimate.shape[0] - 1)
        eigenvalues, directions = np.linalg.eigh(covariance)
        noise_along = np.einsum("ij,ik,kj->j", directions, xhat_noise, directions)
        excited = eigenvalues > EXCITATION_RATIO * noise_along
        coverage_inverse = np.linalg.pinv(estimate_c.T @ estimate_c + n_train * xhat_noise)
        if not np.any(excited):
            return np.zeros((q, 3)), _MotionDesign.static(coverage_inverse, estimate.mean(axis=0))
        basis = directions[:, excited]  # (3, e)
        scores = estimate_c @ basis  # (N, e)
        design = _MotionDesign(
            centre=estimate.mean(axis=0),
            basis=basis,
            inverse_gram=np.linalg.inv(scores.T @ scores),
            rms=np.sqrt(np.mean(scores**2, axis=0)),
            coverage_inverse=coverage_inverse,
        )
        coefficients, *_ = np.linalg.lstsq(scores, parity_c, rcond=None)  # (e, q)
        # Keep only parity components whose leak is significant (regression F test at
        # LEAK_SIGNIFICANCE): fitting noise would extrapolate badly when the motion later
        # leaves the range seen in training.
        n_train, n_excited = scores.shape
        explained = ((scores @ coefficients) ** 2).sum(axis=0)  # (q,)
        unexplained = ((parity_c - scores @ coefficients) ** 2).sum(axis=0)
        dof = n_train - n_excited - 1
        ratio = (explained / n_excited) / np.maximum(unexplained / dof, 1e-300)
        significant = f_distribution.sf(ratio, n_excited, dof) < LEAK_SIGNIFICANCE / q
        if KEEP_LEAKS_IF_ANY and significant.any():
            # Scale-factor and misalignment errors leak into every parity component: once
            # one component shows it, a component whose leak the test could not see on this
            # window still has one (up to the test's critical value, several standard
            # errors), and dropping it leaves that whole leak in the test. Kept, its error
            # is the regression error, which the prediction variance carries.
            significant[:] = True
        return (basis @ (coefficients * significant[None, :])).T, design  # (q, 3)

    # --- online --------------------------------------------------------------------------

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; one row per input sample (causal)."""
        if self.array is None:
            raise CalibrationError(f"{self.name}: process() called before fit()")
        block = self.tracker.apply(block)
        out: dict[str, DetectionBlock] = {}
        for sensor_type, model in self.models.items():
            triads = block.get(sensor_type)
            n_sensors = model.projection.shape[1]
            if triads is None:
                out[sensor_type] = DetectionBlock.empty(len(block), n_sensors)
                continue
            measurements = self.array.select(triads, sensor_type)
            inflation = self.inflations.get(sensor_type)
            factors = None if inflation is None else inflation.factors(measurements, block.t_ns)
            out[sensor_type] = self._process_type(model, measurements, factors)
        return out

    def _process_type(
        self, model: _TypeModel, measurements: np.ndarray, factors: np.ndarray | None = None
    ) -> DetectionBlock:
        n_samples = measurements.shape[0]
        n_sensors = model.projection.shape[1]
        deviation = model.transform(measurements)  # (N, q)
        sums, counts = model.window.push(deviation)
        mean_deviation = sums / counts[:, None]  # dp_t, (N, q)
        components = mean_deviation @ model.eigenvectors  # (N, q)
        extra, coverage = model.leverage(measurements @ model.estimator.T)
        extra = extra * model.leak_tolerance  # SCHEFFE_LEAK: the mean worst-motion ratio
        # prediction variance: moving-mean noise + error of the fitted mean and leak at xbar_t
        leverage = 1.0 / model.n_train + extra[:, None] * model.leak_weight[None, :]  # (N, q)
        variance = model.eigenvalues[None, :] * (
            model.inflation_l[counts - 1] + model.inflation_n[None, :] * leverage
        )  # (N, q)
        model.samples_seen += n_samples
        model.samples_beyond += int(np.sum(coverage > COVERAGE_LEVERAGE))
        if n_samples:
            model.max_leverage_ratio = max(model.max_leverage_ratio, float(coverage.max()))
        normalised = components**2 / variance
        k = model.n_components
        q = model.projection.shape[0]
        tests_residual = self.residual_test and q > k
        level = self.alpha / 2.0 if tests_residual else self.alpha
        statistic = normalised[:, :k].sum(axis=1) / plug_in_quantile(
            level, np.array([k]), float(np.min(model.variance_dof[:k]))
        )
        if tests_residual:
            residual = (components[:, k:] ** 2).sum(axis=1)  # Q, squared norm
            leverage_q = 1.0 / model.n_train + extra * model.leak_weight_q
            threshold_q = model.residual_threshold(level)[counts - 1] * model.residual_scale(
                counts, leverage_q
            )
            statistic = np.maximum(statistic, residual / threshold_q)
        if factors is not None:  # sampling-time jitter in motion (detectors/jitter.py)
            statistic = statistic / factors
        alarm = statistic > 1.0
        scores = np.full((n_samples, n_sensors), np.nan)
        isolated = np.full(n_samples, NO_ISOLATION, dtype=np.int32)
        amplitude = np.full(n_samples, np.nan)
        if self.space == "parity" and q >= 2:
            valid = model.direction_norms > 0
            projections = mean_deviation @ model.projection  # (N, n): v_j . dp
            lengths = np.linalg.norm(mean_deviation, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                cosines = np.abs(projections) / (
                    lengths[:, None] * np.where(valid, model.direction_norms, np.nan)[None, :]
                )
            scores = np.arccos(np.clip(cosines, 0.0, 1.0))
            best = np.argmin(np.where(np.isnan(scores), np.inf, scores), axis=1)
            rows = np.flatnonzero(alarm)
            chosen = best[rows]
            isolable = model.isolable[chosen] & np.isfinite(scores[rows, chosen])
            isolated[rows] = np.where(isolable, chosen, NOT_ISOLABLE)
            norms2 = model.direction_norms[chosen] ** 2
            amplitude[rows] = np.where(isolable, projections[rows, chosen] / norms2, np.nan)
        else:
            isolated[alarm] = NOT_ISOLABLE
        return DetectionBlock(
            statistic=statistic,
            threshold=np.ones(n_samples),
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=scores,
        )

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        return {
            s: DetectionBlock.empty(0, model.projection.shape[1])
            for s, model in self.models.items()
        }

    def calibration_warnings(self) -> list[str]:
        """Warnings about the calibration window, from what was processed so far.

        One per sensor type whose motion left the range the calibration window covered on
        more than ``COVERAGE_WARNING`` of the samples (prediction leverage above
        ``COVERAGE_LEVERAGE`` times that of the training centre): there the leak model
        extrapolates, the threshold widens with the prediction variance and the test loses
        power (without the widening it would raise false alarms).
        """
        messages = []
        for sensor_type, model in self.models.items():
            if not model.samples_seen or not np.any(model.motion.coverage_inverse):
                continue
            if not model.leak_fitted and model.motion.basis.shape[1] > 0:
                continue  # motion in calibration, and no leak: its range does not matter
            share = model.samples_beyond / model.samples_seen
            if share <= COVERAGE_WARNING:
                continue
            unit, scale = ("deg/s", np.rad2deg(1.0)) if sensor_type == "gyro" else ("m/s^2", 1.0)
            rms = ", ".join(f"{v * scale:.3g}" for v in model.motion.rms) or "none"
            messages.append(
                f"{self.name}: {sensor_type}: the calibration window lacks the motion the leak"
                f" model needs: {share:.0%} of the samples move beyond its range (leverage up"
                f" to {model.max_leverage_ratio:.0f}x the training centre's;"
                f" {model.motion.basis.shape[1]} of 3 axes excited in calibration, RMS"
                f" {rms} {unit} along its principal axes); thresholds were widened there. Calibrate on a window that"
                " covers the motion (--calibrate START:END)"
            )
        return messages

    def metadata(self) -> dict[str, Any]:
        """Parameters and training results (JSON-ready)."""
        types: dict[str, Any] = {}
        for sensor_type, model in self.models.items():
            k = model.n_components
            q = model.projection.shape[0]
            total = float(model.eigenvalues.sum())
            types[sensor_type] = {
                "n_sensors": int(model.projection.shape[1]),
                "dimension": int(q),
                "components": int(k),
                "eigenvalues": model.eigenvalues.tolist(),
                "variance_dof": model.variance_dof.tolist(),
                "explained_variance": float(model.eigenvalues[:k].sum() / total) if total else None,
                "lag1_autocorrelation": model.rho.tolist(),
                "training_mean": model.mean.tolist(),
                "leak_matrix": model.leak.tolist(),
                "isolable": model.isolable.tolist(),
                "residual_test": bool(self.residual_test and q > k),
                "calibration_motion_rms": model.motion.rms.tolist(),
                "excited_axes": int(model.motion.basis.shape[1]),
                "samples_beyond_calibrated_motion": int(model.samples_beyond),
                "max_leverage_ratio": float(model.max_leverage_ratio),
            }
        return {
            "detector": self.name,
            "params": {
                "alpha": self.alpha,
                "components": self.components,
                "window_s": self.window_s,
                "window_samples": self.window_samples,
                "space": self.space,
                "residual_test": self.residual_test,
                "leak": self.leak,
                "types": ",".join(self.sensor_types),
                "track_bias": self.tracker.tau_s,
            },
            "tracked_bias_change": self.tracker.metadata(),
            "variances": (
                f"{VARIANCE_ESTIMATE} (kept components: sample eigenvalues; discarded:"
                f" out of {FOLDS} folds)"
                if VARIANCE_ESTIMATE == "mixed"
                else VARIANCE_ESTIMATE
            ),
            "statistic": "max(T/chi2_{1-a}(k), Q/chi2_{1-a}(q-k)), a = alpha/2; threshold 1",
            "untested": dict(self.untested),
            "scores": "angle between each sensor's parity direction and the mean parity"
            " deviation, rad (smallest = isolated)",
            "types": types,
        }
