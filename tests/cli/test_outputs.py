"""Every command's outputs: never an input (path, symlink, hard link), never each other,
no temporary file left on failure or on SIGTERM/SIGINT, one-line messages for any error."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.cli.conftest import assert_one_line_error

REPO = Path(__file__).resolve().parents[2]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if ".tmp" in p.name)


def alias(kind: str, target: Path, directory: Path) -> Path:
    """``target`` itself, or a symlink / hard link to it in ``directory``."""
    if kind == "path":
        return target
    at = directory / f"alias-{kind}{target.suffix}"
    if kind == "symlink":
        at.symlink_to(target)
    else:
        os.link(target, at)
    return at


#: command -> (input file name in the work directory, argv with IN and OUT placeholders)
COMMANDS = {
    "inject": (
        "log.mcap",
        ["inject", "IN", "--fault", "step:imu0.gyro.x,at=0.5s,amp=1deg/s", "-o", "OUT"],
    ),
    "detect": ("log.mcap", ["detect", "IN", "-d", "glt", "-o", "OUT"]),
    "report --json": ("det.mcap", ["report", "IN", "--json", "OUT"]),
    "report --markdown": ("det.mcap", ["report", "IN", "--markdown", "OUT"]),
    "report --csv": ("det.mcap", ["report", "IN", "--csv", "OUT"]),
    "report --junit": ("det.mcap", ["report", "IN", "--junit", "OUT"]),
    "report --plot": ("det.mcap", ["report", "IN", "--plot", "OUT"]),
    "tune": ("log.mcap", ["tune", "IN", "-o", "OUT"]),
    "ingest": ("cap.bin", ["ingest", "IN", "-o", "OUT"]),
    "ingest --layout": ("layout.toml", ["ingest", "cap.bin", "--layout", "IN", "-o", "OUT"]),
    "ingest --array": ("array.toml", ["ingest", "cap.bin", "--array", "IN", "-o", "OUT"]),
    "inject --faults": ("faults.toml", ["inject", "log.mcap", "--faults", "IN", "-o", "OUT"]),
    "detect --array": (
        "array.toml",
        ["detect", "log.mcap", "-d", "glt", "--array", "IN", "-o", "OUT"],
    ),
    "calibrate --array": ("array.toml", ["calibrate", "log.mcap", "--array", "IN", "-o", "OUT"]),
}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, detected_log) -> Path:
    from tests.cli.conftest import invoke

    base = tmp_path_factory.mktemp("outputs")
    made = invoke(
        [
            "simulate",
            "--preset",
            "paper-table4",
            "--duration",
            "1s",
            "-o",
            base / "log.mcap",
            "--capture",
            base / "cap.bin",
        ]
    )
    assert made.code == 0, made.stderr
    shutil.copyfile(detected_log, base / "det.mcap")
    (base / "layout.toml").write_text(
        'sync = "AA"\nn_imus = 1\nrate_hz = 100\n[[record]]\nname = "gyro_x"\ntype = "i16"\n'
        'scale = "1deg/s"\n[[record]]\nname = "gyro_y"\ntype = "i16"\nscale = "1deg/s"\n'
        '[[record]]\nname = "gyro_z"\ntype = "i16"\nscale = "1deg/s"\n'
    )
    (base / "array.toml").write_text("not even read\n")
    (base / "faults.toml").write_text(
        '[[fault]]\nmodel = "step"\nsensor = "imu0.gyro.x"\nat = "0.5s"\namp = "1deg/s"\n'
    )
    return base


@pytest.mark.parametrize("kind", ["path", "symlink", "hardlink"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_output_equal_to_an_input_is_refused(cli, workdir, tmp_path, command, kind):
    name, argv = COMMANDS[command]
    source = workdir / name
    before = sha(source)
    out = alias(kind, source, tmp_path)
    args = [str(source) if a == "IN" else str(out) if a == "OUT" else a for a in argv]
    args = [str(workdir / a) if (workdir / a).is_file() and a != name else a for a in args]
    result = cli(args)
    assert_one_line_error(result, 2, "is the input file")
    assert sha(source) == before
    assert leftovers(workdir) == [] and leftovers(tmp_path) == []


@pytest.mark.parametrize("kind", ["path", "symlink", "hardlink"])
def test_simulate_refuses_one_file_for_mcap_and_capture(cli, tmp_path, kind):
    target = tmp_path / "x.bin"
    target.write_bytes(b"keep me")
    other = alias(kind, target, tmp_path)
    result = cli(["simulate", "--preset", "paper-table4", "-o", target, "--capture", other])
    assert_one_line_error(result, 2, "are the same file")
    assert target.read_bytes() == b"keep me"
    assert leftovers(tmp_path) == []
    both_stdout = cli(["simulate", "--preset", "paper-table4", "-o", "-", "--capture", "-"])
    assert_one_line_error(both_stdout, 2, "only one output can go to stdout")


def test_report_refuses_a_roc_figure_over_its_input(cli, workdir, tmp_path):
    """--roc FILE with --plot also writes FILE's name with .png: never over the input."""
    log = tmp_path / "r.png"
    shutil.copyfile(workdir / "det.mcap", log)
    before = sha(log)
    result = cli(["report", log, "--roc", tmp_path / "r.csv", "--plot", tmp_path / "p.png"])
    assert_one_line_error(result, 2, "is the input file")
    assert sha(log) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.png"]


