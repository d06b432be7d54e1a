import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.capture import load_layout, parse_capture
from imufdi_cli.errors import CaptureError, ImufdiError, LayoutError
from imufdi_cli.log import ImuBlock

from .conftest import LAYOUTS


def parse_all(data, layout, **kwargs):
    blocks, stats = parse_capture(data, layout, **kwargs)
    return ImuBlock.concatenate(list(blocks)), stats


def test_builtin_csv_sensor_id_columns_in_si():
    text = "t,imu0.gyro.x,imu0.gyro.y,imu0.gyro.z,imu0.accel.x,imu0.accel.y,imu0.accel.z\n"
    text += "0.00,0.1,0.2,0.3,1,2,9.8\n0.01,0.4,0.5,0.6,1,2,9.7\n"
    block, stats = parse_all(text.encode(), load_layout("csv"))
    assert_array_equal(block.t_ns, [0, 10_000_000])
    assert_allclose(block.gyro[:, 0, :], [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    assert_allclose(block.accel[1, 0], [1, 2, 9.7])
    assert stats.frames_ok == 2 and stats.n_imus == 1


@pytest.mark.parametrize("delimiter", [",", "\t", ";"])
@pytest.mark.parametrize("chunk_size", [7, 1 << 16])
def test_mapped_columns_units_and_delimiters(delimiter, chunk_size):
    layout = load_layout(LAYOUTS / "logger-csv.toml")
    names = ["timestamp_us"] + [f"{s}{k}_{a}" for k in range(2) for s in "ga" for a in "xyz"]
    rows = [delimiter.join(names)]
    rows += [delimiter.join(["1000"] + ["1"] * 12), delimiter.join(["3000"] + ["2"] * 12)]
    block, stats = parse_all(("\r\n".join(rows) + "\r\n").encode(), layout, chunk_size=chunk_size)
    assert_array_equal(block.t_ns, [1_000_000, 3_000_000])
    assert_allclose(block.gyro[1, 1], [math.radians(2.0)] * 3)
    assert_allclose(block.accel[0, 0], [9.80665] * 3)
    assert stats.frames_ok == 2 and stats.rows_malformed == 0


def test_malformed_rows_are_dropped_and_counted():
    text = "t,imu0.gyro.x,imu0.gyro.y,imu0.gyro.z\n0,1,2,3\n0.01,1,x,3\n0.02,1,2\n\n0.03,nan,1,1\n0.04,4,5,6"
    block, stats = parse_all(text.encode(), load_layout("csv", sensors=("gyro",)))
    assert_array_equal(block.t_ns, [0, 40_000_000])
    assert stats.rows_malformed == 3
    assert stats.bytes_dropped == len("0.01,1,x,3\n0.02,1,2\n0.03,nan,1,1\n")
    with pytest.raises(CaptureError, match="strict"):
        parse_all(text.encode(), load_layout("csv", sensors=("gyro",)), strict=True)


def test_missing_column_and_empty_capture():
    with pytest.raises(CaptureError, match="no IMU columns"):
        parse_all(b"t,a,b\n1,2,3\n", load_layout("csv"))
    with pytest.raises(CaptureError, match="empty"):
        parse_all(b"", load_layout("csv"))
    with pytest.raises(CaptureError, match="'timestamp_us' not in the header"):
        parse_all(b"t,g0_x\n", load_layout(LAYOUTS / "logger-csv.toml"))


def test_bad_csv_tables():
    from imufdi_cli.capture import layout_from_dict

    with pytest.raises(LayoutError, match="valid: auto"):
        layout_from_dict({"csv": {"delimiter": "|", "gyro": {"columns": "g{k}{axis}"}}})
    with pytest.raises(LayoutError, match="template"):
        layout_from_dict({"csv": {"gyro": {"columns": "gyro"}}})
    with pytest.raises(LayoutError, match="unknown unit"):
        layout_from_dict({"csv": {"gyro": {"columns": "g{k}{axis}", "unit": "furlong"}}})


@settings(max_examples=100, deadline=2000)
@given(st.binary(max_size=400), st.integers(1, 100))
def test_arbitrary_bytes_only_imufdi_errors(data, chunk):
    try:
        blocks, _ = parse_capture(
            b"t,imu0.gyro.x,imu0.gyro.y,imu0.gyro.z\n" + data,
            load_layout("csv", sensors=("gyro",)),
            chunk_size=chunk,
        )
        for block in blocks:
            assert np.all(np.isfinite(block.gyro))
    except ImufdiError:
        pass


TOKENS = [
    "1.5",
    " -2.25 ",
    "+1e-3",
    ".5",
    "5.",
    "-0",
    "nan",
    "inf",
    "1e500",
    "1_000",
    "x",
    "",
    "0x10",
    "4.9406564584124654e-324",
]


@pytest.mark.parametrize("delimiter", [",", ";", "\t", " "])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numpy_reader_and_row_by_row_parse_agree(monkeypatch, delimiter, seed):
    """numpy's C reader (whole chunks of well-formed rows) and the row-by-row fallback
    give the same samples and counts, whatever the tokens (plain and odd numbers,
    non-finite, garbage, wrong field counts, blank lines)."""
    import imufdi_cli.capture.csvcap as csvcap

    rng = np.random.default_rng(seed)
    names = ["t"] + [f"imu{k}.{s}.{a}" for k in range(2) for s in ("gyro", "accel") for a in "xyz"]
    lines = [delimiter.join(names)]
    for row in range(400):
        values = [f"{row * 0.01:.2f}"] + [repr(float(v)) for v in rng.normal(size=12)]
        if rng.random() < 0.5:  # a few odd tokens in half of the chunks' rows
            for _ in range(rng.integers(1, 3)):
                values[rng.integers(0, 13)] = TOKENS[rng.integers(len(TOKENS))]
        if rng.random() < 0.02:
            values = values[:-1]
        lines.append("" if rng.random() < 0.02 else delimiter.join(values))
    data = ("\n".join(lines) + "\n").encode()
    layout = load_layout("csv")
    fast, fast_stats = parse_all(data, layout, chunk_size=700)
    monkeypatch.setattr(csvcap, "_fast_table", lambda rows, delimiter, wanted: None)
    slow, slow_stats = parse_all(data, layout, chunk_size=700)
    assert_array_equal(fast.t_ns, slow.t_ns)
    assert fast.gyro.tobytes() == slow.gyro.tobytes()
    assert fast.accel.tobytes() == slow.accel.tobytes()
    assert fast_stats.to_dict() == slow_stats.to_dict()
    assert fast_stats.frames_ok > 100
