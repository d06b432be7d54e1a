"""Suite-wide settings and hooks (docs/testing.md: suite time)."""

from __future__ import annotations

import gc
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable, Generator
from pathlib import Path
from types import ModuleType

import pytest

# One BLAS thread per test process, as the `imufdi` command runs (imufdi_cli.cli): the suite
# runs two xdist workers on two cores, and numpy's and scipy's OpenBLAS would each add a
# thread per core to every worker; on thin matrices those threads only spin against the
# other worker (tests/detectors 41-46 -> 32-35 s of CPU, pca-parity's 45-dimension
# eigenvalue test 3-4 -> 0.3 s). Set here, when pytest loads this file and before any test
# module imports numpy; xdist workers inherit it from the controller. A value set by the
# user is kept (no test depends on it: stored float references are compared to tolerances
# that cover the summation order of any thread count, tests/references.py).
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _var in THREAD_VARS:
    os.environ.setdefault(_var, "1")


# No cyclic garbage collection while the test modules are imported and collected: the
# collector kept walking the growing heap of modules, functions and items (about 200 000
# objects, all alive to the end of the session) and took 1.2-1.4 s of the 5.5-7 s of CPU
# of a cold collection (`--collect-only -n 0`, load 7). Reference counting frees what is
# not in a cycle as usual; the cycles made meanwhile are collected once at the end of
# collection (below).
gc.disable()


#: fixtures giving a scipy package as a test's independent oracle (imported on first use)
SCIPY_ORACLES = frozenset({"scipy_stats"})


def _first_use_group(item: pytest.Item) -> int:
    """0 for a test that pays a cost once per process on first use (a Hypothesis test:
    Hypothesis parses the source of every imported ``imufdi_cli`` module for constants to
    try, about 1.4 s of CPU in a fresh process; a test drawing a matplotlib figure: the
    import, about 1 s; a test asking for a scipy oracle fixture (:data:`SCIPY_ORACLES`):
    its import, about 1.2 s for scipy.stats), 1 for the others."""
    from hypothesis import is_hypothesis_test

    function = getattr(item, "obj", None)
    if function is not None and is_hypothesis_test(function):
        return 0
    if item.get_closest_marker("draws") or item.get_closest_marker("campaign_figure"):
        return 0
    if SCIPY_ORACLES & set(getattr(item, "fixturenames", ())):
        return 0
    return 1


#: an item's first-use group (:func:`_first_use_group`), set at collection
_FIRST_USE = pytest.StashKey[int]()


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> Generator[None, None, None]:
    """Hypothesis tests and figure-drawing tests first, each group otherwise in collection
    order (the same order in every xdist worker, as xdist requires). Work stealing gives
    the first worker the first half of the items and steals from the tail, so these run on
    one worker and the other never pays their first-use costs.

    Hypothesis's constants scan is deferred to that worker. Hypothesis's pytest plugin
    (6.155) scans the source of every imported ``imufdi_cli`` module for constants to try
    in its own ``pytest_collection_modifyitems`` when a Hypothesis test was collected
    (about 1.4 s of CPU in a fresh clone, HypothesisWorks/hypothesis#4627), so every
    worker paid it. While the other implementations of this hook run (this one wraps
    them), the scan returns the constants found so far without scanning; the first
    Hypothesis test's provider calls the same function and scans every module imported by
    then (the scan is incremental: modules imported later are scanned on later calls), so
    the tests draw from the same constants, found once, in the worker that runs them."""
    for item in items:
        item.stash[_FIRST_USE] = _first_use_group(item)
    items[:] = sorted(items, key=lambda item: item.stash[_FIRST_USE])  # sorted() is stable
    try:
        from hypothesis.internal.conjecture import providers
    except ImportError:  # another Hypothesis layout: nothing deferred
        providers = None
    scan = getattr(providers, "_get_local_constants", None)
    if scan is None or not hasattr(providers, "_local_constants"):
        yield
        return
    providers._get_local_constants = lambda: providers._local_constants  # type: ignore[union-attr]
    try:
        yield
    finally:
        providers._get_local_constants = scan  # type: ignore[union-attr]


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session: pytest.Session) -> None:
    """Collect the cycles collection made (the collector was off, above), then move what
    is left alive (imported modules, collected items: about 200 000 objects) out of the
    garbage collector's sight: they live to the end of the session, so every full
    collection would walk them again for nothing, as would the five collections pytest
    runs at the end of a session to report unraisable exceptions. Then the collector runs
    as usual for the objects the tests make."""
    gc.collect()
    gc.freeze()
    gc.enable()