def test_report_refuses_a_roc_figure_over_its_plot(cli, workdir, tmp_path):
    result = cli(
        ["report", workdir / "det.mcap", "--roc", tmp_path / "x.csv", "--plot", tmp_path / "x.png"]
    )
    assert_one_line_error(result, 2, "are the same file")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "argv",
    [
        ["detect", "log.mcap", "-d", "glt", "-o", ""],
        ["inject", "log.mcap", "--fault", "step:imu0.gyro.x,amp=1deg/s", "-o", ""],
        ["report", "det.mcap", "--markdown", ""],
        ["report", "det.mcap", "--json", ""],
        ["simulate", "--preset", "paper-table4", "-o", "x.mcap", "--capture", ""],
        ["ingest", "cap.bin", "-o", ""],
        ["calibrate", "log.mcap", "-o", ""],
        ["campaign", "spec.toml", "-o", ""],
    ],
    ids=lambda argv: " ".join(a or "''" for a in argv[:1] + argv[-2:]),
)
def test_an_empty_output_name_is_a_usage_error(cli, workdir, argv, monkeypatch):
    """`-o ''` is not `-o` left out: no default output is written in its place."""
    monkeypatch.chdir(workdir)
    before = sorted(p.name for p in workdir.iterdir())
    result = cli(argv)
    assert_one_line_error(result, 2, "'' is an empty file name")
    assert sorted(p.name for p in workdir.iterdir()) == before


def test_report_refuses_two_outputs_in_one_file(cli, workdir, tmp_path):
    out = tmp_path / "r.txt"
    result = cli(["report", workdir / "det.mcap", "--json", out, "--markdown", out])
    assert_one_line_error(result, 2, "--json")
    assert not out.exists()


def test_campaign_refuses_results_over_its_spec(cli, tmp_path):
    results = tmp_path / "res"
    results.mkdir()
    spec = results / "summary.md"  # odd, but an input all the same
    spec.write_text(
        '[[base]]\npreset = "paper-table4"\noptions = { duration = "1s" }\n'
        '[[fault]]\nmodel = "step"\nsensor = "imu0.gyro.x"\nat = "0.5s"\namp = "1deg/s"\n'
        '[[detector]]\nname = "glt"\n'
    )
    before = sha(spec)
    result = cli(["campaign", spec, "-o", results, "--jobs", "1"])
    assert_one_line_error(result, 2, "is the input file")
    assert sha(spec) == before


def test_output_into_a_missing_directory_is_a_usage_error(cli, workdir, tmp_path):
    result = cli(["report", workdir / "det.mcap", "--json", tmp_path / "no" / "r.json"])
    assert_one_line_error(result, 2, "does not exist")


