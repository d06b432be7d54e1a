"""Streaming, block-size independent injection of faults into IMU samples
(part of :mod:`imufdi_cli.faults`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from imufdi_cli.array import SENSOR_TYPES, ArrayConfig
from imufdi_cli.errors import FaultSpecError, TruthError
from imufdi_cli.faults.models import METADATA_FORMAT, Fault
from imufdi_cli.faults.spec import validate_faults
from imufdi_cli.faults.truth import _load_record, faults_from_metadata
from imufdi_cli.log import ImuBlock

# --- injection --------------------------------------------------------------------------


@dataclass
class _FaultState:
    """Streaming state of one fault on its (imu, sensor type) stream."""

    fault: Fault
    axes: np.ndarray  # (k,) axis indices
    rng: np.random.Generator
    at_ns: int
    until_ns: int | None
    stuck_value: np.ndarray | None = None  # (k,)
    last_t_ns: int | None = None  # previous sample stamp (spikes: Poisson step)
    active_count: int = 0  # faulty samples seen so far
    last_event: np.ndarray | None = None  # (k,) active index of the last spike start
    last_sign: np.ndarray | None = None  # (k,) sign of the last spike


class FaultInjector:
    """Apply faults to a stream of IMU samples, deterministically given ``seed``.

    Parameters
    ----------
    faults : list of Fault
        Faults of this run, in application order. Faults without an id are numbered
        ``f<k>`` after any previous faults.
    array : ArrayConfig
    seed : int
        Seed of the random models (noise, spikes).
    t0_ns : int
        Log start (first IMU sample stamp), ns; ``at``/``until`` count from it.
    log_duration_s : float, optional
        When known, faults starting after the log ends are rejected.
    previous_metadata : dict, optional
        An ``imufdi.faults`` record already in the log; kept in :meth:`metadata`.
    """

    def __init__(
        self,
        faults: list[Fault],
        array: ArrayConfig,
        *,
        seed: int,
        t0_ns: int,
        log_duration_s: float | None = None,
        previous_metadata: Mapping[str, str] | None = None,
    ) -> None:
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise FaultSpecError(f"seed must be a non-negative integer, got {seed!r}")
        self.array = array
        self.seed = int(seed)
        self.t0_ns = int(t0_ns)
        self.previous_runs: list[dict[str, Any]] = []
        if previous_metadata is not None:
            if previous_metadata and "json" not in previous_metadata:
                raise TruthError("imufdi.faults metadata has no 'json' entry")
            record = _load_record(previous_metadata["json"]) if previous_metadata else None
            if record is not None:
                self.previous_runs = [*record.pop("previous", []), record]
        try:
            previous_faults = [
                Fault.from_dict(item) for run in self.previous_runs for item in run["faults"]
            ]
        except TruthError as err:  # a fault the schema let through but Fault refuses
            raise TruthError(f"imufdi.faults metadata: {err}") from err
        taken = {f.id for f in previous_faults if f.id}
        validate_faults(faults, array, log_duration_s=log_duration_s, taken_ids=taken)
        taken |= {f.id for f in faults if f.id}
        numbered: list[Fault] = []
        counter = len(previous_faults)
        for fault in faults:
            if not fault.id:
                while f"f{counter}" in taken:
                    counter += 1
                fault = Fault(**{**fault.__dict__, "id": f"f{counter}"})
                taken.add(fault.id)
                counter += 1
            numbered.append(fault)
        self.faults: list[Fault] = numbered
        self._streams: dict[tuple[int, str], list[_FaultState]] = {}
        for index, fault in enumerate(numbered):
            state = _FaultState(
                fault=fault,
                axes=np.asarray(fault.axes, dtype=np.intp),
                rng=np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(index,))),
                at_ns=fault.at_ns,
                until_ns=fault.until_ns,
            )
            self._streams.setdefault((fault.imu, fault.sensor_type), []).append(state)

    def affects(self, imu: int, sensor_type: str) -> bool:
        """Whether any fault acts on this IMU's sensor type."""
        return (int(imu), sensor_type) in self._streams

    def apply(self, imu: int, sensor_type: str, t_ns: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Faulted copy of one IMU's triads of one sensor type.

        Parameters
        ----------
        imu : int
        sensor_type : str
        t_ns : ndarray, shape (N,), int64
            Stamps, ns, increasing; consecutive calls per (imu, sensor_type) continue in time.
        values : ndarray, shape (N, 3)
            Measurements in the IMU frame, SI.

        Returns
        -------
        ndarray, shape (N, 3), float64
            New array (the input is not modified).
        """
        out = np.array(values, dtype=np.float64, copy=True)
        if out.ndim != 2 or out.shape[1] != 3:
            raise ValueError(f"values must have shape (N, 3), got {out.shape}")
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if t_ns.shape != (out.shape[0],):
            raise ValueError(f"t_ns must have shape ({out.shape[0]},), got {t_ns.shape}")
        states = self._streams.get((int(imu), sensor_type))
        if not states or out.shape[0] == 0:
            if states and t_ns.size:
                for state in states:
                    state.last_t_ns = int(t_ns[-1])
            return out
        rel = t_ns - np.int64(self.t0_ns)
        for state in states:
            self._apply_one(state, t_ns, rel, out)
        return out

    def _apply_one(
        self, state: _FaultState, t_ns: np.ndarray, rel: np.ndarray, out: np.ndarray
    ) -> None:
        fault = state.fault
        axes = state.axes
        before = rel < state.at_ns
        active = ~before
        if state.until_ns is not None:
            active &= rel < state.until_ns
        n_active = int(np.count_nonzero(active))
        if fault.model == "stuck":
            if np.any(before):
                last_before = np.flatnonzero(before)[-1]
                state.stuck_value = out[last_before, axes].copy()
            if n_active and state.stuck_value is None:
                state.stuck_value = out[np.flatnonzero(active)[0], axes].copy()
        previous_t = state.last_t_ns
        state.last_t_ns = int(t_ns[-1])
        if n_active == 0:
            return
        rows = np.flatnonzero(active)
        block = out[np.ix_(rows, axes)]
        params = fault.params
        if fault.model == "step":
            block += params["amp"]
        elif fault.model == "drift":
            elapsed_s = (rel[rows] - np.int64(state.at_ns)).astype(np.float64) * 1e-9
            block += params["rate"] * elapsed_s[:, None]
        elif fault.model == "noise":
            block += params["sigma"] * state.rng.standard_normal((n_active, axes.size))
        elif fault.model == "stuck":
            assert state.stuck_value is not None
            block[:] = state.stuck_value
        elif fault.model == "scale":
            with np.errstate(over="ignore"):  # a huge input value becomes inf: flagged later
                block *= params["factor"]
        elif fault.model == "spikes":
            block += self._spikes(state, t_ns, rows, previous_t)
        out[np.ix_(rows, axes)] = block
        state.active_count += n_active

    def _spikes(
        self, state: _FaultState, t_ns: np.ndarray, rows: np.ndarray, previous_t: int | None
    ) -> np.ndarray:
        """Spike offsets for the faulty rows, shape (n_active, k); updates burst state."""
        params = state.fault.params
        n_active, k = rows.size, state.axes.size
        # time since the previous sample of the stream: Poisson event probability per sample
        stamps = t_ns.astype(np.float64)
        dt = np.empty(t_ns.size)
        dt[1:] = np.diff(stamps) * 1e-9
        dt[0] = (
            (t_ns[0] - previous_t) * 1e-9
            if previous_t is not None
            else 1.0 / float(self.array.rate_hz)
        )
        probability = -np.expm1(-params["rate"] * np.clip(dt[rows], 0.0, None))
        draws = state.rng.random((n_active, k, 2))  # fixed: 2 uniforms per sample and axis
        events = draws[:, :, 0] < probability[:, None]
        signs = np.where(draws[:, :, 1] < 0.5, -1.0, 1.0)
        if state.last_event is None or state.last_sign is None:
            state.last_event = np.full(k, -(2**62), dtype=np.int64)
            state.last_sign = np.ones(k)
        local = np.arange(n_active)
        position = np.maximum.accumulate(np.where(events, local[:, None], -1), axis=0)
        has_event = position >= 0
        safe = np.clip(position, 0, None)
        event_index = np.where(has_event, state.active_count + safe, state.last_event[None, :])
        sign = np.where(
            has_event, np.take_along_axis(signs, safe, axis=0), state.last_sign[None, :]
        )
        global_index = state.active_count + local[:, None]
        in_burst = (global_index - event_index) < int(params["width"])
        state.last_event = event_index[-1].astype(np.int64)
        state.last_sign = sign[-1].copy()
        return np.where(in_burst, params["amp"] * sign, 0.0)

    def apply_block(self, block: ImuBlock) -> ImuBlock:
        """Faulted copy of an aligned block (all IMUs, all sensor types present)."""
        fields: dict[str, np.ndarray | None] = {}
        for sensor_type in SENSOR_TYPES:
            triads = block.get(sensor_type)
            if triads is None:
                fields[sensor_type] = None
                continue
            result = np.array(triads, dtype=np.float64, copy=True)
            for imu, stream_type in self._streams:
                if stream_type == sensor_type and imu < result.shape[1]:
                    result[:, imu, :] = self.apply(imu, sensor_type, block.t_ns, triads[:, imu, :])
            fields[sensor_type] = result
        return ImuBlock(t_ns=block.t_ns.copy(), **fields)

    def truth_events(self) -> list[dict[str, Any]]:
        """Start/end events of this run's faults, in time order.

        Each is ``{"event": "start"|"end", "t_ns": int, "t_s": float, "fault_id": str,
        "fault": Fault.to_dict()}``; faults lasting to the end of the log have no end event.
        """
        events: list[dict[str, Any]] = []
        for fault in self.faults:
            marks = [("start", fault.at_ns)]
            if fault.until_ns is not None:
                marks.append(("end", fault.until_ns))
            for name, offset in marks:
                events.append(
                    {
                        "event": name,
                        "t_ns": self.t0_ns + offset,
                        "t_s": offset * 1e-9,
                        "fault_id": fault.id,
                        "fault": fault.to_dict(),
                    }
                )
        events.sort(key=lambda e: (e["t_ns"], e["event"] != "end"))
        return events

    def metadata(self) -> dict[str, str]:
        """The ``imufdi.faults`` metadata record: ``{"json": ...}``.

        The JSON holds ``format``, ``seed``, ``t0_ns``, ``faults`` (this run, SI) and
        ``previous`` (earlier injection runs on the same log, oldest first).
        """
        record = {
            "format": METADATA_FORMAT,
            "seed": self.seed,
            "t0_ns": self.t0_ns,
            "faults": [fault.to_dict() for fault in self.faults],
            "previous": self.previous_runs,
        }
        return {"json": json.dumps(record, separators=(",", ":"), sort_keys=True)}

    def all_faults(self) -> list[Fault]:
        """Previous runs' faults followed by this run's."""
        return faults_from_metadata(self.metadata())
