"""ros2msg schema parsing and the compiled CDR layout."""

from __future__ import annotations

import string

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio import MessageBatch
from imufdi_cli.mcapio.cdr import CdrCodec
from imufdi_cli.mcapio.cdr_message import decode_cdr_message
from imufdi_cli.mcapio.msgdef import parse_ros2msg
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, STATUS_SCHEMA

NESTED = """# comment line
int32 CONSTANT=7
string<=10 name  # bounded string
uint8 flag
pkg/Inner[2] pair
float64[] values
Inner last
================================================================================
MSG: pkg/Inner
int16 a 3
float64 b
"""


def test_parse_imu_schema() -> None:
    defs = parse_ros2msg("sensor_msgs/msg/Imu", IMU_SCHEMA)
    imu = defs["sensor_msgs/msg/Imu"]
    assert [f.name for f in imu.fields][:3] == ["header", "orientation", "orientation_covariance"]
    assert imu.fields[2].array == "fixed" and imu.fields[2].size == 9
    assert [f.name for f in defs["geometry_msgs/msg/Quaternion"].fields] == ["x", "y", "z", "w"]
    assert defs["std_msgs/msg/Header"].fields[0].type_name == "builtin_interfaces/msg/Time"


def test_layout_offsets_of_imu_are_static_after_the_frame_id() -> None:
    codec = CdrCodec("sensor_msgs/msg/Imu", IMU_SCHEMA)
    leaves = codec.layout.leaves
    assert leaves["angular_velocity.x"].segment == leaves["linear_acceleration.z"].segment
    assert leaves["linear_acceleration.x"].offset - leaves["angular_velocity.x"].offset == 96


def _encode_nested(name: str, flag: int, pair, values, last, big: bool) -> bytes:
    import struct

    e = ">" if big else "<"
    out = bytearray(b"\x00\x00\x00\x00" if big else b"\x00\x01\x00\x00")

    def align(n: int) -> None:
        out.extend(b"\0" * ((-(len(out) - 4)) % n))

    raw = name.encode() + b"\0"
    out += struct.pack(e + "I", len(raw)) + raw
    out += struct.pack(e + "B", flag)
    for a, b in pair:
        align(2)
        out += struct.pack(e + "h", a)
        align(8)
        out += struct.pack(e + "d", b)
    align(4)
    out += struct.pack(e + "I", len(values))
    if values:
        align(8)
        out += struct.pack(e + f"{len(values)}d", *values)
    align(2)
    out += struct.pack(e + "h", last[0])
    align(8)
    out += struct.pack(e + "d", last[1])
    return bytes(out)


message_strategy = st.tuples(
    st.text(alphabet=string.ascii_letters, max_size=10),
    st.integers(0, 255),
    st.lists(
        st.tuples(st.integers(-(2**15), 2**15 - 1), st.floats(allow_nan=False)),
        min_size=2,
        max_size=2,
    ),
    st.lists(st.floats(allow_nan=False), max_size=5),
    st.tuples(st.integers(-(2**15), 2**15 - 1), st.floats(allow_nan=False)),
    st.booleans(),
)


@given(st.lists(message_strategy, min_size=1, max_size=6))
def test_bulk_walker_matches_per_message_decoder(messages) -> None:
    codec = CdrCodec("pkg/msg/Outer", NESTED)
    payloads = [_encode_nested(*m) for m in messages]
    batch = MessageBatch.from_payloads(0, np.zeros(len(payloads), np.int64), payloads)
    paths = ["flag", "pair[1].a", "pair[1].b", "last.a", "last.b", "values"]
    little, positions, sizes = codec.positions(batch, paths)
    assert little.tolist() == [not m[5] for m in messages]
    last_b = codec.read(batch, little, positions["last.b"], "f8", 1)[:, 0]
    pair_a = codec.read(batch, little, positions["pair[1].a"], "i2", 1)[:, 0]
    for i, m in enumerate(messages):
        general = decode_cdr_message(codec.defs, codec.root, payloads[i])
        assert general["name"] == m[0]
        assert general["last"]["b"] == last_b[i] == m[4][1]
        assert general["pair"][1]["a"] == pair_a[i] == m[2][1][0]
        assert sizes["values"][i] == len(m[3])
        assert general["values"] == m[3]
        assert codec.decoder()(payloads[i]) == general  # the cached, compiled decoder


def test_message_decoder_refuses_truncated_messages_and_is_compiled_once() -> None:
    """Every cut of a message is refused with the field that runs past the end (or the
    encapsulation header), never decoded short; the codec compiles one decoder."""
    codec = CdrCodec("pkg/msg/Outer", NESTED)
    payload = _encode_nested("abc", True, [(1, 0.5), (-2, 1.5)], [0.25, 0.5], (3, 2.5), False)
    decode = codec.decoder()
    assert codec.decoder() is decode
    whole = decode(payload)
    assert whole["values"] == [0.25, 0.5] and whole["name"] == "abc"
    for cut in range(len(payload)):
        with pytest.raises(McapInputError, match="CDR"):
            decode(payload[:cut])


def test_schema_errors() -> None:
    with pytest.raises(McapInputError, match="no definition of pkg/msg/Missing"):
        CdrCodec("pkg/msg/A", "pkg/Missing thing\n")
    with pytest.raises(McapInputError, match="cannot parse line"):
        parse_ros2msg("pkg/msg/A", "float64\n")
    codec = CdrCodec("imufdi_msgs/msg/FdiStatus", STATUS_SCHEMA)
    assert "scores" in codec.layout.leaves
