"""Principal components of the training parity deviations and the statistics of their
moving means: variance inflation of autocorrelated means, plug-in (F) quantiles, and the
out-of-sample variance estimates of the principal directions."""

from __future__ import annotations

import numpy as np

from imufdi_cli.detectors.pca_parity import choices
from imufdi_cli.maths.quantiles import chi2
from imufdi_cli.maths.quantiles import f as f_distribution


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
    return np.clip(rho, choices.RHO_FLOOR, 0.99)


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
    if not np.isfinite(estimate_dof) or not choices.USE_F_THRESHOLD:
        return np.asarray(chi2.ppf(1.0 - level, dof), dtype=np.float64)
    return np.asarray(dof * f_distribution.ppf(1.0 - level, dof, estimate_dof), dtype=np.float64)


def descending_eigh(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (q,) and eigenvectors (columns, (q, q)) of a symmetric matrix (q, q), in
    descending eigenvalue order (``numpy.linalg.eigh`` gives them ascending)."""
    values, vectors = np.linalg.eigh(matrix)
    order = np.argsort(values)[::-1]
    return values[order], vectors[:, order]


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
    _, directions = descending_eigh(covariance_a)
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
    _, directions = descending_eigh(centred.T @ centred)
    labels = fold_labels(n_rows, block, folds)
    energy = np.zeros(q)
    for fold in np.unique(labels):
        held = labels == fold
        rest = centred[~held]
        projected = centred[held] @ descending_eigh(rest.T @ rest)[1]
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
    ``"folds"``: out-of-fold variances for every direction. ``"halves"``:
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
    if choices.VARIANCE_ESTIMATE == "halves":
        variances, directions = cross_fitted_components(centred, block)
        return variances, directions, np.full(q, float(n_rows - cross_fit_split(n_rows, block)))
    if choices.VARIANCE_ESTIMATE in ("folds", "mixed"):
        variances, directions = cross_validated_components(centred, block, choices.FOLDS)
        rows[:] = n_rows / 2.0
        if choices.VARIANCE_ESTIMATE == "mixed":
            kept = directions[:, :n_components]
            variances[:n_components] = np.einsum("ij,ij->j", centred @ kept, centred @ kept) / max(
                n_rows - 1, 1
            )
            rows[:n_components] = n_rows - 1
        return variances, directions, rows
    eigenvalues, directions = descending_eigh(centred.T @ centred / max(n_rows - 1, 1))
    return eigenvalues, directions, rows
