"""Run the real console entry point in-process, with byte-level stdin/stdout."""

from __future__ import annotations

import io
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from imufdi_cli.cli import main


@dataclass
class CliResult:
    code: int
    stdout: bytes
    stderr: str

    @property
    def out(self) -> str:
        return self.stdout.decode("utf-8", "replace")


def invoke(args: list[str], stdin: bytes = b"") -> CliResult:
    out_buffer, err_buffer = io.BytesIO(), io.BytesIO()
    saved = sys.stdin, sys.stdout, sys.stderr
    wrappers = (
        io.TextIOWrapper(io.BytesIO(stdin)),
        io.TextIOWrapper(out_buffer, write_through=True),
        io.TextIOWrapper(err_buffer, write_through=True),
    )
    sys.stdin, sys.stdout, sys.stderr = wrappers
    code = 0
    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        sys.stdin, sys.stdout, sys.stderr = saved
    result = CliResult(
        code, out_buffer.getvalue(), err_buffer.getvalue().decode("utf-8", "replace")
    )
    for wrapper in wrappers:
        wrapper.detach()  # keep the byte buffers open past the wrappers' lifetime
    return result


@pytest.fixture
def cli():
    return invoke


def assert_one_line_error(result: CliResult, code: int, fragment: str) -> None:
    """Exit ``code`` and exactly one error line, the last line on stderr (a summary of
    what was done before the error may precede it), containing ``fragment``."""
    assert result.code == code, (result.code, result.stderr)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("imufdi: error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], result.stderr
    assert fragment in errors[0], errors[0]
    assert "Traceback" not in result.stderr


@pytest.fixture(scope="session")
def table4_log(tmp_path_factory) -> Path:
    """A paper-table4 log (seed 1), simulated once per session."""
    path = tmp_path_factory.mktemp("logs") / "table4.mcap"
    result = invoke(["simulate", "--preset", "paper-table4", "--seed", "1", "-o", path])
    assert result.code == 0, result.stderr
    return path


@pytest.fixture(scope="session")
def faulty_log(tmp_path_factory, table4_log) -> Path:
    """table4_log with the 0.9 deg/s step on imu0.gyro.x at 2.5 s."""
    path = tmp_path_factory.mktemp("logs") / "faulty.mcap"
    result = invoke(
        ["inject", table4_log, "--fault", "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s", "-o", path]
    )
    assert result.code == 0, result.stderr
    return path


@pytest.fixture(scope="session")
def detected_log(tmp_path_factory, faulty_log) -> Path:
    path = tmp_path_factory.mktemp("logs") / "detected.mcap"
    result = invoke(["detect", faulty_log, "-d", "glt", "-o", path])
    assert result.code == 0, result.stderr
    return path


@dataclass(frozen=True)
class FreshRun:
    """``imufdi ARGS`` run in a fresh interpreter with stdout and stderr on pipes:
    ``modules``, every module it had imported at the end (``sys.modules``)."""

    modules: frozenset[str]
    stdout: str
    stderr: str


@pytest.fixture(scope="session")
def fresh_imufdi(fresh_python):
    """``run(args)``: :class:`FreshRun` of ``python -m imufdi_cli ARGS`` (through runpy, as
    ``-m`` runs it), once per session and per ``args`` (tests/conftest.py's
    ``fresh_python``): the start-up tests of several files read one process."""

    def run(args: list[str]) -> FreshRun:
        probe = (
            "import json, runpy, sys\n"
            f"sys.argv = ['imufdi', *{[str(a) for a in args]!r}]\n"
            "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
            "except SystemExit:\n    pass\n"
            "sys.stderr.write('\\n' + json.dumps(sorted(sys.modules)))\n"
        )
        done = fresh_python(probe)
        assert done.returncode == 0, done.stderr
        *stderr, modules = done.stderr.splitlines()
        return FreshRun(frozenset(json.loads(modules)), done.stdout, "\n".join(stderr))

    return run
