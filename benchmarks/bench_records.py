"""Message records of varying payload lengths: the writer's serialisation against per-byte
index arrays, in the same run.

:func:`imufdi_cli.mcapio.records.build_message_records` lays out a batch as consecutive
Message records (31-byte head, payload). Payloads of one length are copied as rows; payloads
of varying lengths (alarm and episode events, status or Imu messages
whose frame ids differ in length) used to go through index arrays of every record and
payload byte (about 4 int64 arrays per byte). They are now copied per length, one void element per
record (a few lengths), or joined per message (many lengths). This script times both on
the same batches, checks they give the same bytes, and prints the ratio.

    python benchmarks/bench_records.py [--messages 4000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from imufdi_cli.mcapio.records import (
    MESSAGE_HEADER_SIZE,
    MessageBatch,
    build_message_records,
    message_headers,
)


def per_byte(batch: MessageBatch) -> np.ndarray:
    """The records as the writer used to build them (per-byte index arrays)."""
    n = len(batch)
    lengths = batch.length.astype(np.int64)
    header = message_headers(batch)  # unchanged since
    header_bytes = header.view(np.uint8).reshape(n, MESSAGE_HEADER_SIZE)
    sizes = lengths + MESSAGE_HEADER_SIZE
    starts = np.zeros(n, np.int64)
    np.cumsum(sizes[:-1], out=starts[1:])
    out = np.empty(int(sizes.sum()), dtype=np.uint8)
    head_index = starts[:, None] + np.arange(MESSAGE_HEADER_SIZE, dtype=np.int64)[None, :]
    out[head_index] = header_bytes
    n_payload = int(lengths.sum())
    payload_starts = starts + MESSAGE_HEADER_SIZE
    delta_dst = np.repeat(payload_starts - np.cumsum(lengths) + lengths, lengths)
    delta_src = np.repeat(batch.offset - np.cumsum(lengths) + lengths, lengths)
    running = np.arange(n_payload, dtype=np.int64)
    out[running + delta_dst] = batch.data[running + delta_src]
    return out


def _batch(n: int, n_lengths: int, seed: int) -> MessageBatch:
    rng = np.random.default_rng(seed)
    lengths = rng.choice(rng.integers(60, 400, n_lengths), n)
    payloads = [rng.integers(0, 256, int(k), dtype=np.uint8).tobytes() for k in lengths]
    return MessageBatch.from_payloads(rng.integers(1, 20, n), np.arange(n) * 10**6, payloads)


def _best(fn, batch: MessageBatch, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn(batch)
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--messages", type=int, default=4000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    print(f"{args.messages} messages, payloads of 60-400 bytes; best of {args.repeat}")
    for n_lengths in (2, 4, 16, 1000):
        batch = _batch(args.messages, n_lengths, seed=n_lengths)
        records, _ = build_message_records(batch)
        assert records.tobytes() == per_byte(batch).tobytes()
        new = _best(lambda b: build_message_records(b), batch, args.repeat)
        old = _best(per_byte, batch, args.repeat)
        print(
            f"  {n_lengths:5d} lengths: per-byte {old * 1e3:7.2f} ms, now {new * 1e3:6.2f} ms,"
            f" ratio {old / new:5.1f}x"
        )
    print(f"load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