# --- unexpected exceptions ------------------------------------------------------------


def test_an_empty_memory_error_still_gives_one_informative_line(cli, workdir, monkeypatch):
    import imufdi_cli.info

    def boom(*args, **kwargs):
        raise MemoryError()

    monkeypatch.setattr(imufdi_cli.info, "log_info", boom)
    result = cli(["info", workdir / "log.mcap"])
    assert_one_line_error(result, 3, "out of memory")
    monkeypatch.setenv("IMUFDI_DEBUG", "1")
    debug = cli(["info", workdir / "log.mcap"])
    assert debug.code == 3
    assert "Traceback" in debug.stderr and "MemoryError" in debug.stderr
    assert debug.stderr.strip().splitlines()[-1].startswith("imufdi: error: out of memory")


def test_a_bug_is_exit_4_with_its_class(cli, workdir, monkeypatch):
    import imufdi_cli.info

    def boom(*args, **kwargs):
        raise KeyError()

    monkeypatch.setattr(imufdi_cli.info, "log_info", boom)
    result = cli(["info", workdir / "log.mcap"])
    assert_one_line_error(result, 4, "internal error (KeyError (no message))")


# --- signals ------------------------------------------------------------------------


def _interruptible() -> None:
    """In the child: SIGINT back to its default, as from a terminal. A pytest started as a
    background job without job control ignores SIGINT, the child would inherit SIG_IGN,
    and imufdi (rightly) keeps an ignored signal ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_long_simulate(directory: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("IMUFDI_DEBUG", None)
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "imufdi_cli",
            "simulate",
            "--imus",
            "8",
            "--rate",
            "1kHz",
            "--duration",
            "2h",
            "-o",
            str(directory / "long.mcap"),
            "--capture",
            str(directory / "long.bin"),
        ],
        env=env,
        cwd=directory,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_interruptible,
    )


def _wait_for_partial_output(process: subprocess.Popen, directory: Path) -> None:
    """Until both temporary files hold data (the command is mid-write)."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()[1]
        sizes = [p.stat().st_size for p in directory.glob(".long.*.tmp")]
        if len(sizes) == 2 and min(sizes) > 0:
            return
        time.sleep(0.05)
    process.kill()
    pytest.fail("the simulation never started writing")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("signum", "code", "fragment"),
    [(signal.SIGTERM, 143, "terminated by SIGTERM"), (signal.SIGINT, 130, "interrupted")],
)
def test_a_signal_mid_write_removes_the_partial_outputs(tmp_path, signum, code, fragment):
    process = _start_long_simulate(tmp_path)
    _wait_for_partial_output(process, tmp_path)
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == code, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert lines == [f"imufdi: error: {fragment}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.slow
def test_temps_of_a_killed_writer_are_removed_by_the_next_write(cli, tmp_path):
    process = _start_long_simulate(tmp_path)
    _wait_for_partial_output(process, tmp_path)
    process.kill()  # SIGKILL: no handler can run
    process.communicate(timeout=60)
    assert len(list(tmp_path.glob(".long.*.tmp"))) == 2
    result = cli(
        [
            "simulate",
            "--preset",
            "paper-table4",
            "--duration",
            "1s",
            "-o",
            tmp_path / "long.mcap",
            "--capture",
            tmp_path / "long.bin",
        ]
    )
    assert result.code == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.bin", "long.mcap"]


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE semantics")
def test_a_file_size_limit_mid_write_is_exit_3_and_leaves_nothing(tmp_path):
    import resource

    def limit() -> None:  # `ulimit -f 200`: writes past 200 KiB fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (200 * 1024, 200 * 1024))

    for extra in ([], ["--capture", str(tmp_path / "long.bin")]):
        process = subprocess.run(
            [
                sys.executable,
                "-m",
                "imufdi_cli",
                "simulate",
                "--preset",
                "paper-table4",
                "--duration",
                "30s",
                "-o",
                str(tmp_path / "long.mcap"),
                *extra,
            ],
            env=dict(os.environ, PYTHONPATH=str(REPO)),
            preexec_fn=limit,
            capture_output=True,
            text=True,
            timeout=300,
        )
        lines = [line for line in process.stderr.splitlines() if line.strip()]
        assert process.returncode == 3, process.stderr
        assert len(lines) == 1 and "File too large" in lines[0], process.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == []


def _with_huge_log_time(source: Path, target: Path) -> None:
    """Copy a log with the mcap package, giving its 50th message log_time 2^63 + 5."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(source, "rb") as stream, open(target, "wb") as out:
        reader = make_reader(stream)
        writer = Writer(out)
        writer.start("ros2", "test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for index, (schema, channel, message) in enumerate(reader.iter_messages()):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            log_time = (1 << 63) + 5 if index == 49 else message.log_time
            writer.add_message(channels[channel.id], log_time, message.data, message.publish_time)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        writer.finish()


@pytest.fixture(scope="module")
def huge_log(tmp_path_factory, workdir) -> Path:
    """workdir's log with one log time beyond int64, written once and only read."""
    source = tmp_path_factory.mktemp("huge") / "huge.mcap"
    _with_huge_log_time(workdir / "log.mcap", source)
    return source


@pytest.mark.parametrize("command", ["detect", "inject"])
def test_a_log_time_beyond_int64_is_bad_data_not_a_bug(cli, huge_log, tmp_path, command):
    before = huge_log.read_bytes()
    extra = ["-d", "glt"] if command == "detect" else ["--fault", "step:imu0.gyro.x,amp=1deg/s"]
    result = cli([command, huge_log, *extra, "-o", tmp_path / "out.mcap"])
    assert result.code == 3, result.stderr
    assert_one_line_error(result, 3, "")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no partial output
    assert huge_log.read_bytes() == before


def test_info_warns_of_a_log_time_beyond_int64(cli, huge_log):
    """info describes the log, and says which message detect and inject will refuse."""
    result = cli(["info", huge_log])
    assert result.code == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert any(
        "log time beyond 2^63 ns (/imu" in w and "9223372036854775813" in w for w in warnings
    )
    strict = cli(["info", huge_log, "--strict"])
    assert_one_line_error(strict, 3, "log time beyond 2^63 ns")


@pytest.mark.slow
def test_an_ignored_signal_stays_ignored(tmp_path):
    """nohup (SIGHUP ignored) must keep working: the handler is not installed over SIG_IGN."""
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import signal, sys; signal.signal(signal.SIGHUP, signal.SIG_IGN)\n"
            "from imufdi_cli.cli import main\n"
            "main(sys.argv[1:])",
            "simulate",
            "--preset",
            "paper-table4",
            "--duration",
            "60s",
            "-o",
            str(tmp_path / "x.mcap"),
        ],
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".x.mcap.*.tmp")):
        assert process.poll() is None, process.communicate()[1]
        assert time.monotonic() < deadline
        time.sleep(0.02)
    process.send_signal(signal.SIGHUP)
    _, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.mcap"]


