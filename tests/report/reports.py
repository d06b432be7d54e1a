"""A hand-made report shared by the gate and renderer tests."""

from __future__ import annotations

import numpy as np

from imufdi_cli.metrics import FaultWindow, compute_metrics
from imufdi_cli.report import Report, ReportEntry

KNOWN = ["glt", "pca-parity"]


def hand_made_report(with_truth: bool = True) -> Report:
    """One glt/gyro entry of 100 samples at 100 Hz on 3 sensors: fault f0 on sensor 0 from
    sample 50; alarms at 3, 4 (2 false of 50 fault-free: FAR 4 %) and from 55 (5 of 50
    faulty missed: MAR 10 %), isolated to sensor 0 except sample 60 (to sensor 2: FIR
    1/45)."""
    n = 100
    t = np.arange(n, dtype=np.int64) * 10_000_000
    faulty = np.zeros((n, 3), bool)
    if with_truth:
        faulty[50:, 0] = True
    alarm = np.zeros(n, bool)
    alarm[[3, 4]] = True  # 2 false alarms of 50 fault-free samples: FAR 4 %
    alarm[55:] = True  # 5 of 50 faulty samples missed: MAR 10 %
    isolated = np.where(alarm, 0, -1)
    isolated[60] = 2  # one false isolation of 45 detected faulty samples
    windows = [FaultWindow("f0", (0,), 50 * 10_000_000)] if with_truth else []
    metrics = compute_metrics(t, alarm, isolated, faulty, windows, episode_gaps=(10, 100))
    entry = ReportEntry(
        detector="glt",
        sensor_type="gyro",
        sensor_ids=["imu0.gyro.x", "imu1.gyro.x", "imu2.gyro.x"],
        metrics=metrics,
        t_ns=t,
        statistic=np.where(alarm, 10.0, 1.0),
        threshold=np.full(n, 6.6),
        alarm=alarm,
        scores=np.zeros((n, 3)),
        faulty=faulty,
    )
    return Report(
        source="x.mcap",
        has_truth=with_truth,
        faults=[{"id": "f0", "spec": "step:imu0.gyro.x,at=0.5s,amp=1deg/s"}] if with_truth else [],
        entries=[entry],
        notes=[],
        t0_ns=0,
    )
