"""Design choices of pca-parity, read at call time (benchmarks and tests switch them to
compare variants: ``monkeypatch.setattr(pca_parity.choices, "SCHEFFE_LEAK", False)``)."""

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
#: with lever-arm columns (maths/rigid.py) instead of H alone.
MAX_LEVER_ARM = 1e-3
#: Significance level (Bonferroni over the parity components) of the F test that keeps a
#: parity component's fitted leak.
LEAK_SIGNIFICANCE = 1e-3
#: How the variance of each principal direction is estimated from the calibration window:
#: ``"folds"`` (directions from the whole window, variances out of fold,
#: ``cross_validated_components``), ``"halves"`` (directions from one half, variances from
#: the other, ``cross_fitted_components``; held the level but cost power) or
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
