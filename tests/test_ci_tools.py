"""tools/second_cpu.py and tools/floors.py, the choices .ci/run makes with them."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools"

#: numpy 2.4's and numpy 2.0's x86 dispatch targets (their names changed in between)
DISPATCH_2_4 = ["X86_V3", "X86_V4", "AVX512_ICL", "AVX512_SPR"]
DISPATCH_2_0 = [
    "SSSE3", "SSE41", "POPCNT", "SSE42", "AVX", "F16C", "FMA3", "AVX2", "AVX512F", "AVX512CD",
    "AVX512_KNL", "AVX512_KNM", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL", "AVX512_ICL",
]  # fmt: skip
AVX2_FLAGS = {"pni", "sse4_2", "avx", "avx2", "fma"}


@pytest.fixture(scope="module")
def second_cpu() -> dict:
    return runpy.run_path(str(TOOLS / "second_cpu.py"))


def test_the_highest_simd_level_the_cpu_has_is_switched_off(second_cpu) -> None:
    disable = second_cpu["simd_to_disable"]
    everything = dict.fromkeys(DISPATCH_2_4 + DISPATCH_2_0, True)
    # AVX-512: every AVX-512 target (numpy then runs its AVX2 loops), in either naming
    assert disable(DISPATCH_2_4, everything) == ["X86_V4", "AVX512_ICL", "AVX512_SPR"]
    no_phi = {**everything, "AVX512_KNL": False, "AVX512_KNM": False}
    assert disable(DISPATCH_2_0, no_phi) == [
        "AVX512F", "AVX512CD", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL", "AVX512_ICL",
    ]  # fmt: skip
    # AVX2 is the best: its targets (numpy then runs its SSE loops)
    avx2 = {name: not name.startswith(("AVX512", "X86_V4")) for name in everything}
    assert disable(DISPATCH_2_4, avx2) == ["X86_V3"]
    assert disable(DISPATCH_2_0, avx2) == ["AVX", "F16C", "FMA3", "AVX2"]
    # nothing above the baseline: nothing to switch off; another architecture: its highest
    assert disable(DISPATCH_2_4, {}) == []
    assert disable(["ASIMDHP", "ASIMDDP", "SVE"], {"ASIMDHP": True, "ASIMDDP": True}) == ["ASIMDDP"]


def test_the_openblas_kernel_is_one_older_than_the_cpus_best(second_cpu) -> None:
    older = second_cpu["older_kernel"]
    assert older(AVX2_FLAGS | {"avx512f", "avx512bw"}) == "Haswell"
    assert older(AVX2_FLAGS) == "Sandybridge"
    assert older({"pni", "sse4_2", "avx"}) == "Nehalem"
    assert older({"pni", "sse4_2"}) == "Prescott"
    assert older({"pni"}) is None  # nothing older to run
    assert older(set()) is None


def test_floors_pin_every_floored_requirement_but_the_linters(tmp_path) -> None:
    floors = runpy.run_path(str(TOOLS / "floors.py"))["floors"]
    pyproject = tmp_path / "pyproject.toml"
    pyproject.write_text(
        "[project]\n"
        'dependencies = ["numpy>=2.0", "click>=8.1,!=8.3.0", "tomli>=2.0; python_version < \'3.11\'",'
        ' "zlib-ng"]\n'
        "[project.optional-dependencies]\n"
        'dask = ["dask[distributed]>=2024.1"]\n'
        'test = ["pytest>=8.4", "ruff>=0.5", "mypy>=1.8", "numpy>=2.1"]\n'
    )
    assert floors(pyproject) == [
        "numpy==2.0", "click==8.1", "tomli==2.0", "dask==2024.1", "pytest==8.4",
    ]  # fmt: skip
    # the project's own: every runtime dependency is floored
    pins = {line.split("==")[0] for line in floors()}
    assert {"numpy", "scipy", "click", "rich", "zstandard", "lz4", "zlib-ng", "mcap"} <= pins
    assert not pins & {"ruff", "mypy", "import-linter"}
    tool = runpy.run_path(str(TOOLS / "floors.py"))
    assert tool["oldest_python"]() == "3.10"
    tests = tool["test_requirements"]()
    assert "pytest>=8.4" in tests and not [r for r in tests if r.startswith(("ruff", "mypy"))]
