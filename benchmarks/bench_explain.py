"""Benchmark: where the episode explanations of ``imufdi detect -d glt`` spend their CPU.

The targets (docs/performance.md): ``detect -d glt`` with explanations at most 2x ``imufdi
info``, ``--no-explain`` at most 1.3x. On a clean 16-IMU turntable log glt at alpha = 1 %
raises thousands of false alarm episodes an hour (docs/episodes.md). This runs ``detect -d
glt`` on a simulated log (tuning seed ``--seed``) with and without explanations, and with
timers around the explanation's parts:

- closing episodes: each episode's window, its isolated sensor's consensus residual and
  the healthy sensors' residuals (the fit's arguments);
- the one-sample episodes of the per-sample test, explained by their sample alone
  (:meth:`~imufdi_cli.episodes.EpisodeBuilder._explain_samples`);
- the fits of the others, batched across episodes
  (:func:`~imufdi_cli.episodes.batch.fit_models_batch`);
- the variance-drop monitor, and the builder's own bookkeeping (runs, fragments) besides.

It prints CPU seconds, ms per episode, each part's share and the load average (a shared
machine: the shares mean more than the seconds), and checks on the captured motion designs
that numpy's stacked SVD gives the one-by-one floats.

    python benchmarks/bench_explain.py                # 10-minute log
    python benchmarks/bench_explain.py --minutes 3

With ``--reference`` (a copy of the ``episodes`` package, e.g. main's) it also replays every
call detect made to its episode builders (construction, measurements, status rows, finish)
through the reference package's builders and this one's, alternating call by call so that
the load of a shared machine falls on both alike; it compares every explained episode
(``to_dict()``, JSON: every bit of a float) and prints the CPU of both and their ratio::

    rm -rf /tmp/episodes_ref && mkdir /tmp/episodes_ref
    git archive main imufdi_cli/episodes | tar -x -C /tmp/episodes_ref
    python benchmarks/bench_explain.py --reference /tmp/episodes_ref/imufdi_cli/episodes
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the CLI's pin: the thread count changes bits

import numpy as np

import imufdi_cli.episodes.builder as builder_module
from imufdi_cli.detect import detect_file
from imufdi_cli.pipeline import simulate_file


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


class Timers:
    """Process-CPU timers around module functions (restored by :meth:`restore`)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = collections.defaultdict(float)
        self.calls: collections.Counter[str] = collections.Counter()
        self._restore: list[tuple[Any, str, Any]] = []
        self.designs: list[np.ndarray] = []

    def wrap(self, owner: Any, name: str, key: str) -> None:
        inner = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            begin = time.process_time()
            try:
                return inner(*args, **kwargs)
            finally:
                self.seconds[key] += time.process_time() - begin
                self.calls[key] += 1

        self._restore.append((owner, name, inner))
        setattr(owner, name, timed)

    def restore(self) -> None:
        for owner, name, inner in reversed(self._restore):
            setattr(owner, name, inner)
        self._restore.clear()


class BuilderCalls:
    """Every top-level call detect makes to an :class:`EpisodeBuilder` (construction,
    ``feed``, ``rows``, ``finish``), inputs copied, in order; nested ones (a builder's own
    variance-drop builder) are left to the builder being replayed."""

    def __init__(self) -> None:
        self.events: list[tuple[str, int, tuple[Any, ...], dict[str, Any]]] = []
        self._ids: dict[int, int] = {}
        self._depth = 0
        self._restore: list[tuple[str, Any]] = []

    def start(self) -> None:
        cls = builder_module.EpisodeBuilder
        for name in ("__init__", "feed", "rows", "finish"):
            inner = getattr(cls, name)
            self._restore.append((name, inner))
            setattr(cls, name, self._spy(name, inner))

    def stop(self) -> None:
        for name, inner in self._restore:
            setattr(builder_module.EpisodeBuilder, name, inner)
        self._restore.clear()

    def _spy(self, name: str, inner: Any) -> Any:
        def spy(builder: Any, *args: Any, **kwargs: Any) -> Any:
            top = self._depth == 0
            if top and name != "__init__" and id(builder) in self._ids:
                self.events.append(
                    (name, self._ids[id(builder)], copy.deepcopy(args), copy.deepcopy(kwargs))
                )
            self._depth += 1
            try:
                return inner(builder, *args, **kwargs)
            finally:
                self._depth -= 1
                if top and name == "__init__":
                    self._ids[id(builder)] = len(self._ids)
                    self.events.append(
                        (name, self._ids[id(builder)], copy.deepcopy(args), copy.deepcopy(kwargs))
                    )

        return spy


