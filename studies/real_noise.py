"""The real board's parity noise at rest and in hand motion, and simple CUSUM tests on it.

A study on the MIMU4444 recordings exp_1 and exp_2 (the tuning recordings; exp_3 and exp_4
are kept for evaluation and are not opened here, exp_5..exp_10 are held out). Each
recording is ingested and calibrated with imufdi itself (``ingest_file`` and
``calibrate_file``, the functions behind ``imufdi ingest`` and ``imufdi calibrate``), then
every table is computed four ways: calibrated on exp_1 and tested on exp_2 and vice versa
(out of sample), and calibrated and tested on the same recording (in sample).

The quantity studied is the whitened parity residual of each sensor j of a type::

    y_w = y / sigma                     (sigma: the calibration's per-sensor noise)
    r   = (I - H_w H_w^+) y_w            (H_w = H / sigma; accelerometers: [H | lever arms])
    u_j = r_j / sqrt(P_jj)               (P = I - H_w H_w^+; the per-sensor GLR statistic)
    z_j = (u_j - mean_W u_j) / std_W u_j (W: the 2-10 s window at the start of the test)

``z_j`` is what a per-sensor test standardised by a short calibration window sees; a bias
f on sensor j shifts it by ``f sqrt(P_jj) / (sigma_j std_W u_j)``.

Sections (each prints its tables as Markdown):

1. At rest: variance, tails, correlation (ACF, long-run-variance factors), slow wander
   (offsets per orientation, RMS/max over 1, 2, 8 minutes, Allan deviation, steps at
   turn-over against drift within an orientation), and an exponential bias reference.
2. In hand motion: the residual's variance against |w|, |w_dot|, |f| terms, a variance
   model fitted on one recording and tested on the other, against calibrate's jitter model.
3. Two-sided CUSUM on z (design shifts 1, 2, 4 sigma, clip 4 or 5, h = ln(gamma K)):
   false episodes per hour per channel with the Poisson 95 % upper bound, with and without
   the bias reference, the long-run-variance scaling and the motion model; the same runs
   on i.i.d. Gaussian noise of the same length (seeded) as the ideal reference; delays
   and isolation on faults injected with ``inject_file`` (``imufdi inject``).

Run (about 2-4 minutes on one core)::

    python studies/real_noise.py [--data /work/data/mimu4444] [--work DIR] [--seed 0]

``--seed`` drives only the Gaussian reference runs (nothing is tuned on them).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imufdi_cli.array import ArrayConfig  # noqa: E402
from imufdi_cli.calibrate import calibrate_file, find_static  # noqa: E402
from imufdi_cli.faults import inject_file  # noqa: E402
from imufdi_cli.maths.jitter import MotionInflation  # noqa: E402
from imufdi_cli.maths.parity import residual_projector  # noqa: E402
from imufdi_cli.maths.rigid import accel_design  # noqa: E402
from imufdi_cli.mcapio import read_array  # noqa: E402
from imufdi_cli.pipeline import ingest_file  # noqa: E402
from imufdi_cli.validity import flag_values  # noqa: E402

LAYOUT = ROOT / "docs" / "layouts" / "mimu4444.toml"
BASE = ROOT / "imufdi_cli" / "sample_logs" / "mimu4444-array.toml"
RECORDINGS = ("exp_1", "exp_2")
TYPES = ("gyro", "accel")
WINDOW_S = (2.0, 10.0)  # the detector's calibration window (test recording)
G = 9.80665
DEG = math.pi / 180.0
#: Physical unit per type for the printed offsets.
UNIT = {"gyro": ("deg/s", 1.0 / DEG), "accel": ("m/s^2", 1.0)}


# --- data ---------------------------------------------------------------------------------


@dataclass
class Recording:
    """A recording's raw samples and the labels of its rows (from its own accelerometers)."""

    name: str
    path: Path
    log_array: ArrayConfig
    t: np.ndarray  # (N,) s from the first sample
    t_ns: np.ndarray  # (N,) int ns
    raw: dict[str, np.ndarray]  # type -> (N, m, 3) raw SI
    bad: dict[str, np.ndarray]  # type -> (N,) clipped or invalid row
    intervals: list  # StaticInterval (labels: at rest)
    interval_id: np.ndarray  # (N,) index of the static interval, -1 elsewhere
    motion_start: float  # end of the last static interval, s

    @property
    def static(self) -> np.ndarray:
        return self.interval_id >= 0

    @property
    def motion(self) -> np.ndarray:
        return self.t > self.motion_start + 1.0


def load_recording(name: str, path: Path) -> Recording:
    log_array, block = read_array(str(path))
    t = block.t_s()
    if block.gyro is None or block.accel is None:
        raise SystemExit(f"{path}: the study needs gyros and accelerometers")
    raw = {"gyro": block.gyro, "accel": block.accel}
    bad = {}
    for s in TYPES:
        clipped, invalid = flag_values(raw[s], s, log_array.range.get(s))
        bad[s] = (clipped | invalid).any(axis=(1, 2))
    usable = ~(bad["gyro"] | bad["accel"])
    intervals, _ = find_static(log_array, raw["accel"], raw["gyro"], t, usable)
    interval_id = np.full(len(t), -1)
    for i, item in enumerate(intervals):
        interval_id[(t >= item.start_s) & (t <= item.end_s)] = i
    return Recording(name, path, log_array, t, block.t_ns, raw, bad, intervals, interval_id,
                     float(intervals[-1].end_s))  # fmt: skip


@dataclass
class Residual:
    """Whitened per-sensor parity residuals of one type, one (calibration, test) pair."""

    cal: str
    test: str
    sensor_type: str
    ids: list[str]
    u: np.ndarray  # (N, n) r_j / sqrt(P_jj), unit variance if sigma is right
    z: np.ndarray  # (N, n) standardised by the 2-10 s window
    window_mean: np.ndarray  # (n,)
    window_std: np.ndarray  # (n,)
    scale: np.ndarray  # (n,) physical size of one unit of z (SI)
    valid: np.ndarray  # (N,) rows the type's test can use
    inflation: np.ndarray  # (N,) calibrate's jitter model 1 + A_t (causal)
    features: dict[str, np.ndarray] = field(default_factory=dict)  # (N,) motion terms
    kappa: np.ndarray = field(default_factory=lambda: np.ones(0))  # (n,) noise spread


def noise(array: ArrayConfig, sensor_type: str) -> np.ndarray:
    """The calibration's per-sensor noise sigma (n,), SI (``imufdi calibrate`` writes it)."""
    sigma = array.sensor_noise(sensor_type)
    if sigma is None:
        raise SystemExit(f"the calibration has no {sensor_type}_noise: run imufdi calibrate")
    return sigma


def design(array: ArrayConfig, sensor_type: str) -> np.ndarray:
    if sensor_type == "accel":
        return accel_design(array, sensor_type)
    return array.measurement_matrix(sensor_type)


def consensus(array: ArrayConfig, raw: np.ndarray, sensor_type: str) -> np.ndarray:
    """Least-squares consensus (N, 3) of calibrated sensors of a type on H (body frame)."""
    y = array.select(array.calibrate_triads(raw, sensor_type), sensor_type)
    sigma = noise(array, sensor_type)
    h_w = array.measurement_matrix(sensor_type) / sigma[:, None]
    return np.asarray((y / sigma) @ np.linalg.pinv(h_w).T)


def backward_rate(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Causal backward difference (N, k): row i uses rows i-1 and i; row 0 is 0."""
    out = np.zeros_like(x)
    dt = np.diff(t)
    out[1:] = np.diff(x, axis=0) / dt[:, None]
    return out


def residuals(cal_name: str, cal: ArrayConfig, rec: Recording, sensor_type: str) -> Residual:
    raw = rec.raw[sensor_type]
    y = cal.select(cal.calibrate_triads(raw, sensor_type), sensor_type)
    sigma = noise(cal, sensor_type)
    h = design(cal, sensor_type)
    h_w = h / sigma[:, None]
    projector = residual_projector(h_w)
    diag = np.sqrt(np.diag(projector))
    u = ((y / sigma) @ projector.T) / diag
    valid = ~rec.bad[sensor_type]
    if sensor_type == "accel":  # the motion terms come from the gyros
        valid &= ~rec.bad["gyro"]
    win = (rec.t >= WINDOW_S[0]) & (rec.t < WINDOW_S[1]) & valid
    mean, std = u[win].mean(axis=0), u[win].std(axis=0, ddof=1)
    z = (u - mean) / std
    inflation = MotionInflation(h_w, sigma, cal.jitter.get(sensor_type, 0.0), cal.rate_hz)
    factors = inflation.factors(np.where(valid[:, None], y, 0.0), rec.t_ns)
    res = Residual(cal_name, rec.name, sensor_type, cal.sensor_ids(sensor_type), u, z, mean,
                   std, sigma / diag * std, valid, factors)  # fmt: skip
    # motion terms, causal (gyro consensus for w; accel consensus for f)
    w = consensus(cal, np.where(rec.bad["gyro"][:, None, None], 0.0, rec.raw["gyro"]), "gyro")
    f = consensus(cal, rec.raw["accel"], "accel")
    w_dot = backward_rate(w, rec.t)
    f_dot = backward_rate(f, rec.t)
    spread_ = cal.sensor_noise_spread(sensor_type)
    res.kappa = np.ones(len(res.ids)) if spread_ is None else np.asarray(spread_, float)
    res.features = {
        "w2": np.sum(w**2, axis=1),  # |w|^2, (rad/s)^2
        "wdot2": np.sum(w_dot**2, axis=1),  # |w_dot|^2, (rad/s^2)^2
        "w4": np.sum(w**2, axis=1) ** 2,  # |w|^4 (centripetal lever arm)
        "fdot2": np.sum(f_dot**2, axis=1),  # |f_dot|^2, (m/s^3)^2
        "df2": (np.linalg.norm(f, axis=1) - G) ** 2,  # (|f| - g)^2, (m/s^2)^2
    }
    return res


# --- statistics ---------------------------------------------------------------------------


def segments(mask: np.ndarray) -> Iterator[tuple[int, int]]:
    """[start, stop) index ranges of the runs of True in ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    yield from zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True)


