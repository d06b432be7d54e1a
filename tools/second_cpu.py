"""Print the environment of a second CPU configuration, for running the tests on it.

The last bits of floating-point results depend on which SIMD loops numpy dispatches to and
which kernel OpenBLAS picks for the CPU; the test suite must pass whatever they are
(tests/references.py). This chooses, on this machine, a configuration other than the
default, valid on any x86-64 machine that can run the default:

- ``NPY_DISABLE_CPU_FEATURES``: the highest SIMD level among the targets numpy dispatches to
  and this CPU has, switched off (on an AVX-512 machine every AVX-512 target, so numpy runs
  its AVX2 loops; on an AVX2 machine the AVX2 targets, so it runs its SSE loops), read at
  run time from numpy (target names differ between numpy releases);
- ``OPENBLAS_CORETYPE``: a kernel older than the one OpenBLAS picks for this CPU, from the
  CPU's flags: Haswell (AVX2 + FMA) where AVX-512 exists, Sandybridge (AVX) where AVX2 is
  the best, Nehalem (SSE4.2) where AVX is, Prescott (SSE3) otherwise.

Prints ``NAME=value`` lines on stdout (for ``env``), and on stderr what numpy and OpenBLAS
run with and without them (checked in a fresh interpreter)::

    mapfile -t cpu < <(python tools/second_cpu.py) && env "${cpu[@]}" python -m pytest
"""

from __future__ import annotations

import ctypes
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

#: OpenBLAS kernels from the newest to the oldest, each with the CPU flags (as Linux names
#: them in /proc/cpuinfo) that it needs
KERNELS = (
    ("SkylakeX", {"avx512f", "avx2", "fma"}),
    ("Haswell", {"avx2", "fma"}),
    ("Sandybridge", {"avx"}),
    ("Nehalem", {"sse4_2"}),
    ("Prescott", {"pni"}),  # SSE3
)

_SIMD_STATE = """
import json, numpy as np
try:
    from numpy._core import _multiarray_umath as m
except ImportError:
    from numpy.core import _multiarray_umath as m
import scipy.linalg  # noqa: F401 (loads scipy's OpenBLAS)
print(json.dumps({
    "numpy": np.__version__,
    "dispatch": list(m.__cpu_dispatch__),
    "baseline": list(m.__cpu_baseline__),
    "features": {k: bool(v) for k, v in m.__cpu_features__.items()},
    "openblas": __CORES__(),
}))
"""


def openblas_cores() -> dict[str, str]:
    """Library file name -> core name of every OpenBLAS loaded in this process (Linux)."""
    cores: dict[str, str] = {}
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return cores
    paths = sorted(
        {
            line.split()[-1]
            for line in maps.splitlines()
            if "openblas" in line.lower() and "/" in line
        }
    )
    for path in paths:
        try:
            library = ctypes.CDLL(path)
        except OSError:
            continue
        for symbol in (
            "scipy_openblas_get_corename64_",
            "scipy_openblas_get_corename",
            "openblas_get_corename64_",
            "openblas_get_corename",
        ):
            function = getattr(library, symbol, None)
            if function is not None:
                function.restype = ctypes.c_char_p
                cores[Path(path).name] = function().decode()
                break
    return cores


def state(env: dict[str, str]) -> dict:
    """numpy's SIMD targets and OpenBLAS's cores in a fresh interpreter with ``env``."""
    code = (
        "import ctypes, sys\nfrom pathlib import Path\n"
        + _function_source()
        + _SIMD_STATE.replace("__CORES__", "openblas_cores")
    )
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    result: dict = json.loads(done.stdout)
    return result


def _function_source() -> str:
    import inspect

    return inspect.getsource(openblas_cores) + "\n"


def _tier(target: str) -> int | None:
    """SIMD level of an x86 dispatch target of numpy (None: another architecture's)."""
    if target.startswith("AVX512") or target == "X86_V4":
        return 4
    if target in {"AVX", "F16C", "FMA3", "AVX2", "X86_V3"}:
        return 3
    if target.startswith(("SSE", "SSSE")) or target in {"POPCNT", "X86_V2"}:
        return 2
    return None


def simd_to_disable(dispatch: list[str], features: dict[str, bool]) -> list[str]:
    """The dispatch targets of the highest SIMD level this CPU has (on another architecture
    than x86, the last, i.e. highest, target it has)."""
    available = [target for target in dispatch if features.get(target)]
    tiers = [_tier(target) for target in available]
    if not available:
        return []
    if all(tier is not None for tier in tiers):
        top = max(t for t in tiers if t is not None)
        return [target for target, tier in zip(available, tiers) if tier == top]
    return available[-1:]


def cpu_flags() -> set[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def older_kernel(flags: set[str]) -> str | None:
    """The kernel one step below the newest this CPU can run (None if it runs none)."""
    runnable = [name for name, needs in KERNELS if needs <= flags]
    if not runnable:
        return None
    newest = [name for name, _ in KERNELS].index(runnable[0])
    older = [name for name, needs in KERNELS[newest + 1 :] if needs <= flags]
    return older[0] if older else None


def main() -> int:
    base_env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE")
    }
    default = state(base_env)
    chosen: dict[str, str] = {}
    disable = simd_to_disable(default["dispatch"], default["features"])
    if disable:
        chosen["NPY_DISABLE_CPU_FEATURES"] = " ".join(disable)
    kernel = (
        older_kernel(cpu_flags()) if platform.machine().lower() in ("x86_64", "amd64") else None
    )
    if kernel is not None:
        chosen["OPENBLAS_CORETYPE"] = kernel
    second = state({**base_env, **chosen})

    def loops(s: dict) -> str:
        on = [t for t in s["dispatch"] if s["features"].get(t)]
        return " ".join(on) if on else f"baseline only ({' '.join(s['baseline'])})"

    def cores(s: dict) -> str:
        return ", ".join(f"{core} ({name})" for name, core in s["openblas"].items()) or "unknown"

    say = sys.stderr.write
    say(f"second CPU configuration (numpy {default['numpy']}):\n")
    say(f"  default: numpy dispatches {loops(default)}; OpenBLAS cores {cores(default)}\n")
    for name, value in chosen.items():
        say(f"  {name}={value}\n")
    say(f"  second:  numpy dispatches {loops(second)}; OpenBLAS cores {cores(second)}\n")
    if loops(second) == loops(default):
        say("  warning: numpy's SIMD loops could not be changed on this machine\n")
    if kernel is None or cores(second) == cores(default):
        say("  warning: OpenBLAS's kernel could not be changed on this machine\n")
    for name, value in chosen.items():
        print(f"{name}={value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
