"""Reader limits: crafted bombs exit 3 under a 1 GB address-space limit and a timeout,
and the limits are overridable."""

from __future__ import annotations

import io
import json
import os
import resource
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.mcapio import McapSource
from imufdi_cli.mcapio.cdr import CdrCodec
from imufdi_cli.mcapio.cdr_message import decode_cdr_message
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.msgdef import parse_ros2msg
from imufdi_cli.mcapio.schemas import IMU_SCHEMA
from tests.mcapio.mcap_files import imu_file, imu_file_with_schema, wrap, zero_chunk

ROOT = Path(__file__).resolve().parents[2]
#: Address space of each bomb run; the CLI itself (numpy, scipy, rich) needs about 0.5 GB.
MEMORY_LIMIT = 1 << 30
#: A guard against hangs only (a run takes a few seconds, mostly imports).
TIMEOUT_S = 120


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


#: Runs CLI commands in one process (imports once): argv JSON list of [args, stdin file or
#: null]; stdin is fed through a real pipe, as in a shell pipeline. Prints JSON results.
_RUNNER = """
import contextlib, io, json, os, sys, threading
from imufdi_cli.cli import main

def feed(fd, path):
    with open(fd, "wb") as pipe, open(path, "rb") as source:
        try:
            pipe.write(source.read())
        except BrokenPipeError:
            pass

results = []
for args, stdin_path in json.loads(sys.argv[1]):
    out, err, code = io.StringIO(), io.StringIO(), 0
    saved = sys.stdin
    feeder = None
    if stdin_path:
        read_end, write_end = os.pipe()
        feeder = threading.Thread(target=feed, args=(write_end, stdin_path))
        feeder.start()
        sys.stdin = io.TextIOWrapper(open(read_end, "rb"))
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main(args)
    except SystemExit as exc:
        code = exc.code
    finally:
        if feeder is not None:
            sys.stdin.close()
            feeder.join()
        sys.stdin = saved
    results.append([code, out.getvalue(), err.getvalue()])
print(json.dumps(results))
"""


def _run_all(runs: list[tuple[list[str], str | None]]) -> list[tuple[int, str, str]]:
    """Run CLI commands under the memory limit and the timeout; (exit code, stdout, stderr)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("IMUFDI_")}
    env["PYTHONPATH"] = str(ROOT)
    result = subprocess.run(
        [sys.executable, "-c", _RUNNER, json.dumps(runs)],
        capture_output=True,
        timeout=TIMEOUT_S,
        preexec_fn=_limit_memory,
        env=env,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    return [tuple(r) for r in json.loads(result.stdout)]


def _schema_bomb_texts() -> dict[str, bytes]:
    levels = "".join(f"===\nMSG: pkg/T{i}\npkg/T{i + 1}[4] a\n" for i in range(30))
    return {
        "header-array": b"std_msgs/Header[1000000000] h\n" + IMU_SCHEMA,
        "string-array": b"string[100000000] s\n" + IMU_SCHEMA,
        "4^30-leaves": b"pkg/T0 t\n"
        + IMU_SCHEMA
        + levels.encode()
        + b"===\nMSG: pkg/T30\nfloat64 x\n",
        "recursive": b"pkg/R r\n" + IMU_SCHEMA + b"===\nMSG: pkg/R\npkg/R r\n",
    }


def _bombs() -> dict[str, bytes]:
    mib256 = 256 << 20
    bombs = {
        "lz4-256MiB-declared": wrap(zero_chunk(mib256, "lz4")),
        "lz4-256MiB-declared-1000": wrap(zero_chunk(mib256, "lz4", declared=1000)),
        "zstd-256MiB-declared": wrap(zero_chunk(mib256, "zstd")),
        "zstd-256MiB-declared-1000": wrap(zero_chunk(mib256, "zstd", declared=1000)),
        "zstd-60MiB-of-zeros-within-limit": wrap(zero_chunk(60 << 20, "zstd")),
    }
    for name, text in _schema_bomb_texts().items():
        bombs[f"schema-{name}"] = imu_file_with_schema(text)
    return bombs


def _one_line(stderr: str, prefix: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(prefix), lines
    assert not lines[0].rstrip().endswith(":") and "Traceback" not in stderr
    return lines[0]


def _huge_record_length() -> tuple[bytes, int]:
    """A valid file whose third chunk claims 77,309,414,278 bytes, and that chunk's offset."""
    data = imu_file(chunked=True, n_imus=2, n_samples=60, chunk_size=2000)
    position, chunks = 8, []
    while data[position] != 0x0F:
        (length,) = struct.unpack_from("<Q", data, position + 1)
        chunks += [position] if data[position] == 0x06 else []
        position += 9 + length
    bad = bytearray(data)
    bad[chunks[2] + 1 : chunks[2] + 9] = struct.pack("<Q", 77_309_414_278)
    return bytes(bad), chunks[2]