def excess_kurtosis(x: np.ndarray) -> float:
    x = x - x.mean()
    return float(np.mean(x**4) / np.mean(x**2) ** 2 - 3.0)


def acf_pooled(z: np.ndarray, mask: np.ndarray, lags: Sequence[int]) -> np.ndarray:
    """Autocorrelation (lags,) pooled over sensors and the runs of ``mask`` (each run's
    mean removed)."""
    num = np.zeros(len(lags))
    den = 0.0
    for a, b in segments(mask):
        x = z[a:b] - z[a:b].mean(axis=0)
        den += float(np.sum(x**2))
        for i, lag in enumerate(lags):
            if b - a > lag:
                num[i] += float(np.sum(x[lag:] * x[:-lag]))
    return num / den


def lrv_factors(z: np.ndarray, mask: np.ndarray, length: int) -> np.ndarray:
    """Per sensor (n,): variance of the means of L-sample blocks x L / variance, blocks
    inside the runs of ``mask`` (each run's mean removed; the bias of that removal,
    a factor 1 - L / run length, corrected)."""
    block_sq = np.zeros(z.shape[1])
    var_sq = np.zeros(z.shape[1])
    blocks = 0
    samples = 0
    for a, b in segments(mask):
        k = (b - a) // length
        if k < 2:
            continue
        x = z[a : a + k * length]
        x = x - x.mean(axis=0)
        means = x.reshape(k, length, -1).mean(axis=1)
        block_sq += np.sum(means**2, axis=0) / (1.0 - 1.0 / k)
        var_sq += np.sum(x**2, axis=0) / (1.0 - 1.0 / (k * length))
        blocks += k
        samples += k * length
    return (block_sq / blocks) * length / (var_sq / samples)


def allan_deviation(x: np.ndarray, mask: np.ndarray, m: int) -> np.ndarray:
    """Overlapping Allan deviation (n,) at cluster size m, from pairs of adjacent clusters
    that both lie inside one run of ``mask``."""
    total = np.zeros(x.shape[1])
    count = 0
    for a, b in segments(mask):
        if b - a < 2 * m + 1:
            continue
        c = np.cumsum(np.concatenate([np.zeros((1, x.shape[1])), x[a:b]]), axis=0)
        means = (c[m:] - c[:-m]) / m  # cluster means starting at each index
        d = means[m:] - means[:-m]
        total += np.sum(d**2, axis=0)
        count += d.shape[0]
    return np.sqrt(0.5 * total / count)


def poisson_upper(count: int, conf: float = 0.95) -> float:
    """One-sided upper confidence bound of a Poisson mean given ``count`` events."""
    from scipy.stats import chi2

    return float(0.5 * chi2.ppf(conf, 2 * (count + 1)))


