"""Bank-of-estimators detector: structured residuals, isolation and identification.

Berbra, Gentil, Lesecq, "Identification of multiple faults in an Inertial Measurement Unit"
(docs/algorithms/bank.md). Each estimator of the bank is blind to one measurement, so a fault
on measurement j leaves estimator j intact while it corrupts every other one (the paper's
fault signature tables: Table 1 for accelerometers/magnetometers, Table 2 for gyros). The
residual of the blind measurement against the intact estimator is the fault amplitude
(identification). Two modes, chosen from the data (``mode=auto``):

``marg`` — one IMU with a 3-axis accelerometer, a 3-axis magnetometer and gyros, as in the
paper. Measurements are normalised, ``y = [a / |g|, m / |B|]`` (6 components, sensor frame);
the navigation-frame references are ``g_n = [0, 0, 1]`` and ``h_n = [sin psi, 0, cos psi]``,
psi the angle between specific force and magnetic field measured in the calibration window
(the paper's ``h_m = [1/2, 0, sqrt(3)/2]`` is psi = 30 deg). Estimator ``i`` (i = 1..6)
minimises ``sum_{c != i} (y_c - h_c . C(q)^T r_c)^2`` over the attitude q (nonlinear least
squares, batched Gauss-Newton from an SVD/Wahba warm start), a seventh uses all six. Its
residual vector ``R_i = y - y_hat(q_i)``; with a fault f on component j only ``R_j`` keeps
a single non-zero component, ``R_j[j] = f`` (Table 1). Gyro residuals (Table 2): the
attitude of a fault-free estimator (the full one; during an accel/mag alarm, the clean
series, among those of the estimators blind to a component isolated since the alarm
began, with the smallest peak z^2, the test abstaining while one of them is unobservable;
a series idle for over ``GYRO_MAX_GAP_S`` restarts) gives the body rate from ``q_dot = 1/2 Xi(q) w`` by finite differences
(``w = 2 Xi(q_mid)^T (q_k - q_{k-1}) / Te``); the residual ``g - H_g w`` (gyro averaged over
the same interval) is smoothed by the first-order filter ``y_k = a y_{k-1} + (1 - a) x_k``,
``a = exp(-Te / tau)``. A gyro fault shows only in its own residual.

``array`` — arrays without magnetometers (e.g. 16 IMUs): for each sensor j an estimator of
the body rate (or specific force) from all OTHER sensors of its type by weighted least
squares; the residual of j is normalised by its predicted std. A fault on j shows fully in
residual j and weakly in every residual whose estimator uses j, so isolation proceeds by
exclusion: the strongest residual above threshold is isolated, its sensor removed from
every estimator, the residuals recomputed, and so on up to ``max_faults`` sensors — which
isolates simultaneous faults on different sensors, unlike a single-fault GLT.

Thresholds: residuals normalised to unit variance from calibration; per sample the largest
squared residual is compared with the chi-square(1) quantile at ``1 - alpha / n`` (Bonferroni
over the n residuals of the test, so the per-sample false-alarm rate is at most alpha). In
array mode sigma and bias are estimated from the calibration window, so the quantile is the
F(1, nu) one with nu from the variance of those estimates (``estimated_threshold``): with
chi-square(1) the level was 1.2-1.5 alpha on paper-table4 (48 gyros, 200 samples).

Under a false-alarm budget (``false_alarms``, ``imufdi detect --false-alarms 1/h``) the
same residuals are decided sequentially, several simultaneous faults isolated by exclusion
(:mod:`.budget`).

Modules, by concern: :mod:`.thresholds` (robust scale, estimated and Bonferroni
thresholds), :mod:`.array_mode` (leave-one-out estimators of an array), :mod:`.marg` (the
bank of attitude estimators of one MARG IMU), :mod:`.gyro` (the gyro test of marg mode),
:mod:`.budget` (the sequential tests under a budget), :mod:`.detector` (parameters, fit,
the accelerometer/magnetometer test, metadata). Every
public name is importable from this package, as before the split into modules.
"""

from __future__ import annotations

from imufdi_cli.detectors.bank.array_mode import leave_one_out_matrix
from imufdi_cli.detectors.bank.detector import BankDetector
from imufdi_cli.detectors.bank.marg import (
    CONVERGED_STEP,
    ESTIMATOR_MASKS,
    FULL_ESTIMATOR,
    GYRO_BLIND_STD_RATIO,
    GYRO_MAX_GAP_S,
    MAX_BLIND_STD_RATIO,
    BankDetails,
)
from imufdi_cli.detectors.bank.thresholds import (
    MAD_TO_STD,
    SIGMA_FLOOR,
    bonferroni_threshold,
    estimated_threshold,
    robust_std,
)

__all__ = [
    "CONVERGED_STEP",
    "ESTIMATOR_MASKS",
    "FULL_ESTIMATOR",
    "GYRO_BLIND_STD_RATIO",
    "GYRO_MAX_GAP_S",
    "MAD_TO_STD",
    "MAX_BLIND_STD_RATIO",
    "SIGMA_FLOOR",
    "BankDetails",
    "BankDetector",
    "bonferroni_threshold",
    "estimated_threshold",
    "leave_one_out_matrix",
    "robust_std",
]
