"""Benchmark and identity check of the episode fits: this ``episodes.fit_models`` against a
reference copy of the ``episodes`` package (or of the ``episodes.py`` it was split from) on
calls captured from real detect runs.

Performance work on the fitting functions must not change a float (a change of
classification is a change of method, made on purpose). This captures every
``fit_models`` call (arguments and result) of ``imufdi detect`` runs on simulated logs,
replays each through the worktree's ``fit_models`` and through the reference module (for
example the file as it is on main), compares the fits bit for bit (JSON of every field,
fitted curves included) and prints the CPU of both, their ratio and the load average.

    rm -rf /tmp/episodes_ref && mkdir /tmp/episodes_ref
    git archive main imufdi_cli/episodes | tar -x -C /tmp/episodes_ref
    python benchmarks/bench_fit_models.py --reference /tmp/episodes_ref/imufdi_cli/episodes
    python benchmarks/bench_fit_models.py --reference /tmp/episodes_ref/imufdi_cli/episodes \
        --minutes 10

(a single file, e.g. ``git show 1234abc:imufdi_cli/episodes.py`` from before the split, is
loaded as it is.)

Logs (made at run time; tuning seeds only): a 16-IMU 100 Hz turntable log of ``--minutes``
(glt's false episodes), and paper-table4 with a step, drift, noise, stuck, spikes and scale
fault injected, seed ``--seed``, run through glt, pca-parity, noise-glr and bank.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import imufdi_cli.episodes as episodes
import imufdi_cli.episodes.builder as builder_module
from imufdi_cli.detect import detect_file
from imufdi_cli.faults import inject_file
from imufdi_cli.pipeline import simulate_file

FAULTS = [
    "step:imu{i}.gyro.x,at={at}s,duration=4s,amp=0.9deg/s",
    "drift:imu{i}.gyro.y,at={at}s,duration=4s,rate=10deg/s^2",
    "noise:imu{i}.gyro.z,at={at}s,duration=4s,factor=3",
    "stuck:imu{i}.gyro.x,at={at}s,duration=4s",
    "spikes:imu{i}.gyro.y,at={at}s,duration=4s,rate=5Hz,amp=3deg/s",
    "scale:imu{i}.gyro.z,at={at}s,duration=4s,factor=1.05",
]


def capture(workdir: Path, minutes: float, seed: int) -> list[tuple[Any, ...]]:
    """Every fit_models call (args, kwargs) of the detect runs."""
    calls: list[tuple[Any, ...]] = []
    inner = builder_module.fit_models_batch  # what EpisodeBuilder calls, per batch

    def spy(problems: Any) -> Any:
        calls.extend(problems)
        return inner(problems)

    turntable, table4, faulty = (workdir / n for n in ("t.mcap", "p.mcap", "pf.mcap"))
    out = workdir / "out.mcap"
    simulate_file(
        None,
        str(turntable),
        seed=seed,
        options={
            "imus": 16,
            "rate": "100Hz",
            "duration": f"{minutes * 60}s",
            "motion": "turntable",
        },
    )
    simulate_file("paper-table4", str(table4), seed=seed, options={"duration": 70.0})
    specs = [f.format(i=j % 4, at=8 + 10 * j + 0.37) for j, f in enumerate(FAULTS)]
    inject_file(str(table4), str(faulty), specs, [], seed=seed)
    builder_module.fit_models_batch = spy  # type: ignore[assignment]
    try:
        detect_file(str(turntable), str(out), [("glt", {})])
        for name in ("glt", "pca-parity", "noise-glr", "bank"):
            detect_file(str(faulty), str(out), [(name, {})])
    finally:
        builder_module.fit_models_batch = inner  # type: ignore[assignment]
    return calls


def load_reference(path: str) -> Any:
    """The reference module: one file, or a copy of the package (a directory), loaded as
    ``episodes_reference`` with its own ``imufdi_cli.episodes`` imports pointed at itself."""
    if Path(path).is_dir():
        copy = Path(tempfile.mkdtemp(prefix="imufdi-episodes-ref-")) / "episodes_reference"
        copy.mkdir()
        for source in Path(path).glob("*.py"):
            text = source.read_text().replace("imufdi_cli.episodes", "episodes_reference")
            (copy / source.name).write_text(text)
        spec = importlib.util.spec_from_file_location(
            "episodes_reference", copy / "__init__.py", submodule_search_locations=[str(copy)]
        )
    else:
        spec = importlib.util.spec_from_file_location("episodes_reference", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules["episodes_reference"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def fingerprint(fits: list[Any]) -> list[tuple[str, Any]]:
    """Every field of every fit to the bit (JSON keeps a float's bits), curves included."""
    out = []
    for fit in fits:
        curve = None if fit.curve is None else (fit.curve[0].tobytes(), float(fit.curve[1]).hex())
        out.append((json.dumps(fit.to_dict(), sort_keys=True), curve))
    return out


def compare_batches(calls: list[Any], repeat: int) -> None:
    """The same windows through ``fit_models_batch`` (as the builder fits them, in batches
    of ``builder.FIT_BATCH``) against ``fit_models`` one at a time, alternated: CPU and
    ratio, and how the fits agree (the model ranking and every onset and end exactly; sizes,
    bounds and BICs to a relative 1e-9: the batched sums are taken in another order)."""
    from imufdi_cli.episodes.batch import fit_models_batch

    size = builder_module.FIT_BATCH
    best = {"serial": float("inf"), "batched": float("inf")}
    serial: list[Any] = []
    batched: list[Any] = []
    for _ in range(repeat):
        begin = time.process_time()
        serial = [episodes.fit_models(*a, **k) for a, k in calls]
        middle = time.process_time()
        batched = []
        for start in range(0, len(calls), size):
            batched += fit_models_batch(calls[start : start + size])
        best["serial"] = min(best["serial"], middle - begin)
        best["batched"] = min(best["batched"], time.process_time() - middle)
    ranking = values = 0
    for one, many in zip(serial, batched, strict=True):
        if [(f.model, f.onset_index, f.end_index) for f in one] != [
            (f.model, f.onset_index, f.end_index) for f in many
        ]:
            ranking += 1
            continue
        for f, g in zip(one, many, strict=True):
            for x, y in ((f.size, g.size), (f.low, g.low), (f.high, g.high), (f.bic, g.bic)):
                if x == y or (x != x and y != y):  # (infinities and NaNs alike)
                    continue
                if not abs(x - y) <= 1e-9 * max(abs(x), abs(y), 1e-300):
                    values += 1
    print(
        f"batched ({size} windows a call): CPU serial {best['serial']:.2f} s, batched"
        f" {best['batched']:.2f} s, ratio {best['batched'] / best['serial']:.3f};"
        f" windows ranked differently {ranking}, values beyond 1e-9 {values}, of {len(calls)}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--reference", required=True, help="copy of the episodes package or episodes.py"
    )
    parser.add_argument("--minutes", type=float, default=3.0, help="turntable log length")
    parser.add_argument("--seed", type=int, default=1, help="simulation seed (tuning seeds)")
    parser.add_argument("--repeat", type=int, default=2, help="alternated passes (best kept)")
    args = parser.parse_args()
    reference = load_reference(args.reference)
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    with tempfile.TemporaryDirectory(prefix="imufdi-bench-fits-") as tmp:
        calls = capture(Path(tmp), args.minutes, args.seed)
    print(f"{len(calls)} fit_models calls captured")

    def as_reference(kwargs: dict[str, Any]) -> dict[str, Any]:
        ref = kwargs.get("reference")
        if ref is None:
            return kwargs
        # every field the reference's Reference has (an older one may lack the newer ones,
        # e.g. correlation_sq: leaving a field out would compare different inputs)
        names = [f.name for f in dataclasses.fields(reference.Reference)]
        converted = reference.Reference(**{name: getattr(ref, name) for name in names})
        return {**kwargs, "reference": converted}

    differ = 0
    best = {"reference": float("inf"), "this": float("inf")}
    for _ in range(args.repeat):
        spent = {"reference": 0.0, "this": 0.0}
        for call_args, kwargs in calls:
            begin = time.process_time()
            expected = reference.fit_models(*call_args, **as_reference(kwargs))
            middle = time.process_time()
            got = episodes.fit_models(*call_args, **kwargs)
            spent["reference"] += middle - begin
            spent["this"] += time.process_time() - middle
            differ += fingerprint(expected) != fingerprint(got)
        best = {k: min(best[k], v) for k, v in spent.items()}
    print(f"fits that differ: {differ} of {len(calls) * args.repeat}")
    print(
        f"CPU: reference {best['reference']:.2f} s, this {best['this']:.2f} s"
        f" ({best['this'] / max(len(calls), 1) * 1e3:.2f} ms a call),"
        f" ratio {best['this'] / best['reference']:.3f}"
    )
    compare_batches(calls, args.repeat)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