def table(title: str, header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    print(f"\n### {title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(_fmt(v) for v in row) + " |")
    sys.stdout.flush()


def _fmt(v: object) -> str:
    if isinstance(v, float):
        if v != v:
            return "-"
        if v == 0:
            return "0"
        if abs(v) >= 1000:
            return f"{v:.0f}"
        if abs(v) >= 10:
            return f"{v:.1f}"
        if abs(v) >= 0.01:
            return f"{v:.3f}"
        return f"{v:.2e}"
    return str(v)


# --- 1. at rest ---------------------------------------------------------------------------


def rest_rows(rec: Recording, res: Residual) -> np.ndarray:
    """Static rows after the calibration window, usable for the type."""
    return rec.static & res.valid & (rec.t >= WINDOW_S[1])


def interval_means(rec: Recording, res: Residual, x: np.ndarray | None = None) -> tuple:
    """Per static interval (after the window): start time (I,), mean of x (I, n)."""
    x = res.z if x is None else x
    rows = rest_rows(rec, res)
    starts, means = [], []
    for i, _ in enumerate(rec.intervals):
        sel = rows & (rec.interval_id == i)
        if np.count_nonzero(sel) >= 100:
            starts.append(float(rec.t[sel][0]))
            means.append(x[sel].mean(axis=0))
    return np.array(starts), np.array(means)


def within(rec: Recording, res: Residual) -> np.ndarray:
    """z at rest with each static interval's mean removed (rows of rest_rows)."""
    rows = rest_rows(rec, res)
    out = res.z[rows].copy()
    ids = rec.interval_id[rows]
    for i in np.unique(ids):
        out[ids == i] -= out[ids == i].mean(axis=0)
    return out


def spread(v: np.ndarray) -> str:
    return f"{np.median(v):.3f} [{np.min(v):.3f}, {np.max(v):.3f}]"


GAUSS_TAIL = {4: 6.334e-5, 5: 5.733e-7}


def section_rest(pairs: dict, recs: dict) -> None:
    rows_var, rows_acf = [], []
    for (cal, test, s), res in pairs.items():
        rec = recs[test]
        rows = rest_rows(rec, res)
        z = res.z[rows]
        w = within(rec, res)
        _unit, k = UNIT[s]
        tag = "in" if cal == test else "out"
        rows_var.append([s, f"{cal}->{test} ({tag})", f"{np.count_nonzero(rows) / 62.5 / 60:.1f}",
                         spread(res.window_std), spread(res.scale * k), spread(z.var(axis=0)),
                         spread(w.var(axis=0)), excess_kurtosis((w / w.std(axis=0)).ravel()),
                         float(np.mean(np.abs(z) > 4)) / GAUSS_TAIL[4],
                         float(np.mean(np.abs(z) > 5)) / GAUSS_TAIL[5]])  # fmt: skip
        acf = acf_pooled(res.z, rows, (1, 2, 3, 5, 10))
        rows_acf.append([s, f"{cal}->{test} ({tag})", *acf,
                         *(spread(lrv_factors(res.z, rows, L)) for L in (5, 20, 100))])  # fmt: skip
    table("1a. At rest: variance and tails of z (static rows after 10 s; median [min, max] over "
          "the 24 sensors)",
          ["type", "cal->test", "min tested", "window std of u (1 = calibrate's sigma)",
           "1 sigma of z (deg/s or m/s^2)", "var z", "var z, interval means removed",
           "excess kurtosis", "P(|z|>4) / Gaussian", "P(|z|>5) / Gaussian"], rows_var)  # fmt: skip
    table("1b. At rest: temporal correlation (ACF pooled over sensors, each interval's mean "
          "removed; long-run-variance factor F_L = L var(L-means) / var, median [min, max])",
          ["type", "cal->test", "acf 1", "acf 2", "acf 3", "acf 5", "acf 10", "F_5", "F_20",
           "F_100"], rows_acf)  # fmt: skip


def section_wander(pairs: dict, recs: dict) -> None:
    rows_w, rows_steps, rows_adev = [], [], []
    for (cal, test, s), res in pairs.items():
        rec = recs[test]
        _unit, k = UNIT[s]
        starts, means = interval_means(rec, res)
        tag = "in" if cal == test else "out"
        row = [s, f"{cal}->{test} ({tag})"]
        for minutes in (1, 2, 8):
            sel = starts < WINDOW_S[1] + 60 * minutes
            m = means[sel]
            phys = m * res.scale * k
            row += [f"{np.sqrt(np.mean(m**2)):.2f} / {np.max(np.abs(m)):.2f}",
                    f"{np.sqrt(np.mean(phys**2)):.3f} / {np.max(np.abs(phys)):.3f}"]  # fmt: skip
        rows_w.append(row)
        # steps at turn-over: jumps of the orientation means against white noise, and
        # against orientations 8 apart (a drift in time grows with the distance)
        rows = rest_rows(rec, res)
        durations = [
            np.count_nonzero(rows & (rec.interval_id == i)) for i in range(len(rec.intervals))
        ]
        white = math.sqrt(2.0 / np.mean([d for d in durations if d >= 100]))
        jump = float(np.sqrt(np.mean(np.diff(means, axis=0) ** 2)))
        far = float(np.sqrt(np.mean((means[8:] - means[:-8]) ** 2)))
        worst = res.ids[int(np.argmax(np.max(np.abs(means), axis=0)))]
        rows_steps.append([s, f"{cal}->{test} ({tag})", jump, white,
                           math.sqrt(max(0.0, jump**2 - white**2)), far, worst])  # fmt: skip
        static = rec.static & res.valid
        adev = [np.median(allan_deviation(res.z, static, m)) for m in (1, 10, 62, 312, 625)]
        # the interval means as a coarse series (one point per orientation, ~25 s apart)
        coarse = [float(np.median(np.sqrt(0.5 * np.mean((means[j:] - means[:-j]) ** 2, axis=0))))
                  for j in (1, 2, 4, 8)]  # fmt: skip
        rows_adev.append([s, f"{cal}->{test} ({tag})", *adev, *coarse])
    table("1c. Slow wander: offset of each sensor's mean in each orientation from the 2-10 s "
          "calibration value, RMS / max over the sensors and the orientations that start within "
          "1, 2, 8 minutes of the window (z units = sigma, and physical: deg/s or m/s^2)",
          ["type", "cal->test", "1 min (sigma)", "1 min (phys)", "2 min (sigma)",
           "2 min (phys)", "8 min (sigma)", "8 min (phys)"], rows_w)  # fmt: skip
    table("1d. Steps at turn-over or drift? RMS over sensors of the change of the orientation "
          "mean between successive orientations (sigma units), what white noise alone gives, the "
          "excess (quadratic difference), the change between orientations 8 apart (~200 s), "
          "and the sensor with the largest offset",
          ["type", "cal->test", "RMS jump", "white-noise jump", "excess", "8 apart",
           "worst sensor"], rows_steps)  # fmt: skip
    table("1e. Allan deviation of z (median over sensors, sigma units; white noise: "
          "1/sqrt(m)); inside static intervals for 0.016-10 s, and from orientation means "
          "k orientations apart (k = 1, 2, 4, 8: ~25, 50, 100, 200 s; white: 0.045 for 20 s)",
          ["type", "cal->test", "0.016 s", "0.16 s", "1 s", "5 s", "10 s", "k=1", "k=2",
           "k=4", "k=8"], rows_adev)  # fmt: skip


def orientation_repeat(pairs: dict, recs: dict) -> None:
    """Do the per-orientation offsets repeat between the two recordings (same orientation
    sequence): orientation-dependent (g-sensitivity, misalignment) rather than drift."""
    rows = []
    for s in TYPES:
        for cal in RECORDINGS:
            a = pairs[(cal, "exp_1", s)]
            b = pairs[(cal, "exp_2", s)]
            _, ma = interval_means(recs["exp_1"], a)
            _, mb = interval_means(recs["exp_2"], b)
            da = np.array([i.direction for i in recs["exp_1"].intervals])
            db = np.array([i.direction for i in recs["exp_2"].intervals])
            k = min(len(ma), len(mb))
            agree = np.einsum("ij,ij->i", da[:k], db[:k])
            # offsets relative to each recording's own mean over orientations (removes the
            # turn-on bias); physical units
            pa = (ma[:k] - ma[:k].mean(axis=0)) * a.scale
            pb = (mb[:k] - mb[:k].mean(axis=0)) * b.scale
            rho = float(np.corrcoef(pa.ravel(), pb.ravel())[0, 1])
            per = [np.corrcoef(pa[:, j], pb[:, j])[0, 1] for j in range(pa.shape[1])]
            common = np.sqrt(np.mean(((pa + pb) / 2) ** 2))
            diff = np.sqrt(np.mean(((pa - pb) / 2) ** 2))
            _unit, f = UNIT[s]
            rows.append([s, cal, f"{np.min(agree):.3f}", rho, float(np.median(per)),
                         float(common * f), float(diff * f)])  # fmt: skip
    table("1f. Do the orientation offsets repeat? exp_1 and exp_2 run the same 20 "
          "orientations in the same order: correlation of each sensor's per-orientation offset "
          "(own mean over orientations removed) between the recordings, and the RMS of the "
          "repeating part (half-sum) and of the non-repeating part (half-difference)",
          ["type", "calibration", "min cos between matched directions", "corr (all sensors)",
           "median corr per sensor", "RMS repeating (phys)", "RMS not repeating (phys)"],
          rows)  # fmt: skip


TAUS_S = (10.0, 20.0, 30.0, 60.0, 120.0, 300.0)
REF_CLIP = 3.0  # innovation clip of the reference, sigma


def reference_path(z: np.ndarray, tau_s: float, rate_hz: float) -> np.ndarray:
    """Exponential reference before each row (N, n): e_i = e_{i-1} + clip(z_{i-1} -
    e_{i-1}, +-REF_CLIP) / (tau f); e_0 = 0 (the calibration window's value)."""
    step = 1.0 / (tau_s * rate_hz)
    out = np.empty_like(z)
    e = np.zeros(z.shape[1])
    for i in range(z.shape[0]):
        out[i] = e
        e = e + step * np.clip(z[i] - e, -REF_CLIP, REF_CLIP)
    return out


def absorbed(signal_sigma: np.ndarray, tau_s: float, rate_hz: float) -> np.ndarray:
    """Share of a deterministic fault signal (sigma units, (N,)) held by the reference."""
    e = reference_path(signal_sigma[:, None], tau_s, rate_hz)[:, 0]
    return e / np.where(signal_sigma == 0, 1.0, signal_sigma)


def section_reference(pairs: dict, recs: dict) -> None:
    rows = []
    for (cal, test, s), res in pairs.items():
        rec = recs[test]
        sel = rest_rows(rec, res)
        z = res.z[sel]
        ids = rec.interval_id[sel]
        tag = "in" if cal == test else "out"
        row = [s, f"{cal}->{test} ({tag})"]
        for tau in (math.inf, *TAUS_S):
            e = np.zeros_like(z) if math.isinf(tau) else reference_path(z, tau, 62.5)
            d = z - e
            means = np.array([d[ids == i].mean(axis=0) for i in np.unique(ids)])
            row.append(f"{np.sqrt(np.mean(means**2)):.2f} / {np.max(np.abs(means)):.2f}")
        rows.append(row)
    table(
        "1g. Offset left by an exponential bias reference at rest (sigma units, RMS / max over "
        "sensors and orientations of the orientation mean of z - e; reference started at the "
        "window value, innovations clipped at 3 sigma, frozen between orientations)",
        ["type", "cal->test", "fixed (window)", *(f"tau {t:g} s" for t in TAUS_S)],
        rows,
    )
    # lag behind faults, sigma = the median gyro 1-sigma of z (deg/s)
    sigma = float(np.median(pairs[("exp_1", "exp_2", "gyro")].scale)) / DEG
    t = np.arange(0, 10, 1 / 62.5)
    step = np.full(t.size, 0.3 / sigma)
    drift = 1.0 * t / sigma
    lag_rows = []
    for tau in TAUS_S:
        a_step = absorbed(step, tau, 62.5)
        a_drift = absorbed(drift, tau, 62.5)
        at = {x: round(x * 62.5) for x in (0.5, 1.0, 2.0, 5.0)}
        lag_rows.append([f"{tau:g}", float(a_step[at[2.0]]), float(a_step[at[5.0]]),
                         float(a_drift[at[0.5]]), float(a_drift[at[1.0]]),
                         float(a_drift[at[2.0]])])  # fmt: skip
    table(f"1h. Share of a fault absorbed by an ungated reference (innovations clipped at 3 "
          f"sigma, sigma = {sigma:.3f} deg/s): 0.3 deg/s step after 2 s and 5 s, 1 deg/s^2 "
          "drift after 0.5, 1, 2 s (a gate closed at the alarm stops the absorption there)",
          ["tau s", "step 2 s", "step 5 s", "drift 0.5 s", "drift 1 s", "drift 2 s"],
          lag_rows)  # fmt: skip


# --- 2. in hand motion --------------------------------------------------------------------


def moving_rows(rec: Recording, res: Residual) -> np.ndarray:
    """Rows not at rest (the moves between orientations and the motion phase) after the
    window, usable, with a usable predecessor (the backward differences)."""
    rows = ~rec.static & res.valid & (rec.t >= WINDOW_S[1])
    rows[1:] &= res.valid[:-1]
    rows[0] = False
    return rows


#: Terms of the polynomial variance model per type (the brief's form).
POLY_TERMS = {"gyro": ("wdot2", "w2"), "accel": ("fdot2", "wdot2", "w2", "w4", "df2")}
#: Bin edges of |w_dot| (rad/s^2) for the binned variance model.
WDOT_EDGES = np.array([0.0, 3.0, 10.0, 30.0, 60.0, 100.0, 200.0, 300.0, 600.0, 1000.0, 2000.0])
W_EDGES = np.array([0.0, 0.3, 1.0, 2.0, 3.0, 5.0, 8.0])  # |w| rad/s


@dataclass
class VarianceModel:
    """A per-type variance factor v_t >= 1 of z in motion (z / sqrt(v) ~ unit variance)."""

    name: str
    kind: str  # poly, bins, jitter, cross
    coef: dict[str, float] = field(default_factory=dict)  # poly: term -> a (per unit^2)
    table: np.ndarray | None = None  # bins: (len(WDOT_EDGES), len(W_EDGES)) factors

    def factors(self, res: Residual) -> np.ndarray:
        if self.kind == "poly":
            v = np.ones(res.z.shape[0])
            for term, a in self.coef.items():
                v += a * res.features[term]
            return v
        if self.kind == "bins":
            i, j = _bin_index(res)
            return np.asarray(self.table)[i, j]
        if self.kind == "jitter":
            return res.inflation
        if self.kind == "cross":  # robust cross-sectional scale of the same sample
            return np.maximum(1.0, np.median(res.z**2, axis=1) / CHI2_1_MEDIAN)
        return np.ones(res.z.shape[0])


CHI2_1_MEDIAN = 0.45494  # median of chi2(1)


def _bin_index(res: Residual) -> tuple[np.ndarray, np.ndarray]:
    i = np.clip(np.digitize(np.sqrt(res.features["wdot2"]), WDOT_EDGES) - 1, 0, WDOT_EDGES.size - 1)
    j = np.clip(np.digitize(np.sqrt(res.features["w2"]), W_EDGES) - 1, 0, W_EDGES.size - 1)
    return i, j


def fit_poly(res: Residual, rows: np.ndarray) -> VarianceModel:
    """Gaussian maximum likelihood of v = 1 + sum a_k phi_k (a_k >= 0) on z at ``rows``,
    pooled over the sensors (each row contributes sum_j z_j^2 with n degrees of freedom)."""
    from scipy.optimize import minimize

    terms = POLY_TERMS[res.sensor_type]
    phi = np.stack([res.features[t][rows] for t in terms], axis=1)
    scale = phi.mean(axis=0) + 1e-30
    phi = phi / scale
    q = np.sum(res.z[rows] ** 2, axis=1)
    n = res.z.shape[1]

    def nll(theta: np.ndarray) -> float:
        v = 1.0 + phi @ np.exp(theta)
        return float(np.sum(n * np.log(v) + q / v)) / q.size

    start = np.full(len(terms), math.log(max(q.mean() / n, 1.0) / len(terms)))
    fit = minimize(nll, start, method="Nelder-Mead", options={"maxiter": 4000, "xatol": 1e-4,
                                                            "fatol": 1e-8})  # fmt: skip
    coef = np.exp(fit.x) / scale
    return VarianceModel("poly", "poly", dict(zip(terms, coef.tolist(), strict=True)))


def fit_bins(res: Residual, rows: np.ndarray) -> VarianceModel:
    """Per (|w_dot|, |w|) bin, the mean of z^2 over its rows and sensors (the Gaussian ML of
    a piecewise-constant variance); bins with < 200 sensor-samples take their |w_dot| row's
    value, 1 at rest."""
    i, j = _bin_index(res)
    q = np.mean(res.z**2, axis=1)
    table = np.ones((WDOT_EDGES.size, W_EDGES.size))
    for a in range(WDOT_EDGES.size):
        row = rows & (i == a)
        fallback = float(q[row].mean()) if np.count_nonzero(row) >= 10 else np.nan
        for b in range(W_EDGES.size):
            sel = row & (j == b)
            table[a, b] = q[sel].mean() if np.count_nonzero(sel) >= 10 else fallback
    # empty |w_dot| rows: the nearest filled one below (monotone fill), at least 1
    for a in range(WDOT_EDGES.size):
        for b in range(W_EDGES.size):
            if not np.isfinite(table[a, b]):
                table[a, b] = table[a - 1, b] if a > 0 else 1.0
    return VarianceModel("bins", "bins", table=np.maximum(table, 1.0))


def standardized_stats(res: Residual, v: np.ndarray, rows: np.ndarray) -> list[object]:
    x = res.z / np.sqrt(v)[:, None]
    xs = x[rows]
    var = xs.var(axis=0)
    q = np.sum(res.z[rows] ** 2, axis=1)
    n = res.z.shape[1]
    nll = float(np.mean(np.log(v[rows]) + q / (n * v[rows])))
    # calibration of the model across |w_dot| bins: worst ratio of the bin variance
    i, _ = _bin_index(res)
    ratios = []
    for a in range(WDOT_EDGES.size):
        sel = rows & (i == a)
        if np.count_nonzero(sel) >= 100:
            ratios.append(float(np.mean(x[sel] ** 2)))
    return [spread(var), f"{min(ratios):.2f} .. {max(ratios):.2f}", nll,
            excess_kurtosis(xs.ravel()), float(np.mean(np.abs(xs) > 4)) / GAUSS_TAIL[4],
            float(np.mean(np.abs(xs) > 5)) / GAUSS_TAIL[5], float(acf_pooled(x, rows, (1,))[0]),
            float(np.median(lrv_factors(x, rows, 20))),
            float(np.median(lrv_factors(x, rows, 100)))]  # fmt: skip


def section_motion(pairs: dict, recs: dict) -> dict:
    """Binned variance, fitted models (fit on the calibration recording's own residuals,
    tested on the other) and their standardized statistics. Returns the fitted models per
    (calibration recording, type)."""
    bins_rows = []
    for (cal, test, s), res in pairs.items():
        if cal == test:
            continue
        rec = recs[test]
        rows = moving_rows(rec, res)
        q = np.mean(res.z**2, axis=1)
        i, _ = _bin_index(res)
        cells = []
        for a in range(WDOT_EDGES.size):
            sel = rows & (i == a)
            cells.append(f"{q[sel].mean():.3g} ({np.count_nonzero(sel)})" if sel.any() else "-")
        bins_rows.append([s, f"{cal}->{test}", *cells])
    heads = [f"<{WDOT_EDGES[a + 1]:g}" if a + 1 < WDOT_EDGES.size else f">{WDOT_EDGES[a]:g}"
             for a in range(WDOT_EDGES.size)]  # fmt: skip
    table(
        "2a. In motion (moves between orientations and the motion phase): mean z^2 (pooled "
        "over sensors; rows) by |w_dot| in rad/s^2 (causal backward difference of the gyro "
        "consensus)",
        ["type", "cal->test", *heads],
        bins_rows,
    )
    wbins = []
    for (cal, test, s), res in pairs.items():
        if cal == test:
            continue
        rows = moving_rows(recs[test], res)
        q = np.mean(res.z**2, axis=1)
        _, j = _bin_index(res)
        wbins.append([s, f"{cal}->{test}", *(f"{q[rows & (j == b)].mean():.3g}"
                      if np.any(rows & (j == b)) else "-" for b in range(W_EDGES.size))])  # fmt: skip
    table("2b. The same by |w| (rad/s)", ["type", "cal->test",
          *(f"<{W_EDGES[b + 1]:g}" if b + 1 < W_EDGES.size else f">{W_EDGES[b]:g}"
            for b in range(W_EDGES.size))], wbins)  # fmt: skip
    models: dict = {}
    coef_rows = []
    for cal in RECORDINGS:
        for s in TYPES:
            res = pairs[(cal, cal, s)]
            rows = moving_rows(recs[cal], res)
            poly = fit_poly(res, rows)
            models[(cal, s)] = {"poly": poly, "bins": fit_bins(res, rows),
                                "jitter": VarianceModel("jitter", "jitter"),
                                "cross": VarianceModel("cross", "cross"),
                                "none": VarianceModel("none", "none")}  # fmt: skip
            coef_rows.append([s, cal, ", ".join(f"{k} {v:.3g}" for k, v in poly.coef.items()),
                              ", ".join(f"{v:.3g}" for v in models[(cal, s)]["bins"].table.max(
                                  axis=1))])  # fmt: skip
    table(
        "2c. Fitted variance models (Gaussian ML, moving rows of the recording itself): "
        "polynomial v = 1 + sum a_k phi_k (phi: wdot2 = |w_dot|^2 (rad/s^2)^2, w2 = |w|^2, "
        "w4 = |w|^4, fdot2 = |f_dot|^2 (m/s^3)^2, df2 = (|f| - g)^2), and the binned model's "
        "largest factor per |w_dot| bin",
        ["type", "fitted on", "polynomial a_k", "binned, max per |w_dot| bin"],
        coef_rows,
    )
    stat_rows = []
    for (cal, test, s), res in pairs.items():
        rec = recs[test]
        rows = moving_rows(rec, res)
        tag = "in" if cal == test else "out"
        for name, model in models[(cal, s)].items():
            if name == "none":
                continue
            v = model.factors(res)
            stat_rows.append([s, f"{cal}->{test} ({tag})", name, *standardized_stats(res, v, rows)])
    table("2d. z / sqrt(v) on the moving rows: per-sensor variance (median [min, max]), worst "
          "and best |w_dot| bin's mean square, Gaussian negative log-likelihood per sensor-sample "
          "(lower is better; v from the calibration recording), excess kurtosis, tail rates "
          "against Gaussian, lag-1 ACF, F_20, F_100 (models: poly, bins fitted on the "
          "calibration recording; jitter = calibrate's [jitter] 1 + A_t; cross = the robust "
          "cross-sectional scale median_j z_j^2 / 0.455 of the same sample)",
          ["type", "cal->test", "model", "var", "bins", "nll", "kurtosis", "|z|>4 / G",
           "|z|>5 / G", "acf 1", "F_20", "F_100"], stat_rows)  # fmt: skip
    return models


WINDOWS = (1, 8, 16, 31, 62, 125)  # samples: 0.016 .. 2 s


def moving_mean(x: np.ndarray, rows: np.ndarray, width: int) -> np.ndarray:
    """Causal mean (N, n) of x over the last ``width`` rows of ``rows`` (rows outside are
    skipped: the window spans the usable rows only); NaN until ``width`` usable rows."""
    out = np.full(x.shape, np.nan)
    idx = np.flatnonzero(rows)
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x[idx]]), axis=0)
    if idx.size >= width:
        out[idx[width - 1 :]] = (c[width:] - c[:-width]) / width
    return out


