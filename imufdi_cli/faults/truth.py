"""Ground truth: which sensors are faulty when, and the ``imufdi.faults`` metadata record
(part of :mod:`imufdi_cli.faults`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from imufdi_cli.errors import TruthError
from imufdi_cli.faults.models import METADATA_NAME, Fault
from imufdi_cli.jsonin import check, loads

# --- ground truth -----------------------------------------------------------------------


def active_mask(
    faults: Sequence[Fault], sensor_ids: Sequence[str], t_ns: np.ndarray, t0_ns: int
) -> np.ndarray:
    """Ground truth: which sensors are faulty at which samples.

    Parameters
    ----------
    faults : sequence of Fault
    sensor_ids : sequence of str
        Columns, e.g. ``array.sensor_ids("gyro")``.
    t_ns : ndarray, shape (N,), int64
        Sample stamps, ns.
    t0_ns : int
        Log start (first IMU sample stamp), ns.

    Returns
    -------
    ndarray, shape (N, n), bool
        ``[i, j]`` true when a fault acting on ``sensor_ids[j]`` is active at ``t_ns[i]``
        (``at <= t - t0 < until``). Spikes faults count as active over their whole window.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    mask = np.zeros((t_ns.shape[0], len(sensor_ids)), dtype=bool)
    column = {sensor: j for j, sensor in enumerate(sensor_ids)}
    for fault in faults:
        columns = [column[s] for s in fault.sensors if s in column]
        if columns:
            mask[:, columns] |= fault.active(t_ns, t0_ns)[:, None]
    return mask


def faults_from_metadata(meta: Mapping[str, str]) -> list[Fault]:
    """All faults recorded in an ``imufdi.faults`` metadata record (earlier runs first)."""
    if "json" not in meta:
        raise TruthError(f"{METADATA_NAME} metadata has no 'json' entry")
    record = _load_record(meta["json"])
    faults: list[Fault] = []
    try:
        for run in [*record.get("previous", []), record]:
            faults += [Fault.from_dict(item) for item in run.get("faults", [])]
    except TruthError as err:  # a fault the schema let through but Fault refuses
        raise TruthError(f"{METADATA_NAME} metadata: {err}") from err
    return faults


def _load_record(text: str) -> dict[str, Any]:
    """The ``imufdi.faults`` JSON checked against its schema (TruthError, exit 3, naming
    the bad value; :mod:`imufdi_cli.metadata`)."""
    from imufdi_cli.metadata import FAULTS_SCHEMA

    where = f"{METADATA_NAME} metadata"
    record = check(loads(text, where, TruthError), FAULTS_SCHEMA, where, TruthError)
    return record  # type: ignore[no-any-return]
