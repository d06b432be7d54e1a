"""The imufdi group loads each command's module on demand, and lists them all."""

from __future__ import annotations

import pytest

from imufdi_cli.cli import cli
from imufdi_cli.cli.app import COMMAND_MODULES
from imufdi_cli.detectors import DETECTORS
from tests.cli.conftest import invoke


def test_command_table_matches_the_commands() -> None:
    defined = {name: command.callback.__module__ for name, command in cli.commands.items()}
    assert defined == COMMAND_MODULES


# The start-up tests read one fresh interpreter per command line (tests/cli/conftest.py's
# ``fresh_imufdi``, shared with test_plain.py and test_simulate.py).


def test_a_command_imports_only_its_own_module(fresh_imufdi, table4_log) -> None:
    run = fresh_imufdi(["info", table4_log])
    loaded = [m for m in run.modules if m.startswith("imufdi_cli.cli.")]
    assert "/imu15/data_raw" in run.stdout
    others = set(COMMAND_MODULES.values()) - {"imufdi_cli.cli.describe"}
    assert "imufdi_cli.cli.describe" in loaded
    assert not others & set(loaded)


def test_info_does_not_import_what_reading_does_not_need(fresh_imufdi, table4_log) -> None:
    """Start-up time: ``imufdi info`` compiles neither the writer, the pipeline nor the
    bag-directory reader, and imports no thread pool, TOML parser or hashlib."""
    unneeded = (
        "imufdi_cli.mcapio.writer",
        "imufdi_cli.mcapio.imu_writer",
        "imufdi_cli.pipeline",
        "imufdi_cli.mcapio.bagdir",
        "concurrent",
        "tomllib",
        "secrets",
        "scipy",
        "rich",
    )
    run = fresh_imufdi(["info", table4_log])
    loaded = [m for m in run.modules if m.startswith(("imufdi_cli.mcapio.", *unneeded))]
    assert "/imu15/data_raw" in run.stdout
    assert "imufdi_cli.mcapio.summary" in loaded
    assert not {m.split(".")[0] if not m.startswith("imufdi") else m for m in loaded} & set(
        unneeded
    )


@pytest.fixture(scope="session")
def detected_clean_log(tmp_path_factory, table4_log):
    """table4_log through ``detect -d glt``: a report of it has no ground truth (a note)."""
    path = tmp_path_factory.mktemp("logs") / "detected-clean.mcap"
    result = invoke(["detect", table4_log, "-d", "glt", "-o", path])
    assert result.code == 0, result.stderr
    return path


@pytest.mark.parametrize("truth", [False, True])
def test_report_does_not_import_what_scoring_does_not_need(
    fresh_imufdi, detected_clean_log, detected_log, truth: bool
) -> None:
    """Start-up time: ``imufdi report`` in a pipe imports neither the episode fits, the
    writer, the detector registry, xml (only --junit writes XML), rich (not even for its
    "no ground truth" note) nor scipy."""
    unneeded = (
        "imufdi_cli.episodes.builder",
        "imufdi_cli.episodes.fits",
        "imufdi_cli.mcapio.writer",
        "imufdi_cli.detectors",
        "xml",
        "rich",
        "scipy",
    )
    run = fresh_imufdi(["report", detected_log if truth else detected_clean_log])
    assert "glt.gyro" in run.stdout
    assert ("no ground truth" in run.stdout) is not truth
    loaded = {m for m in run.modules if m.startswith(unneeded)}
    assert not loaded


def test_help_lists_every_command(fresh_imufdi) -> None:
    section = fresh_imufdi(["--help"]).stdout.split("Commands:\n")[1].split("\n\n")[0]
    listed = [line.split()[0] for line in section.splitlines()]
    assert listed == sorted(COMMAND_MODULES)


@pytest.fixture(scope="session")
def moving_log(tmp_path_factory):
    """A 2.5 s wearable12 log (12 IMUs, moving: cnn-map's calibration needs rotation)."""
    path = tmp_path_factory.mktemp("logs") / "wearable12.mcap"
    result = invoke(["simulate", "--preset", "wearable12", "--duration", "2.5s", "-o", path])
    assert result.code == 0, result.stderr
    return path


@pytest.mark.slow  # a fresh interpreter running all 8 detectors, 2-3 s of CPU; the default
# run keeps tests/detectors/test_registry.py's probe of every detector class's imports
def test_detect_with_every_detector_imports_scipy_only_as_the_detectors_use_it(
    fresh_imufdi, moving_log, tmp_path_factory
) -> None:
    """Start-up time: scipy is imported where it is used, through its public API: the
    normal and F distribution functions (scipy.special), the NNLS of the noise calibration and the jitter root
    (scipy.optimize), the bank's and the px4 selector's filters and woa's envelope
    (scipy.signal); nothing imports a private scipy module by itself. One interpreter runs every detector, the costly ones
    reduced (woa-mvmd-glt's search to its initial two whales: it still computes their
    fitness, whose envelope is scipy.signal.hilbert's; cnn-map's training to one epoch of
    two filters)."""
    out = tmp_path_factory.mktemp("detect") / "all.mcap"
    selected = [arg for name in sorted(DETECTORS) for arg in ("-d", name)]
    reduced = ["woa-mvmd-glt.population=2", "woa-mvmd-glt.iterations=0"]
    reduced += ["cnn-map.epochs=1", "cnn-map.filters=2"]
    params = [arg for param in reduced for arg in ("--param", param)]
    run = fresh_imufdi(["detect", moving_log, *selected, *params, "--no-explain", "-o", out])
    assert out.exists(), run.stderr
    assert all(f"│ {name} " in run.stderr + run.stdout for name in DETECTORS), run.stderr
    assert {"scipy.special", "scipy.optimize", "scipy.signal"} <= run.modules