def physical(res: Residual) -> np.ndarray:
    """Each sensor's residual z in its physical unit (deg/s or m/s^2), (N, n)."""
    return res.z * res.scale[None, :] * UNIT[res.sensor_type][1]


def section_spatial(pairs: dict, recs: dict) -> None:
    """The motion residual scaled by each row's own spread over the sensors (what the
    budgeted accelerometer bank does in motion, docs/algorithms/sequential.md)."""
    rows = []
    for (cal, test, s), res in pairs.items():
        if cal == test:
            continue
        moving = recs[test].motion & res.valid
        z = res.z[moving]
        spread = np.median(z * z, axis=1) / 0.4549364231195724
        e = z / np.sqrt(spread)[:, None]
        acf = [float(np.mean(e[lag:] * e[:-lag]) / np.mean(e * e)) for lag in (1, 2, 5, 10)]
        blocks = e[: e.shape[0] // 10 * 10].reshape(-1, 10, e.shape[1]).mean(axis=1)
        jitter = np.sqrt(res.inflation[moving])
        rows.append([f"{cal} -> {test}", s, f"{np.median(jitter) / np.median(np.sqrt(spread)):.2f}",
                     f"{np.mean(z * z / jitter[:, None] ** 2):.2f}",
                     f"{np.mean(z**4) / np.mean(z * z) ** 2:.0f}",
                     " ".join(f"{a:+.3f}" for a in acf),
                     f"{10 * np.mean(blocks**2) / np.mean(e * e):.2f}",
                     f"{np.mean(np.abs(e) > 3.5):.4f}"])  # fmt: skip
    table("The motion residual scaled by each row's spread (median_i z^2 / 0.4549)",
          ["pair", "type", "jitter sd / row spread (medians)", "E[z^2 / (1+A)]", "kurtosis",
           "autocorrelation, lags 1 2 5 10", "long-run factor (10)", "share beyond 3.5"],
          rows)  # fmt: skip


def section_windows(pairs: dict, recs: dict) -> None:
    rows_out = []
    for (cal, test, s), res in pairs.items():
        if cal == test:
            continue
        rec = recs[test]
        rows = rec.motion & res.valid
        x = physical(res)
        base = float(np.sqrt(np.mean(x[rows] ** 2)))
        cells = []
        for width in WINDOWS:
            m = moving_mean(x, rows, width)
            m = m[np.isfinite(m[:, 0])]
            rms = float(np.sqrt(np.mean(m**2)))
            cells.append(f"{rms:.3g} / {np.abs(m).max():.3g} (F {width * rms**2 / base**2:.2f})")
        rows_out.append([s, f"{cal}->{test}", f"{np.count_nonzero(rows) / RATE_HZ:.0f}", *cells])
    table("2e. The motion residual averages out: causal moving mean of each sensor's residual "
          "over the last W usable samples in the motion phase (physical units, deg/s or "
          "m/s^2): RMS / max over sensors and samples, and F = W var(mean) / var (white "
          "noise: 1; the residual's running sum stays bounded when F falls like 1/W)",
          ["type", "cal->test", "s tested", *(f"W={w}" for w in WINDOWS)], rows_out)  # fmt: skip


# --- 3. sequential tests ------------------------------------------------------------------

RATE_HZ = 62.5
MERGE_GAP = 6  # samples (0.1 s): alarm runs closer than this are one episode
H_SCAN = (4.0, 6.0, 8.0, 10.0, 12.0, 14.0)
REFERENCE_TAU_S = 30.0  # the bias reference of the CUSUM runs (section 1g)
CAP = 5.0  # S is capped at h + min(CAP, RECOVERY d^2 / 2): an alarm ends soon after the fault
RECOVERY = 31  # samples (0.5 s): the recovery bound of small (motion) designs
ISO_CAP = 100.0  # cap of the unclipped statistics that isolate (above h)
BLOCK = 16  # samples per update of the bias reference
MOTION_GATE = 2.0  # the reference is frozen where the motion factor v exceeds this
#: Grid of the motion-model multiplier lambda (v = 1 + lambda (v_model - 1)).
LAMBDA_GRID = (0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 5.6, 8.0, 11.0, 16.0, 23.0, 32.0)


def threshold(n_sensors: int, designs: Sequence[float] = (1.0, 2.0, 4.0)) -> float:
    """h = ln(gamma K): gamma samples per hour, K = 2 sides x sensors x designs."""
    return math.log(RATE_HZ * 3600.0 * 2 * n_sensors * len(designs))


@dataclass
class Variant:
    name: str
    clip: float = 5.0
    tau_s: float = 0.0  # bias reference time constant (0: the window offset, fixed)
    lrv: bool = False  # divide by sqrt(max(1, F_L)), L = 2 h / d^2 per design (calibration rec.)
    motion: str = "none"  # variance model (section 2 and :func:`motion_models`)
    sigma: str = "window"  # window: the 2-10 s std; pooled: calibrate's sigma; kappa: pooled
    #                        sigma with the variance times sqrt(kappa) (calibrate's spread)
    gate_max_s: float = 10.0  # the reference is frozen at most this long per alarm
    designs: tuple[float, ...] = (1.0, 2.0, 4.0)  # design shifts, sigma
    physical: bool = False  # designs in rest-sigma units: d_t = d / sqrt(v_t) in motion


def run_cusum(res: Residual, rows: np.ndarray, variant: Variant, v: np.ndarray,
              lrv: np.ndarray, h: float, isolate: bool = False,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Two-sided CUSUM per sensor and design over the rows ``rows`` (in order; other rows
    are skipped, the state held).

    ``S+ = min(h + min(CAP, RECOVERY d^2 / 2), max(0, S+ + d x - d^2 / 2))`` and the mirror
    ``S-``, with
    ``x = clip((u - e) / (s sqrt(F v)), +-c)``: u the whitened residual, e the reference
    (the window mean, or the exponential reference gated while the sensor is in alarm,
    S > h, for at most ``gate_max_s``, or while the board moves, v > MOTION_GATE), s the
    sensor's sigma, F the long-run-variance factor (n, designs), v the motion variance
    factor (N,) or (N, n). No reset: an alarm lasts while S > h. With ``physical`` the
    designs are fault sizes in rest sigmas, so in motion the design on x is ``d / sqrt(v)``
    (the log-likelihood ratio of a fixed fault in N(0, v) noise).

    Returns the processed row indices (K,), each sensor's largest statistic over designs
    and sides (K, n), and (``isolate``; else empty) the same of the unclipped statistics
    (capped at h + ISO_CAP), which isolate: a large fault saturates the clip on the faulty
    sensor and on the sensors correlated with it (|rho| up to 0.58 for the
    accelerometers), so the clipped statistics tie.

    The reference and its gates are updated once per BLOCK samples (0.26 s, with the sum of
    the block's clipped innovations; tau >= 10 s), the statistics every sample.
    """
    idx = np.flatnonzero(rows)
    u = res.u[idx]
    n = u.shape[1]
    designs = np.asarray(variant.designs)
    ref = res.window_mean.copy()
    step = 1.0 / (variant.tau_s * RATE_HZ) if variant.tau_s > 0 else 0.0
    if variant.sigma == "window":
        sigma = res.window_std
    elif variant.sigma == "pooled":
        sigma = np.ones(n)
    else:
        sigma = res.kappa**0.25
    gate = REF_CLIP * sigma
    scale = sigma[:, None] * (np.sqrt(np.maximum(lrv, 1.0)) if variant.lrv else 1.0)  # (n, D)
    vv = np.broadcast_to(np.sqrt(v[idx]).reshape(idx.size, -1), (idx.size, n))
    moving = vv.max(axis=1) ** 2 > MOTION_GATE
    out = np.empty((idx.size, n))
    iso = np.empty((idx.size if isolate else 0, n))
    state = np.zeros((n, designs.size, 2))  # S+ and S- per sensor and design
    iso_state = np.zeros_like(state)
    history = np.empty((BLOCK, *state.shape))
    held = np.zeros(n)
    hold = variant.gate_max_s * RATE_HZ
    iso_top = h + ISO_CAP
    c = variant.clip
    sign = np.array([1.0, -1.0])
    for a in range(0, idx.size, BLOCK):
        b = min(a + BLOCK, idx.size)
        raw = (u[a:b] - ref)[:, :, None] / (scale[None] * vv[a:b, :, None])  # (B, n, D)
        d = designs[None, None, :] / (vv[a:b, :, None] if variant.physical else 1.0)
        half = 0.5 * d**2
        inc = d[..., None] * np.clip(raw, -c, c)[..., None] * sign - half[..., None]
        tops = np.broadcast_to(h + np.minimum(CAP, RECOVERY * half), (b - a, n, designs.size))
        tops = tops[..., None]  # (B, n, D, 1)
        for i in range(b - a):
            np.clip(state + inc[i], 0.0, tops[i], out=state)
            history[i] = state
        out[a:b] = history[: b - a].max(axis=(2, 3))
        if isolate:
            inc = d[..., None] * raw[..., None] * sign - half[..., None]
            for i in range(b - a):
                np.clip(iso_state + inc[i], 0.0, iso_top, out=iso_state)
                history[i] = iso_state
            iso[a:b] = history[: b - a].max(axis=(2, 3))
        alarmed = np.any(out[a:b] > h, axis=0)
        held = np.where(alarmed, held + (b - a), 0.0)
        still = ~moving[a:b]
        if step and still.any():
            free = ~alarmed | (held > hold)
            innovation = np.clip(u[a:b][still] - ref, -gate, gate).sum(axis=0)
            ref += step * free * innovation
    return idx, out, iso


def episodes(alarm: np.ndarray) -> list[tuple[int, int]]:
    """Alarm runs (start, stop) in processed-sample index, merged across gaps of at most
    MERGE_GAP samples."""
    merged: list[tuple[int, int]] = []
    for a, b in segments(alarm):
        if merged and a - merged[-1][1] <= MERGE_GAP:
            merged[-1] = (merged[-1][0], b)
        else:
            merged.append((a, b))
    return merged


def count_rate(count: int, seconds: float) -> str:
    hours = seconds / 3600.0
    if hours <= 0:
        return "-"
    return f"{count} ({count / hours:.3g}/h, <= {poisson_upper(count) / hours:.3g}/h)"


def gaussian_reference(rng: np.random.Generator, samples: int, n: int, variant: Variant,
                       h_values: Sequence[float]) -> dict[float, int]:  # fmt: skip
    """Episodes at each threshold of the same CUSUM on i.i.d. N(0, 1) (samples, n)."""
    fake = Residual("gauss", "gauss", "gauss", [], rng.standard_normal((samples, n)),
                    np.zeros((samples, n)), np.zeros(n), np.ones(n), np.ones(n),
                    np.ones(samples, bool), np.ones(samples))  # fmt: skip
    plain = Variant("g", variant.clip, designs=variant.designs)
    _, stat, _ = run_cusum(fake, np.ones(samples, bool), plain, np.ones(samples),
                           np.ones((n, len(plain.designs))), math.inf)  # fmt: skip
    top = stat.max(axis=1)
    return {hh: len(episodes(top > hh)) for hh in h_values}


SMALL = (2.0, 4.0)
REST_VARIANTS = [
    Variant("window sigma, fixed offset, clip 5", 5.0),
    Variant("window sigma, fixed offset, clip 4", 4.0),
    Variant("window sigma, ref (gate unlimited), clip 4", 4.0, REFERENCE_TAU_S,
            gate_max_s=math.inf),
    Variant("window sigma, ref, clip 4", 4.0, REFERENCE_TAU_S),
    Variant("window sigma, ref, LRV, clip 4", 4.0, REFERENCE_TAU_S, True),
    Variant("pooled sigma, ref, clip 4", 4.0, REFERENCE_TAU_S, sigma="pooled"),
    Variant("kappa sigma, ref, clip 4", 4.0, REFERENCE_TAU_S, sigma="kappa"),
    Variant("kappa sigma, ref, LRV, clip 4", 4.0, REFERENCE_TAU_S, True, sigma="kappa"),
    Variant("kappa sigma, ref, LRV, clip 5", 5.0, REFERENCE_TAU_S, True, sigma="kappa"),
    Variant("kappa sigma, ref 10 s, LRV, clip 4", 4.0, 10.0, True, sigma="kappa"),
    Variant("window sigma, ref, LRV, clip 4, d 2/4", 4.0, REFERENCE_TAU_S, True,
            designs=SMALL),
    Variant("kappa sigma, ref, LRV, clip 4, d 2/4", 4.0, REFERENCE_TAU_S, True, sigma="kappa",
            designs=SMALL),
    Variant("kappa sigma, ref 10 s, LRV, clip 4, d 2/4", 4.0, 10.0, True, sigma="kappa",
            designs=SMALL),
]  # fmt: skip
#: The rest configurations the continuous runs and the faults use, with each motion model:
#: R = designs 2/4 sigma of the standardized residual; P = "physical" designs 2..32 rest
#: sigmas (in motion d / sqrt(v)).
BASES = {
    "R": {"clip": 4.0, "tau_s": REFERENCE_TAU_S, "lrv": True, "sigma": "kappa", "designs": SMALL},
    "P": {"clip": 4.0, "tau_s": REFERENCE_TAU_S, "lrv": True, "sigma": "kappa",
          "designs": (2.0, 4.0, 8.0, 16.0, 32.0), "physical": True},
}  # fmt: skip
BASE_NAMES = {"R": "kappa sigma, ref, LRV, clip 4, d 2/4",
              "P": "kappa sigma, ref, LRV, clip 4, physical d 2..32"}  # fmt: skip
MOTION_NAMES = ("none", "jitter", "jitter x lambda", "poly", "poly per sensor x lambda")


def best(motion: str, base: str = "R") -> Variant:
    return Variant(f"{BASE_NAMES[base]}, motion {motion}", motion=motion,
                   **BASES[base])  # type: ignore[arg-type]  # fmt: skip


def lrv_of(pairs: dict, recs: dict, cal: str, s: str, designs: Sequence[float]) -> np.ndarray:
    """(n, designs): F_L of each sensor at rest in the calibration recording, L = 2 h / d^2
    (the memory of the design-d CUSUM at its threshold, in samples)."""
    res = pairs[(cal, cal, s)]
    h = threshold(res.z.shape[1], designs)
    lengths = [max(2, round(2 * h / d**2)) for d in designs]
    rows = rest_rows(recs[cal], res)
    return np.stack([lrv_factors(res.z, rows, L) for L in lengths], axis=1)


@dataclass
class ScaledModel:
    """A section-2 model with per-sensor factors c_j and a multiplier lambda:
    ``v_jt = 1 + lambda c_j (v_t - 1)``."""

    base: VarianceModel
    sensor: np.ndarray | None = None
    lam: float = 1.0

    def factors(self, res: Residual) -> np.ndarray:
        v = self.base.factors(res)
        if self.sensor is None and self.lam == 1.0:
            return v
        c = np.ones(res.z.shape[1]) if self.sensor is None else self.sensor
        return 1.0 + self.lam * (v[:, None] - 1.0) * c[None, :]


def sensor_factors(res: Residual, rows: np.ndarray, v: np.ndarray) -> np.ndarray:
    """c_j (n,): each sensor's mean of z_j^2 / v_t over the rows where v_t > 10 (clearly
    moving): its share of the pooled motion variance."""
    sel = rows & (v > 10.0)
    return np.asarray(np.mean(res.z[sel] ** 2 / v[sel, None], axis=0))


def fit_lambda(res: Residual, rec: Recording, model: ScaledModel, variant: Variant,
               lrv: np.ndarray) -> float:  # fmt: skip
    """The smallest lambda of LAMBDA_GRID whose CUSUM, run over every usable row of the
    calibration recording itself (in sample, so that the reference has followed the biases
    at rest), has no false episode starting on a moving row where the model's factor
    exceeds MOTION_GATE (where lambda acts); the largest if none."""
    h = threshold(res.z.shape[1], variant.designs)
    rows = res.valid & (rec.t >= WINDOW_S[1])
    # episodes lambda can act on: starting where the model itself says the board moves
    factors = model.base.factors(res)
    moving = moving_rows(rec, res) & (factors.reshape(len(rec.t), -1).max(axis=1) > MOTION_GATE)
    lo, hi = 0, len(LAMBDA_GRID) - 1

    def clean(i: int) -> bool:
        trial = ScaledModel(model.base, model.sensor, LAMBDA_GRID[i])
        idx, stat, _ = run_cusum(res, rows, variant, trial.factors(res), lrv, h)
        return not any(moving[idx[a]] for a, _ in episodes(stat.max(axis=1) > h))

    if clean(lo):
        return LAMBDA_GRID[lo]
    if not clean(hi):
        return LAMBDA_GRID[hi]
    while hi - lo > 1:  # clean(hi), not clean(lo)
        mid = (lo + hi) // 2
        if clean(mid):
            hi = mid
        else:
            lo = mid
    return LAMBDA_GRID[hi]


def motion_models(pairs: dict, recs: dict, models: dict) -> dict:
    """The motion models of the CUSUM runs per (calibration recording, type, base), fitted
    on the calibration recording: section 2's, calibrate's jitter model times a fitted
    lambda, and the polynomial model with per-sensor factors times a fitted lambda."""
    out: dict = {}
    rows_out = []
    for cal in RECORDINGS:
        for s in TYPES:
            res = pairs[(cal, cal, s)]
            rec = recs[cal]
            base = models[(cal, s)]
            rows = moving_rows(rec, res)
            c_j = sensor_factors(res, rows, base["poly"].factors(res))
            for key in BASES:
                variant = best("fit", key)
                lrv = lrv_of(pairs, recs, cal, s, variant.designs)
                jitter = ScaledModel(base["jitter"])
                jitter.lam = fit_lambda(res, rec, jitter, variant, lrv)
                poly_s = ScaledModel(base["poly"], c_j)
                poly_s.lam = fit_lambda(res, rec, poly_s, variant, lrv)
                out[(cal, s, key)] = {
                    "none": ScaledModel(base["none"]), "jitter": ScaledModel(base["jitter"]),
                    "jitter x lambda": jitter, "poly": ScaledModel(base["poly"]),
                    "poly per sensor x lambda": poly_s}  # fmt: skip
                extremes = f"{res.ids[int(np.argmin(c_j))]} / {res.ids[int(np.argmax(c_j))]}"
                rows_out.append([s, cal, BASE_NAMES[key], jitter.lam, poly_s.lam, spread(c_j),
                                 extremes])  # fmt: skip
    table("3c. Motion models for the CUSUM, fitted on the calibration recording: lambda (the "
          "smallest of a grid for which the CUSUM, run over the whole recording, has no false "
          "episode starting on a moving row where the model's factor exceeds 2) for "
          "calibrate's jitter model and for the "
          "polynomial model with per-sensor factors c_j (their median [min, max])",
          ["type", "fitted on", "CUSUM", "jitter lambda", "poly lambda", "poly c_j",
           "lowest / highest c_j"],
          rows_out)  # fmt: skip
    return out


def section_cusum(pairs: dict, recs: dict, scaled: dict, rng: np.random.Generator) -> None:
    rest_table, scan_table, cont_table = [], [], []
    for (cal, test, s), res in pairs.items():
        if cal == test:
            continue
        rec = recs[test]
        n = res.z.shape[1]
        rows = rest_rows(rec, res)
        seconds = np.count_nonzero(rows) / RATE_HZ
        ones = np.ones(len(rec.t))
        for variant in REST_VARIANTS:
            h = threshold(n, variant.designs)
            lrv = lrv_of(pairs, recs, cal, s, variant.designs)
            _, stat, _ = run_cusum(res, rows, variant, ones, lrv, h)
            top = stat.max(axis=1)
            eps = episodes(top > h)
            worst = sorted({res.ids[int(np.argmax(stat[a]))] for a, _ in eps})
            rest_table.append([s, f"{cal}->{test}", variant.name, f"{h:.2f}",
                               f"{seconds / 60:.1f}", count_rate(len(eps), seconds),
                               ", ".join(worst[:3]) + (" ..." if len(worst) > 3 else "")])  # fmt: skip
            if variant.name in (REST_VARIANTS[1].name, REST_VARIANTS[7].name,
                                REST_VARIANTS[11].name):  # fmt: skip
                scan_table.append([s, f"{cal}->{test}", variant.name,
                                   *(f"{len(episodes(top > hh)) / seconds * 3600:.3g}"
                                     for hh in (*H_SCAN, h))])  # fmt: skip
        for variant in (REST_VARIANTS[1], REST_VARIANTS[11]):
            h = threshold(n, variant.designs)
            ref = gaussian_reference(rng, int(np.count_nonzero(rows)), n, variant, (*H_SCAN, h))
            scan_table.append([s, f"Gaussian, same length as {test}",
                               f"clip 4, d {'/'.join(f'{d:g}' for d in variant.designs)}",
                               *(f"{ref[hh] / seconds * 3600:.3g}" for hh in (*H_SCAN, h))])  # fmt: skip
        # continuous: every usable row after the window, with the motion models
        rows = res.valid & (rec.t >= WINDOW_S[1])
        classes = {"static": rec.static, "moves": ~rec.static & ~rec.motion,
                   "motion phase": ~rec.static & rec.motion}  # fmt: skip
        runs = [("R", m) for m in MOTION_NAMES]
        runs += [("P", m) for m in ("none", "jitter x lambda", "poly per sensor x lambda")]
        for key, motion in runs:
            variant = best(motion, key)
            h = threshold(n, variant.designs)
            lrv = lrv_of(pairs, recs, cal, s, variant.designs)
            v = scaled[(cal, s, key)][motion].factors(res)
            idx, stat, _ = run_cusum(res, rows, variant, v, lrv, h)
            top = stat.max(axis=1)
            eps = episodes(top > h)
            row = [s, f"{cal}->{test}", f"{key}, {motion}"]
            for mask in classes.values():
                seconds = np.count_nonzero(rows & mask) / RATE_HZ
                count = sum(1 for a, _ in eps if mask[idx[a]])
                share = float(np.mean(top[mask[idx]] > h))
                row += [f"{seconds / 60:.1f}", count_rate(count, seconds), share]
            cont_table.append(row)
    table("3a. At rest (static rows after 10 s, the moves skipped; out of sample): false "
          "episodes per channel (sensor type: 24 sensors x designs x 2 sides), h = ln(gamma K); "
          "count (rate, Poisson 95 % upper bound) and the sensors that raised them. sigma: "
          "window = the 2-10 s std, pooled = calibrate's noise, kappa = pooled with the "
          "variance x sqrt(kappa); ref = exponential reference, tau 30 s unless said, gated "
          "while in alarm for at most 10 s unless said; LRV = max(1, F_L) per sensor and "
          "design, L = 2h/d^2, from the calibration recording; designs d = 1/2/4 sigma unless "
          f"said; S capped at h + {CAP:g} (small designs: h + {RECOVERY} d^2/2)",
          ["type", "cal->test", "variant", "h", "min tested", "false episodes", "sensors"],
          rest_table)  # fmt: skip
    table("3b. Episodes per hour at lower thresholds h (rest rows), against the same CUSUM on "
          "i.i.d. Gaussian noise of the same size (seeded; the ideal model)",
          ["type", "data", "variant", *(f"h={hh:g}" for hh in H_SCAN), "h design"],
          scan_table)  # fmt: skip
    table("3d. Continuous run (every usable row after 10 s; R = kappa sigma, ref, LRV, clip 4, "
          "d 2/4; P = the same with physical designs 2..32) with each motion model (3c; "
          "fitted on the calibration recording): tested "
          "minutes, false episodes (rate, upper bound) and share of samples in alarm, by where "
          "the episode starts", ["type", "cal->test", "motion model", "static min",
                                 "static episodes", "static in alarm", "moves min",
                                 "moves episodes", "moves in alarm", "motion min",
                                 "motion episodes", "motion in alarm"], cont_table)  # fmt: skip


# --- 3d. delays on injected faults --------------------------------------------------------

REST_FAULT_S = 5.0
MOTION_FAULT_S = 4.0


Fault = tuple[str, str, float, float, str, float]  # spec, sensor, onset, end, model, size SI


def fault_specs(rec: Recording) -> dict[str, list[Fault]]:
    """Sets of faults (one faulty log each), as (spec, sensor id, onset s, end s, model,
    size: step amplitude or drift rate, SI): 'A' = a
    0.9 deg/s gyro step and a 0.05 g accel step (another IMU) in the middle of every static
    orientation; 'B' = a 0.3 deg/s gyro step (odd orientations) or a 1 deg/s^2 gyro drift
    (even ones); 'M1', 'M2' = 5 deg/s gyro and 0.2 g accel steps of 4 s in the motion
    phase, every 10 s, alternating between the two logs."""
    out: dict[str, list] = {"A": [], "B": []}
    for i, item in enumerate(rec.intervals):
        start = max(item.start_s, WINDOW_S[1] + 1.0)
        mid = (start + item.end_s) / 2
        at, until = mid - REST_FAULT_S / 2, mid + REST_FAULT_S / 2
        if at < start:
            continue
        g = f"imu{i % 8}.gyro.{'xyz'[i % 3]}"
        a = f"imu{(i + 3) % 8}.accel.{'xyz'[(i + 1) % 3]}"
        window = f"at={at:.3f}s,until={until:.3f}s"
        out["A"].append((f"step:{g},{window},amp=0.9deg/s", g, at, until, "step", 0.9 * DEG))
        out["A"].append((f"step:{a},{window},amp=0.05g", a, at, until, "step", 0.05 * G))
        if i % 2:
            out["B"].append((f"step:{g},{window},amp=0.3deg/s", g, at, until, "step", 0.3 * DEG))
        else:
            out["B"].append((f"drift:{g},{window},rate=1deg/s^2", g, at, until, "drift", DEG))
    # motion: two logs, faults 20 s apart in each (a small design's alarm can take several
    # seconds to end after a fault), 10 s apart over both
    out["M1"], out["M2"] = [], []
    t = rec.motion_start + 3.0
    k = 0
    while t + MOTION_FAULT_S < rec.t[-1] - 1.0:
        g = f"imu{(k + 1) % 8}.gyro.{'xyz'[k % 3]}"
        a = f"imu{(k + 5) % 8}.accel.{'xyz'[(k + 2) % 3]}"
        window = f"at={t:.3f}s,until={t + MOTION_FAULT_S:.3f}s"
        target = out["M1" if k % 2 == 0 else "M2"]
        end = t + MOTION_FAULT_S
        target.append((f"step:{g},{window},amp=5deg/s", g, t, end, "step", 5 * DEG))
        target.append((f"step:{a},{window},amp=0.2g", a, t, end, "step", 0.2 * G))
        t += 10.0
        k += 1
    return out


FAULT_VARIANTS = [
    Variant("window sigma, fixed offset, clip 5, d 1/2/4, motion none", 5.0),
    Variant("kappa sigma, ref 10 s, LRV, clip 4, d 1/2/4, motion jitter", 4.0, 10.0, True,
            "jitter", "kappa"),
    *(best(m) for m in ("jitter", "jitter x lambda", "poly per sensor x lambda")),
    *(best(m, "P") for m in ("jitter x lambda", "poly per sensor x lambda")),
]  # fmt: skip
FAULT_BASE = {v.name: ("P" if v.physical else "R") for v in FAULT_VARIANTS}


def oracle_delay(res: Residual, t: np.ndarray, idx: np.ndarray, k: np.ndarray, j: int,
                 fault: Fault, variant: Variant, v: np.ndarray, lrv: np.ndarray,
                 h: float) -> float | None:  # fmt: skip
    """Delay (s) of the CUSUM matched to this very fault (its size and shape known) under
    the variant's noise model: the first processed row of the fault where the summed
    Kullback-Leibler information ``sum mu_t^2 / 2`` reaches h (Lorden's asymptotic delay
    h / KL for a step; mu_t = the fault's shift of x_j at row t). None: not within the
    fault."""
    _, _, at, _, model, size = fault
    if variant.sigma == "window":
        sigma = res.window_std[j]
    elif variant.sigma == "pooled":
        sigma = 1.0
    else:
        sigma = res.kappa[j] ** 0.25
    lrv_j = float(np.max(np.maximum(lrv[j], 1.0))) if variant.lrv else 1.0
    gain = res.window_std[j] / res.scale[j]  # shift of u_j per SI unit of fault
    rows = idx[k]
    amplitude = size if model == "step" else size * (t[rows] - at)
    vj = v[rows] if v.ndim == 1 else v[rows, j]
    mu = amplitude * gain / (sigma * math.sqrt(lrv_j) * np.sqrt(vj))
    reached = np.flatnonzero(np.cumsum(0.5 * mu**2) >= h)
    return None if reached.size == 0 else float(t[rows[reached[0]]] - at)


def isolated(stat: np.ndarray, iso: np.ndarray) -> int:
    """The sensor a detection names: the largest (clipped) statistic; among sensors tied
    with it (a large fault saturates the clip and the cap on the faulty sensor and on the
    sensors correlated with it), the largest unclipped statistic."""
    tied = stat >= stat.max() - 1e-9
    return int(np.argmax(np.where(tied, iso, -np.inf)))


def section_faults(pairs: dict, recs: dict, cals: dict, scaled: dict, work: Path) -> None:
    results: dict[tuple[str, str, str], list] = {}
    for cal_name, test in (("exp_1", "exp_2"), ("exp_2", "exp_1")):
        rec = recs[test]
        cal = cals[cal_name]
        for set_name, faults in fault_specs(rec).items():
            faulty = work / f"{test}-faults-{set_name}.mcap"
            inject_file(str(rec.path), str(faulty), [f[0] for f in faults], [], seed=0)
            frec = load_recording(test, faulty)
            frec.intervals, frec.interval_id = rec.intervals, rec.interval_id  # clean labels
            frec.motion_start = rec.motion_start
            for s in TYPES:
                res = residuals(cal_name, cal, frec, s)
                rows = res.valid & (frec.t >= WINDOW_S[1])
                mine = [f for f in faults if f".{s}." in f[0]]
                if not mine:
                    continue
                for variant in FAULT_VARIANTS:
                    h = threshold(res.z.shape[1], variant.designs)
                    lrv = lrv_of(pairs, recs, cal_name, s, variant.designs)
                    model = scaled[(cal_name, s, FAULT_BASE[variant.name])][variant.motion]
                    v = model.factors(res)
                    idx, stat, iso = run_cusum(res, rows, variant, v, lrv, h, isolate=True)
                    for fault in mine:
                        spec, sensor, at, until, _, _ = fault
                        kind = spec.split(",")[-1].split("=")[1]
                        where = "motion" if at > rec.motion_start else "rest"
                        j = res.ids.index(sensor)
                        k = np.flatnonzero((frec.t[idx] >= at) & (frec.t[idx] < until))
                        key = (f"{s} {kind} {where}", f"{cal_name}->{test}", variant.name)
                        before = bool(k.size and k[0] > 0 and np.any(stat[k[0] - 1] > h))
                        oracle = oracle_delay(res, frec.t, idx, k, j, fault, variant, v, lrv, h)
                        hit = k[np.max(stat[k], axis=1) > h]
                        if hit.size == 0:
                            results.setdefault(key, []).append((None, False, before, oracle))
                            continue
                        delay = float(frec.t[idx[hit[0]]] - at)
                        right = isolated(stat[hit[0]], iso[hit[0]]) == j
                        results.setdefault(key, []).append((delay, right, before, oracle))
    rows_out = []
    for (fault_name, pair, name), items in results.items():
        delays = np.array([d for d, _, _, _ in items if d is not None])
        oracles = np.array([o for _, _, _, o in items if o is not None])
        found = delays.size
        rows_out.append([fault_name, pair, name, f"{found}/{len(items)}",
                         float(np.mean(delays)) if found else math.nan,
                         float(np.max(delays)) if found else math.nan,
                         sum(r for d, r, _, _ in items if d is not None),
                         sum(b for _, _, b, _ in items),
                         f"{oracles.size}/{len(items)}",
                         float(np.mean(oracles)) if oracles.size else math.nan])  # fmt: skip
    rows_out.sort(key=lambda r: (str(r[0]), FAULT_ORDER[str(r[2])], str(r[1])))
    table("3e. Injected faults (inject_file, the function of imufdi inject; steps on raw chip "
          "values; rest faults 5 s mid-orientation, motion faults 4 s, 20 s apart in each "
          "log): detected within the fault, delay from onset to the first sample whose "
          "statistic exceeds h (the decision time: every term is causal, no look-ahead), "
          "isolated to the faulty sensor (largest statistic at that sample, ties broken by the "
          "unclipped statistics), faults "
          "whose channel was already in alarm on the sample before the onset, and the oracle: "
          "the CUSUM matched to the fault's exact size under the same noise model (Lorden, "
          "h / KL), detected within the fault and its mean delay",
          ["fault", "cal->test", "variant", "detected", "mean delay s", "max delay s",
           "right sensor", "in alarm at onset", "oracle detected", "oracle delay s"],
          rows_out)  # fmt: skip


FAULT_ORDER = {v.name: i for i, v in enumerate(FAULT_VARIANTS)}


# --- driver -------------------------------------------------------------------------------


def prepare(data: Path, work: Path) -> tuple[dict, dict]:
    """Ingest and calibrate each recording (what ``imufdi ingest`` and ``imufdi calibrate``
    do); returns the recordings and their calibrated arrays."""
    recs, cals = {}, {}
    missing = [str(data / f"{n}.bin") for n in RECORDINGS if not (data / f"{n}.bin").is_file()]
    if missing:
        raise SystemExit(f"no recording {', '.join(missing)}: give --data, the folder with "
                         "the MIMU4444 exp_1.bin and exp_2.bin")  # fmt: skip
    for name in RECORDINGS:
        path = work / f"{name}.mcap"
        stats = ingest_file(str(data / f"{name}.bin"), str(path), layout=str(LAYOUT),
                            array_path=str(BASE))  # fmt: skip
        result = calibrate_file(str(path))
        cals[name] = result.array
        result.array.save(work / f"{name}-cal.toml")
        recs[name] = load_recording(name, path)
        rec = recs[name]
        print(
            f"- {name}: {stats.frames_ok} frames, {len(rec.intervals)} static intervals "
            f"({np.count_nonzero(rec.static) / RATE_HZ / 60:.1f} min), motion phase from "
            f"{rec.motion_start:.0f} s ({(rec.t[-1] - rec.motion_start) / 60:.1f} min), "
            f"{np.count_nonzero(rec.bad['gyro'])} clipped gyro rows; jitter sigma_t "
            + ", ".join(f"{k} {v * 1e3:.3f} ms" for k, v in result.jitter_s.items())
        )
    return recs, cals


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/work/data/mimu4444"),
                        help="folder with exp_1.bin and exp_2.bin")  # fmt: skip
    parser.add_argument("--work", type=Path, default=None, help="folder for the MCAP logs")
    parser.add_argument("--seed", type=int, default=0, help="seed of the Gaussian reference")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        print("## The MIMU4444 parity residual at rest and in motion (exp_1, exp_2)\n")
        recs, cals = prepare(args.data, work)
        pairs = {(c, t, s): residuals(c, cals[c], recs[t], s)
                 for s in TYPES for c in RECORDINGS for t in RECORDINGS}  # fmt: skip
        section_rest(pairs, recs)
        section_wander(pairs, recs)
        orientation_repeat(pairs, recs)
        section_reference(pairs, recs)
        models = section_motion(pairs, recs)
        section_spatial(pairs, recs)
        section_windows(pairs, recs)
        scaled = motion_models(pairs, recs, models)
        section_cusum(pairs, recs, scaled, np.random.default_rng(args.seed))
        section_faults(pairs, recs, cals, scaled, work)
    print(f"\n(run time {time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