def replay(
    events: list[tuple[str, int, tuple[Any, ...], dict[str, Any]]], packages: dict[str, Any]
) -> tuple[dict[str, float], int, int]:
    """The calls through each package's EpisodeBuilder, alternating call by call (which goes
    first alternates too): CPU per package, episodes, episodes that differ."""
    builders: dict[str, dict[int, Any]] = {name: {} for name in packages}
    spent = dict.fromkeys(packages, 0.0)
    episodes = differ = 0
    order = list(packages)
    for i, (name, ident, args, kwargs) in enumerate(events):
        outputs = {}
        for side in order if i % 2 == 0 else order[::-1]:
            call_args, call_kwargs = copy.deepcopy(args), copy.deepcopy(kwargs)
            begin = time.process_time()
            if name == "__init__":
                builders[side][ident] = packages[side].EpisodeBuilder(*call_args, **call_kwargs)
                result = None
            else:
                result = getattr(builders[side][ident], name)(*call_args, **call_kwargs)
            spent[side] += time.process_time() - begin
            if result is not None:
                outputs[side] = [json.dumps(e.to_dict(), sort_keys=True) for e in result]
        if outputs:
            first, *rest = outputs.values()
            episodes += len(first)
            differ += sum(
                any(a != b for a, b in zip(first, o)) or len(o) != len(first) for o in rest
            )
    return spent, episodes, differ


def monitor_rows(
    events: list[tuple[str, int, tuple[Any, ...], dict[str, Any]]], packages: dict[str, Any]
) -> tuple[int, int]:
    """The variance-drop monitor of each package (a builder made from the arguments of the
    first builder detect fed) on every measurement block fed to that builder: (blocks, blocks
    whose status rows differ in any bit). Its rows become episodes only on an alarm, so
    the episodes alone do not show its statistic."""
    fed = next((e[1] for e in events if e[0] == "feed"), None)
    init = next((e for e in events if e[0] == "__init__" and e[1] == fed), None)
    if init is None:
        return 0, 0
    blocks = [e[2][0] for e in events if e[0] == "feed" and e[1] == fed]
    monitors = {}
    for name, package in packages.items():
        kwargs = {**init[3], "variance_drop": True}
        drop = package.EpisodeBuilder(*init[2], **kwargs)._drop
        if drop is None:
            return 0, 0
        monitors[name] = drop[0]
    differ = 0
    for block in blocks:
        rows = [monitors[name].update(block.copy()) for name in packages]
        fields = ("alarm", "isolated", "statistic", "threshold")
        differ += any(
            getattr(rows[0], f).tobytes() != getattr(other, f).tobytes()
            for other in rows[1:]
            for f in fields
        )
    return len(blocks), differ


