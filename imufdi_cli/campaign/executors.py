"""Where runs execute: this process, a local process pool, or dask.distributed."""

from __future__ import annotations

import gc
import os
import threading
import time
from collections import deque
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.campaign.run import execute_run, run_and_store, store_result
from imufdi_cli.errors import UsageError

#: BLAS/OpenMP thread caps for worker processes: on a small machine, one BLAS thread per
#: worker process; several threads per worker only fight over the same cores.
WORKER_THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


#: A pool worker is sent runs in chunks of about this many seconds of work (estimated
#: from the runs finished so far), so that the per-task cost of the pool (pickling, pipes,
#: wake-ups: about a millisecond) stays small against short runs.
CHUNK_SECONDS = 0.5
#: Most runs in one chunk (progress is reported per chunk).
MAX_CHUNK = 16


class _Executor:
    """Runs descriptions somewhere and writes each result to ``runs_dir/<key>.json`` as
    soon as it is known; :meth:`run` yields their statuses (:func:`store_result`) as they
    finish."""

    def start(self, runs: int) -> None:
        """Get ready for about ``runs`` runs (e.g. start worker processes)."""

    def run(self, runs: Sequence[dict[str, Any]], runs_dir: Path) -> Iterator[dict[str, Any]]:
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


def start_method() -> str:
    """How pool workers start: ``fork`` when this process has one thread and its BLAS is
    already pinned to one thread (as the ``imufdi`` command does), so that workers start in
    milliseconds with every module the spec loaded already imported; otherwise
    ``forkserver`` (forking a multi-threaded process is unsafe), else ``spawn``."""
    import multiprocessing

    methods = multiprocessing.get_all_start_methods()
    pinned = all(os.environ.get(k) == v for k, v in WORKER_THREAD_ENV.items())
    if "fork" in methods and threading.active_count() == 1 and pinned:
        return "fork"
    return "forkserver" if "forkserver" in methods else "spawn"


def _init_worker(parent_pid: int | None, forked: bool) -> None:
    """Pool worker initializer: one BLAS thread, default signal handling, and exit when
    the parent is gone.

    A forked worker inherits the campaign's Python signal handlers (the CLI turns SIGTERM
    into an exception); it gets the defaults of a fresh interpreter back. A campaign process
    killed with SIGKILL cannot stop its pool; the watchdog makes the orphaned workers exit
    instead of waiting forever for work: it watches the worker's parent (the campaign, or
    for ``forkserver`` the server, which exits with the campaign) and exits when the worker
    is re-parented. ``parent_pid``: the campaign's pid when it is the parent (None for
    forkserver), to notice a campaign that died before the worker started.
    """
    os.environ.update(WORKER_THREAD_ENV)
    if forked:
        import signal

        signal.signal(signal.SIGINT, signal.default_int_handler)
        for name in ("SIGTERM", "SIGHUP"):
            if hasattr(signal, name):
                signal.signal(getattr(signal, name), signal.SIG_DFL)
    watched = os.getppid() if parent_pid is None else parent_pid

    def watch() -> None:
        while os.getppid() == watched:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="imufdi-parent-watchdog", daemon=True).start()


