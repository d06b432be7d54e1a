"""Start-up time of the CLI against ``python -c "import numpy"``, same run.

Usage: python benchmarks/bench_startup.py [--repeat 15] [--bytecode both|warm|source]

Every stage of a shell pipeline and every TAB completion pays the CLI's start-up, so it is
measured as a ratio against the floor any numpy tool pays: a fresh interpreter importing
numpy. Each command runs ``--repeat`` times in fresh processes, interleaved so that a
change of machine load hits all of them alike; the median wall time (the claim) and the
median CPU time (user + system, less sensitive to a loaded machine; compare it between
checkouts, not to numpy: ``python -c "import numpy"`` spends CPU in OpenBLAS's threads,
while imufdi sets one BLAS thread before numpy loads) are reported.

Target (docs/performance.md): ``imufdi --help`` and ``imufdi info small.mcap``
each <= 2x ``python -c "import numpy"``. Also prints which heavy modules (scipy, the
detectors, matplotlib, rich's markdown) ``imufdi --help`` imports: none should be there,
and whether ``imufdi info`` in a pipe imports rich (it should not).

``--detect``: instead, ``imufdi detect LOG -d NAME`` for every detector on a 3 s
wearable12 log simulated at run time (start-up, calibration and a few hundred samples:
what a user waits for on a short log), median CPU per detector, interleaved with the same
commands of another checkout (``--before``, e.g. an exported copy of main) and with
``python -c "import numpy"``; the ratio after/before is the claim (no detector
imports scipy.stats or scipy.signal).

``--scipy``: instead, what importing scipy's subpackages costs over ``python -c "import
numpy"`` (interleaved, median CPU and peak RSS): the price each one puts on a command that
uses it (docs/architecture.md lists which code imports which, always where it is used).

Two bytecode states, each against its own numpy baseline (numpy's bytecode is installed
with it in both): ``warm`` — the project's ``__pycache__`` written and used, as after
``pip install`` or any earlier run; ``source`` — the project's modules compiled from
source at every start (its ``__pycache__`` removed, ``PYTHONDONTWRITEBYTECODE=1``), as in a
shell that sets that variable and runs a checkout with ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SMALL = ROOT / "imufdi_cli" / "sample_logs" / "paper-table4.mcap"


def _time(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one run; CPU = user + system of the child. It runs in the
    timed checkout (``-m`` and ``-c`` put the working directory first on sys.path)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(
        cmd,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
        cwd=env["IMUFDI_BENCH_TREE"],
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _environment(bytecode: str, tree: Path = ROOT) -> dict[str, str]:
    """The environment of one bytecode state (see the module docstring) running the
    ``imufdi_cli`` of checkout ``tree``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), env.get("PYTHONPATH")]))
    env["IMUFDI_BENCH_TREE"] = str(tree)
    if bytecode == "source":
        for cache in (tree / "imufdi_cli").rglob("__pycache__"):
            shutil.rmtree(cache, ignore_errors=True)
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    else:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def measure(bytecode: str, repeat: int, tree: Path = ROOT) -> dict[str, float]:
    """Median wall time per command, and print the ratios to the numpy import."""
    py = sys.executable
    commands = {
        "python -c 'import numpy'": [py, "-c", "import numpy"],
        "imufdi --help": [py, "-m", "imufdi_cli", "--help"],
        "imufdi info small.mcap": [py, "-m", "imufdi_cli", "info", str(SMALL)],
    }
    env = _environment(bytecode, tree)
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in commands}
    for cmd in commands.values():  # warm the file cache (and, if warm, the bytecode) once
        _time(cmd, env)
    for _ in range(repeat):
        for name, cmd in commands.items():
            times[name].append(_time(cmd, env))
    wall = {name: statistics.median(t[0] for t in values) for name, values in times.items()}
    cpu = {name: statistics.median(t[1] for t in values) for name, values in times.items()}
    floor, cpu_floor = wall["python -c 'import numpy'"], cpu["python -c 'import numpy'"]
    print(f"bytecode: {bytecode}  (median wall; median CPU = user + system)")
    for name in commands:
        print(
            f"  {name:28s} wall {wall[name] * 1000:7.1f} ms {wall[name] / floor:5.2f}x"
            f"   CPU {cpu[name] * 1000:7.1f} ms {cpu[name] / cpu_floor:5.2f}x numpy import"
        )
    return {name: wall[name] / floor for name in commands}


