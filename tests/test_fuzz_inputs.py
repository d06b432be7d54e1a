"""tools/fuzz_inputs.py: each mutation family, a few inputs through every reading command
(the full run, 1,000 inputs, is the tool's own: its figures are in the report of the work
that extended it). No run exits 4 or prints a traceback, no input is modified, no alias
goes unrefused, no partial output is left."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "fuzz_inputs.py"


@pytest.fixture(scope="module")
def fuzz_tool():
    spec = importlib.util.spec_from_file_location("fuzz_inputs", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["fuzz_inputs"] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bases(fuzz_tool, tmp_path_factory):
    import contextlib
    import io

    workdir = tmp_path_factory.mktemp("fuzz-bases")
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return fuzz_tool.build_bases(workdir)


BAD = (
    "exit 4",
    "traceback",
    "hang",
    "empty message",
    "multi-line error",
    "input modified",
    "leftover files",
    "output after failure",
    "alias not refused",
)


@pytest.mark.parametrize(
    ("family", "files"),
    [("bytes", 1), ("metadata", 1), ("numeric", 1), ("gaps", 1), ("aliases", 14)],
)
def test_a_family_of_mutations_breaks_nothing(fuzz_tool, bases, tmp_path, family, files):
    report = fuzz_tool.fuzz(tmp_path, files=files, seed=7, jobs=1, families=[family], bases=bases)
    total = report["total"]
    expected = files if family == "aliases" else files * len(fuzz_tool.COMMANDS)
    assert total["runs"] == expected
    assert {k: total.get(k, 0) for k in BAD} == dict.fromkeys(BAD, 0), report["examples"]
    assert report["bases_modified"] == []
    if family == "aliases":  # every case (14) refused before anything was written
        assert total.get("exit 2", 0) == files == len(fuzz_tool.ALIAS_CASES)


def test_the_metadata_mutator_writes_hostile_records(fuzz_tool, bases, tmp_path):
    from imufdi_cli.mcapio import McapSource

    rng = np.random.default_rng(3)
    seen = set()
    for i in range(6):
        target = tmp_path / f"m{i}.mcap"
        how = fuzz_tool.mutate_metadata(bases["detected"], target, rng)
        name, kind = how.split(":")
        seen.add(kind)
        with McapSource(target) as src:
            record = src.metadata[name]
        original = McapSource(bases["detected"]).metadata.get(name)
        assert record != original, how
    assert {"scalar", "deep", "field"} <= seen


def test_the_gap_and_numeric_mutators_change_the_samples(fuzz_tool, bases, tmp_path):
    rng = np.random.default_rng(4)
    for mutator in (fuzz_tool.mutate_gaps, fuzz_tool.mutate_numeric):
        for i in range(4):
            target = tmp_path / f"{mutator.__name__}{i}.mcap"
            how = mutator(bases["zstd"], target, rng)
            assert target.stat().st_size > 0, how
            assert target.read_bytes() != bases["zstd"].read_bytes(), how


@pytest.mark.slow
def test_every_family_on_more_inputs(fuzz_tool, bases, tmp_path):
    """60 inputs, the five families in turn, two at a time."""
    report = fuzz_tool.fuzz(tmp_path, files=60, seed=11, jobs=2, bases=bases)
    total = report["total"]
    assert {k: total.get(k, 0) for k in BAD} == dict.fromkeys(BAD, 0), report["examples"]
    assert report["bases_modified"] == []
