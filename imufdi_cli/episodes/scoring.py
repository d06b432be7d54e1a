"""Scoring explained episodes against injected truth: which fault each episode matches
(:func:`match_episodes`), and the class accuracy and interval coverage per true model
(:class:`EpisodeTally`, :func:`score_episodes`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: the fault parameter each model's size estimates (faults.py keys, SI)
TRUTH_SIZE_KEYS = {
    "step": "amp",
    "drift": "rate",
    "noise": "factor",
    "scale": "factor",
    "spikes": "amp",
}


def truth_size(fault: dict[str, Any]) -> float | None:
    """The size an explanation of ``fault`` (a :meth:`Fault.to_dict`) should find, or None
    (stuck, or a noise fault given by sigma without a factor)."""
    key = TRUTH_SIZE_KEYS.get(str(fault.get("model")))
    value = None if key is None else fault.get("params", {}).get(key)
    return None if value is None else float(value)


def match_episodes(
    episodes: Sequence[dict[str, Any]], faults: Sequence[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Match each episode (:meth:`Episode.to_dict`) to the injected fault it explains.

    ``faults`` hold ``id``, ``model``, ``sensors``, ``params`` and absolute ``start_ns`` /
    ``end_ns`` (None: to the end of the log). An episode matches a fault when its first
    isolated sensor is one of the fault's sensors and its alarms overlap the fault's
    window; it is ``wrong_sensor`` when it overlaps a fault on another sensor of its type,
    and ``false`` otherwise. Returns one record per episode: ``{"match": "fault" |
    "wrong_sensor" | "false", "fault_id", "true_class", "class_right", "true_size",
    "covered"}`` (:meth:`EpisodeMatcher.match`).
    """
    from imufdi_cli.mcapio.events import match_fields  # the explanation's fields (its format)

    matcher = EpisodeMatcher(faults)
    return [matcher.match(*match_fields(episode)) for episode in episodes]


class EpisodeMatcher:
    """:func:`match_episodes` for one set of injected faults, prepared once (each fault's
    sensor types, window and true size), matching episodes one at a time from the few
    fields it needs (:func:`imufdi_cli.mcapio.events.match_fields`, or the typed fields of an ``episode`` event)."""

    def __init__(self, faults: Sequence[dict[str, Any]]) -> None:
        self.faults = [
            (
                fault,
                fault["start_ns"],
                fault.get("end_ns"),
                {_sensor_type(s) for s in fault.get("sensors", [])},
                truth_size(fault),
            )
            for fault in faults
        ]

    def match(
        self,
        sensor_type: str,
        start_ns: int,
        end_ns: int,
        first: str | None,
        model: str | None,
        low: float | None,
        high: float | None,
    ) -> dict[str, Any]:
        """The match record of one episode (:func:`match_episodes`).

        Parameters
        ----------
        sensor_type : str
        start_ns, end_ns : int
            The episode's first and last alarmed sample, ns (log time).
        first : str or None
            Its first isolated sensor.
        model : str or None
            The best fit's fault model; ``low``, ``high`` its 90 % interval (SI, None when
            there is none).
        """
        kind, hit, size = "false", None, None
        for fault, start, end, types, true_size in self.faults:
            if end_ns < start or (end is not None and start_ns >= end):
                continue
            if sensor_type not in types:
                continue
            if first in fault["sensors"]:
                kind, hit, size = "fault", fault, true_size
                break
            kind = "wrong_sensor"
        record: dict[str, Any] = {"match": kind, "fault_id": None if hit is None else hit["id"]}
        if hit is not None:
            record["true_class"] = hit["model"]
            record["class_right"] = model == hit["model"]
            record["true_size"] = size
            record["covered"] = (
                None
                if size is None or not record["class_right"] or low is None or high is None
                else bool(low <= size <= high)
            )
        return record


def _sensor_type(sensor_id: str) -> str | None:
    """``imu3.gyro.x`` -> ``gyro`` (None for an id without a type)."""
    parts = sensor_id.split(".")
    return parts[1] if len(parts) > 1 else None


class EpisodeTally:
    """Streaming figures of one detector and sensor type's episodes (bounded memory)."""

    def __init__(self) -> None:
        self.episodes = 0
        self.matched = 0
        self.wrong_sensor = 0
        self.false = 0
        self.calibration = 0  # in the calibration window: in sample, not scored
        self.per_model: dict[str, dict[str, int]] = {}

    def add(self, match: dict[str, Any]) -> None:
        """Count one episode with its :func:`match_episodes` record."""
        self.episodes += 1
        if match["match"] == "false":
            self.false += 1
        elif match["match"] == "wrong_sensor":
            self.wrong_sensor += 1
        else:
            self.matched += 1
            row = self.per_model.setdefault(
                match["true_class"], {"episodes": 0, "class_right": 0, "sized": 0, "covered": 0}
            )
            row["episodes"] += 1
            row["class_right"] += bool(match["class_right"])
            if match["covered"] is not None:
                row["sized"] += 1
                row["covered"] += bool(match["covered"])

    def result(self, hours: float | None) -> dict[str, Any]:
        """Episodes, false episodes (per hour of ``hours`` of fault-free log), and for
        matched ones the share classified right and the share of size intervals covering
        the truth, overall and per true fault model (None when undefined)."""
        per_model = {}
        for model, row in sorted(self.per_model.items()):
            per_model[model] = {
                **row,
                "class_accuracy": row["class_right"] / row["episodes"],
                "coverage": row["covered"] / row["sized"] if row["sized"] else None,
            }
        right = sum(r["class_right"] for r in self.per_model.values())
        covered = sum(r["covered"] for r in self.per_model.values())
        sized = sum(r["sized"] for r in self.per_model.values())
        return {
            "episodes": self.episodes,
            "matched": self.matched,
            "wrong_sensor": self.wrong_sensor,
            "false": self.false,
            "in_calibration": self.calibration,
            "false_episodes_per_hour": self.false / hours if hours else None,
            "class_accuracy": right / self.matched if self.matched else None,
            "coverage": covered / sized if sized else None,
            "per_model": per_model,
        }


def score_episodes(matches: Sequence[dict[str, Any]], hours: float | None) -> dict[str, Any]:
    """:class:`EpisodeTally` figures of the :func:`match_episodes` records of a list."""
    tally = EpisodeTally()
    for match in matches:
        tally.add(match)
    return tally.result(hours)
