"""campaign.executors: start method, chunking, pool workers writing their own results."""

from __future__ import annotations

import json
import textwrap
import threading

import pytest

from imufdi_cli.campaign import WORKER_THREAD_ENV, LocalExecutor, load_spec, run_key
from imufdi_cli.campaign.executors import MAX_CHUNK, chunk_size, start_method
from imufdi_cli.campaign.run import execute_run, run_order

SPEC = """
[campaign]
seeds = [0, 1, 2]
calibrate = "0s:0.6s"

[[base]]
preset = "paper-table4"
options = { duration = "1s" }

[[base]]
preset = "conical6"
options = { duration = "1s" }

[[fault]]
model = "step"
sensor = "imu0.gyro.z"
at = "0.7s"
amp = ["0.3deg/s", "0.9deg/s"]

[[detector]]
name = "glt"
"""


@pytest.fixture
def runs(tmp_path):
    path = tmp_path / "spec.toml"
    path.write_text(textwrap.dedent(SPEC))
    return sorted(load_spec(path).runs, key=run_order)


def test_chunk_size_starts_at_one_and_targets_half_a_second_of_work():
    assert chunk_size([], 100, 2) == 1  # nothing known yet
    assert chunk_size([0.1] * 5, 100, 2) == 5  # 0.5 s / 0.1 s
    assert chunk_size([2.0], 100, 2) == 1  # long runs go one by one
    assert chunk_size([1e-4], 10_000, 2) == MAX_CHUNK
    assert chunk_size([0.0], 10_000, 2) == MAX_CHUNK
    # the end of the queue still spreads over the workers: 8 left, 2 workers -> 1
    assert chunk_size([1e-4], 8, 2) == 1
    assert chunk_size([1e-4], 40, 2) == 5


def test_start_method_forks_only_a_single_threaded_pinned_process(monkeypatch):
    for name, value in WORKER_THREAD_ENV.items():
        monkeypatch.setenv(name, value)
    if threading.active_count() == 1:
        assert start_method() == "fork"
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait)
    thread.start()
    try:
        assert start_method() in ("forkserver", "spawn")
    finally:
        stop.set()
        thread.join()
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    assert start_method() in ("forkserver", "spawn")


def _run_files(runs_dir):
    return {p.name: p.read_bytes() for p in sorted(runs_dir.glob("*.json"))}


@pytest.mark.slow  # a pool of two worker processes, 2 s
@pytest.mark.parametrize("method", ["fork", "forkserver"])
def test_pool_workers_write_the_same_results_as_this_process(runs, tmp_path, method):
    serial = tmp_path / "serial"
    serial.mkdir()
    statuses = list(LocalExecutor(1).run(runs, serial))
    pooled = tmp_path / "pooled"
    pooled.mkdir()
    executor = LocalExecutor(2, method=method)
    try:
        executor.start(len(runs))
        pooled_statuses = list(executor.run(runs, pooled))
    finally:
        executor.close()
    assert sorted(s["key"] for s in pooled_statuses) == sorted(s["key"] for s in statuses)
    assert all(s["ok"] and s["seconds"] >= 0 for s in pooled_statuses)
    assert set(pooled_statuses[0]) == {"key", "ok", "seconds"}  # statuses, not results
    files = _run_files(pooled)
    assert len(files) == len(runs)
    # the figures are the same; only the measured seconds differ
    for name, data in _run_files(serial).items():
        a, b = json.loads(data), json.loads(files[name])
        a.pop("seconds"), b.pop("seconds")
        assert a == b


def test_runs_grouped_by_base_and_seed_share_one_simulation(runs):
    from imufdi_cli.campaign import run as run_module

    run_module._simulated.cache_clear()
    for desc in runs:
        assert execute_run(desc)["ok"]
    info = run_module._simulated.cache_info()
    assert info.misses == 6  # 2 bases x 3 seeds, each simulated once
    assert info.hits == len(runs) - 6
    # the cached base log is not modified by the runs that used it
    first = runs[0]
    again = execute_run(first)
    run_module._simulated.cache_clear()
    fresh = execute_run(first)
    again.pop("seconds"), fresh.pop("seconds")
    assert again == fresh and again["key"] == run_key(first)
