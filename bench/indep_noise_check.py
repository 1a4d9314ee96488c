"""Hold ``gyroharness noise`` against still-gyro files made by generators that are not ours.

Each case writes three-axis CSV data files the way a user would (DESIGN.md data file: ``t_s`` and
``gyro_*_rad_s``, or raw MPU-6050 integer LSB in the tomisuarez2 logger layout, converted by
``gyroharness convert``), runs ``gyroharness noise FILE --json`` through the click command
in-process (the same code path as the console script, without 3 s of imports per file), and
compares every reported term and its 95 % interval with the generator's truth.  Generators:
``tests/indep_noise.py`` (white, cumulative-sum random walk, allantools' Kasdin power law, FFT
1/f shaping, gnss-ins-sim's Gauss–Markov, sums of GMs, integer-LSB rounding).

    PYTHONPATH=$PWD python bench/indep_noise_check.py --cases all --seeds 4 --out /tmp/indep/res.json
    PYTHONPATH=$PWD python bench/indep_noise_check.py --summarise /tmp/indep/res.json
    PYTHONPATH=$PWD python bench/indep_noise_check.py --drift 60,600 --cases rw_kalibr_200Hz_1h --seeds 8

Truth: N, K, B, GM σ/τc as generated; with output rounding the white density the data carry is
√(N² + LSB²/(12·fs)) (rounding adds white rate noise when the noise spans ≳ ½ LSB, Widrow).
Datasheet values (cited beside each preset) are the typical specification converted once:
°/s/√Hz × π/180 = rad/√s; °/h × π/180/3600 = rad/s; a datasheet "bias stability"/"in-run bias
stability" is the ADEV floor, so IEEE B = floor/0.664.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import zlib
from dataclasses import dataclass, field

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from tests import indep_noise as G  # noqa: E402

DEG = math.pi / 180.0
DPH = DEG / 3600.0  # °/h → rad/s


@dataclass(frozen=True)
class Case:
    name: str
    fs_hz: float
    duration_s: float
    N: float = 0.0  # rad/√s
    K: float = 0.0  # rad/s/√s (cumulative sum)
    B: float = 0.0  # rad/s, IEEE 952 flicker coefficient
    flicker: str = "fft"  # fft | allantools
    gms: tuple = ()  # ((σ rad/s, τc s), ...) gnss-ins-sim style
    lsb_per_dps: float | None = None  # integer rounding
    raw_mpu6050: bool = False  # write the tomisuarez2 raw-LSB layout and convert
    note: str = ""
    expect: dict = field(default_factory=dict)  # extra truth statements


# Datasheet values (typical), converted once:
# MPU-6050: InvenSense PS-MPU-6000A-00 rev 3.4 §6.1: rate noise spectral density 0.005 °/s/√Hz,
#   ±250 °/s sensitivity 131 LSB/(°/s).  Bias instability not specified.
# BMI088: Bosch BST-BMI088-DS001 (gyro): noise density 0.014 °/s/√Hz, bias stability 2 °/h
#   (ADEV floor); ±2000 °/s: 16.384 LSB/(°/s).
# ICM-42688-P: TDK DS-000347 Table 1: rate noise spectral density 0.0028 °/s/√Hz; ±2000 dps
#   16.4 LSB/dps.  Bias instability not specified.
# FOG-like: KVH DSP-1760 datasheet: angle random walk ≤ 0.012 °/√h, bias instability ≤ 0.05 °/h
#   (ADEV floor, 25 °C).
# gnss-ins-sim "mid accuracy" IMU (its IMU381-like preset): arw 0.25 °/√h, gyro bias drift
#   3.5 °/h with correlation time 100 s (first-order GM).
MPU_N = 0.005 * DEG
BMI_N, BMI_FLOOR = 0.014 * DEG, 2.0 * DPH
ICM_N = 0.0028 * DEG
FOG_N, FOG_FLOOR = 0.012 * DEG / 60.0, 0.05 * DPH
GIS_N, GIS_GM = 0.25 * DEG / 60.0, (3.5 * DPH, 100.0)
F = G.FLICKER_FLOOR

CASES = {
    c.name: c
    for c in [
        Case("white_mpu6050_100Hz_10min", 100, 600, N=MPU_N),
        Case("white_icm42688_1kHz_10min", 1000, 600, N=ICM_N),
        Case("white_bmi088_400Hz_20min", 400, 1200, N=BMI_N),
        Case(
            "rw_kalibr_200Hz_1h",
            200,
            3600,
            N=1.7e-4,
            K=1.9e-5,
            note="Kalibr-yaml-like N, K (continuous-time units); cumsum random walk",
        ),
        Case("rw_kalibr_200Hz_2h", 200, 7200, N=1.7e-4, K=4e-6),
        Case("flicker_fft_fog_100Hz_2h", 100, 7200, N=FOG_N, B=FOG_FLOOR / F, flicker="fft"),
        Case("flicker_kasdin_fog_100Hz_2h", 100, 7200, N=FOG_N, B=FOG_FLOOR / F, flicker="allantools"),
        Case("flicker_fft_bmi088_100Hz_2h", 100, 7200, N=BMI_N, B=BMI_FLOOR / F, flicker="fft"),
        Case("flicker_fft_strong_100Hz_1h", 100, 3600, N=1e-4, B=5e-5, flicker="fft"),
        Case("flicker_kasdin_strong_100Hz_1h", 100, 3600, N=1e-4, B=5e-5, flicker="allantools"),
        Case("gm_gnss_ins_sim_100Hz_1h", 100, 3600, N=GIS_N, gms=(GIS_GM,)),
        Case("gm_gnss_ins_sim_100Hz_2h", 100, 7200, N=GIS_N, gms=(GIS_GM,)),
        Case(
            "gm_sum4_100Hz_2h",
            100,
            7200,
            N=1e-4,
            gms=((2e-5, 3.0), (2e-5, 30.0), (2e-5, 300.0), (2e-5, 3000.0)),
            note="four GMs a decade apart: ≈ a flicker floor between ~5 s and ~5000 s",
            # Σ 2σ²τc/(1+(2πfτc)²) over τc log-spaced a decade apart ≈ (2σ²/ln10)∫τc/(1+(2πfτc)²)
            # dln τc = σ²/(2f ln10) = B²/(2πf) ⇒ B = σ√(π/ln10) between the τc's
            expect={
                "bias_instability_rad_s": 2e-5 * math.sqrt(math.pi / math.log(10.0)),
                "correlated_sigma_rad_s": "n/a",
            },
        ),
        Case("flicker_kasdin_bmi088_100Hz_2h", 100, 7200, N=BMI_N, B=BMI_FLOOR / F, flicker="allantools"),
        Case("gm_gnss_ins_sim_100Hz_4h", 100, 14400, N=GIS_N, gms=(GIS_GM,)),
        Case("quant_mpu6050_raw_100Hz_30min", 100, 1800, N=MPU_N, lsb_per_dps=131.0, raw_mpu6050=True),
        Case("quant_icm42688_2000dps_100Hz_20min", 100, 1200, N=ICM_N, lsb_per_dps=16.4),
        Case("quant_icm42688_2000dps_1kHz_10min", 1000, 600, N=ICM_N, lsb_per_dps=16.4),
        Case("quant_bmi088_2000dps_400Hz_20min_flicker", 400, 1200, N=BMI_N, B=BMI_FLOOR / F, lsb_per_dps=16.384),
        # a flicker plateau of 3.5 octaves between N's crossing (13 s) and K's (150 s),
        # the levels of experiments.noise_study.plateau_mix(3.5); 2 h at 20 Hz, where the lowest
        # periodogram bins are red (the old line detector took bin 2 for a line)
        Case("nbk_plateau_fft_20Hz_2h", 20, 7200, N=1e-4, B=4.134e-5, K=3.884e-6, flicker="fft"),
        Case("nbk_plateau_kasdin_20Hz_2h", 20, 7200, N=1e-4, B=4.134e-5, K=3.884e-6, flicker="allantools"),
    ]
}


def make_axes(case: Case, rng: np.random.Generator) -> np.ndarray:
    n = int(round(case.duration_s * case.fs_hz))
    cols = []
    for _ in range(3):
        x = np.zeros(n)
        if case.N:
            x += G.white(n, case.fs_hz, case.N, rng)
        if case.K:
            x += G.random_walk(n, case.fs_hz, case.K, rng)
        if case.B:
            gen = G.flicker_fft if case.flicker == "fft" else G.flicker_allantools
            x += gen(n, case.fs_hz, case.B, rng)
        for s, tc in case.gms:
            x += G.gauss_markov_gnss_ins_sim(n, case.fs_hz, s, tc, rng)
        cols.append(x)
    return np.column_stack(cols)


def truth(case: Case) -> dict:
    N = case.N
    if case.lsb_per_dps:
        # rounding is memoryless, so the rounded white noise stays white; its variance is the
        # exact second moment of the rounded zero-mean Gaussian (Sheppard's σ² + Δ²/12 is 3 %
        # high in N at σ = 0.46 LSB: the ICM-42688-P at ±2000 dps, 100 Hz)
        lsb = DEG / case.lsb_per_dps
        N = math.sqrt(rounded_gaussian_var(case.N * math.sqrt(case.fs_hz), lsb) / case.fs_hz)
    t = {
        "arw_rad_per_sqrt_s": N,
        "bias_instability_rad_s": case.B or None,
        "rrw_rad_per_s_sqrt_s": case.K or None,
        "quantization_rad": None,
        "rate_ramp_rad_s2": None,
    }
    t.update(case.expect)
    if len(case.gms) == 1:
        s, tc = case.gms[0]
        t["correlated_sigma_rad_s"] = G.gm_stationary_sigma(s, tc, case.fs_hz)
        t["correlated_tau_c_s"] = tc
    elif not case.gms:
        t["correlated_sigma_rad_s"] = None
    return t


def rounded_gaussian_var(sigma: float, lsb: float) -> float:
    """Var(Δ·round(x/Δ)) for x ~ N(0, σ²), by the sum over output levels."""
    from scipy.stats import norm

    k = np.arange(-int(12 * sigma / lsb) - 2, int(12 * sigma / lsb) + 3)
    p = norm.cdf((k + 0.5) * lsb / sigma) - norm.cdf((k - 0.5) * lsb / sigma)
    return float(np.sum(p * (k * lsb) ** 2))


def write_file(case: Case, omega: np.ndarray, path: str) -> str:
    """Write as a user would; returns the data file to analyse."""
    n = omega.shape[0]
    t = np.arange(n) / case.fs_hz
    if case.raw_mpu6050:
        counts = G.quantize_lsb(omega, case.lsb_per_dps)
        acc = np.tile(np.array([[0, 0, 16384]], dtype=np.int64), (n, 1))
        raw = path[:-4] + "_raw.csv"
        with open(raw, "w") as fh:
            fh.write(
                f"Fs,{case.fs_hz:g}\nLogging Type,static\nInitialization time,0\nWaiting time,0\nax,ay,az,gx,gy,gz\n"
            )
            np.savetxt(fh, np.column_stack([acc, counts]), fmt="%d", delimiter=",")
        _cli(["convert", raw, "--format", "tomisuarez2", "-o", path, "--force"])
        return path
    if case.lsb_per_dps:  # quantized, written in °/s as the driver's counts / sensitivity
        counts = G.quantize_lsb(omega, case.lsb_per_dps)
        vals, hdr, fmt = counts / case.lsb_per_dps, "gyro_{}_deg_s", "%.10g"
    else:
        vals, hdr, fmt = omega, "gyro_{}_rad_s", "%.9e"
    with open(path, "w") as fh:
        fh.write("# generator: tests/indep_noise.py " + case.name + "\n")
        fh.write("t_s," + ",".join(hdr.format(a) for a in "xyz") + "\n")
        np.savetxt(fh, np.column_stack([t, vals]), fmt=["%.6f", fmt, fmt, fmt], delimiter=",")
    return path


_GROUP = None


def _cli(args: list[str]) -> str:
    global _GROUP
    from click.testing import CliRunner

    from gyrocore.cli import build_group

    if _GROUP is None:
        _GROUP = build_group(["experiments.commands"])
    r = CliRunner().invoke(_GROUP, args, catch_exceptions=False)
    if r.exit_code != 0:
        raise RuntimeError(f"gyroharness {' '.join(args)} -> exit {r.exit_code}: {r.output[-400:]}")
    return r.stdout if hasattr(r, "stdout") else r.output


def run_case(case: Case, seed: int, workdir: str, *, plot: bool = False, keep: bool = False) -> list[dict]:
    rng = np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(case.name.encode())]))
    omega = make_axes(case, rng)
    path = os.path.join(workdir, f"{case.name}_s{seed}.csv")
    f = write_file(case, omega, path)
    args = ["noise", f, "--json"] + (["--plot", path[:-4] + ".png"] if plot else [])
    t0 = time.process_time()
    out = json.loads(_cli(args))
    cpu = time.process_time() - t0
    if not keep:
        for p in (path, path[:-4] + "_raw.csv"):
            if os.path.exists(p):
                os.remove(p)
    tr = truth(case)
    rows = []
    for ax, res in out["axes"].items():
        for name, tv in tr.items():
            if name not in res or tv == "n/a":
                continue
            lo, hi = res["ci95"][name]
            lo = 0.0 if lo is None else lo
            hi = math.inf if hi is None else hi  # JSON null = unbounded (inf is not JSON)
            rows.append(
                {
                    "case": case.name,
                    "seed": seed,
                    "axis": ax,
                    "term": name,
                    "truth": tv,
                    "reported": res[name],
                    "estimate": res["estimate"][name],
                    "lo": lo,
                    "hi": hi,
                    "covered": (tv is None and lo == 0.0) or (tv is not None and lo <= tv <= hi),
                    "claimed": res[name] is not None,
                    "ambiguous": res.get("ambiguous", {}),
                    "cpu_s": cpu,
                }
            )
        # what a user reads off the ADEV plot: min ADEV / 0.664
        curve = res.get("curve") or {}
        if curve.get("taus_s"):
            Bf, tmin = G.adev_floor_B(np.asarray(curve["taus_s"]), np.asarray(curve["adev_rad_s"]))
            rows.append(
                {
                    "case": case.name,
                    "seed": seed,
                    "axis": ax,
                    "term": "adev_floor_B",
                    "truth": tr.get("bias_instability_rad_s"),
                    "reported": Bf,
                    "estimate": Bf,
                    "lo": None,
                    "hi": None,
                    "covered": None,
                    "claimed": True,
                    "tau_min_s": tmin,
                    "ambiguous": {},
                    "cpu_s": cpu,
                }
            )
    return rows


def summarise(rows: list[dict]) -> str:
    from collections import defaultdict

    by = defaultdict(list)
    for r in rows:
        by[(r["case"], r["term"])].append(r)
    out = [
        "| generator | term | truth | reported (median; range) | claimed | interval covers truth |",
        "|---|---|---|---|---|---|",
    ]
    for (c, t), rs in by.items():
        tv = rs[0]["truth"]
        if t == "adev_floor_B":
            vals = [r["reported"] for r in rs]
            out.append(
                f"| {c} | min ADEV/0.664 | {tv if tv is None else f'{tv:.3g}'} | {np.median(vals):.3g}; "
                f"{min(vals):.3g}–{max(vals):.3g} (τ_min {np.median([r['tau_min_s'] for r in rs]):.0f} s) | — | — |"
            )
            continue
        if t == "correlated_tau_c_s" and tv is None:
            continue
        claimed = sum(r["claimed"] for r in rs)
        cov = sum(bool(r["covered"]) for r in rs)
        est = [r["reported"] for r in rs if r["reported"] is not None]
        est_s = f"{np.median(est):.3g}; {min(est):.3g}–{max(est):.3g}" if est else "null"
        mark = "" if (tv is None) == (claimed == 0) or tv is not None else " **false claim**"
        out.append(
            f"| {c} | {t} | {'absent' if tv is None else f'{tv:.3g}'} | {est_s} | {claimed}/{len(rs)}{mark} | "
            f"{cov}/{len(rs)} |"
        )
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="all", help="comma list of case names or 'all'")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--seed0", type=int, default=7000)
    ap.add_argument("--workdir", default="/tmp/indep")
    ap.add_argument("--out", default=None)
    ap.add_argument("--plot", action="store_true")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--summarise", default=None, help="print the table of a saved result JSON")
    ap.add_argument(
        "--drift",
        default=None,
        metavar="W,H",
        help="instead: heading drift over H s after a W-s bias window, measured vs predicted",
    )
    a = ap.parse_args(argv)
    if a.drift:
        w, h = (float(v) for v in a.drift.split(","))
        os.makedirs(a.workdir, exist_ok=True)
        names = list(CASES) if a.cases == "all" else a.cases.split(",")
        for name in names:
            print(json.dumps(drift_check(CASES[name], a.seeds, a.seed0, w, h, a.workdir)), flush=True)
        return
    if a.summarise:
        print(summarise(json.load(open(a.summarise))))
        return
    os.makedirs(a.workdir, exist_ok=True)
    names = list(CASES) if a.cases == "all" else a.cases.split(",")
    rows = []
    for name in names:
        for s in range(a.seed0, a.seed0 + a.seeds):
            t0 = time.time()
            rows += run_case(CASES[name], s, a.workdir, plot=a.plot and s == a.seed0, keep=a.keep)
            print(f"{name} seed {s}: {time.time() - t0:.1f} s", file=sys.stderr, flush=True)
            if a.out:
                with open(a.out, "w") as fh:
                    json.dump(rows, fh)
    print(summarise(rows))


def drift_sd_rad(terms: dict, window_s: float, horizon_s: float) -> float:
    """Predicted SD of the heading error ∫(ω − b̂)dt over ``horizon_s`` after a still window of
    ``window_s`` whose mean is taken as the bias: θ = H·(ȳ[W, W+H] − ȳ[0, W]), its variance from
    the block covariances of :func:`gyrocore.calib.budget.block_covariance` (the drift model the
    error budget uses) for each term.  ``terms``: the noise JSON keys (None/absent = 0)."""
    from gyrocore.calib.budget import Blocks, block_covariance

    t0 = np.array([0.0, window_s])
    t1 = np.array([window_s, window_s + horizon_s])
    bl = Blocks(
        i0=np.array([0, 1]),
        i1=np.array([1, 2]),
        t0_s=t0,
        t1_s=t1,
        scored=np.array([False, True]),
        segment=np.zeros(2, int),
        window=np.array([0, -1]),
    )
    d = np.array([1.0, -1.0])
    var = 0.0
    for key, term, sq in (
        ("arw_rad_per_sqrt_s", "arw", 1),
        ("bias_instability_rad_s", "bias_instability", 1),
        ("rrw_rad_per_s_sqrt_s", "rrw", 1),
    ):
        v = terms.get(key) or 0.0
        if v:
            var += v * v * float(d @ block_covariance(bl, term) @ d)
    s, tc = terms.get("correlated_sigma_rad_s") or 0.0, terms.get("correlated_tau_c_s") or 0.0
    if s and tc:
        var += s * s * float(d @ block_covariance(bl, "correlated", tau_c_s=tc) @ d)
    return horizon_s * math.sqrt(var)


def drift_check(case: Case, seeds: int, seed0: int, window_s: float, horizon_s: float, workdir: str) -> dict:
    """Measured heading-error RMS of the generated files (bias = mean of the first window,
    integrated over the horizon after it) against the drift predicted from the truth and from
    what ``gyroharness noise`` reports (a null term counts 0, as the budget takes it)."""
    meas, pred_rep = [], []
    for s in range(seed0, seed0 + seeds):
        rng = np.random.default_rng(np.random.SeedSequence([s, zlib.crc32(case.name.encode())]))
        omega = make_axes(case, rng)
        path = os.path.join(workdir, f"drift_{case.name}_s{s}.csv")
        out = json.loads(_cli(["noise", write_file(case, omega, path), "--json"]))
        os.remove(path)
        iw = int(round(window_s * case.fs_hz))
        ih = int(round(horizon_s * case.fs_hz))
        for k, ax in enumerate("xyz"):
            x = omega[:, k]
            meas.append((x[iw : iw + ih].mean() - x[:iw].mean()) * horizon_s)
            pred_rep.append(drift_sd_rad(out["axes"][ax], window_s, horizon_s))
    tr = {k: v for k, v in truth(case).items() if isinstance(v, float)}
    return {
        "case": case.name,
        "window_s": window_s,
        "horizon_s": horizon_s,
        "axes": len(meas),
        "measured_rms_deg": math.degrees(math.sqrt(np.mean(np.square(meas)))),
        "predicted_truth_deg": math.degrees(drift_sd_rad(tr, window_s, horizon_s)),
        "predicted_reported_deg_median": math.degrees(float(np.median(pred_rep))),
        "predicted_reported_deg_range": [math.degrees(min(pred_rep)), math.degrees(max(pred_rep))],
    }


if __name__ == "__main__":
    main()
