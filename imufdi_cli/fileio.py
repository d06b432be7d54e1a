"""The one output path of imufdi: atomic outputs, ``-`` for stdin/stdout, output checks.

Every file the CLI writes goes through this module:

- :func:`check_outputs` decides whether a command may write its outputs: it refuses an
  output that is one of the command's inputs (the same file, compared by device and
  inode, so symlinks and hard links are caught too; derived outputs such as the figure
  ``report --roc FILE --plot`` writes beside FILE included), an output or stdout open on
  the file stdin reads, stdout open on an input, two outputs of one command that are the
  same file, and an empty output name;
- :func:`atomic_path` / :func:`open_atomic` / :func:`create_temp` write a temporary file
  ``.NAME.PID.RANDOM.tmp`` beside the target and rename it into place only when the whole
  output, including its final flush and close, succeeded. On any failure (an exception,
  ``ENOSPC``/``EFBIG`` on flush or close, SIGINT/SIGTERM turned into exceptions by the
  CLI) the temporary file is removed and the target is left as it was. An existing output
  that is not a regular file (``/dev/null``, a FIFO) is written in place, never replaced.

A writer killed with SIGKILL cannot clean up; the next write to the same target removes
temporary files whose writer process (the PID in the name) no longer exists on this host.
"""

from __future__ import annotations

import os
import re
import stat
import sys
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from imufdi_cli.errors import InputDataError, OutputError, UsageError