# --- stdin and stdout open on an input ----------------------------------------------


def invoke_on_files(args: list, stdin: Path | None = None, stdout: Path | None = None, mode="ab"):
    """``imufdi ARGS < stdin 1<> stdout`` (``mode`` "r+b") or ``>> stdout`` ("ab"), in this
    process: sys.stdin/sys.stdout are text wrappers over those files, as in a shell."""
    import io

    from imufdi_cli.cli import main
    from tests.cli.conftest import CliResult

    err = io.BytesIO()
    saved = sys.stdin, sys.stdout, sys.stderr
    opened = []
    if stdin is not None:
        opened.append(open(stdin, "rb"))
        sys.stdin = io.TextIOWrapper(opened[-1])
    if stdout is not None:
        opened.append(open(stdout, mode))
        sys.stdout = io.TextIOWrapper(opened[-1], write_through=True)
    err_wrapper = sys.stderr = io.TextIOWrapper(err, write_through=True)
    code = 0
    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.stderr.flush()
        wrappers = [w for w in (sys.stdin, sys.stdout) if w not in saved[:2]]
        sys.stdin, sys.stdout, sys.stderr = saved
        for wrapper in wrappers:
            try:
                wrapper.flush()
            except ValueError:
                pass
        for handle in opened:
            handle.close()
        err_wrapper.detach()  # keep the buffer open past the wrapper
    return CliResult(code, b"", err.getvalue().decode())


