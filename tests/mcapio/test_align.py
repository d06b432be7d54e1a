"""Time alignment: the regular-array fast path gives what the general path gives."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from imufdi_cli.mcapio.align import _Aligner


class _General(_Aligner):
    """The aligner without its fast path (the reference)."""

    def _resolve_regular(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        return None


class _Counting(_Aligner):
    """The aligner, counting the resolutions its fast path made."""

    fast = 0

    def _resolve_regular(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        result = super()._resolve_regular(*args, **kwargs)
        type(self).fast += result is not None
        return result


def _run(cls, parts, names, widths, finals):
    aligner = cls(names, widths, tolerance=3_000_000, max_pending=1000)
    out = []
    for (streams, t_ns, values), final in zip(parts, finals):
        aligner.add(streams, t_ns, values)
        stamps, per_stream = aligner.resolve(final=final)
        out.append((stamps, [np.array(v) for v in per_stream]))
    return out, aligner


def _regular(rng, n_slots, n_streams, start):
    t = (start + np.arange(n_slots)) * 10_000_000
    streams = np.tile(np.arange(n_streams), n_slots)
    values = rng.normal(size=(n_slots * n_streams, 6))
    return streams, np.repeat(t, n_streams), values


@pytest.mark.parametrize("irregular", [False, True])
def test_fast_path_matches_the_general_path(irregular):
    rng = np.random.default_rng(7)
    names = [f"/imu{k}" for k in range(4)] + ["/imu0/mag"]
    widths = [6, 6, 6, 6, 3]
    parts = []
    start = 0
    for size in (1, 5, 40, 3, 17):
        streams, t, values = _regular(rng, size, len(names), start)
        if irregular and size == 40:  # a gap, a duplicate and a skewed stamp
            keep = np.ones(streams.size, bool)
            keep[7] = False
            streams, t, values = streams[keep], t[keep], values[keep]
            streams = np.r_[streams, 2]
            t = np.r_[t, t[-1]]
            values = np.r_[values, values[-1:]]
            t[12] += 1_000_000
        parts.append((streams, t, values))
        start += size
    finals = [False, False, False, False, True]
    _Counting.fast = 0
    fast, fast_aligner = _run(_Counting, parts, names, widths, finals)
    # regular: every resolution by the fast path; irregular: the general path at least
    # for the damaged part
    assert _Counting.fast == 5 if not irregular else 1 <= _Counting.fast < 5
    slow, slow_aligner = _run(_General, parts, names, widths, finals)
    for (t_fast, v_fast), (t_slow, v_slow) in zip(fast, slow):
        np.testing.assert_array_equal(t_fast, t_slow)
        assert len(v_fast) == len(v_slow)
        for a, b in zip(v_fast, v_slow):
            np.testing.assert_array_equal(a, b)
    assert dataclasses.asdict(fast_aligner.stats) == dataclasses.asdict(slow_aligner.stats)
    assert fast_aligner.boundary == slow_aligner.boundary
    total = sum(t.size for t, _ in fast)
    assert total == (66 - (1 if irregular else 0))


@pytest.mark.parametrize("seed", range(4))
def test_fast_path_takes_pieces_that_end_inside_a_slot(seed):
    """A file's chunks end anywhere inside a time slot: the fast path still resolves every
    piece (the incomplete newest slot waits for the next one) and gives what the general
    path gives."""
    rng = np.random.default_rng(seed)
    names = [f"/imu{k}" for k in range(4)] + ["/imu0/mag"]
    widths = [6, 6, 6, 6, 3]
    streams, t, values = _regular(rng, 60, len(names), 0)
    cuts = np.sort(rng.choice(np.arange(1, streams.size), size=6, replace=False))
    cuts = np.r_[cuts[cuts % len(names) != 0], streams.size - 2]  # every cut inside a slot
    edges = np.r_[0, cuts, streams.size]
    parts = [(streams[a:b], t[a:b], values[a:b]) for a, b in itertools.pairwise(edges)]
    finals = [False] * (len(parts) - 1) + [True]
    _Counting.fast = 0
    fast, fast_aligner = _run(_Counting, parts, names, widths, finals)
    assert _Counting.fast == len(parts)
    slow, slow_aligner = _run(_General, parts, names, widths, finals)
    for (t_fast, v_fast), (t_slow, v_slow) in zip(fast, slow):
        np.testing.assert_array_equal(t_fast, t_slow)
        for a, b in zip(v_fast, v_slow):
            np.testing.assert_array_equal(a, b)
    assert dataclasses.asdict(fast_aligner.stats) == dataclasses.asdict(slow_aligner.stats)
    assert fast_aligner.boundary == slow_aligner.boundary
    assert sum(t.size for t, _ in fast) == 60


def test_an_incomplete_newest_slot_out_of_order_is_left_to_the_general_path():
    rng = np.random.default_rng(3)
    names = ["/imu0", "/imu1", "/imu2"]
    streams, t, values = _regular(rng, 5, 3, 0)
    streams = np.r_[streams, 1]  # the next slot starts with the second stream
    t = np.r_[t, t[-1] + 10_000_000]
    values = np.r_[values, values[:1]]
    _Counting.fast = 0
    (stamps, _), *_ = _run(_Counting, [(streams, t, values)], names, [6, 6, 6], [False])[0]
    assert _Counting.fast == 0
    np.testing.assert_array_equal(stamps, np.arange(4) * 10_000_000)


def test_a_log_that_ends_inside_a_slot_ends_as_the_general_path_ends_it():
    rng = np.random.default_rng(5)
    names = [f"/imu{k}" for k in range(4)]
    streams, t, values = _regular(rng, 30, 4, 0)
    streams, t, values = streams[:-2], t[:-2], values[:-2]  # the last slot lacks two IMUs
    parts = [(streams[a:b], t[a:b], values[a:b]) for a, b in ((0, 41), (41, 87), (87, 118))]
    finals = [False, False, True]
    _Counting.fast = 0
    fast, fast_aligner = _run(_Counting, parts, names, [6] * 4, finals)
    assert _Counting.fast == 2  # the final resolution is the general path's
    slow, slow_aligner = _run(_General, parts, names, [6] * 4, finals)
    for (t_fast, v_fast), (t_slow, v_slow) in zip(fast, slow):
        np.testing.assert_array_equal(t_fast, t_slow)
        for a, b in zip(v_fast, v_slow):
            np.testing.assert_array_equal(a, b)
    assert dataclasses.asdict(fast_aligner.stats) == dataclasses.asdict(slow_aligner.stats)