@pytest.hookimpl(wrapper=True, trylast=True)
def pytest_runtest_teardown(
    item: pytest.Item, nextitem: pytest.Item | None
) -> Generator[None, None, None]:
    """After a worker's last first-use test (the next item is of the other group, or there
    is none), collect and freeze again, as after collection (:func:`pytest_collection_finish`):
    what those tests left alive is mostly the packages they imported (scipy.stats,
    matplotlib, Hypothesis' engine: about 90 000 objects that live to the end of the
    session), which every later full collection, and the five at the end of the session,
    walked again (the five: about 0.3 s of that worker's CPU, after its last test). As
    after collection, only what survived a full collection is frozen; an object alive here
    that became cyclic garbage later would stay uncollected (a session fixture's cycle)."""
    result = yield
    if item.stash.get(_FIRST_USE, 1) == 0 and (
        nextitem is None or nextitem.stash.get(_FIRST_USE, 1) != 0
    ):
        gc.collect()
        gc.freeze()
    return result


def _bytecode_is_fresh(source: Path, pyc: Path) -> bool:
    """Whether ``pyc`` has the header that Python's import system and pytest's assertion
    rewriter both check (PEP 552, timestamp-based: magic number, zero flags, the source's
    mtime and size, little-endian 32-bit), so the import will load it instead of compiling
    ``source`` again."""
    try:
        with open(pyc, "rb") as file:
            header = file.read(16)
        stat = source.stat()
    except OSError:
        return False
    return (
        len(header) == 16
        and header[:4] == importlib.util.MAGIC_NUMBER
        and header[4:8] == b"\x00\x00\x00\x00"
        and int.from_bytes(header[8:12], "little") == int(stat.st_mtime) & 0xFFFFFFFF
        and int.from_bytes(header[12:16], "little") == stat.st_size & 0xFFFFFFFF
    )


def _sources_to_compile(config: pytest.Config) -> list[tuple[Path, bool]]:
    """``(file, rewritten)`` for the test files of this run's paths (``rewritten``: a file
    pytest imports through its assertion rewriter, i.e. a ``conftest.py`` or one matching
    ``python_files``, when asserts are rewritten) and, when a path is a directory (a run
    of many test files, which import most of the package), every module of
    ``imufdi_cli``."""
    from fnmatch import fnmatch

    rewrite = config.getoption("assertmode") == "rewrite"
    patterns = [*config.getini("python_files"), "conftest.py"]
    root = Path(config.rootpath)
    trees = set()
    for arg in config.args:
        path = Path(arg.split("::", 1)[0])
        trees.add(path if path.is_absolute() else Path(config.invocation_params.dir) / path)
    if any(tree.is_dir() for tree in trees):
        trees.add(root / "imufdi_cli")
    files: dict[Path, bool] = {}
    for tree in trees:
        for file in [tree] if tree.is_file() else sorted(tree.rglob("*.py")):
            in_package = (root / "imufdi_cli") in file.parents
            files[file] = (
                rewrite and not in_package and any(fnmatch(file.name, p) for p in patterns)
            )
    return sorted(files.items())


