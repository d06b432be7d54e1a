"""imufdi_cli.api: the typed Python API, and the example of docs/python-api.md run as written."""

from __future__ import annotations

import contextlib
import hashlib
import io
import re
import textwrap
from pathlib import Path

import pytest

import imufdi_cli
import imufdi_cli.api as imufdi
from imufdi_cli.detect import DetectResult
from imufdi_cli.errors import DetectorConfigError, ImufdiError, InputDataError, UsageError
from imufdi_cli.report import Report

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "python-api.md"
FAULT = "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"


def _blocks(section: str) -> list[tuple[str, str]]:
    """The fenced blocks ``(language, text)`` of one ``## `` section of the page."""
    text = PAGE.read_text(encoding="utf-8")
    body = text.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```(\w+)\n(.*?)```", body, flags=re.S)


def _run(code: str, cwd: Path, monkeypatch: pytest.MonkeyPatch, scope: dict | None = None) -> str:
    monkeypatch.chdir(cwd)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(PAGE), "exec"), {} if scope is None else scope)
    return out.getvalue()


@pytest.fixture(scope="module")
def detected(tmp_path_factory) -> Path:
    """paper-table4 (seed 1) with the page's step fault, detected by glt: the API's inputs."""
    work = tmp_path_factory.mktemp("api")
    imufdi.simulate(work / "base.mcap", preset="paper-table4", seed=1)
    imufdi.inject(work / "base.mcap", work / "faulty.mcap", [FAULT], seed=1)
    imufdi.detect(work / "faulty.mcap", work / "detected.mcap", ["glt"], explain=False)
    return work


def test_the_pages_example_runs_and_prints_what_the_page_shows(tmp_path, monkeypatch) -> None:
    """The example block as written, in an empty directory. The counts and figures are
    compared to the page's within a margin: on another CPU's rounding a sample at the
    threshold may move (one or two alarms of 500, 0.01 of a rate), and no more."""
    (lang, code), (out_lang, shown) = _blocks("An example: simulate, inject, detect, report")
    assert (lang, out_lang) == ("python", "text")
    printed = _run(code, tmp_path, monkeypatch).splitlines()
    expected = shown.splitlines()
    assert len(printed) == len(expected)
    assert printed[:2] == expected[:2]  # sizes and the fault spec: exact
    number = re.compile(r"-?\d+(?:\.\d+)?")
    for got, want in zip(printed[2:], expected[2:], strict=True):
        assert number.sub("#", got) == number.sub("#", want)  # the same words, in order
        for a, b in zip(number.findall(got), number.findall(want), strict=True):
            margin = 2.0 if "." not in b else 0.01
            assert abs(float(a) - float(b)) <= margin, (got, want)
    assert {p.name for p in tmp_path.iterdir()} == {"base.mcap", "faulty.mcap", "detected.mcap"}


def test_the_pages_error_example_prints_what_the_page_shows(detected, monkeypatch) -> None:
    (lang, code), (_, shown) = _blocks("Errors")[:2]
    assert lang == "python"
    before = hashlib.sha256((detected / "faulty.mcap").read_bytes()).hexdigest()
    printed = _run(code, detected, monkeypatch, {"imufdi": imufdi})
    assert printed == shown
    assert hashlib.sha256((detected / "faulty.mcap").read_bytes()).hexdigest() == before


def test_detector_parameters_pass_through_to_the_detector(detected) -> None:
    """A parameter reaches the detector as --param would give it: a looser level alarms
    more, as a number or as the CLI's string, and an unknown one names the valid ones."""
    faulty, out = detected / "faulty.mcap", detected / "out.mcap"

    def alarms(params: dict) -> int:
        result = imufdi.detect(faulty, out, {"glt": params}, explain=False)
        assert isinstance(result, DetectResult)
        return result.summaries["glt"]["gyro"].alarms

    strict, loose = alarms({"alpha": 1e-6}), alarms({"alpha": 0.2})
    assert strict < loose
    assert alarms({"alpha": "0.2"}) == loose
    budgeted = imufdi.detect(faulty, out, {"glt": {"false_alarms": "1/h"}}, explain=False)
    assert budgeted.summaries["glt"]["gyro"].events < loose
    with pytest.raises(DetectorConfigError, match=r"glt\.false_alarms: cannot read 'lots'"):
        imufdi.detect(faulty, out, {"glt": {"false_alarms": "lots"}})
    # the command's --false-alarms: the same budget for every detector that takes one
    everyone = imufdi.detect(faulty, out, ["glt"], false_alarms="1/h", explain=False)
    assert everyone.summaries["glt"]["gyro"].events == budgeted.summaries["glt"]["gyro"].events
    with pytest.raises(UsageError, match="false_alarms must be >= 0"):
        imufdi.detect(faulty, out, ["glt"], false_alarms=-1.0)
    with pytest.raises(DetectorConfigError, match=r"unknown parameter glt\.alpah; valid: alpha"):
        imufdi.detect(faulty, out, {"glt": {"alpah": 0.1}})


