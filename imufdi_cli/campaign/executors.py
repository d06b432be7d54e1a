"""Where runs execute: this process, a local process pool, or dask.distributed."""

from __future__ import annotations

import itertools
import os
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from typing import Any

from imufdi_cli.campaign.run import execute_run
from imufdi_cli.errors import UsageError

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass


#: BLAS/OpenMP thread caps for worker processes: on a small machine, one BLAS thread per
#: worker process; several threads per worker only fight over the same cores.
WORKER_THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


class _Executor:
    """submit(desc) -> future-like; results streamed back with as_completed semantics."""

    def run(self, runs: Sequence[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        raise NotImplementedError

    def close(self) -> None:
        pass


@contextmanager
def worker_thread_env() -> Iterator[None]:
    """Set :data:`WORKER_THREAD_ENV` in ``os.environ`` for the block (restored after).

    Worker processes started inside the block (spawned pool workers, dask nannies) inherit
    it before they import numpy, so each uses one BLAS thread.
    """
    saved = {name: os.environ.get(name) for name in WORKER_THREAD_ENV}
    os.environ.update(WORKER_THREAD_ENV)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _init_worker(parent_pid: int) -> None:
    """Pool worker initializer: one BLAS thread, and exit when the parent is gone.

    A campaign process killed with SIGKILL cannot stop its pool; the watchdog makes the
    orphaned workers exit instead of waiting forever for work.
    """
    os.environ.update(WORKER_THREAD_ENV)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="imufdi-parent-watchdog", daemon=True).start()


class LocalExecutor(_Executor):
    """A process pool on this machine (``--jobs``); ``jobs=1`` runs in this process.

    Workers are *spawned* (fresh interpreters) with :data:`WORKER_THREAD_ENV` set before
    they import numpy; at most ``2 * jobs`` runs are in flight, so an interruption loses
    little.
    """

    def __init__(self, jobs: int, *, pool: bool | None = None) -> None:
        if jobs < 1:
            raise UsageError(f"--jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.pool = pool  # None: a pool when jobs > 1; True/False forces it (benchmarks)

    def run(self, runs: Sequence[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        use_pool = self.jobs > 1 and len(runs) > 1 if self.pool is None else self.pool
        if not use_pool:
            for desc in runs:
                yield execute_run(desc)
            return
        import multiprocessing

        context = multiprocessing.get_context("spawn")
        with worker_thread_env():
            pool = ProcessPoolExecutor(
                max_workers=min(self.jobs, len(runs)),
                mp_context=context,
                initializer=_init_worker,
                initargs=(os.getpid(),),
            )
            try:
                pending: set[Future[dict[str, Any]]] = set()
                queue = iter(runs)
                for desc in itertools.islice(queue, 2 * self.jobs):
                    pending.add(pool.submit(execute_run, desc))
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:
                        nxt = next(queue, None)
                        if nxt is not None:
                            pending.add(pool.submit(execute_run, nxt))
                        yield future.result()
            finally:
                pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(_Executor):
    """dask.distributed: ``tcp://host:port`` (an existing scheduler) or ``local:N``
    (a LocalCluster of N single-threaded worker processes on loopback)."""

    def __init__(self, scheduler: str) -> None:
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError as err:
            raise UsageError(
                "--scheduler needs dask.distributed: pip install 'imufdi-cli[dask]'"
            ) from err
        self.cluster = None
        if scheduler.startswith("local:"):
            try:
                workers = int(scheduler.split(":", 1)[1])
                if workers < 1:
                    raise ValueError
            except ValueError:
                raise UsageError(
                    f"--scheduler {scheduler!r}: local:N needs N >= 1 workers"
                ) from None
            with worker_thread_env():
                self.cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                )
            self.client = Client(self.cluster)
        elif scheduler.startswith("tcp://"):
            try:
                self.client = Client(scheduler, timeout=20)
            except OSError as err:
                raise UsageError(f"--scheduler {scheduler}: cannot connect ({err})") from err
        else:
            raise UsageError(
                f"--scheduler {scheduler!r}: valid forms are tcp://HOST:PORT and local:N"
            )

    def run(self, runs: Sequence[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        from dask.distributed import as_completed

        futures = [self.client.submit(execute_run, desc, pure=False) for desc in runs]
        for future in as_completed(futures):
            yield future.result()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