def _share_cold_bytecode(config: pytest.Config) -> None:
    """xdist workers share out compiling the package and rewriting the test modules'
    asserts (about 0.8 + 2.7 s of CPU in a fresh clone, which every worker paid in full
    for the same files while importing them at collection): before collecting, worker *i*
    of *n* writes the missing or stale bytecode of every *n*-th file by size (pytest's
    rewritten ``*.pytest-*.pyc`` for test files, Python's own ``.pyc`` for the package),
    then checks the others' files and writes any not yet there (two workers may both write
    one file: each write is atomic, as in pytest's and Python's own imports); the imports
    then load the bytecode as in a warm run. Nothing is done where bytecode is not written
    (``PYTHONDONTWRITEBYTECODE``), outside xdist, or with another pytest whose assertion
    rewriter lacks the functions used here; what any test runs is the same either way."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if sys.dont_write_bytecode or count < 2 or not worker.startswith("gw"):
        return
    try:
        from _pytest.assertion.rewrite import (
            PYC_TAIL,
            _rewrite_test,
            _write_pyc,
            assertstate_key,
            get_cache_dir,
        )
    except ImportError:
        return
    import py_compile

    index = int(worker[2:]) % count
    files = sorted(_sources_to_compile(config), key=lambda item: -item[0].stat().st_size)
    mine, others = files[index::count], [f for i, f in enumerate(files) if i % count != index]
    state = config.stash.get(assertstate_key, None)
    for source, rewritten in mine + others[::-1]:
        try:
            if rewritten:
                if state is None:
                    continue
                cache_dir = get_cache_dir(source)
                pyc = cache_dir / (source.name[:-3] + PYC_TAIL)
                if not _bytecode_is_fresh(source, pyc):
                    cache_dir.mkdir(exist_ok=True)
                    stat, code = _rewrite_test(source, config)
                    _write_pyc(state, code, stat, pyc)
            else:
                pyc = Path(importlib.util.cache_from_source(str(source)))
                if not _bytecode_is_fresh(source, pyc):
                    py_compile.compile(
                        str(source),
                        cfile=str(pyc),
                        doraise=True,
                        invalidation_mode=py_compile.PycInvalidationMode.TIMESTAMP,
                    )
        except (OSError, SyntaxError, ValueError, py_compile.PyCompileError):
            continue  # the import will compile it (and report a syntax error) as usual
        except (TypeError, AttributeError):  # another pytest's private functions
            return


@pytest.hookimpl(trylast=True)
def pytest_sessionstart(session: pytest.Session) -> None:
    """The xdist controller collects nothing (its workers do) and so never reaches
    :func:`pytest_collection_finish`: it collects and freezes its modules and plugins here
    (pytest's five collections at its end then walk only what the session made: 0.2 ->
    0.1 s), then gets its collector back. A worker shares out
    the cold bytecode with the other workers before collecting
    (:func:`_share_cold_bytecode`)."""
    if session.config.pluginmanager.has_plugin("dsession"):
        gc.collect()
        gc.freeze()
        gc.enable()
    else:
        _share_cold_bytecode(session.config)


#: whether the running test may draw the campaign figure (it is marked ``campaign_figure``)
_CAMPAIGN_FIGURE = {"draw": False}


def _campaign_plot_curves(summary: object, out: object) -> None:
    """The campaign driver's ``plot_curves`` in a test process: the real figure in tests
    marked ``campaign_figure``, nothing in the others (:func:`pytest_runtest_setup`)."""
    if _CAMPAIGN_FIGURE["draw"]:
        from imufdi_cli.campaign import plots

        plots.plot_curves(summary, out)  # type: ignore[arg-type]


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """A campaign draws ``detection.png`` at its end (matplotlib, 0.3-0.9 s of
    CPU per campaign), which only the tests marked ``campaign_figure`` look at; the others
    (resume, locks, gates, failures, summaries) run a driver that skips the figure. The
    figure itself is tested in ``campaign/test_plots.py`` and, drawn by the driver, in the
    marked test(s). Campaigns run in a subprocess draw it as usual.

    The driver's ``plot_curves`` is replaced once per test process by
    :func:`_campaign_plot_curves`, and the marker is read here before each test's
    fixtures (an autouse ``monkeypatch`` fixture doing the same would cost about 0.2 ms of
    CPU in each of the ~1 250 default tests)."""
    _CAMPAIGN_FIGURE["draw"] = item.get_closest_marker("campaign_figure") is not None
    from imufdi_cli.campaign import driver

    if driver.plot_curves is not _campaign_plot_curves:
        driver.plot_curves = _campaign_plot_curves  # type: ignore[assignment]


try:
    from _pytest.tmpdir import tmppath_result_key
except ImportError:  # another pytest: its own tmp_path, as it comes
    tmppath_result_key = None

#: the next number of each ``tmp_path`` directory name in this test process
_TMP_NUMBERS: dict[str, int] = {}


def _numbered_dir(root: Path, prefix: str) -> Path:
    """``root / f"{prefix}{n}"`` created (mode 0o700) with the lowest ``n`` not yet used
    by this process for ``prefix`` and not taken on disk: the names pytest's ``tmp_path``
    gives in a fresh base directory, without its scan of every entry of the base directory
    for each test (quadratic in the number of tests) and its ``<prefix>current`` symlink."""
    number = _TMP_NUMBERS.get(prefix, 0)
    while True:
        path = root / f"{prefix}{number}"
        try:
            path.mkdir(mode=0o700)
        except FileExistsError:
            number += 1
            continue
        _TMP_NUMBERS[prefix] = number + 1
        return path


if tmppath_result_key is not None:

    @pytest.fixture
    def tmp_path(
        request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
    ) -> Generator[Path, None, None]:
        """pytest's ``tmp_path`` (pytest 9: ``_pytest/tmpdir.py``), a new empty directory
        per test under the session's base temporary directory, named as pytest names it
        (the test's name, non-word characters as ``_``, cut at 30 characters, then a
        number) and kept or removed by the same retention policy, made without pytest's
        ``make_numbered_dir``: that lists the whole base directory to find the next number
        and replaces a ``current`` symlink for every test, about 1.2 ms of CPU per test in
        a worker's run (the suite's 315 default tests that take ``tmp_path``: about 0.4 s).
        """
        name = re.sub(r"[\W]", "_", request.node.name)[:30]
        path = _numbered_dir(tmp_path_factory.getbasetemp(), name)
        yield path
        # as pytest: remove the directory if the policy is "failed" and the test passed
        policy = tmp_path_factory._retention_policy
        result = request.node.stash[tmppath_result_key]
        if policy == "failed" and result.get("call", True):
            shutil.rmtree(path, ignore_errors=True)
        del request.node.stash[tmppath_result_key]


@pytest.fixture(scope="session")
def fresh_python() -> Callable[[str], subprocess.CompletedProcess[str]]:
    """``run(code)``: ``python -c code`` in a fresh interpreter (this session's environment,
    output captured as text), run once per session and per ``code``: tests that look at
    what one fresh process imported share it instead of each starting its own interpreter
    (0.25-0.45 s of CPU each). The result is read-only."""
    done: dict[str, subprocess.CompletedProcess[str]] = {}

    def run(code: str) -> subprocess.CompletedProcess[str]:
        if code not in done:
            done[code] = subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True, check=False
            )
        return done[code]

    return run


@pytest.fixture(scope="session")
def mimu4444_cut_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real sample ``imufdi_cli/sample_logs/mimu4444-exp1-cut.bin`` (300 s of MIMU4444
    exp_1: ten static orientations, then hand motion) ingested by ``imufdi ingest`` with its
    layout and the uncalibrated array, once per test process and read-only: the CLI's
    calibrate and detect tests and cnn-map's motion check read the same log (0.2-0.45 s of
    CPU to ingest)."""
    from tests.cli.conftest import invoke

    root = Path(__file__).resolve().parents[1]
    samples = root / "imufdi_cli" / "sample_logs"
    out = tmp_path_factory.mktemp("mimu4444") / "cut.mcap"
    result = invoke(
        ["ingest", samples / "mimu4444-exp1-cut.bin",
         "--layout", root / "docs" / "layouts" / "mimu4444.toml",
         "--array", samples / "mimu4444-array.toml", "-o", out]
    )  # fmt: skip
    assert result.code == 0, result.stderr
    return out


@pytest.fixture(scope="session")
def scipy_stats() -> ModuleType:
    """``scipy.stats``, the independent oracle of the tests of ``imufdi_cli``'s own
    distribution functions and of the detectors' statistics, imported at first use (about
    1.2 s of CPU): no ``imufdi_cli`` module imports it, so only the test processes that run
    a test asking for it pay the import, and :func:`pytest_collection_modifyitems` moves
    those tests to the front, onto the first xdist worker."""
    import scipy.stats

    return scipy.stats
