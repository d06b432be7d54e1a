"""Alarm events: bulk FdiEvent encoding against one message at a time, in the same run.

``detect`` used to queue each alarm start/end as its own message (one ``add_json`` ->
``add_batch`` per event, each with its own channel check), which was measured at
about a quarter of detect time on alarm-heavy logs. Events are now encoded per block with
:func:`imufdi_cli.mcapio.encode_fdi_events` and queued with one ``add_batch``. This script
times both ways of writing the same events (K alarm changes in blocks of 4096 samples,
into an in-memory MCAP) and prints the ratio.

Reading (report's cost of the episodes): ``--episodes E`` episode events (an
explanation with every fault model's fit, about 2 kB of JSON each) are interleaved with
the alarm events in batches of ``--per-batch`` messages, and read the way ``imufdi
report`` reads them now (:func:`~imufdi_cli.mcapio.events.decode_episode_events`: the
typed fields, no JSON) and the way it used to (every message decoded, every
explanation's JSON parsed). Prints both per message, and their ratio.

    python benchmarks/bench_events.py [--events 20000] [--episodes 2000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import time

import numpy as np

from imufdi_cli.mcapio import McapWriter, encode_fdi_events, register_events_channel
from imufdi_cli.mcapio.events import encode_fdi_event_dicts
from imufdi_cli.mcapio.records import MessageBatch

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


def _alarm_batch(channel: int, events: dict[str, np.ndarray]) -> MessageBatch:
    """glt's gyro alarm starts and ends of ``events`` (:func:`_events`), encoded in bulk."""
    return encode_fdi_events(
        channel,
        events["t_ns"],
        detector="glt",
        sensor_type="gyro",
        sensor_ids=IDS,
        alarm=events["alarm"],
        isolated=events["isolated"],
        amplitude=events["amplitude"],
        statistic=events["statistic"],
    )


def bulk(events: dict[str, np.ndarray], per_block: int) -> int:
    out = io.BytesIO()
    with McapWriter(out) as writer:
        channel = register_events_channel(writer)
        n = events["t_ns"].shape[0]
        for start in range(0, n, per_block):
            part = {k: v[start : start + per_block] for k, v in events.items()}
            writer.add_batch(_alarm_batch(channel, part))
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


def _episode(k: int) -> dict:
    """An explanation as detect writes it: every model fitted, spikes with its rate."""
    from imufdi_cli.episodes import MODELS, Episode, FaultFit

    start = 10**12 + k * 10**9
    fits = [
        FaultFit(model, 0.01 * j, 0.009 * j, 0.011 * j, 40 + j, -1000.0 + j, {"rate_hz": 2.5})
        for j, model in enumerate(MODELS)
    ]
    return Episode(
        detector="glt",
        sensor_type="gyro",
        start_ns=start,
        end_ns=start + 123_456_789,
        decided_start_ns=start + 5_000_000,
        decided_end_ns=start + 128_456_789,
        alarms=17,
        sensors=[IDS[k % 3], IDS[(k + 1) % 3]],
        peak_ratio=3.25,
        runner_up=IDS[(k + 1) % 3],
        runner_up_share=0.125,
        fits=fits,
        amplitude=0.0123,
    ).to_dict()


def reading(events: dict[str, np.ndarray], n_episodes: int, per_batch: int, repeat: int) -> None:
    """Time reading alarm and episode events: the report's walk against a full decode."""
    from imufdi_cli.mcapio.events import (
        EVENTS_TOPIC,
        EpisodeEvent,
        decode_episode_events,
        decode_events,
        encode_episode_events,
    )
    from imufdi_cli.mcapio.records import ChannelInfo, SchemaInfo
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA, FDI_EVENT_SCHEMA_NAME

    schema = SchemaInfo(1, FDI_EVENT_SCHEMA_NAME, "ros2msg", FDI_EVENT_SCHEMA)
    channel = ChannelInfo(1, EVENTS_TOPIC, "cdr", {}, schema)
    n = events["t_ns"].shape[0]
    alarms = _alarm_batch(1, events)
    explained = encode_episode_events(1, [_episode(k) for k in range(n_episodes)])
    # episodes spread evenly among the alarms
    order = np.argsort(
        np.concatenate([np.arange(n) / n, np.arange(n_episodes) / max(n_episodes, 1)]),
        kind="stable",
    )
    payloads = [alarms.payload(i) for i in range(n)]
    payloads += [explained.payload(i) for i in range(n_episodes)]
    joined = MessageBatch.from_payloads(1, np.arange(len(order)), [payloads[i] for i in order])
    batches = [joined.select(slice(i, i + per_batch)) for i in range(0, len(order), per_batch)]

    def walk() -> int:
        return sum(len(decode_episode_events(b, channel)) for b in batches)

    def full() -> int:
        return sum(
            len(
                [
                    EpisodeEvent.from_explanation(e["episode"])
                    for e in decode_events(b, channel)
                    if "episode" in e
                ]
            )
            for b in batches
        )

    times: dict[str, list[float]] = {"walk": [], "full decode": []}
    for _ in range(repeat):
        for name, fn in (("walk", walk), ("full decode", full)):
            start = time.process_time()
            found = fn()
            times[name].append(time.process_time() - start)
            assert found == n_episodes
    best = {k: min(v) for k, v in times.items()}
    size = len(json.dumps(_episode(0)))
    print(
        f"reading {n} alarm events and {n_episodes} episode events ({size} B of JSON each),"
        f" {per_batch} per batch, best of {repeat} (CPU):"
    )
    for name, seconds in best.items():
        print(
            f"  {name:12s} {seconds * 1e3:8.1f} ms  ({seconds / len(order) * 1e6:.2f} us/message)"
        )
    print(f"  ratio full decode / walk: {best['full decode'] / best['walk']:.1f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--events", type=int, default=20000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--per-block", type=int, default=200, help="events per 4096-sample block")
    parser.add_argument("--episodes", type=int, default=2000, help="episode events to read")
    parser.add_argument("--per-batch", type=int, default=400, help="messages per batch read")
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
    reading(events, args.episodes, args.per_batch, args.repeat)
    print(f"load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