#: Temporary names: ``.<target name>.<pid>.<random>.tmp`` (plus an optional suffix).
_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[0-9a-f]{12}\.tmp(\.\w+)?$")


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def remove_stale_temps(target: str | Path) -> list[Path]:
    """Remove temporary files of ``target`` left by writers that no longer run (SIGKILL).

    Only names of the form this module creates, with the PID of a process that does not
    exist, are removed. Returns the removed paths.
    """
    target = Path(target)
    directory = target.parent if str(target.parent) else Path(".")
    removed: list[Path] = []
    try:
        entries = list(directory.iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = _TEMP_RE.match(entry.name)
        if match is None or match.group("name") != target.name:
            continue
        if _pid_alive(int(match.group("pid"))):
            continue
        try:
            entry.unlink()
            removed.append(entry)
        except OSError:
            pass
    return removed


def is_special(path: str | Path) -> bool:
    """True for an existing output that is not a regular file or directory (``/dev/null``,
    a FIFO, ``/dev/stdout``): written in place, never replaced by a renamed file."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def create_temp(path: str | Path, *, suffix: str = "", sweep: bool = True) -> tuple[int, Path]:
    """Create the temporary file of output ``path``; returns ``(fd, temp_path)``.

    The file is created beside the target (same file system, so the final rename is
    atomic) with the mode an ordinary new file would get. The caller owns ``fd`` and must
    either rename the temporary file over ``path`` or :func:`discard_temp` it. With
    ``sweep`` (default), stale temporary files of ``path`` are removed first
    (:func:`remove_stale_temps`, one directory listing); writers of many small files in one
    directory (campaign run results) sweep once themselves and pass ``sweep=False``.

    Raises
    ------
    UsageError
        The directory does not exist, the target is a directory, or the temporary file
        cannot be created (permissions, read-only file system).
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise UsageError(f"cannot write {target}: directory {directory} does not exist")
    if target.is_dir():
        raise UsageError(f"cannot write {target}: it is a directory")
    if sweep:
        remove_stale_temps(target)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        temp = directory / f".{target.name}.{os.getpid()}.{os.urandom(6).hex()}.tmp{suffix}"
        try:
            fd = os.open(temp, flags, 0o666)  # the umask applies, as for any new file
        except FileExistsError:
            continue
        except OSError as err:
            raise UsageError(f"cannot write {target}: {err.strerror or err}") from err
        return fd, temp
    raise UsageError(f"cannot write {target}: no free temporary name in {directory}")


def discard_temp(temp: str | Path) -> None:
    """Remove a temporary file (missing is fine)."""
    try:
        os.unlink(temp)
    except FileNotFoundError:
        pass


def commit_temp(temp: str | Path, path: str | Path) -> None:
    """Rename a finished temporary file over its target (atomic on POSIX)."""
    os.replace(temp, path)


@contextmanager
def atomic_path(path: str | Path, *, suffix: str = "") -> Iterator[str]:
    """Yield a temporary path beside ``path``; rename it into place only on success.

    On any exception (including KeyboardInterrupt and the CLI's termination exception)
    the temporary file is removed and ``path`` is left as it was. ``suffix`` is appended
    to the temporary name (for writers that choose the format from the extension).
    """
    if is_special(path):
        yield str(path)
        return
    fd, temp = create_temp(path, suffix=suffix)
    os.close(fd)
    try:
        yield str(temp)
        commit_temp(temp, path)
    except BaseException:
        discard_temp(temp)
        raise


@contextmanager
def open_atomic(path: str | Path, mode: str = "wb", *, sweep: bool = True) -> Iterator[IO[bytes]]:
    """Open an atomic output file for writing in binary ``mode``.

    The file is flushed and closed before the rename; a failure there (disk full, file
    size limit) removes the temporary file and propagates.
    """
    if mode not in ("wb", "w+b"):
        raise ValueError(f"open_atomic is for binary writing, got mode {mode!r}")
    if is_special(path):
        with open(path, "wb") as special:
            yield special
        return
    fd, temp = create_temp(path, sweep=sweep)
    handle: IO[bytes] | None = None
    try:
        handle = os.fdopen(fd, mode)
        yield handle
        try:
            handle.close()  # flush errors (ENOSPC, EFBIG) surface here, before the rename
        except OSError as err:
            raise OutputError(
                f"cannot write {path}: {err.strerror or err}; nothing was written"
            ) from err
        commit_temp(temp, path)
    except BaseException:
        if handle is None:
            os.close(fd)
        else:
            try:
                handle.close()
            except OSError:
                pass
        discard_temp(temp)
        raise


def write_text(path: str, text: str, *, sweep: bool = True) -> None:
    """Write text to ``path`` atomically, or to stdout when ``path`` is ``-``."""
    if path == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    with open_atomic(path, sweep=sweep) as handle:
        try:
            handle.write(text.encode("utf-8"))
        except OSError as err:
            raise OutputError(
                f"cannot write {path}: {err.strerror or err}; nothing was written"
            ) from err


def check_input(path: str) -> None:
    """Raise InputDataError (exit 3) when an input path is missing or not a file (a rosbag2
    directory, holding metadata.yaml, counts as one)."""
    if path == "-":
        return
    p = Path(path)
    if not p.exists():
        raise InputDataError(f"{path}: no such file")
    if not p.is_file() and not (p.is_dir() and (p / "metadata.yaml").is_file()):
        raise InputDataError(f"{path}: not a regular file (nor a rosbag2 directory)")


def default_output(source: str, suffix: str) -> str:
    """Output path derived from an input (``run.mcap`` -> ``run-<suffix>.mcap``); stdin -> stdout."""
    if source == "-":
        return "-"
    p = Path(source)
    return str(p.with_name(f"{p.stem}-{suffix}.mcap"))


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when two paths name the same file: same device and inode (symlinks and hard
    links included), or the same resolved path when either does not exist yet."""
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        try:
            return Path(a).resolve() == Path(b).resolve()
        except (OSError, RuntimeError):
            return os.path.abspath(a) == os.path.abspath(b)
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def _bag_files(path: Path) -> list[str]:
    """The files a rosbag2 input reads: given its directory or its ``metadata.yaml``, every
    regular file in that directory (split MCAP files, metadata)."""
    if path.is_dir():
        directory = path
    elif path.name == "metadata.yaml":
        directory = path.parent
    else:
        return []
    try:
        return [str(entry) for entry in directory.iterdir() if entry.is_file()]
    except OSError:
        return []


def derived_output(path: str | Path, suffix: str) -> str:
    """The output a command derives from another output ``path``: its name with the
    extension replaced by ``suffix`` (``report --roc roc.csv --plot`` also writes
    ``roc.png``). Commands pass it to :func:`check_outputs` like any named output."""
    return os.path.splitext(str(path))[0] + suffix


def _fd_name(fd: int) -> str:
    """The path of the file open on ``fd`` (Linux /proc), else ``fd N``."""
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return f"fd {fd}"


def stream_file(stream: object) -> tuple[tuple[int, int], str] | None:
    """``((st_dev, st_ino), path)`` of the regular file a standard stream is open on
    (``< file``, ``> file``, ``>> file``, ``1<> file``); None for a pipe, a terminal, a
    device such as /dev/null, or a stream without a file descriptor (a test's buffer)."""
    try:
        fd = stream.fileno()  # type: ignore[attr-defined]
        info = os.fstat(fd)
    except (AttributeError, OSError, ValueError):
        return None
    if not stat.S_ISREG(info.st_mode):
        return None
    return (info.st_dev, info.st_ino), _fd_name(fd)


def _identity(path: str | Path) -> tuple[int, int] | None:
    try:
        info = os.stat(path)
    except (OSError, ValueError):
        return None
    return info.st_dev, info.st_ino


def check_outputs(
    inputs: Iterable[str | Path | None],
    outputs: Sequence[tuple[str, str | Path | None]],
    *,
    streams: bool = True,
) -> None:
    """Decide whether a command may write its outputs: the one check every command makes
    before it reads or writes anything.

    Refused (UsageError, exit 2, naming the option, the output and the input):

    - an output that is one of the inputs, by path, symlink or hard link (device and
      inode), including the outputs a command derives from others
      (:func:`derived_output`);
    - with ``streams``: an output, or stdout, that is the file an input read from stdin
      (``-``) is open on (``imufdi inject - -o a.mcap < a.mcap``); stdout open on an input
      (``1<> a.mcap``, ``>> a.mcap``), whether or not the command would write to it; an
      output that is the file stdout is open on;
    - two outputs that are the same file (``/dev/null`` twice is fine), or more than one
      output on stdout (``-``);
    - an empty output name (``-o ''``).

    Parameters
    ----------
    inputs : iterable of path or None
        Every file the command reads (None is skipped; ``-`` is stdin); a rosbag2
        directory (or its ``metadata.yaml``) stands for every file in it.
    outputs : sequence of (label, path or None)
        Every file the command writes with the option that names it, e.g.
        ``("--json", "report.json")`` (None is skipped; ``-`` is stdout).
    streams : bool
        Also compare the files stdin and stdout are open on (default).

    Raises
    ------
    UsageError
        Naming the option, the output and the input (or the other output).
    """
    given = [(label, p) for label, p in outputs if p is not None]
    for label, p in given:
        if str(p) == "":
            raise UsageError(f"{label} '' is an empty file name; give a file name, or - for stdout")
    to_stdout = [label for label, p in given if str(p) == "-"]
    if len(to_stdout) > 1:
        raise UsageError(
            f"{' - and '.join(to_stdout)} -: only one output can go to stdout;"
            " give the others a file"
        )
    sources = [str(p) for p in inputs if p is not None]
    files: list[str] = []
    for source in sources:
        if source == "-":
            continue
        files.append(source)
        files += _bag_files(Path(source))
    named = [(label, str(p)) for label, p in given if str(p) != "-"]
    for label, out in named:
        for source in files:
            if same_file(out, source):
                raise UsageError(
                    f"{label} {out} is the input file {source}; inputs are never modified"
                )
    if streams:
        _check_streams(files, named, reads_stdin="-" in sources)
    regular = [
        (label, out) for label, out in named if not is_special(out)
    ]  # /dev/null twice is fine
    for i, (label, out) in enumerate(regular):
        for other_label, other in regular[i + 1 :]:
            if same_file(out, other):
                raise UsageError(
                    f"{label} {out} and {other_label} {other} are the same file;"
                    " give each output its own path"
                )


def _check_streams(files: list[str], named: list[tuple[str, str]], *, reads_stdin: bool) -> None:
    """:func:`check_outputs`' part on the files stdin and stdout are open on."""
    stdin = stream_file(sys.stdin) if reads_stdin else None
    stdout = stream_file(sys.stdout)
    if stdin is not None:
        for label, out in named:
            if _identity(out) == stdin[0]:
                raise UsageError(
                    f"{label} {out} is the file stdin reads ({stdin[1]}), an input;"
                    " inputs are never modified"
                )
    if stdout is None:
        return
    if stdin is not None and stdin[0] == stdout[0]:
        raise UsageError(
            f"stdout is open on {stdout[1]}, the file stdin reads (an input); inputs are"
            " never modified: send stdout to another file"
        )
    for source in files:
        if _identity(source) == stdout[0]:
            raise UsageError(
                f"stdout is open on the input file {source}; inputs are never modified:"
                " send stdout to another file"
            )
    for label, out in named:
        if _identity(out) == stdout[0]:
            raise UsageError(
                f"{label} {out} is the file stdout is open on; give {label} another file,"
                " or - to write it to stdout"
            )


def check_output(source: str | None, output: str, *, label: str = "output") -> None:
    """Refuse to write over an input file (inputs are never modified)."""
    check_outputs([source], [(label, output)])
