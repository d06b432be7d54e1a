"""The floor child of benchmarks/bench_detect_floor.py: what ``detect --no-explain`` must
write without any detection (a verbatim copy and glt's status rows), as a valid MCAP."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from mcap.reader import make_reader

import imufdi_cli.api as imufdi
from imufdi_cli.mcapio.status import read_status

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_detect_floor.py"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_detect_floor", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def floor_run(bench: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    work = tmp_path_factory.mktemp("floor")
    log = work / "log.mcap"
    imufdi.simulate(log, preset="paper-table4", duration=3.0, seed=1)
    out = work / "floor.mcap"
    assert bench.main(["--floor-child", str(log), str(out)]) == 0
    return log, out


def _messages(path: Path) -> tuple[dict[str, list[tuple[int, bytes]]], dict[str, int]]:
    """Per topic: (log time, payload) of every message, and the summary's counts."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
        topics: dict[str, list[tuple[int, bytes]]] = {}
        for _, channel, message in reader.iter_messages():
            topics.setdefault(channel.topic, []).append((message.log_time, bytes(message.data)))
    return topics, counts


def test_floor_output_is_the_input_plus_glt_status_rows(floor_run: tuple[Path, Path]) -> None:
    log, out = floor_run
    given, _ = _messages(log)
    written, counts = _messages(out)
    samples = len(given["/imu0/data_raw"])
    assert samples == 300  # 3 s at 100 Hz
    # every input message copied as it is, nothing else but the two status channels
    assert {t: v for t, v in written.items() if not t.startswith("/imufdi/glt/")} == given
    assert sorted(set(written) - set(given)) == ["/imufdi/glt/accel", "/imufdi/glt/gyro"]
    for topic in ("/imufdi/glt/accel", "/imufdi/glt/gyro"):
        assert counts[topic] == len(written[topic]) == samples
        # glt's row for 48 sensors (16 IMUs x 3 axes): mcapio.status's layout, m = 0
        assert {len(data) for _, data in written[topic]} == {36 + 40 + 8 * 48 + 4 + 48 + 4}
    summary = imufdi.info(out)  # what `imufdi info OUT` prints
    assert summary["n_samples"] == samples and not summary["warnings"]


def test_floor_rows_hold_incompressible_chi_square_like_values(
    floor_run: tuple[Path, Path],
) -> None:
    _, out = floor_run
    status = read_status(out)
    assert sorted(status) == [("glt", "accel"), ("glt", "gyro")]
    for rows in status.values():
        assert rows.scores.shape == (300, 48)
        assert not rows.alarm.any()
        assert (rows.isolated == -1).all()
        assert rows.isolated_set is not None and not rows.isolated_set.any()
        assert np.isnan(rows.amplitude).all()
        assert np.unique(rows.threshold).size == 1
        values = np.concatenate([rows.statistic, rows.scores.ravel()])
        assert (values >= 0).all()
        # squared standard normals: mean 1; over 14,700 draws its standard error is
        # sqrt(2 / 14,700) = 0.012, so 0.1 is more than 8 of them
        assert abs(values.mean() - 1.0) < 0.1
        assert np.unique(values).size == values.size  # no repeated values to compress


def test_floor_child_bad_input_is_one_line_exit_3(
    bench: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "not.mcap"
    bad.write_bytes(b"not an MCAP file at all")
    out = tmp_path / "out.mcap"
    assert bench.main(["--floor-child", str(bad), str(out)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")
    assert not out.exists()


@pytest.mark.parametrize(
    ("skip", "copied", "status"),
    [(["copy"], False, True), (["status"], True, False), (["copy", "status"], False, False)],
)
def test_floor_parts_leave_out_what_they_skip(
    bench: ModuleType,
    floor_run: tuple[Path, Path],
    tmp_path: Path,
    skip: list[str],
    copied: bool,
    status: bool,
) -> None:
    log, _ = floor_run
    out = tmp_path / "part.mcap"
    argv = ["--floor-child", str(log), str(out)]
    assert bench.main([*argv, *(a for s in skip for a in ("--skip", s))]) == 0
    given, _ = _messages(log)
    written, _ = _messages(out)
    expected = set(given) if copied else set()
    if status:
        expected |= {"/imufdi/glt/accel", "/imufdi/glt/gyro"}
    assert set(written) == expected
