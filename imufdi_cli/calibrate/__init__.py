"""``imufdi calibrate``: per-chip calibration of an IMU array from its own log.

Parity-space detection needs the IMUs of an array to agree with each other, not with
truth. This module estimates, for every triad, ``calibrated = M (raw - b)``
(:class:`~imufdi_cli.array.TriadCalibration`) from a log with static intervals in several
orientations (and some motion for the gyro matrices):

**Static intervals** are found automatically: the moving standard deviation (1 s window)
of the array-mean specific force and angular rate in the body frame stays under three
times its own 10th percentile (the noise floor), with absolute caps, for at least
``min_static`` seconds; half a second more is trimmed at each end. Intervals whose gravity
directions lie within 10 degrees are one orientation; the *coverage* of directions is
``3 lambda_min`` of the mean ``u u^T`` over orientations (1: isotropic, 0: coplanar).

**Accelerometers** — multi-position calibration (Skog & Händel, "Calibration of a MEMS
inertial measurement unit", IMEKO XVIII, 2006; Tedaldi, Pretto & Menegatti, "A robust and
easy to implement method for IMU calibration without external equipments", ICRA 2014,
eq. 10-11, there with one triad against ``|f| = g``), here jointly for all triads as in
the array self-calibration of Carlsson, Skog & Jaldén (IEEE Sensors J. 21(6), 2021): at
rest in orientation ``i`` every triad measures the same specific force ``f_i`` with
``|f_i| = g``::

    R_k M_k (a_ki - b_k) = f_i          for every triad k and orientation i

solved by alternating least squares: given the ``M, b``, ``f_i = g normalize(mean_k R_k
M_k (a_ki - b_k))``; given the ``f_i``, each triad's ``[M_k | -M_k b_k]`` is a linear least
squares problem (12 unknowns, 3 equations per orientation: needs >= 4 non-coplanar
orientations; fewer give biases only). The common rotation of all triads is not
observable at rest: it is fixed so that the triads' mean rotation is the nominal one
(polar factor of ``mean_k R_k M_k R_k^T``).

**Gyroscopes** — bias ``b_k`` = mean raw rate over the static intervals; ``M_k`` from the
motion samples (not static, not clipped) relative to the array consensus ``w = mean_k R_k
M_k (w_k - b_k)``, by alternating least squares again, with the gauge ``mean_k R_k M_k
R_k^T = I`` (the array's mean scale and axes stay nominal: agreement, not truth). Without
motion on every axis (RMS consensus rate under :data:`MIN_MOTION_RATE`) only biases are
estimated, with a warning.

**Noise levels** — each sensor's white-noise sigma after calibration, from the parity
residuals of every static interval, pooled over the intervals (:func:`static_noise`). On the MIMU4444 board
the gyro noise changes with the orientation (a narrow-band 8-16 Hz component on some
z-axis gyros, up to 1.5x in sigma, docs/real-arrays.md), so the typical level over many
orientations is a better reference for a parity test than a few seconds in one of them.
Stored per IMU as ``<type>_noise``; glt uses it (``sigma_source=auto``).

**Sampling-time jitter** — the residual between triads grows from the noise at rest to
~45x it in hand motion. Each type's ``sigma_t`` of the model of
:mod:`imufdi_cli.maths.jitter` (noise variance ``1 + sigma_t^2 |ydot_w|^2 / n`` in
whitened units) is fitted by moments on the motion rows (not near a static interval, not
clipped, predecessor usable) with the calibrated noise levels and the lever-arm design
for accelerometers; stored as ArrayConfig ``[jitter]``, used by glt and pca-parity.

**Streaming.** A log is read in blocks, once per pass (static intervals; interval means,
gyro bias and the sums of the gyro rates' products in motion; noise, spread, residuals and
time offsets with the calibration; jitter with the noise levels: :func:`calibrate_blocks`):
every stage keeps sums, and the per-row values that need more than sums (the static
spread and its exact 10th percentile, the jitter level fit's rows) go to temporary files
(:mod:`imufdi_cli.calibrate.passes`). Peak memory does not grow with the log's length
(``benchmarks/bench_calibrate.py``); the accelerometer fit's grows with the number of
static intervals. The results are those of the whole log in memory to rounding (sums
taken in another order; 1e-11 relative on the bundled cut).

**Chip time offsets** (a diagnostic, not applied) — a chip sampling ``dt_k`` later than
the others reads ``w(t + dt_k) ~ w + w_dot dt_k``; its gyro residual from the consensus in
motion is regressed on the consensus angular acceleration, giving ``dt_k`` (relative to
the array's mean sampling instant) and the share of that chip's residual it explains.
On the MIMU4444 recordings every offset is below 0.01 ms and explains nothing
(docs/real-arrays.md), so no compensation is built; a warning names chips where an offset
explains more than :data:`TIME_OFFSET_WARNING` of the residual.
"""

from imufdi_cli.calibrate.motion import JITTER_FITS, jitter_stage, motion_rows, time_offsets
from imufdi_cli.calibrate.noise import expected_normal_range, noise_spread, static_noise
from imufdi_cli.calibrate.run import (
    CalibrationResult,
    calibrate_block,
    calibrate_blocks,
    calibrate_file,
)
from imufdi_cli.calibrate.static import (
    STANDARD_GRAVITY,
    StaticInterval,
    body_consensus,
    find_static,
    group_orientations,
)
from imufdi_cli.calibrate.triads import TriadFigures, calibrate_accel, calibrate_gyro

__all__ = [
    "JITTER_FITS",
    "STANDARD_GRAVITY",
    "CalibrationResult",
    "StaticInterval",
    "TriadFigures",
    "body_consensus",
    "calibrate_accel",
    "calibrate_block",
    "calibrate_blocks",
    "calibrate_file",
    "calibrate_gyro",
    "expected_normal_range",
    "find_static",
    "group_orientations",
    "jitter_stage",
    "motion_rows",
    "noise_spread",
    "static_noise",
    "time_offsets",
]
