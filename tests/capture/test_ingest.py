import json

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.capture import CaptureEncoder, Corruption, encode_capture, ingest, load_layout
from imufdi_cli.errors import CaptureError

from .conftest import random_block

mcapio = pytest.importorskip("imufdi_cli.mcapio")


def test_ingest_writes_samples_array_and_stats(tmp_path):
    layout = load_layout("mpu6500-array")
    block = random_block(200, 3, seed=5)
    encoded = encode_capture(
        block, layout, corrupt=Corruption(garbage=2, flipped=1), rng=np.random.default_rng(1)
    )
    out = tmp_path / "out.mcap"
    stats = ingest(encoded.data, out, layout=layout, array=None)
    assert stats.frames_ok == 199 and stats.frames_bad_checksum == 1
    array, read = mcapio.read_array(out)
    assert array.n_imus == 3 and array.rate_hz == pytest.approx(100.0)
    assert_array_equal(read.t_ns, block.t_ns[encoded.intact])
    assert_allclose(
        read.gyro, block.gyro[encoded.intact], atol=0.5 * layout.record[4].scale * 1.0001
    )
    with mcapio.McapSource(out) as source:
        metadata = source.metadata
    record = json.loads(metadata["imufdi.ingest"]["json"])
    assert record["stats"]["frames_ok"] == 199
    assert record["layout"]["name"] == "mpu6500-array"


def test_ingest_checks_the_array_and_empty_captures(tmp_path):
    layout = load_layout("mpu6500-array")
    data = encode_capture(random_block(10, 2), layout).data
    with pytest.raises(CaptureError, match="array config 4"):
        ingest(data, tmp_path / "a.mcap", layout=layout, array=ArrayConfig.co_aligned(4))
    with pytest.raises(CaptureError, match="no frames"):
        ingest(b"\x00" * 100, tmp_path / "b.mcap", layout=layout)
    assert not (tmp_path / "b.mcap").exists()


def test_streaming_encoder_continues_the_counter():
    from imufdi_cli.capture import parse_capture

    block = random_block(100, 2)
    encoder = CaptureEncoder(corrupt=True, seed=1)
    data = b"".join(encoder.encode(block.slice(i, i + 50)) for i in (0, 50)) + encoder.finish()
    blocks, stats = parse_capture(data, load_layout("mpu6500-array"))
    list(blocks)
    assert {k: getattr(stats, k) for k in encoder.expected} == encoder.expected


def test_chunk_sizes_change_the_layout_not_the_samples(tmp_path):
    """Small read rounds and MCAP chunks that cut samples: the same samples as the
    defaults, every message found by the mcap package's indexed reader, in time order."""
    from mcap.reader import make_reader

    layout = load_layout("mpu6500-array")
    block = random_block(300, 4, seed=2)
    corrupt = Corruption(garbage=2, cut=1)
    data = encode_capture(block, layout, corrupt=corrupt, rng=np.random.default_rng(4)).data
    default = tmp_path / "default.mcap"
    small = tmp_path / "small.mcap"
    ingest(data, default, layout=layout)
    ingest(data, small, layout=layout, chunk_size=999, mcap_chunk_size=3000)
    _, expected = mcapio.read_array(default)
    _, read = mcapio.read_array(small)
    assert_array_equal(read.t_ns, expected.t_ns)
    assert read.gyro.tobytes() == expected.gyro.tobytes()  # type: ignore[union-attr]
    assert read.accel.tobytes() == expected.accel.tobytes()  # type: ignore[union-attr]
    with small.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and len(summary.chunk_indexes) > 100
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=False)]
    assert len(times) == 4 * len(expected.t_ns) and times == sorted(times)
    with mcapio.McapSource(small) as source:
        record = json.loads(source.metadata["imufdi.ingest"]["json"])
    assert record["parameters"]["mcap_chunk_size"] == 3000