def test_detectors_by_name_in_order_and_bad_selections(detected) -> None:
    faulty, out = detected / "faulty.mcap", detected / "out.mcap"
    result = imufdi.detect(faulty, out, ["glt", "bank"], calibrate=(0, "2s"), explain=False)
    assert list(result.summaries) == ["glt", "bank"]
    with pytest.raises(DetectorConfigError, match=r"unknown detector 'nope'; valid: .*glt"):
        imufdi.detect(faulty, out, ["nope"])
    with pytest.raises(DetectorConfigError, match="selected twice"):
        imufdi.detect(faulty, out, ["glt", "glt"])
    with pytest.raises(DetectorConfigError, match="no detector selected"):
        imufdi.detect(faulty, out, [])
    with pytest.raises(ImufdiError, match="0 <= START < END"):
        imufdi.detect(faulty, out, ["glt"], calibrate="2s:1s")
    with pytest.raises(UsageError, match="stamps='utc'; valid: auto, header, log"):
        imufdi.detect(faulty, out, ["glt"], stamps="utc")


def test_an_output_that_is_an_input_is_refused_and_the_input_kept(detected) -> None:
    faulty = detected / "faulty.mcap"
    before = hashlib.sha256(faulty.read_bytes()).hexdigest()
    with pytest.raises(UsageError, match="inputs are never modified") as err:
        imufdi.detect(faulty, faulty, ["glt"])
    assert err.value.exit_code == 2
    with pytest.raises(UsageError, match="inputs are never modified"):
        imufdi.inject(faulty, str(faulty), [FAULT])
    assert hashlib.sha256(faulty.read_bytes()).hexdigest() == before
    with pytest.raises(InputDataError, match="no such file") as missing:
        imufdi.report(detected / "absent.mcap")
    assert missing.value.exit_code == 3


def test_report_and_info_of_the_detected_log(detected) -> None:
    report = imufdi.report(detected / "detected.mcap")
    assert isinstance(report, Report) and report.has_truth
    gyro = next(e for e in report.entries if (e.detector, e.sensor_type) == ("glt", "gyro"))
    assert gyro.metrics.faulty_samples > 0 and 0.0 <= gyro.metrics.mar <= 1.0
    later = imufdi.report(detected / "detected.mcap", start="1s", persist=2)
    assert later.entries[0].metrics.samples < report.entries[0].metrics.samples
    with pytest.raises(UsageError, match="persist=0: need an integer >= 1"):
        imufdi.report(detected / "detected.mcap", persist=0)
    summary = imufdi.info(detected / "detected.mcap")
    assert summary["n_imus"] == 16 and list(summary["detectors"]) == ["glt"]
    assert [f["spec"] for f in summary["faults"]] == [FAULT]


def test_simulate_options_and_inject_needs_a_fault(tmp_path) -> None:
    result = imufdi.simulate(tmp_path / "free.mcap", imus=6, rate="200Hz", duration=0.5, seed=3)
    assert (result.n_imus, result.rate_hz, result.samples) == (6, 200.0, 100)
    with pytest.raises(UsageError, match="no fault given"):
        imufdi.inject(tmp_path / "free.mcap", tmp_path / "out.mcap")
    with pytest.raises(UsageError, match="expected a path"):
        imufdi.simulate(3)  # type: ignore[arg-type]


def test_calibrate_checks_its_fit_name(detected) -> None:
    with pytest.raises(UsageError, match="jitter_fit='fast'; valid: level, moments, off"):
        imufdi.calibrate(detected / "base.mcap", jitter_fit="fast")


def test_campaign_from_a_spec_file(tmp_path) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text(
        textwrap.dedent(
            """
            [campaign]
            seeds = [0]
            calibrate = "0s:0.6s"

            [[base]]
            preset = "paper-table4"
            options = { duration = "1s" }

            [[fault]]
            model = "step"
            sensor = "imu0.gyro.x"
            at = "0.7s"
            amp = "0.9deg/s"

            [[detector]]
            name = "glt"
            """
        )
    )
    result = imufdi.campaign(spec, tmp_path / "results", jobs=1)
    assert (result.total, result.executed, result.failed) == (1, 1, 0)
    assert (tmp_path / "results" / "summary.json").is_file()


def test_import_imufdi_cli_is_cheap_and_its_names_are_lazy(fresh_python) -> None:
    done = fresh_python(
        "import sys, imufdi_cli\n"
        "print(sorted(m for m in sys.modules if m.startswith(('imufdi_cli', 'numpy'))))\n"
        "print(imufdi_cli.DetectResult.__module__, imufdi_cli.api.__name__)\n"
    )
    assert done.returncode == 0, done.stderr
    loaded, names = done.stdout.splitlines()
    assert loaded == "['imufdi_cli', 'imufdi_cli._version']"
    assert names == "imufdi_cli.detect imufdi_cli.api"


def test_the_package_exports_what_it_lists() -> None:
    for name in imufdi_cli.__all__:
        assert getattr(imufdi_cli, name) is not None
        assert name in dir(imufdi_cli)
    assert set(imufdi.__all__) <= set(vars(imufdi))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        imufdi_cli.nope  # noqa: B018


def test_ingest_a_capture(tmp_path) -> None:
    capture = ROOT / "imufdi_cli" / "sample_logs" / "paper-table4.cap"
    stats = imufdi.ingest(capture, tmp_path / "table4.mcap")
    assert stats.frames_ok > 400  # (the sample has a few corrupt frames on purpose)
    assert imufdi.info(tmp_path / "table4.mcap")["n_imus"] == 16
    with pytest.raises(UsageError, match="inputs are never modified"):
        imufdi.ingest(capture, capture)
