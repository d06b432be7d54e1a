"""The streaming helpers of calibrate: spools, exact order statistics and percentile, the
streamed moving standard deviation, the static scan in blocks."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli.calibrate import passes
from imufdi_cli.calibrate.static import _moving_std


def _spool(values: np.ndarray, piece: int = 333) -> passes.Spool:
    spool = passes.Spool(np.float64)
    for start in range(0, len(values), piece):
        spool.append(values[start : start + piece])
    return spool


def test_a_spool_gives_back_its_rows_in_order():
    rows = np.arange(30.0).reshape(10, 3)
    spool = passes.Spool(np.float64, (3,))
    spool.append(rows[:4])
    spool.append(rows[4:])
    assert len(spool) == 10
    np.testing.assert_array_equal(spool.read(2, 7), rows[2:7])
    np.testing.assert_array_equal(np.concatenate([c for _, c in spool.chunks(3)]), rows)
    assert spool.read(8, 100).shape == (2, 3) and spool.read(5, 5).shape == (0, 3)
    with pytest.raises(ValueError):
        spool.append(np.zeros((2, 2)))
    spool.close()


VALUES = {
    "normal": np.random.default_rng(1).normal(size=5000),
    "small positive": np.abs(np.random.default_rng(2).normal(size=3001)) * 1e-3,
    "all equal": np.full(700, 2.5),
    "zeros and -0": np.r_[np.zeros(300), -np.zeros(10), np.random.default_rng(3).random(200)],
    "one": np.array([3.0]),
    "two": np.array([-1.0, 4.0]),
    "huge range": np.r_[1e-300, 1e300, -1e300, np.random.default_rng(4).normal(size=100)],
}


@pytest.mark.parametrize("limit", [64, 1 << 20], ids=["radix passes", "collected"])
@pytest.mark.parametrize("name", sorted(VALUES))
def test_percentile_of_a_spool_is_numpys(name, limit, monkeypatch):
    """The exact selection gives np.percentile's value to the bit, also through the radix
    passes of a spool larger than the collection limit."""
    monkeypatch.setattr(passes, "SELECT_LIMIT", limit)
    values = VALUES[name]
    spool = _spool(values)
    ranks = sorted({0, len(values) // 3, len(values) - 1})
    expected = np.sort(values)[ranks]
    assert passes.order_statistics(spool, ranks) == [float(v) for v in expected]
    for q in (0, 10, 33.3, 50, 99.9, 100):
        assert passes.percentile(spool, q) == np.percentile(values, q), q
    spool.close()


@pytest.mark.parametrize(
    ("n", "w"), [(1000, 62), (5, 62), (62, 62), (63, 62), (4000, 1000), (2, 3)]
)
@pytest.mark.parametrize("block", [1, 7, 100, 5000])
def test_the_streamed_moving_std_is_the_whole_one(n, w, block):
    """Each row's centred window, moved inside the log at its ends (known only when the
    stream ends), as _moving_std computes it on the whole log; to rounding (the sums are
    taken over a window's buffer, not the whole log: 1e-9 relative is generous for rows
    of magnitude 10 with unit noise)."""
    x = np.random.default_rng(n + w).normal(size=(n, 3)) + 9.8
    moving = passes.MovingStd(w)
    got = np.concatenate(
        [moving.feed(x[i : i + block]) for i in range(0, n, block)] + [moving.finish()]
    )
    np.testing.assert_allclose(got, _moving_std(x, w), rtol=1e-9, atol=1e-12)


def test_the_static_scan_in_blocks_finds_the_intervals_of_the_whole(monkeypatch):
    from imufdi_cli.calibrate import find_static
    from imufdi_cli.calibrate.static import StaticScan
    from tests.test_calibrate import _geometry, _log

    array = _geometry()
    block, _ = _log(array, np.random.default_rng(8), orientations=5)
    t = block.t_s()
    usable = np.ones(len(t), bool)
    whole, mask = find_static(array, block.accel, block.gyro, t, usable)
    assert len(whole) == 5 and mask.sum() == sum(i.end_row - i.first_row for i in whole)
    monkeypatch.setattr(passes, "SPOOL_CHUNK", 500)  # intervals read in several pieces
    scan = StaticScan(array, True)
    for start in range(0, len(t), 333):
        rows = slice(start, start + 333)
        scan.add(t[rows], block.accel[rows], block.gyro[rows], usable[rows])
    streamed = scan.finish()
    scan.close()
    assert [(i.start_s, i.end_s, i.first_row, i.end_row) for i in streamed] == [
        (i.start_s, i.end_s, i.first_row, i.end_row) for i in whole
    ]
    for a, b in zip(streamed, whole):
        np.testing.assert_allclose(a.direction, b.direction, rtol=1e-12)
