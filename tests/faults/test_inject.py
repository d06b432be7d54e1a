"""Tests of imufdi_cli.faults.inject: inject_file, MCAP in, MCAP out."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli import mcapio
from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import FaultSpecError
from imufdi_cli.faults import (
    METADATA_NAME,
    TRUTH_TOPIC,
    FaultInjector,
    faults_from_metadata,
    inject_file,
    parse_fault_spec,
)
from tests.faults.conftest import RATE_HZ, T0_NS, make_block, rel_s

# --- inject_file: MCAP in, MCAP out --------------------------------------------------------

needs_mcapio = pytest.mark.skipif(
    not all(hasattr(mcapio, n) for n in ("write_array", "read_array", "patch_imu")),
    reason="imufdi_cli.mcapio does not export its API yet",
)


def sha256(path) -> str:
    with open(path, "rb") as handle:
        return hashlib.sha256(handle.read()).hexdigest()


@pytest.fixture
def log_file(tmp_path):
    array = ArrayConfig.co_aligned(3, RATE_HZ, noise={"gyro": 0.01})
    block = make_block(500, n_imus=3)
    block.mag = None
    path = tmp_path / "clean.mcap"
    mcapio.write_array(str(path), array, block)
    return path, array, block


def _messages_by_topic(path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    with mcapio.McapSource(str(path)) as source:
        for batch in source.batches():
            for i in range(len(batch)):
                topic = source.channels[int(batch.channel_id[i])].topic
                out.setdefault(topic, []).append((int(batch.log_time[i]), batch.payload(i)))
    return out


_FILE_SPECS = [
    "step:imu0.gyro.x,at=1s,until=3s,amp=0.9deg/s",
    "noise:imu2.accel,at=0.5s,factor=3,sigma0=0.1m/s^2",
    "spikes:imu2.gyro.z,rate=5Hz,amp=1deg/s",
]


@needs_mcapio
def test_inject_file_values_truth_and_metadata(tmp_path, log_file) -> None:
    path, array, block = log_file
    digest = sha256(path)
    out = tmp_path / "faulty.mcap"
    result = inject_file(str(path), str(out), _FILE_SPECS, [], seed=5)
    assert sha256(path) == digest  # input untouched
    assert result.t0_ns == T0_NS and result.truth_messages == 4
    assert result.imu_topics == ["/imu0/data_raw", "/imu1/data_raw", "/imu2/data_raw"]
    _, faulty = mcapio.read_array(str(out))
    faults = [parse_fault_spec(s, array) for s in _FILE_SPECS]
    expected = FaultInjector(faults, array, seed=5, t0_ns=T0_NS).apply_block(block)
    assert_array_equal(faulty.gyro, expected.gyro)
    assert_array_equal(faulty.accel, expected.accel)
    # unfaulted IMU messages are byte-identical
    before, after = _messages_by_topic(path), _messages_by_topic(out)
    assert after["/imu1/data_raw"] == before["/imu1/data_raw"]
    assert after["/imu0/data_raw"] != before["/imu0/data_raw"]
    truth = mcapio.read_json_topic(str(out), TRUTH_TOPIC)
    assert [(t, e["event"], e["fault_id"]) for t, e in truth] == [
        (T0_NS, "start", "f2"),
        (T0_NS + 500_000_000, "start", "f1"),
        (T0_NS + 1_000_000_000, "start", "f0"),
        (T0_NS + 3_000_000_000, "end", "f0"),
    ]
    with mcapio.McapSource(str(out)) as source:
        meta = source.metadata
    assert "imufdi.array" in meta
    recorded = faults_from_metadata(meta[METADATA_NAME])
    assert [f.spec for f in recorded] == _FILE_SPECS
    assert json.loads(meta[METADATA_NAME]["json"])["seed"] == 5


@needs_mcapio
def test_inject_file_deterministic_bytes(tmp_path, log_file) -> None:
    path, _, _ = log_file
    a, b, c = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"
    inject_file(str(path), str(a), _FILE_SPECS, [], seed=1)
    inject_file(str(path), str(b), _FILE_SPECS, [], seed=1)
    inject_file(str(path), str(c), _FILE_SPECS, [], seed=2)
    assert sha256(a) == sha256(b) != sha256(c)


@needs_mcapio
@pytest.mark.parametrize(
    ("specs", "message"),
    [
        (["step:imu3.gyro.x,amp=1deg/s"], "IMU index 3 is past the array"),
        (["step:imu0.gyro.x,at=9s,amp=1deg/s"], "is after the log ends"),
        (["step:imu0.gyro.x,amp=1deg/s", "stuck:imu0.gyro.q"], "axis 'q'"),
        ([], "needs at least one --fault"),
    ],
)
def test_inject_file_validates_before_writing(tmp_path, log_file, specs, message) -> None:
    path, _, _ = log_file
    out = tmp_path / "never.mcap"
    with pytest.raises(FaultSpecError, match=message):
        inject_file(str(path), str(out), specs, [], seed=0)
    assert list(tmp_path.iterdir()) == [path]


@needs_mcapio
def test_inject_twice_keeps_previous_truth(tmp_path, log_file) -> None:
    path, _, _ = log_file
    once, twice = tmp_path / "once.mcap", tmp_path / "twice.mcap"
    toml = tmp_path / "more.toml"
    toml.write_text('[[fault]]\nmodel = "stuck"\nsensor = "imu1.gyro"\nat = "2s"\n')
    inject_file(str(path), str(once), _FILE_SPECS[:1], [], seed=1)
    result = inject_file(str(once), str(twice), [], [str(toml)], seed=2)
    assert [f.id for f in result.previous_faults] == ["f0"]
    assert [f.id for f in result.faults] == ["f1"]
    truth = mcapio.read_json_topic(str(twice), TRUTH_TOPIC)
    assert sorted(e["fault_id"] for _, e in truth) == ["f0", "f0", "f1"]
    with mcapio.McapSource(str(twice)) as source:
        recorded = faults_from_metadata(source.metadata[METADATA_NAME])
    assert [(f.id, f.model) for f in recorded] == [("f0", "step"), ("f1", "stuck")]


@needs_mcapio
def test_inject_refuses_to_overwrite_input(log_file) -> None:
    path, _, _ = log_file
    with pytest.raises(Exception, match="is the input file") as info:
        inject_file(str(path), str(path), _FILE_SPECS, [], seed=0)
    assert info.value.exit_code == 2  # type: ignore[attr-defined]


@needs_mcapio
def test_inject_from_stdin_matches_file_input(tmp_path, log_file, monkeypatch) -> None:
    import io
    import sys

    path, _, _ = log_file
    from_file, from_stdin = tmp_path / "file.mcap", tmp_path / "stdin.mcap"
    inject_file(str(path), str(from_file), _FILE_SPECS, [], seed=3)
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(path.read_bytes())))
    inject_file("-", str(from_stdin), _FILE_SPECS, [], seed=3)
    assert sha256(from_file) == sha256(from_stdin)


@needs_mcapio
def test_inject_magnetometer(tmp_path) -> None:
    array = ArrayConfig.co_aligned(2, RATE_HZ, sensors=("gyro", "accel", "mag"))
    block = make_block(300, n_imus=2)
    path, out = tmp_path / "mag.mcap", tmp_path / "mag-faulty.mcap"
    mcapio.write_array(str(path), array, block)
    spec = "drift:imu1.mag,at=1s,rate=2uT/s"
    inject_file(str(path), str(out), [spec], [], seed=0)
    _, faulty = mcapio.read_array(str(out))
    t = rel_s(block)
    ramp = np.where(t >= 1.0, 2e-6 * (t - 1.0), 0.0)
    assert_allclose(
        faulty.mag[:, 1, :] - block.mag[:, 1, :], ramp[:, None] * np.ones(3), atol=1e-15
    )
    assert_array_equal(faulty.mag[:, 0, :], block.mag[:, 0, :])
    assert_array_equal(faulty.gyro, block.gyro)


@needs_mcapio
def test_inject_fault_on_missing_topic(tmp_path, log_file) -> None:
    path, _, _ = log_file
    # a log whose recorded array claims magnetometers it carries no topic for
    mag_array = ArrayConfig.co_aligned(3, RATE_HZ, sensors=("gyro", "accel", "mag"))
    no_mag = tmp_path / "nomag.mcap"
    with mcapio.McapSource(str(path)) as source, mcapio.McapWriter(str(no_mag)) as writer:
        writer.copy_channels(source.channels)
        writer.add_metadata("imufdi.array", {"json": mag_array.to_json()})
        for batch in source.batches():
            writer.add_batch(batch)
    out = tmp_path / "never.mcap"
    with pytest.raises(FaultSpecError, match="no mag topic for imu1"):
        inject_file(str(no_mag), str(out), ["step:imu1.mag.x,amp=1uT"], [], seed=0)
    assert not out.exists()