def chunk_size(seconds: Sequence[float], queued: int, jobs: int) -> int:
    """Runs in the next chunk: about :data:`CHUNK_SECONDS` of work at the median run time
    of the last 50 runs (1 before any has finished), at most :data:`MAX_CHUNK`, and small
    enough that the last quarter of the queue still spreads over every worker."""
    if not seconds:
        return 1
    typical = float(np.median(seconds[-50:]))
    size = MAX_CHUNK if typical <= 0.0 else int(CHUNK_SECONDS / typical)
    return max(1, min(size, MAX_CHUNK, queued // (4 * jobs)))


class LocalExecutor(_Executor):
    """A process pool on this machine (``--jobs``); ``jobs=1`` runs in this process.

    Workers start with :func:`start_method` (fork from the campaign process where safe)
    and :data:`WORKER_THREAD_ENV`; they stay up for the whole campaign, take runs in
    chunks (:func:`chunk_size`) in the order given (the campaign groups them by base and
    seed so that a worker simulates a base log once for several runs) and write each
    result themselves, so the campaign process only counts. At most ``2 * jobs`` chunks
    are queued; an interruption loses only the runs being executed.
    """

    def __init__(self, jobs: int, *, pool: bool | None = None, method: str | None = None) -> None:
        if jobs < 1:
            raise UsageError(f"--jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.pool = pool  # None: a pool when jobs > 1; True/False forces it (benchmarks)
        self.method = method  # None: start_method()
        self._pool: ProcessPoolExecutor | None = None

    def _use_pool(self, runs: int) -> bool:
        return self.jobs > 1 and runs > 1 if self.pool is None else self.pool

    def start(self, runs: int) -> None:
        """Start the worker processes now (``min(jobs, runs)`` of them), before the
        campaign opens its lock file, which workers then do not inherit."""
        if self._pool is not None or not self._use_pool(runs):
            return
        import multiprocessing

        method = self.method or start_method()
        context = multiprocessing.get_context(method)
        if method == "forkserver":
            context.set_forkserver_preload(["imufdi_cli.campaign.run"])
        workers = max(1, min(self.jobs, runs))
        if method == "fork":
            # objects of this process go to a permanent generation that the workers'
            # collector never walks: no copy-on-write of the parent's pages by GC
            gc.freeze()
        with worker_thread_env():
            self._pool = ProcessPoolExecutor(
                max_workers=workers,
                mp_context=context,
                initializer=_init_worker,
                initargs=(None if method == "forkserver" else os.getpid(), method == "fork"),
            )
            # start every worker now (fork: all at once, while this process is single-threaded)
            try:
                for future in [self._pool.submit(os.getpid) for _ in range(workers)]:
                    future.result()
            finally:
                gc.unfreeze()  # this process collects as before

    def run(self, runs: Sequence[dict[str, Any]], runs_dir: Path) -> Iterator[dict[str, Any]]:
        if not self._use_pool(len(runs)):
            for desc in runs:
                yield store_result(execute_run(desc), runs_dir)
            return
        self.start(len(runs))
        assert self._pool is not None
        queue = deque(runs)
        seconds: list[float] = []
        pending: set[Future[list[dict[str, Any]]]] = set()

        def submit() -> None:
            size = chunk_size(seconds, len(queue), self.jobs)
            chunk = [queue.popleft() for _ in range(min(size, len(queue)))]
            assert self._pool is not None
            pending.add(self._pool.submit(run_and_store, chunk, str(runs_dir)))

        while queue and len(pending) < 2 * self.jobs:
            submit()
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                statuses = future.result()
                seconds += [float(s["seconds"]) for s in statuses]
                if queue:
                    submit()
                yield from statuses

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(_Executor):
    """dask.distributed: ``tcp://host:port`` (an existing scheduler) or ``local:N``
    (a LocalCluster of N single-threaded worker processes on loopback)."""

    def __init__(self, scheduler: str) -> None:
        # the form is checked before dask.distributed is imported (about 1 s of CPU):
        # a mistyped --scheduler is a usage error whether or not dask is installed
        workers = 0
        if scheduler.startswith("local:"):
            try:
                workers = int(scheduler.split(":", 1)[1])
                if workers < 1:
                    raise ValueError
            except ValueError:
                raise UsageError(
                    f"--scheduler {scheduler!r}: local:N needs N >= 1 workers"
                ) from None
        elif not scheduler.startswith("tcp://"):
            raise UsageError(
                f"--scheduler {scheduler!r}: valid forms are tcp://HOST:PORT and local:N"
            )
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError as err:
            raise UsageError(
                "--scheduler needs dask.distributed: pip install 'imufdi-cli[dask]'"
            ) from err
        self.cluster = None
        if workers:
            with worker_thread_env():
                self.cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                )
            self.client = Client(self.cluster)
        else:
            try:
                self.client = Client(scheduler, timeout=20)
            except OSError as err:
                raise UsageError(f"--scheduler {scheduler}: cannot connect ({err})") from err

    def run(self, runs: Sequence[dict[str, Any]], runs_dir: Path) -> Iterator[dict[str, Any]]:
        from dask.distributed import as_completed

        futures = [self.client.submit(execute_run, desc, pure=False) for desc in runs]
        for future in as_completed(futures):
            # remote workers need not share the results directory: written here
            yield store_result(future.result(), runs_dir)

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