@pytest.mark.slow
def test_bombs_exit_3_under_memory_and_time_limits(tmp_path) -> None:
    """Every bomb exits 3 with one line (also through a pipe with --strict); a huge record
    length is read past (exit 0, a warning naming its offset, reading resumed at the next
    chunk of the chunk index), exit 3 with --strict.
    All in one process limited to 1 GB of address space and a timeout."""
    runs: list[tuple[list[str], str | None]] = []
    names = []
    for name, data in _bombs().items():
        path = tmp_path / f"{name}.mcap"
        path.write_bytes(data)
        runs += [(["info", str(path)], None), (["info", "--strict", "-"], str(path))]
        names += [name, f"{name} (stdin, --strict)"]
    bad, offset = _huge_record_length()
    (tmp_path / "bad.mcap").write_bytes(bad)
    runs += [(["info", str(tmp_path / "bad.mcap")], None)]
    runs += [(["info", "--strict", "-"], str(tmp_path / "bad.mcap"))]
    results = _run_all(runs)
    for name, (code, _, stderr) in zip(names, results):
        assert code == 3, (name, stderr)
        _one_line(stderr, "imufdi: error: ")
    (code, _, warned), (strict_code, _, stderr) = results[-2:]
    assert code == 0
    warnings = [line for line in warned.splitlines() if line.startswith("warning:")]  # stderr
    assert f"at byte {offset} claims 77309414278 bytes" in warnings[0]
    assert "resumed reading at the chunk at byte" in warnings[1]
    assert strict_code == 3
    assert "claims 77309414278 bytes" in _one_line(stderr, "imufdi: error: ")


def test_schema_bombs_compile_within_the_field_budget() -> None:
    for name, text in _schema_bomb_texts().items():
        try:
            codec = CdrCodec("sensor_msgs/msg/Imu", text)
        except McapInputError as err:
            assert name == "recursive" and "recursive" in str(err)
            continue
        # the bomb is the first field: nothing after it is laid out, nothing is expanded
        assert codec.layout.leaves == {} and codec.layout.steps[-1].kind == "opaque", name


def test_fields_before_a_huge_array_stay_readable() -> None:
    text = IMU_SCHEMA.replace(
        b"geometry_msgs/Vector3 linear_acceleration",
        b"geometry_msgs/Vector3 linear_acceleration\nstring[100000000] names",
    )
    codec = CdrCodec("sensor_msgs/msg/Imu", text)
    assert "linear_acceleration.z" in codec.layout.leaves
    assert "linear_acceleration_covariance" not in codec.layout.leaves
    assert len(codec.layout.leaves) < 100


def test_large_fixed_arrays_of_primitives_are_one_field() -> None:
    codec = CdrCodec("pkg/msg/A", "float64[1000000] samples\nuint8 flag\n")
    assert codec.layout.leaves["samples"].count == 1_000_000
    assert codec.layout.leaves["flag"].offset == 8_000_000


def test_general_decoder_is_bounded() -> None:
    defs = parse_ros2msg("pkg/msg/A", "pkg/E[1000000000] e\n===\nMSG: pkg/E\n")
    with pytest.raises(McapInputError, match="IMUFDI_MAX_SCHEMA_FIELDS"):
        decode_cdr_message(defs, "pkg/msg/A", b"\x00\x01\x00\x00")
    seq = parse_ros2msg("pkg/msg/B", "pkg/E[] e\n===\nMSG: pkg/E\n")
    payload = b"\x00\x01\x00\x00" + struct.pack("<I", 4_000_000_000)
    with pytest.raises(McapInputError, match="4000000000 elements"):
        decode_cdr_message(seq, "pkg/msg/B", payload)


def test_limits_from_environment(monkeypatch) -> None:
    monkeypatch.setenv("IMUFDI_MAX_CHUNK_BYTES", "1000")
    monkeypatch.setenv("IMUFDI_MAX_SCHEMA_DEPTH", "3")
    limits = ReaderLimits.from_env()
    assert limits.max_chunk_bytes == 1000 and limits.max_schema_depth == 3
    data = imu_file(chunked=True, n_imus=2, n_samples=30, chunk_size=4000)
    with McapSource(io.BytesIO(data)) as source:
        assert sum(len(b) for b in source.batches()) == 0
    assert "over the limit of 1000 (IMUFDI_MAX_CHUNK_BYTES)" in source.warnings[0]
    monkeypatch.setenv("IMUFDI_MAX_CHUNK_BYTES", "lots")
    with pytest.raises(UsageError, match="IMUFDI_MAX_CHUNK_BYTES"):
        ReaderLimits.from_env()


def test_general_decoder_reads_large_primitive_arrays_at_once() -> None:
    defs = parse_ros2msg("pkg/msg/A", "uint8 flag\nfloat64[200000] samples\nint32[] tail\n")
    values = np.arange(200_000, dtype="<f8")
    payload = (
        b"\x00\x01\x00\x00"
        + b"\x01"
        + b"\x00" * 7  # align to 8
        + values.tobytes()
        + struct.pack("<Iii", 2, -5, 7)
    )
    decoded = decode_cdr_message(defs, "pkg/msg/A", payload)
    assert decoded["flag"] == 1 and decoded["tail"] == [-5, 7]
    np.testing.assert_array_equal(decoded["samples"], values)
    with pytest.raises(McapInputError, match="past its end"):
        decode_cdr_message(defs, "pkg/msg/A", payload[:1000])
