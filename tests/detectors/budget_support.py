"""Helpers of the false-alarm budget tests of pca-parity, bank and woa-mvmd-glt: long
fault-free runs counted in episodes, faults on simulated presets, Poisson bounds."""

from __future__ import annotations

from typing import Any

import numpy as np

from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.simulate import config_from_options, preset, simulate, simulate_block


def fault_free_episodes(
    detector: str,
    params: dict[str, Any],
    preset_name: str,
    hours: float,
    seed: int,
    calibration_s: float = 2.0,
) -> tuple[dict[str, int], float]:
    """False alarm episodes per status channel of ``detector`` on a fault-free simulated
    log of ``hours`` (calibrated on its first ``calibration_s``), and the tested hours
    (after the calibration window), streamed in blocks of 4096 samples."""
    config = config_from_options(preset_name, seed=seed, duration=f"{hours * 3600.0}s")
    array, blocks = simulate(config, block_size=4096)
    instance = make_detector(detector, params)
    need = round(calibration_s * array.rate_hz)
    last: dict[str, bool] = {}
    counts: dict[str, int] = {}
    tested = 0

    def count(outputs: dict[str, DetectionBlock]) -> None:
        for sensor_type, out in outputs.items():
            alarm = np.asarray(out.alarm, bool)
            before = np.concatenate([[last.get(sensor_type, False)], alarm[:-1]])
            counts[sensor_type] = counts.get(sensor_type, 0) + int(np.sum(alarm & ~before))
            if alarm.size:
                last[sensor_type] = bool(alarm[-1])

    for index, block in enumerate(blocks):
        if index == 0:
            assert len(block) > need, "the calibration window fits in the first block"
            instance.fit(block.slice(0, need), array)
            block = block.slice(need, len(block))
        count(instance.process(block))
        tested += len(block)
    count(instance.flush())
    return counts, tested / array.rate_hz / 3600.0


def poisson_upper(events: int, hours: float, level: float = 0.95) -> float:
    """One-sided upper confidence bound of a Poisson rate (per hour) from ``events`` in
    ``hours`` (Garwood: ``chi2_level(2 k + 2) / 2``)."""
    from imufdi_cli.maths.quantiles import chi2

    return float(chi2.ppf(level, 2 * events + 2)) / 2.0 / hours


def faulted_run(
    detector: str,
    params: dict[str, Any],
    preset_name: str,
    specs: tuple[str, ...],
    seed: int,
    duration_s: float,
    calibration_s: float = 2.0,
    block_size: int = 997,
) -> tuple[Any, dict[str, DetectionBlock], Any]:
    """(array, every type's rows after the calibration window, the detector) of a
    simulated log with faults, in uneven blocks, flushed at the end."""
    array, block = simulate_block(preset(preset_name, seed=seed, duration=duration_s))
    if specs:
        faults = [parse_fault_spec(spec, array) for spec in specs]
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    instance = make_detector(detector, params)
    start = round(calibration_s * array.rate_hz)
    instance.fit(block.slice(0, start), array)
    pieces = [
        instance.process(block.slice(i, min(i + block_size, len(block))))
        for i in range(start, len(block), block_size)
    ]
    pieces.append(instance.flush())
    types = pieces[0].keys()
    joined = {
        t: DetectionBlock.concatenate([p[t] for p in pieces if t in p and len(p[t])]) for t in types
    }
    return array, joined, instance


def first_alarm_after(out: DetectionBlock, row: int) -> int | None:
    """Row of the first alarm at or after ``row`` (None: none)."""
    hits = np.flatnonzero(out.alarm[row:])
    return None if hits.size == 0 else row + int(hits[0])
