"""Progress reporting of long library calls (the library never prints; the CLI renders).

A long-running function (``detect_file``, ``inject_file``, ``ingest_file``,
``build_report``) takes an optional ``progress`` callback and calls it now and then with
``(done, total)``: the work done so far and the whole work, in one unit the function
chooses (seconds of log time, bytes of a capture). ``total`` is None when it is not known
in advance (a log read from a pipe has no summary). Callbacks must be cheap; they are
called at most once per block or chunk.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: ``progress(done, total)``; total None when unknown
ProgressCallback = Callable[[float, "float | None"], None]


class LogTimeProgress:
    """Report progress through a log as seconds of log time since its first message.

    Parameters
    ----------
    callback : ProgressCallback or None
        Called with ``(seconds done, log duration in seconds or None)``; None: do nothing.
    time_range : (start_ns, end_ns) or None
        The log's message time range from its summary, if it has one.
    passes : int
        How many times the caller reads the log (see :meth:`next_pass`).
    """

    def __init__(
        self,
        callback: ProgressCallback | None,
        time_range: tuple[int, int] | None,
        *,
        passes: int = 1,
    ) -> None:
        self.callback = callback
        self.passes = passes
        self.pass_index = 0
        self.start_ns = None if time_range is None else int(time_range[0])
        end = None if time_range is None else int(time_range[1])
        self.total_s = (
            None
            if end is None or self.start_ns is None or end <= self.start_ns
            else (end - self.start_ns) * 1e-9
        )

    def at(self, t_ns: int) -> None:
        """The work has reached log time ``t_ns`` (nanoseconds, the log's clock)."""
        if self.callback is None:
            return
        if self.start_ns is None:
            self.start_ns = int(t_ns)
        done = max(0.0, (int(t_ns) - self.start_ns) * 1e-9)
        if self.total_s is not None:
            done = min(done, self.total_s) + self.pass_index * self.total_s
        self.callback(done, None if self.total_s is None else self.passes * self.total_s)

    def next_pass(self) -> None:
        """A function reading the log ``passes`` times starts its next pass (the reported
        total is ``passes`` x the log's duration)."""
        self.pass_index = min(self.pass_index + 1, self.passes - 1)

    def batch(self, batch: Any) -> None:
        """The work has reached the end of a :class:`~imufdi_cli.mcapio.MessageBatch`."""
        if self.callback is not None and len(batch):
            self.at(int(batch.log_time.max()))

    def finish(self) -> None:
        """The work is complete."""
        if self.callback is not None and self.total_s is not None:
            self.callback(self.passes * self.total_s, self.passes * self.total_s)