FAULT_SPEC = "step:imu0.gyro.x,at=0.5s,amp=1deg/s"


@pytest.mark.parametrize(
    ("name", "argv"),
    [
        ("log.mcap", ["inject", "-", "--fault", FAULT_SPEC, "-o", "IN"]),
        ("log.mcap", ["detect", "-", "-d", "glt", "-o", "IN"]),
        ("log.mcap", ["info", "-", "--json", "IN"]),
        ("cap.bin", ["ingest", "-", "-o", "IN"]),
        ("det.mcap", ["report", "-", "--markdown", "IN"]),
    ],
    ids=lambda v: v if isinstance(v, str) else " ".join(v[:1]),
)
def test_an_output_over_the_file_stdin_reads_is_refused(workdir, tmp_path, name, argv):
    source = tmp_path / name
    shutil.copyfile(workdir / name, source)
    before = sha(source)
    result = invoke_on_files([str(source) if a == "IN" else a for a in argv], stdin=source)
    assert_one_line_error(result, 2, "the file stdin reads")
    assert sha(source) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


@pytest.mark.parametrize("mode", ["r+b", "ab"], ids=["1<>", ">>"])
@pytest.mark.parametrize(
    ("name", "argv"),
    [
        ("log.mcap", ["inject", "IN", "--fault", FAULT_SPEC, "-o", "-"]),
        ("log.mcap", ["detect", "IN", "-d", "glt", "-o", "-"]),
        ("log.mcap", ["info", "IN", "--json"]),
        ("log.mcap", ["info", "IN"]),
        ("det.mcap", ["report", "IN", "--markdown", "-"]),
        ("det.mcap", ["report", "IN", "-q"]),
        ("log.mcap", ["inject", "-", "--fault", FAULT_SPEC, "-o", "-"]),
    ],
    ids=lambda v: v if isinstance(v, str) else " ".join(v),
)
def test_stdout_open_on_an_input_is_refused(workdir, tmp_path, name, argv, mode):
    source = tmp_path / name
    shutil.copyfile(workdir / name, source)
    before = sha(source)
    args = [str(source) if a == "IN" else a for a in argv]
    stdin = source if "-" == args[1] else None
    result = invoke_on_files(args, stdin=stdin, stdout=source, mode=mode)
    assert_one_line_error(result, 2, "inputs are never modified")
    assert sha(source) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_an_output_over_the_file_stdout_is_open_on_is_refused(workdir, tmp_path):
    """`-o x.mcap --json - > x.mcap`: the renamed output would orphan what stdout holds."""
    out = tmp_path / "x.mcap"
    out.write_bytes(b"")
    result = invoke_on_files(
        ["detect", workdir / "log.mcap", "-d", "glt", "-o", out, "--json", "-"], stdout=out
    )
    assert_one_line_error(result, 2, "is the file stdout is open on")


def test_streams_on_other_files_are_fine(workdir, tmp_path):
    """The ordinary redirections still work: the input on stdin, the output on stdout."""
    out = tmp_path / "out.mcap"
    result = invoke_on_files(
        ["inject", "-", "--fault", FAULT_SPEC, "-o", "-"],
        stdin=workdir / "log.mcap",
        stdout=out,
        mode="wb",
    )
    assert result.code == 0, result.stderr
    from imufdi_cli.mcapio import McapSource

    with McapSource(out) as src:
        assert "imufdi.faults" in src.metadata


# --- zero-filled files ----------------------------------------------------------------

ZERO_COMMANDS = {
    "info": ["info", "IN"],
    "detect": ["detect", "IN", "-d", "glt", "-o", "OUT.mcap"],
    "inject": ["inject", "IN", "--fault", "step:imu0.gyro.x,amp=1deg/s", "-o", "OUT.mcap"],
    "report": ["report", "IN"],
    "calibrate": ["calibrate", "IN", "-o", "OUT.toml"],
}


