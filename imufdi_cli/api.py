"""The Python API: every command of the CLI as a typed function returning a dataclass.

``import imufdi_cli.api as imufdi``, then::

    imufdi.simulate("base.mcap", preset="paper-table4", seed=1)
    imufdi.inject("base.mcap", "faulty.mcap", ["step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"], seed=1)
    imufdi.detect("faulty.mcap", "detected.mcap", {"glt": {"alpha": 0.001}})
    imufdi.report("detected.mcap").entries

Each function does what the command of the same name does (docs/cli.md), with the same
checks and the same outputs, and returns the library's own result. Times and other
quantities are floats in SI units or strings with a unit (``"2.5s"``, ``"100Hz"``,
``"0.9deg/s"``), as on the command line. Detector parameters pass through unchanged to the
detectors (``{"glt": {"alpha": 0.001, "types": "gyro"}}``), so a parameter a detector
gains needs no change here. Nothing prints and nothing exits: bad input raises a subclass
of :class:`imufdi_cli.errors.ImufdiError` whose ``exit_code`` is the CLI's (2 usage, 3 bad
input data), with a one-line message. An output that would replace an input is refused
(:class:`~imufdi_cli.errors.UsageError`); outputs are written atomically.

The functions live here rather than as ``imufdi_cli.detect`` etc. because those names are
the package's own modules (``imufdi_cli/detect.py``, ``imufdi_cli/report/``, ...).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from imufdi_cli.errors import UsageError
from imufdi_cli.units import parse_quantity, parse_time_range

if TYPE_CHECKING:
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.calibrate import CalibrationResult
    from imufdi_cli.campaign import CampaignResult, CampaignSpec
    from imufdi_cli.capture.stats import IngestStats
    from imufdi_cli.detect import DetectResult
    from imufdi_cli.faults import InjectResult
    from imufdi_cli.fclog import FlightLogIngest
    from imufdi_cli.pipeline import SimulateResult
    from imufdi_cli.report import Report

__all__ = [
    "calibrate",
    "campaign",
    "detect",
    "info",
    "ingest",
    "inject",
    "report",
    "simulate",
]

#: a time: seconds (float) or a string with a unit (``"2.5s"``, ``"500ms"``)
Time = float | str
#: detectors to run: names (default parameters) or ``{name: {parameter: value}}``
Detectors = Sequence[str] | Mapping[str, Mapping[str, Any]]
#: ``--stamps``: ``"auto"``, ``"header"`` or ``"log"`` (MCAP log time)
STAMPS = ("auto", "header", "log")


def _path(value: str | Path, name: str) -> str:
    if not isinstance(value, str | Path):
        raise UsageError(
            f"{name}: expected a path (str or pathlib.Path), got {type(value).__name__}"
        )
    return str(value)


def _time_source(stamps: str) -> str:
    if stamps not in STAMPS:
        raise UsageError(f"stamps={stamps!r}; valid: {', '.join(STAMPS)}")
    return "log_time" if stamps == "log" else stamps


def _window(start: Time | None, end: Time | None) -> tuple[float, float | None] | None:
    """``start``/``end`` as seconds from the first sample (None: the whole log)."""
    if start is None and end is None:
        return None
    start_s = parse_quantity(start, "time", name="start") if start is not None else 0.0
    end_s = parse_quantity(end, "time", name="end") if end is not None else None
    if start_s < 0 or (end_s is not None and end_s <= start_s):
        raise UsageError(f"start={start!r}, end={end!r}: need 0 <= start < end")
    return start_s, end_s


def _range(value: str | tuple[Time, Time | None], name: str) -> tuple[float, float | None]:
    """A ``"START:END"`` string or a ``(start, end)`` pair as seconds."""
    if isinstance(value, str):
        return parse_time_range(value, name=name)
    try:
        start, end = value
    except (TypeError, ValueError):
        raise UsageError(f"{name}: expected 'START:END' or (start, end), got {value!r}") from None
    window = _window(start, end)
    assert window is not None  # start given
    return window


def _detectors(detectors: Detectors) -> list[tuple[str, dict[str, Any]]]:
    """``[(name, params)]`` in the order given, each name known and given once."""
    from imufdi_cli.detectors import check_selection

    if isinstance(detectors, str):
        detectors = [detectors]
    if isinstance(detectors, Mapping):
        items = [(str(name), dict(params or {})) for name, params in detectors.items()]
    else:
        items = [(str(name), {}) for name in detectors]
    check_selection([name for name, _ in items])
    return items


def _array(array: ArrayConfig | str | Path | None) -> ArrayConfig | None:
    from imufdi_cli.array import ArrayConfig

    if array is None or isinstance(array, ArrayConfig):
        return array
    return ArrayConfig.load(_path(array, "array"))


def simulate(
    output: str | Path,
    *,
    preset: str | None = None,
    seed: int = 0,
    imus: int | None = None,
    rate: float | str | None = None,
    duration: Time | None = None,
    motion: str | None = None,
    gyro_noise: float | str | None = None,
    accel_noise: float | str | None = None,
    outliers: bool | None = None,
    chip_bias: float | str | None = None,
    capture: str | Path | None = None,
    corrupt: bool = False,
) -> SimulateResult:
    """Simulate an IMU array log (``imufdi simulate``): a preset, or free options, or a
    preset with some options overridden; bit-reproducible for a given ``seed``.

    Parameters
    ----------
    output : path
        The MCAP written.
    preset : str, optional
        A reference scenario (docs/simulate.md), e.g. ``"paper-table4"``.
    seed : int
        Seed of the one ``numpy.random.Generator`` of the simulation.
    imus, rate, duration, motion, gyro_noise, accel_noise, outliers, chip_bias
        As the options of the same name (``rate="1kHz"``, ``duration="1h"``,
        ``gyro_noise="0.15deg/s"``, ...); None keeps the preset's (or the default).
    capture : path, optional
        Also write a raw serial capture (layout ``mpu6500-array``) of the same samples.
    corrupt : bool
        With ``capture``: a few corrupted stretches in it.

    Returns
    -------
    SimulateResult
        ``output``, ``samples``, ``n_imus``, ``rate_hz``, ``duration_s``,
        ``capture_bytes``.
    """
    from imufdi_cli.fileio import check_outputs
    from imufdi_cli.pipeline import simulate_file

    out = _path(output, "output")
    raw = None if capture is None else _path(capture, "capture")
    check_outputs([], [("output", out), ("capture", raw)])
    given = {
        "imus": imus,
        "rate": rate,
        "duration": duration,
        "motion": motion,
        "gyro_noise": gyro_noise,
        "accel_noise": accel_noise,
        "outliers": outliers,
        "chip_biases": chip_bias,
    }
    options = {k: v for k, v in given.items() if v is not None}
    return simulate_file(preset, out, seed=seed, options=options, capture=raw, corrupt=corrupt)


def ingest(
    capture: str | Path,
    output: str | Path,
    *,
    layout: str | Path | None = None,
    array: str | Path | None = None,
    rate: float | str | None = None,
    strict: bool = False,
    start_time: str | None = None,
    imu_data: str | None = None,
) -> IngestStats | FlightLogIngest:
    """Convert a raw capture or a flight-controller log into an MCAP log (``imufdi
    ingest``). The format is recognised by content: a PX4 ULog or ArduPilot DataFlash log
    (docs/flight-controllers.md), else a capture parsed with ``layout``.

    Parameters
    ----------
    capture, output : path
        The capture or flight log read and the MCAP written.
    layout : str or path, optional
        Captures only: a built-in layout name or a layout TOML file (docs/capture.md);
        default ``mpu6500-array``.
    array : path, optional
        The array config TOML to record (else the layout's, or co-aligned IMUs at a flight
        log's logged positions).
    rate : float or str, optional
        Captures only: the nominal sample rate (``"1kHz"``), else the layout's.
    strict : bool
        Any corrupt frame is an error instead of a counted drop.
    start_time : str, optional
        Wall-clock time of the first sample (ISO 8601), else the device's clock (a flight
        log's GPS time).
    imu_data : str, optional
        Flight logs only: which IMU data (``"auto"``, ``"sensor"``, ``"vehicle_imu"``,
        ``"imu"``, ``"raw"``).

    Returns
    -------
    IngestStats or FlightLogIngest
        What the conversion counted (``as_rows()``, ``to_dict()``): frames good, bad,
        truncated, lost, duplicates and wraps of a capture; streams, rates and UTC of a
        flight log.
    """
    from imufdi_cli.fileio import check_input, check_outputs
    from imufdi_cli.pipeline import ingest_file

    source, out = _path(capture, "capture"), _path(output, "output")
    check_input(source)
    array_path = None if array is None else _path(array, "array")
    check_outputs([source, array_path], [("output", out)])
    result: IngestStats | FlightLogIngest = ingest_file(
        source,
        out,
        layout=None if layout is None else str(layout),
        array_path=array_path,
        rate=None if rate is None else str(rate),
        strict=strict,
        start_time=start_time,
        imu_data=imu_data,
    )
    return result


def inject(
    source: str | Path,
    output: str | Path,
    faults: Sequence[str] = (),
    *,
    fault_files: Sequence[str | Path] = (),
    seed: int = 0,
    compression: str = "zstd",
    topics: Sequence[str] | None = None,
    stamps: str = "auto",
) -> InjectResult:
    """Copy a log with faults injected into its IMU messages, plus the ground truth
    (``imufdi inject``).

    Parameters
    ----------
    source, output : path
        The log read and the copy written.
    faults : sequence of str
        Fault specs (docs/faults.md), e.g. ``"step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"``.
    fault_files : sequence of path
        Fault TOML files, added to ``faults``.
    seed : int
        Seed of the faults' randomness (noise, spikes).
    compression : str
        ``"zstd"``, ``"lz4"`` or ``"none"``.
    topics : sequence of str, optional
        The Imu topics in array order (default: every Imu channel).
    stamps : str
        ``"auto"``, ``"header"`` or ``"log"``.

    Returns
    -------
    InjectResult
        ``faults`` (as recorded), ``messages``, ``messages_patched``, ``warnings``, ...
    """
    from imufdi_cli.faults import inject_file
    from imufdi_cli.fileio import check_input, check_outputs

    src, out = _path(source, "source"), _path(output, "output")
    files = [_path(f, "fault_files") for f in fault_files]
    if isinstance(faults, str):
        faults = [faults]
    if not faults and not files:
        raise UsageError("no fault given; e.g. faults=['step:imu0.gyro.x,at=2.5s,amp=0.9deg/s']")
    check_input(src)
    check_outputs([src, *files], [("output", out)])
    return inject_file(
        src,
        out,
        list(faults),
        files,
        seed=seed,
        compression=compression,
        topics=None if topics is None else list(topics),
        time_source=_time_source(stamps),
    )


def detect(
    source: str | Path,
    output: str | Path,
    detectors: Detectors,
    *,
    calibrate: str | tuple[Time, Time | None] = (0.0, 2.0),
    false_alarms: float | str | None = None,
    start: Time | None = None,
    end: Time | None = None,
    array: ArrayConfig | str | Path | None = None,
    topics: Sequence[str] | None = None,
    strict: bool = False,
    explain: bool = True,
    compression: str = "zstd",
    stamps: str = "auto",
) -> DetectResult:
    """Run detectors over a log and write the annotated copy (``imufdi detect``).

    Parameters
    ----------
    source, output : path
        The log read and the annotated MCAP written (status channels, events, episodes).
    detectors : sequence of str, or mapping of str to mapping
        ``["glt", "bank"]``, or ``{"glt": {"alpha": 0.001}, "bank": {}}``: every
        parameter goes to the detector as ``--param glt.alpha=0.001`` would (values as
        numbers or as the strings the CLI takes, e.g. ``"1/h"``).
    calibrate : str or (start, end)
        The fault-free calibration window, ``"0s:2s"`` or ``(0.0, 2.0)`` seconds from the
        log start.
    false_alarms : float or str, optional
        A false-alarm budget per status channel (``"1/h"``; a float is per second): every
        detector that supports one decides under it unless its own ``false_alarms``
        parameter is given (``imufdi detect --false-alarms``).
    start, end : float or str, optional
        Test only this part of the log.
    array : ArrayConfig or path, optional
        The array geometry, instead of the one recorded in the log.
    topics : sequence of str, optional
        The Imu topics in array order.
    strict : bool
        A truncated input or an inadequate calibration window is an error.
    explain : bool
        Explain alarm episodes with the fault-model fits.
    compression : str
        ``"zstd"``, ``"lz4"`` or ``"none"``.
    stamps : str
        ``"auto"``, ``"header"`` or ``"log"``.

    Returns
    -------
    DetectResult
        ``samples``, ``duration_s``, ``summaries[detector][sensor_type]`` (alarms,
        events, isolated sensors, episodes), ``validity``, ``warnings``, ...
    """
    from imufdi_cli.detect import detect_file
    from imufdi_cli.fileio import check_input, check_outputs

    src, out = _path(source, "source"), _path(output, "output")
    selected = _detectors(detectors)
    window = _range(calibrate, "calibrate")
    budget = None
    if false_alarms is not None:
        budget = parse_quantity(false_alarms, "frequency", name="false_alarms")
        if budget < 0:
            raise UsageError(f"false_alarms must be >= 0 (e.g. '1/h'), got {false_alarms!r}")
    check_input(src)
    params = [v for _, p in selected for v in p.values() if isinstance(v, str | Path)]
    files = [str(v) for v in params if Path(v).is_file()]  # e.g. woa-mvmd-glt's params file
    check_outputs([src, *files], [("output", out)])
    return detect_file(
        src,
        out,
        selected,
        calibrate=window,
        topics=None if topics is None else list(topics),
        strict=strict,
        compression=compression,
        array=_array(array),
        window=_window(start, end),
        time_source=_time_source(stamps),
        explain=explain,
        false_alarms=budget,
    )


def report(
    source: str | Path,
    *,
    persist: int = 1,
    match_far: float | None = None,
    start: Time | None = None,
    end: Time | None = None,
) -> Report:
    """The figures of an annotated log against its ground truth (``imufdi report``).

    Parameters
    ----------
    source : path
        A log written by :func:`detect` (with the truth of :func:`inject`, for the
        detection figures).
    persist : int
        Consecutive alarmed samples needed to count an alarm (>= 1).
    match_far : float, optional
        Also report every detector at this false-alarm rate (its threshold moved there).
    start, end : float or str, optional
        Score only this part of the log.

    Returns
    -------
    Report
        ``entries`` (one per detector and sensor type: FAR, MAR, detection rate =
        1 - MAR, delays, isolation), ``episodes``, ``episode_scores``, ``notes``; its
        ``to_dict()`` is the JSON of ``imufdi report --json``.
    """
    from imufdi_cli.fileio import check_input
    from imufdi_cli.report import build_report

    src = _path(source, "source")
    check_input(src)
    if isinstance(persist, bool) or not isinstance(persist, int) or persist < 1:
        raise UsageError(f"persist={persist!r}: need an integer >= 1")
    return build_report(src, persist=persist, match_far=match_far, window=_window(start, end))


def calibrate(
    source: str | Path,
    *,
    start: Time | None = None,
    end: Time | None = None,
    base: ArrayConfig | str | Path | None = None,
    gravity: float | str = 9.80665,
    min_static: Time = 5.0,
    topics: Sequence[str] | None = None,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Estimate each IMU's calibration from a log with static intervals in several
    orientations (``imufdi calibrate``).

    Parameters
    ----------
    source : path
        The log read (not modified).
    start, end : float or str, optional
        Use only this part of the log.
    base : ArrayConfig or path, optional
        The array config to start from (else the one recorded in the log).
    gravity : float or str
        Local gravity (``9.80665`` m/s^2, or e.g. ``"9.81m/s^2"``).
    min_static : float or str
        Shortest static interval used.
    topics : sequence of str, optional
        The Imu topics in array order.
    jitter_fit : str
        How the sampling-time jitter is fitted: ``"level"``, ``"moments"`` or ``"off"``.

    Returns
    -------
    CalibrationResult
        ``array`` (the calibrated :class:`~imufdi_cli.array.ArrayConfig`: write it with
        ``array.to_toml()``), ``intervals``, ``coverage``, ``residual_rms``,
        ``jitter_s``, ``warnings``, ...
    """
    from imufdi_cli.calibrate import JITTER_FITS, calibrate_file
    from imufdi_cli.fileio import check_input

    src = _path(source, "source")
    check_input(src)
    if jitter_fit not in JITTER_FITS:
        raise UsageError(f"jitter_fit={jitter_fit!r}; valid: {', '.join(JITTER_FITS)}")
    return calibrate_file(
        src,
        window=_window(start, end),
        base=_array(base),
        gravity=parse_quantity(gravity, "acceleration", name="gravity"),
        min_static_s=parse_quantity(min_static, "time", name="min_static"),
        topics=None if topics is None else list(topics),
        jitter_fit=jitter_fit,
    )


def campaign(
    spec: CampaignSpec | str | Path,
    output: str | Path,
    *,
    jobs: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
) -> CampaignResult:
    """Run a fault-injection campaign: inject + detect + report over a matrix of runs
    (``imufdi campaign``; docs/campaign.md).

    Parameters
    ----------
    spec : CampaignSpec or path
        A campaign spec TOML, or one loaded with :func:`imufdi_cli.campaign.load_spec`.
    output : path
        The results directory (runs/, runs.csv, summary.json, summary.md).
    jobs : int, optional
        Worker processes (default: every core).
    scheduler : str, optional
        A dask scheduler, ``"tcp://HOST:PORT"`` or ``"local:N"``.
    resume : bool
        Keep the runs already in ``output``.

    Returns
    -------
    CampaignResult
        ``total``, ``executed``, ``skipped``, ``failed``, ``summary`` (the JSON of
        summary.json), ``rows``, ``seconds``.
    """
    from imufdi_cli.campaign import CampaignSpec, load_spec, run_campaign

    loaded = spec if isinstance(spec, CampaignSpec) else load_spec(_path(spec, "spec"))
    return run_campaign(
        loaded, _path(output, "output"), jobs=jobs, scheduler=scheduler, resume=resume
    )


def info(
    source: str | Path,
    *,
    topics: Sequence[str] | None = None,
    stamps: str = "auto",
    strict: bool = False,
) -> dict[str, Any]:
    """What ``imufdi info`` shows about a log, as the JSON-ready dict of ``imufdi info
    --json``: IMUs, rate, duration, topics, gaps, the faults injected, the detectors that
    wrote it, validity counts, ``warnings``.

    Parameters
    ----------
    source : path
    topics : sequence of str, optional
    stamps : str
        ``"auto"``, ``"header"`` or ``"log"``.
    strict : bool
        A truncated or corrupt log is an error instead of a warning.
    """
    from imufdi_cli.fileio import check_input
    from imufdi_cli.info import log_info

    src = _path(source, "source")
    check_input(src)
    return log_info(
        src,
        topics=None if topics is None else list(topics),
        time_source=_time_source(stamps),
        strict=strict,
    )
