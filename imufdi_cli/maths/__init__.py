"""Shared maths of the detectors, the calibration, the episode fits and the validity checks.

Pure numerical functions on arrays (no I/O, no logs, no detector state):

- :mod:`~imufdi_cli.maths.parity`: parity projections of a redundant array, whitening,
  residual sigmas, isolation statistics, thresholds with estimated sigmas;
- :mod:`~imufdi_cli.maths.rigid`: the rigid-body (lever-arm) accelerometer model;
- :mod:`~imufdi_cli.maths.jitter`: the sampling-time jitter model of the residuals in
  motion;
- :mod:`~imufdi_cli.maths.quantiles`: the normal, chi-square, F and gamma laws;
- :mod:`~imufdi_cli.maths.incomplete`: the incomplete gamma and beta functions and their
  inverses, in pure Python (the quantiles behind the thresholds);
- :mod:`~imufdi_cli.maths.sequential`: sequential tests under a false-alarm budget.

The package sits below :mod:`imufdi_cli.detectors` and above :mod:`imufdi_cli.array`
(docs/architecture.md): it imports only the array model, the units and the errors, and
scipy inside the functions that need it.
"""