def stacked_identity(designs: list[np.ndarray]) -> tuple[int, int]:
    """(groups, matrices) of the captured motion designs stacked by shape whose stacked
    SVD equals the one-by-one SVD to the bit; raises if one differs."""
    groups: dict[tuple[int, ...], list[np.ndarray]] = collections.defaultdict(list)
    for design in designs:
        groups[design.shape].append(design)
    checked = 0
    for members in groups.values():
        if len(members) < 2:
            continue
        stack = np.stack(members)
        u, s, vt = np.linalg.svd(stack, full_matrices=False)
        for i, design in enumerate(members):
            one = np.linalg.svd(design, full_matrices=False)
            if not all(np.array_equal(a, b[i]) for a, b in zip(one, (u, s, vt))):
                raise AssertionError(f"stacked SVD differs for a {design.shape} design")
            checked += 1
    return sum(len(m) >= 2 for m in groups.values()), checked


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="clean log length")
    parser.add_argument("--seed", type=int, default=1, help="simulation seed (tuning seeds)")
    parser.add_argument("--repeat", type=int, default=2, help="runs of each mode (best kept)")
    parser.add_argument(
        "--reference", help="copy of the episodes package to replay the builders' calls through"
    )
    parser.add_argument("--log", help="an existing MCAP log instead of the simulated one")
    args = parser.parse_args()
    print(f"load average before: {load()} ({os.cpu_count()} cores)")
    with tempfile.TemporaryDirectory(prefix="imufdi-bench-explain-") as tmp:
        log, out = Path(args.log or Path(tmp) / "clean.mcap"), str(Path(tmp) / "out.mcap")
        if args.log is None:
            simulate_file(
                None,
                str(log),
                seed=args.seed,
                options={
                    "imus": 16,
                    "rate": "100Hz",
                    "duration": f"{args.minutes * 60}s",
                    "motion": "turntable",
                },
            )

        def cpu(explain: bool) -> float:
            best = float("inf")
            for _ in range(args.repeat):
                begin = time.process_time()
                detect_file(str(log), out, [("glt", {})], explain=explain)
                best = min(best, time.process_time() - begin)
            return best

        cpu(False)  # warm: imports, the quantile caches
        plain, explained = cpu(False), cpu(True)
        timers = Timers()
        timers.wrap(builder_module.EpisodeBuilder, "_close", "close")
        timers.wrap(builder_module.EpisodeBuilder, "_explain_samples", "samples")
        timers.wrap(builder_module, "fit_models_batch", "fits")
        timers.wrap(builder_module.VarianceDropMonitor, "update", "monitor")
        svd = np.linalg.svd  # the motion fit's SVD (the reduced one, with vectors)

        def capture(a: Any, *args: Any, **kwargs: Any) -> Any:
            if kwargs.get("full_matrices") is False and len(timers.designs) < 4000:
                timers.designs.append(np.array(a))
            return svd(a, *args, **kwargs)

        np.linalg.svd = capture  # type: ignore[assignment]
        try:
            begin = time.process_time()
            detect_file(str(log), out, [("glt", {})])
            timed = time.process_time() - begin
        finally:
            np.linalg.svd = svd  # type: ignore[assignment]
            timers.restore()
        calls = BuilderCalls()
        if args.reference:
            calls.start()
            try:
                detect_file(str(log), out, [("glt", {})])
            finally:
                calls.stop()
    episodes = timers.calls["close"]
    explanation = explained - plain
    sec = timers.seconds
    builder = sec["close"] + sec["samples"] + sec["fits"] + sec["monitor"]
    parts = {
        "closing episodes (windows, consensus, fit arguments)": sec["close"],
        "one-sample episodes by their sample": sec["samples"],
        "fits of the others, batched across episodes": sec["fits"],
        "variance-drop monitor": sec["monitor"],
    }
    what = args.log or f"clean {args.minutes:g}-minute turntable log, seed {args.seed}"
    print(f"{what}: {episodes:,} episodes")
    print(f"detect -d glt CPU: {explained:.2f} s, --no-explain {plain:.2f} s")
    print(
        f"explanations: {explanation:.2f} s = {explanation / max(episodes, 1) * 1e3:.2f} ms an"
        f" episode ({explanation / explained:.0%} of detect's CPU)"
    )
    print(f"split (timed run, {timed:.2f} s CPU; these parts {builder:.2f} s):")
    for key, value in parts.items():
        print(
            f"  {key:58s} {value:6.2f} s  {value / max(explanation, 1e-9):6.1%}"
            f"  {value / max(episodes, 1) * 1e3:6.3f} ms/episode"
        )
    groups, checked = stacked_identity(timers.designs)
    print(
        f"stacked SVD of {checked:,} captured motion designs in {groups} shape groups:"
        " identical to one-by-one to the bit"
    )
    if args.reference:
        from bench_fit_models import load_reference

        import imufdi_cli.episodes as this_package

        packages = {"reference": load_reference(args.reference), "this": this_package}
        best: dict[str, float] = {}
        for _ in range(args.repeat):
            spent, count, differ = replay(calls.events, packages)
            best = {k: min(best.get(k, float("inf")), v) for k, v in spent.items()}
        print(
            f"builders' calls replayed ({len(calls.events):,} calls, {count:,} episodes,"
            f" alternated call by call): reference {best['reference']:.2f} s,"
            f" this {best['this']:.2f} s CPU, ratio {best['this'] / best['reference']:.3f};"
            f" episodes that differ: {differ}"
        )
        blocks, rows_differ = monitor_rows(calls.events, packages)
        print(
            f"variance-drop monitor on the {blocks:,} measurement blocks fed:"
            f" status rows that differ (alarm, isolated, statistic, threshold): {rows_differ}"
        )
        differ += rows_differ
        if differ:
            print(f"load average after: {load()}")
            return 1
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
