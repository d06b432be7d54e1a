"""The one output path: input/output checks by inode, atomic writes, cleanup on failure."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from imufdi_cli import fileio
from imufdi_cli.errors import OutputError, UsageError
from imufdi_cli.fileio import (
    atomic_path,
    check_outputs,
    create_temp,
    open_atomic,
    remove_stale_temps,
    same_file,
    write_text,
)


def temps(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith((".tmp", ".tmp.png")))


@pytest.fixture
def source(tmp_path: Path) -> Path:
    path = tmp_path / "in.mcap"
    path.write_bytes(b"precious input")
    return path


def link(kind: str, source: Path, at: Path) -> Path:
    if kind == "plain":
        return source
    if kind == "symlink":
        at.symlink_to(source)
    elif kind == "hardlink":
        os.link(source, at)
    elif kind == "relative":
        return Path(os.path.relpath(source))
    return at


@pytest.mark.parametrize("kind", ["plain", "symlink", "hardlink", "relative"])
def test_an_output_that_is_an_input_is_refused(source, tmp_path, kind):
    out = link(kind, source, tmp_path / "out.json")
    assert same_file(out, source)
    with pytest.raises(UsageError, match=r"--json .* is the input file .*in\.mcap"):
        check_outputs([source], [("--json", out)])


def test_distinct_and_new_files_pass(source, tmp_path):
    other = tmp_path / "other.mcap"
    other.write_bytes(b"precious input")  # same content, another file
    assert not same_file(other, source)
    assert not same_file(tmp_path / "new.mcap", source)
    check_outputs([source, None, "-"], [("-o", other), ("--json", "-"), ("--csv", None)])


@pytest.mark.parametrize("kind", ["plain", "symlink", "hardlink"])
def test_two_outputs_that_are_one_file_are_refused(tmp_path, kind):
    first = tmp_path / "x.bin"
    first.write_bytes(b"old")
    second = first if kind == "plain" else link(kind, first, tmp_path / "y.bin")
    with pytest.raises(UsageError, match=r"-o .* and --capture .* are the same file"):
        check_outputs([], [("-o", first), ("--capture", second)])
    # not created yet: the same path is still the same file
    with pytest.raises(UsageError, match="same file"):
        check_outputs([], [("-o", tmp_path / "new"), ("--capture", tmp_path / "." / "new")])


def test_atomic_path_renames_on_success_and_cleans_up_on_any_exception(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert Path(tmp).parent == tmp_path and Path(tmp).name.startswith(".out.txt.")
        Path(tmp).write_text("new")
        assert target.read_text() == "old"  # nothing visible before the rename
    assert target.read_text() == "new"
    for exc in (ValueError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)), atomic_path(target) as tmp:
            Path(tmp).write_text("half")
            raise exc
        assert target.read_text() == "new"
        assert temps(tmp_path) == []


def test_new_files_get_the_umask_mode(tmp_path):
    write_text(str(tmp_path / "a.txt"), "x")
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o666 & ~mask


class _FailingClose:
    """A file whose close fails like a full disk, after really closing (as io does)."""

    def __init__(self, handle, err: int) -> None:
        self._handle = handle
        self._err = err

    def write(self, data: bytes) -> int:
        return self._handle.write(data)

    def close(self) -> None:
        self._handle.close()
        raise OSError(self._err, os.strerror(self._err))


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EFBIG])
def test_a_failing_close_removes_the_temp_and_keeps_the_target(tmp_path, monkeypatch, err):
    target = tmp_path / "report.json"
    target.write_text("previous")
    real_fdopen = os.fdopen
    monkeypatch.setattr(
        fileio.os, "fdopen", lambda fd, mode: _FailingClose(real_fdopen(fd, mode), err)
    )
    with pytest.raises(OutputError, match=f"cannot write {target}: {os.strerror(err)}") as info:
        write_text(str(target), "x" * 100_000)
    assert isinstance(info.value.__cause__, OSError) and info.value.__cause__.errno == err
    assert target.read_text() == "previous"
    assert temps(tmp_path) == []


def test_create_temp_refuses_missing_directories_and_directory_targets(tmp_path):
    with pytest.raises(UsageError, match="does not exist"):
        create_temp(tmp_path / "nope" / "x.mcap")
    (tmp_path / "d").mkdir()
    with pytest.raises(UsageError, match="is a directory"):
        with open_atomic(tmp_path / "d"):
            pass


def test_stale_temps_of_dead_writers_are_removed(tmp_path):
    # the pid of a process that has exited and been waited for (-S: no site, a quick start)
    with subprocess.Popen([sys.executable, "-S", "-c", "pass"]) as dead:
        pass
    assert dead.returncode == 0
    dead_pid = dead.pid
    stale = tmp_path / f".x.mcap.{dead_pid}.0123456789ab.tmp"
    live = tmp_path / f".x.mcap.{os.getpid()}.0123456789ab.tmp"
    other = tmp_path / f".y.mcap.{dead_pid}.0123456789ab.tmp"
    unrelated = tmp_path / ".x.mcap.notes.tmp"
    for path in (stale, live, other, unrelated):
        path.write_bytes(b"partial")
    assert remove_stale_temps(tmp_path / "x.mcap") == [stale]
    assert live.exists() and other.exists() and unrelated.exists()
    # every new output sweeps its own target's stale temps
    with open_atomic(tmp_path / "y.mcap") as handle:
        handle.write(b"ok")
    assert not other.exists()


def test_special_files_are_written_in_place_never_replaced(tmp_path):
    import threading

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    received: list[bytes] = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()))
    reader.start()
    write_text(str(fifo), "through the pipe")
    reader.join(timeout=30)
    assert received == [b"through the pipe"]
    assert fileio.is_special(fifo)  # still the FIFO, not a renamed regular file
    assert temps(tmp_path) == []
    check_outputs([], [("--json", fifo), ("--markdown", fifo)])  # like /dev/null twice


def test_mcap_writer_writes_into_a_fifo(tmp_path):
    import threading

    from imufdi_cli.mcapio import McapWriter

    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    received: list[bytes] = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()))
    reader.start()
    with McapWriter(fifo) as writer:
        writer.add_metadata("m", {"a": "b"})
    reader.join(timeout=30)
    assert received[0][:8] == b"\x89MCAP0\r\n" and fileio.is_special(fifo)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe.mcap"]


@pytest.mark.parametrize("given", ["directory", "metadata"])
def test_the_files_of_a_bag_directory_are_inputs(tmp_path, given):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (bag / "bag_0.mcap").write_bytes(b"split 0")
    source = bag if given == "directory" else bag / "metadata.yaml"
    for existing in ("bag_0.mcap", "metadata.yaml"):
        with pytest.raises(UsageError, match="is the input file"):
            check_outputs([source], [("-o", bag / existing)])
    check_outputs([source], [("-o", bag / "new.mcap"), ("--json", tmp_path / "r.json")])


def test_stream_file_is_the_regular_file_a_stream_is_open_on(source, tmp_path):
    with open(source, "rb") as handle:
        found = fileio.stream_file(handle)
    assert found is not None and found[0] == (source.stat().st_dev, source.stat().st_ino)
    read_end, write_end = os.pipe()
    try:
        with open(read_end, "rb", closefd=False) as pipe:
            assert fileio.stream_file(pipe) is None  # a pipe cannot be an input file
    finally:
        os.close(read_end)
        os.close(write_end)
    with open(os.devnull, "wb") as null:
        assert fileio.stream_file(null) is None
    import io

    assert fileio.stream_file(io.BytesIO()) is None  # no descriptor at all


def test_check_outputs_compares_stdin_and_stdout_with_the_files(source, tmp_path, monkeypatch):
    other = tmp_path / "other.mcap"
    with open(source, "rb") as stdin:
        monkeypatch.setattr(sys, "stdin", stdin)
        with pytest.raises(UsageError, match="is the file stdin reads"):
            check_outputs(["-"], [("-o", source)])
        check_outputs([source], [("-o", other)])  # stdin is not read: no matter
        check_outputs(["-"], [("-o", other)])
        check_outputs(["-"], [("-o", source)], streams=False)
    with open(source, "ab") as stdout:
        monkeypatch.setattr(sys, "stdout", stdout)
        with pytest.raises(UsageError, match="stdout is open on the input file"):
            check_outputs([source], [])
        with pytest.raises(UsageError, match=r"--json .* is the file stdout is open on"):
            check_outputs([], [("--json", source)])
        check_outputs([other], [("-o", "-")])


def test_check_outputs_refuses_empty_names_and_two_on_stdout(tmp_path):
    with pytest.raises(UsageError, match="-o '' is an empty file name"):
        check_outputs([], [("-o", "")])
    with pytest.raises(UsageError, match="only one output can go to stdout"):
        check_outputs([], [("--csv", "-"), ("--markdown", "-")])


def test_a_derived_output_is_the_name_with_another_extension():
    assert fileio.derived_output("out/roc.csv", ".png") == "out/roc.png"
    assert fileio.derived_output("roc", ".png") == "roc.png"
