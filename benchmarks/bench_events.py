"""Alarm events: bulk FdiEvent encoding against one message at a time, in the same run.

``detect`` used to queue each alarm start/end as its own message (one ``add_json`` ->
``add_batch`` per event, each with its own channel check), which issue 20 measured at
about a quarter of detect time on alarm-heavy logs. Events are now encoded per block with
:func:`imufdi_cli.mcapio.encode_fdi_events` and queued with one ``add_batch``. This script
times both ways of writing the same events (K alarm changes in blocks of 4096 samples,
into an in-memory MCAP) and prints the ratio.

    python benchmarks/bench_events.py [--events 20000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import io
import time

import numpy as np

from imufdi_cli.mcapio import McapWriter, encode_fdi_events, register_events_channel
from imufdi_cli.mcapio.events import encode_fdi_event_dicts

IDS = [f"imu{k}.gyro.{a}" for k in range(16) for a in "xyz"]


def _events(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "t_ns": np.sort(rng.integers(0, 10**12, n)),
        "alarm": np.arange(n) % 2 == 0,
        "isolated": np.where(np.arange(n) % 2 == 0, rng.integers(-2, len(IDS), n), -1),
        "amplitude": rng.normal(size=n),
        "statistic": rng.exponential(10.0, n),
    }


def bulk(events: dict[str, np.ndarray], per_block: int) -> int:
    out = io.BytesIO()
    with McapWriter(out) as writer:
        channel = register_events_channel(writer)
        n = events["t_ns"].shape[0]
        for start in range(0, n, per_block):
            part = {k: v[start : start + per_block] for k, v in events.items()}
            writer.add_batch(
                encode_fdi_events(
                    channel,
                    part["t_ns"],
                    detector="glt",
                    sensor_type="gyro",
                    sensor_ids=IDS,
                    alarm=part["alarm"],
                    isolated=part["isolated"],
                    amplitude=part["amplitude"],
                    statistic=part["statistic"],
                )
            )
    return len(out.getvalue())


def one_by_one(events: dict[str, np.ndarray]) -> int:
    out = io.BytesIO()
    with McapWriter(out) as writer:
        channel = register_events_channel(writer)
        for i in range(events["t_ns"].shape[0]):
            iso = int(events["isolated"][i])
            event = {
                "detector": "glt",
                "sensor_type": "gyro",
                "event": "alarm_start" if events["alarm"][i] else "alarm_end",
                "t_ns": int(events["t_ns"][i]),
                "isolated": IDS[iso] if iso >= 0 else None,
                "isolable": iso != -2,
                "amplitude": float(events["amplitude"][i]),
                "statistic": float(events["statistic"][i]),
            }
            writer.add_batch(encode_fdi_event_dicts(channel, [event["t_ns"]], [event]))
    return len(out.getvalue())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--events", type=int, default=20000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--per-block", type=int, default=200, help="events per 4096-sample block")
    args = parser.parse_args()
    events = _events(args.events)
    times = {"bulk": [], "one by one": []}
    sizes = {}
    for _ in range(args.repeat):
        for name, run in (
            ("bulk", lambda: bulk(events, args.per_block)),
            ("one by one", lambda: one_by_one(events)),
        ):
            start = time.perf_counter()
            sizes[name] = run()
            times[name].append(time.perf_counter() - start)
    best = {k: min(v) for k, v in times.items()}
    print(f"{args.events} alarm events, {args.per_block} per block, best of {args.repeat}:")
    for name, seconds in best.items():
        print(
            f"  {name:10s} {seconds * 1e3:8.1f} ms  ({seconds / args.events * 1e6:.2f} us/event, {sizes[name]} bytes)"
        )
    print(f"  ratio one-by-one / bulk: {best['one by one'] / best['bulk']:.1f}x")


if __name__ == "__main__":
    main()
