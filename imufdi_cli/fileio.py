"""Small file helpers: atomic text outputs, ``-`` for stdin/stdout, output path checks."""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from imufdi_cli.errors import InputDataError, UsageError


@contextmanager
def atomic_path(path: str | Path) -> Iterator[str]:
    """Yield a temporary path beside ``path``; rename it into place only on success.

    On an exception the temporary file is removed and ``path`` is left as it was.
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise UsageError(f"cannot write {target}: directory {directory} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual mode
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path: str, text: str) -> None:
    """Write text to ``path`` atomically, or to stdout when ``path`` is ``-``."""
    if path == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


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


def check_output(source: str | None, output: str) -> None:
    """Refuse to write over an input file (inputs are never modified)."""
    if output == "-" or source in (None, "-"):
        return
    try:
        same = Path(output).resolve() == Path(source).resolve()
    except OSError:
        same = False
    if same:
        raise UsageError(f"output {output} is the input file; inputs are never modified")