def measure_detect(repeat: int, tree: Path, before: Path | None) -> None:
    """Median CPU of ``imufdi detect`` per detector for ``tree`` (and ``before``),
    interleaved, warm bytecode; prints the ratios."""
    import tempfile

    py = sys.executable
    trees = {"after": tree} if before is None else {"after": tree, "before": before}
    envs = {name: _environment("warm", path) for name, path in trees.items()}
    work = Path(tempfile.mkdtemp(prefix="imufdi-bench-startup-"))
    log = work / "wearable12.mcap"
    simulate = ["simulate", "--preset", "wearable12", "--duration", "3s", "-o", str(log)]
    subprocess.run(
        [py, "-m", "imufdi_cli", *simulate],
        check=True,
        env=envs["after"],
        cwd=tree,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    names = [
        "ap-consistency",
        "bank",
        "cnn-map",
        "glt",
        "noise-glr",
        "pca-parity",
        "px4-selector",
        "woa-mvmd-glt",
    ]
    commands = {
        name: [py, "-m", "imufdi_cli", "detect", str(log), "-d", name, "-o", str(work / "out.mcap")]
        for name in names
    }
    numpy_cmd = [py, "-c", "import numpy"]
    cpu: dict[tuple[str, str], list[float]] = {}
    for _ in range(repeat + 1):  # the first round warms the file cache and the bytecode
        for name, cmd in [("python -c 'import numpy'", numpy_cmd), *commands.items()]:
            for which, env in envs.items():
                cpu.setdefault((name, which), []).append(_time(cmd, env)[1])
    shutil.rmtree(work, ignore_errors=True)
    median = {key: statistics.median(values[1:]) for key, values in cpu.items()}
    print(f"imufdi detect, 3 s wearable12 log, median CPU (user + system) of {repeat} runs")
    for name in ["python -c 'import numpy'", *names]:
        after = median[(name, "after")]
        line = f"  {name:26s} after {after * 1000:7.1f} ms"
        if before is not None:
            was = median[(name, "before")]
            line += f"   before {was * 1000:7.1f} ms   after/before {after / was:5.2f}"
        print(line)


def measure_scipy(repeat: int) -> None:
    """Median CPU and peak RSS of importing numpy then one scipy subpackage, interleaved
    with ``import numpy`` alone; prints the excess over it."""
    py = sys.executable
    modules = ["numpy", "scipy.special", "scipy.optimize", "scipy.signal", "scipy.stats"]
    env = _environment("warm")
    samples: dict[str, list[tuple[float, int]]] = {m: [] for m in modules}
    for round_ in range(repeat + 1):  # the first round warms the file cache
        for module in modules:
            code = "import numpy" if module == "numpy" else f"import numpy, {module}"
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            done = subprocess.run(
                [py, "-c", code + "; import resource; "
                 "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"],
                check=True, capture_output=True, text=True, env=env, cwd=env["IMUFDI_BENCH_TREE"],
            )  # fmt: skip
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            if round_:
                samples[module].append((cpu, int(done.stdout.split()[-1])))
    cpu = {m: statistics.median(c for c, _ in v) for m, v in samples.items()}
    rss = {m: statistics.median(r for _, r in v) for m, v in samples.items()}
    print(f"import numpy, then scipy's subpackage: median of {repeat} runs, over numpy alone")
    print(
        f"  {'numpy':16s} CPU {cpu['numpy'] * 1000:6.1f} ms   peak RSS {rss['numpy'] / 1024:6.1f} MiB"
    )
    for module in modules[1:]:
        extra_cpu, extra_rss = cpu[module] - cpu["numpy"], (rss[module] - rss["numpy"]) / 1024
        print(
            f"  {module:16s} CPU +{extra_cpu * 1000:6.1f} ms ({cpu[module] / cpu['numpy']:4.2f}x)"
            f"   peak RSS +{extra_rss:6.1f} MiB"
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=15)
    parser.add_argument("--bytecode", choices=("both", "warm", "source"), default="both")
    parser.add_argument(
        "--tree",
        type=Path,
        default=ROOT,
        help="checkout whose imufdi_cli is timed (e.g. an exported copy of main, to compare"
        " before/after in one run); its __pycache__ is removed for --bytecode source",
    )
    parser.add_argument(
        "--detect",
        action="store_true",
        help="time `imufdi detect -d NAME` for every detector instead (see the docstring)",
    )
    parser.add_argument(
        "--before",
        type=Path,
        default=None,
        help="with --detect: a second checkout timed in the same rounds (e.g. main)",
    )
    parser.add_argument(
        "--scipy",
        action="store_true",
        help="time the import of scipy's subpackages over numpy's instead (see the docstring)",
    )
    args = parser.parse_args()
    py = sys.executable
    if args.scipy:
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        print(f"load average: {load} (2-core target machine; ratios, not seconds, are the claim)")
        measure_scipy(args.repeat)
        return 0
    if args.detect:
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        print(f"load average: {load} (2-core target machine; ratios, not seconds, are the claim)")
        measure_detect(args.repeat, args.tree, args.before)
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        print(f"load average at the end: {load}")
        return 0
    modes = ("source", "warm") if args.bytecode == "both" else (args.bytecode,)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"load average: {load} (2-core target machine; ratios, not seconds, are the claim)")
    if args.tree != ROOT:
        print(f"tree: {args.tree}")
    ratios = {mode: measure(mode, args.repeat, args.tree) for mode in modes}
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"load average at the end: {load}")
    heavy = ("scipy", "matplotlib", "imufdi_cli.detectors.", "imufdi_cli.campaign", "dask")
    probe = (
        "import runpy, sys\n"
        "sys.argv = ['imufdi', '--help']\n"
        "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        f"print(sorted({{m.split('.')[0] if not m.startswith('imufdi') else m "
        f"for m in sys.modules if m.startswith({heavy!r}) and not m.endswith('.base')}}))"
    )
    env = _environment("warm", args.tree)
    done = subprocess.run(
        [py, "-c", probe], capture_output=True, text=True, check=True, env=env, cwd=args.tree
    )
    imported = done.stdout.strip().splitlines()[-1]
    print(f"heavy modules imported by --help: {imported}")
    pipe_probe = probe.replace("'--help'", f"'info', {str(SMALL)!r}").replace(
        f"m.startswith({heavy!r})", "m.startswith('rich')"
    )
    done = subprocess.run(
        [py, "-c", pipe_probe], capture_output=True, text=True, check=True, env=env, cwd=args.tree
    )
    print(f"rich modules imported by info in a pipe: {done.stdout.strip().splitlines()[-1]}")
    for mode, by_command in ratios.items():
        ok = all(by_command[n] <= 2.0 for n in ("imufdi --help", "imufdi info small.mcap"))
        print(f"target <= 2x ({mode} bytecode): " + ("met" if ok else "NOT met"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
