"""Fault models, the fault spec grammar, streaming injection and ground truth.

A fault acts on one sensor axis (``imu3.gyro.z``) or on a whole triad (``imu3.gyro``: the
IMU's present axes) from ``at`` seconds after the log start (the first IMU sample stamp,
``t0_ns``) until ``until`` seconds (exclusive), or to the end of the log. With ``o(t)`` the
nominal output and ``t_f`` the fault start, the models are:

========  ===================================================================================
step      ``o_f(t) = o(t) + amp``                                    (bias jump)
drift     ``o_f(t) = o(t) + rate * (t - t_f)``                       (ramp)
noise     ``o_f(t) = o(t) + sigma * n(t)``, ``n ~ N(0, 1)`` white; with ``factor`` the added
          ``sigma = sigma0 * sqrt(factor^2 - 1)`` so the total std is ``factor * sigma0``
stuck     ``o_f(t) = o(t_s)``, ``t_s`` the last sample before ``t_f`` (the first faulty sample
          when the fault starts with the log)
scale     ``o_f(t) = factor * o(t)`` (``ppm``: ``factor = 1 + ppm * 1e-6``)
spikes    Poisson events of ``rate`` per second, each adding ``+-amp`` (random sign) to
          ``width`` consecutive samples
========  ===================================================================================

Grammar: ``MODEL:SENSOR,key=value,...`` e.g. ``step:imu0.gyro.x,at=2.5s,amp=0.9deg/s``.
Common keys: ``at`` (default 0 s), ``until`` or ``duration`` (optional), ``id`` (optional).
TOML files hold ``[[fault]]`` tables with ``model``, ``sensor`` and the same keys.

Several faults may act on the same sensor: they are applied in list order, each on the
output of the previous ones. Random models draw from one generator per fault, seeded by
``SeedSequence(seed, spawn_key=(fault_index,))``, with a fixed number of draws per faulty
sample, so the output does not depend on how the stream is cut into blocks.

Modules: :mod:`~imufdi_cli.faults.models` (:class:`Fault`, model names),
:mod:`~imufdi_cli.faults.spec` (grammar, TOML files, validation),
:mod:`~imufdi_cli.faults.truth` (ground truth, metadata record),
:mod:`~imufdi_cli.faults.injector` (:class:`FaultInjector`) and
:mod:`~imufdi_cli.faults.inject` (:func:`inject_file`). Everything public is re-exported
here: import from ``imufdi_cli.faults``. Each name is imported from its submodule on first
use (PEP 562 ``__getattr__``): reading the ground truth of a log (``report``) loads the
models, not the injector.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from imufdi_cli.lazy import lazy_exports

if TYPE_CHECKING:
    from imufdi_cli.faults.inject import InjectResult, inject_file
    from imufdi_cli.faults.injector import FaultInjector
    from imufdi_cli.faults.models import (
        METADATA_FORMAT,
        METADATA_NAME,
        MODEL_KEYS,
        MODELS,
        TRUTH_SCHEMA,
        TRUTH_TOPIC,
        Fault,
    )
    from imufdi_cli.faults.spec import (
        fault_from_table,
        load_fault_file,
        parse_fault_spec,
        validate_faults,
    )
    from imufdi_cli.faults.truth import active_mask, faults_from_metadata

#: the submodule of each public name
_WHERE = {
    "InjectResult": "imufdi_cli.faults.inject",
    "inject_file": "imufdi_cli.faults.inject",
    "FaultInjector": "imufdi_cli.faults.injector",
    "METADATA_FORMAT": "imufdi_cli.faults.models",
    "METADATA_NAME": "imufdi_cli.faults.models",
    "MODEL_KEYS": "imufdi_cli.faults.models",
    "MODELS": "imufdi_cli.faults.models",
    "TRUTH_SCHEMA": "imufdi_cli.faults.models",
    "TRUTH_TOPIC": "imufdi_cli.faults.models",
    "Fault": "imufdi_cli.faults.models",
    "fault_from_table": "imufdi_cli.faults.spec",
    "load_fault_file": "imufdi_cli.faults.spec",
    "parse_fault_spec": "imufdi_cli.faults.spec",
    "validate_faults": "imufdi_cli.faults.spec",
    "active_mask": "imufdi_cli.faults.truth",
    "faults_from_metadata": "imufdi_cli.faults.truth",
}


__getattr__ = lazy_exports(__name__, _WHERE, globals())


__all__ = [
    "METADATA_FORMAT",
    "METADATA_NAME",
    "MODELS",
    "MODEL_KEYS",
    "TRUTH_SCHEMA",
    "TRUTH_TOPIC",
    "Fault",
    "FaultInjector",
    "InjectResult",
    "active_mask",
    "fault_from_table",
    "faults_from_metadata",
    "inject_file",
    "load_fault_file",
    "parse_fault_spec",
    "validate_faults",
]