def _zero_filled(path: Path, head: bytes = b"\x89MCAP0\r\n", zeros: int = 64 << 20) -> Path:
    with open(path, "wb") as out:
        out.write(head)
        out.truncate(len(head) + zeros)  # a sparse file: no 64 MB written to the disk
    return path


@pytest.mark.parametrize("command", sorted(ZERO_COMMANDS))
def test_a_zero_filled_file_is_one_problem_not_millions(cli, tmp_path, command):
    """MCAP magic and 64 MB of zeros read as 7.4 million empty records of opcode 0: the
    region is stepped over at once and named in one line (exit 3)."""
    log = _zero_filled(tmp_path / "z.mcap")
    started = time.perf_counter()
    argv = [
        str(log) if a == "IN" else a.replace("OUT", str(tmp_path / "out"))
        for a in ZERO_COMMANDS[command]
    ]
    result = cli(argv)
    assert_one_line_error(result, 3, "67108864 zero bytes at byte 8 skipped")
    assert time.perf_counter() - started < 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["z.mcap"]


def test_a_cut_log_followed_by_zeros_reads_up_to_the_cut(cli, table4_log, tmp_path):
    data = table4_log.read_bytes()  # several chunks: the first ones are whole
    log = _zero_filled(tmp_path / "cut.mcap", data[: len(data) // 2])
    result = cli(["info", log, "--json", tmp_path / "i.json"])
    assert result.code == 0, result.stderr
    import json

    info = json.loads((tmp_path / "i.json").read_text())
    assert info["n_samples"] > 0
    zero_lines = [w for w in info["warnings"] if "zero bytes" in w]
    assert len(zero_lines) == 1, info["warnings"]


#: Runs one command and prints its exit code, wall time and peak RSS (KiB). A process's
#: ru_maxrss starts from the high-water mark of the process it was forked from (exec records
#: the replaced memory's peak), so a command started straight from a test worker that had
#: grown to 400 MB reports 400 MB whatever it used: the command is started from this fresh
#: interpreter (about 10 MB) instead.
_MEASURE = """
import json, os, subprocess, sys, time
started = time.monotonic()
child = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
stderr = child.stderr.read().decode()
_, status, usage = os.wait4(child.pid, 0)
print(json.dumps({"code": os.waitstatus_to_exitcode(status), "seconds": time.monotonic() - started,
                  "maxrss_kib": usage.ru_maxrss, "stderr": stderr}))
"""


def _measured(argv: list[str]) -> dict:
    """Exit code, wall time (s), peak RSS (KiB) and stderr of ``imufdi_cli argv`` run in a
    fresh process (:data:`_MEASURE`)."""
    import json

    done = subprocess.run(
        [sys.executable, "-c", _MEASURE, sys.executable, "-m", "imufdi_cli", *argv],
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout)


def test_the_peak_rss_measured_is_the_commands_own():
    """A parent holding 200 MB more does not move the command's measured peak."""
    import numpy as np

    held = np.ones(200 << 17)  # 200 MB, every page touched
    measured = _measured(["--help"])
    assert measured["code"] == 0 and held.sum() > 0
    assert measured["maxrss_kib"] < 150 * 1024, measured


@pytest.mark.slow
def test_a_zero_filled_file_takes_under_10_s_and_300_mb(tmp_path):
    """The target: every reading command on MCAP magic + 64 MB of zeros exits 3 within
    10 s with a peak RSS under 300 MB (each in a fresh process)."""
    log = _zero_filled(tmp_path / "z.mcap")
    for command, argv in sorted(ZERO_COMMANDS.items()):
        args = [str(log) if a == "IN" else a.replace("OUT", str(tmp_path / "out")) for a in argv]
        measured = _measured(args)
        assert measured["code"] == 3, (command, measured["stderr"])
        assert measured["seconds"] < 10, (command, measured)
        assert measured["maxrss_kib"] < 300 * 1024, (command, measured)
