"""Estimator efficiency: Monte Carlo spread of each estimate over its bound.

Run: ``nice python bench/bench_efficiency.py [--instances 200] [--seed 0] [--json]``.

For each estimator, many independent synthetic recordings are made with
:func:`gyrocore.effects.registry.deterministic` plus white rate noise from an explicit
``np.random.Generator`` (instance ``i`` uses ``SeedSequence(seed).spawn(n)[i]``), the *real*
gyrocore estimator is run on each, and the standard deviation of the estimates over the
instances is divided by the Cramér–Rao bound (or by the spread the estimator's own interval
claims). A ratio of 1 is an efficient estimator (or an honest interval); the Monte Carlo
uncertainty of a ratio of standard deviations from n instances is ≈ 1/√(2(n−1))
(5 % for n = 200), printed beside each ratio.

1. **Static bias** — :class:`gyrocore.calib.bias.StaticBiasCalibrator` (one window spanning a
   still recording of T seconds) with white noise density N (rad/√s). For white Gaussian
   noise the CRB of the bias is σ/√n = N·√fs/√(fs·T) = N/√T. Goal ≤ 1.1 for the mean rule;
   the median rule is shown too (its asymptotic efficiency loss is √(π/2) = 1.2533).
2. **Rate table** — :class:`gyrocore.calibrator.Calibrator` (default options: least squares of
   :mod:`gyrocore.calib.lsq` with the Ljung–Box covariance switch and the robust pass) fitting
   bias, scale, misalignment and g-sensitivity to
   six mounts (each sensor axis up and down) × (still, +rate, −rate). The model
   y − ω_ref = A·θ + e is exactly linear in these effects and e is white Gaussian with σ per
   sample, so the Fisher information is AᵀA/σ² and the CRB of θ_p is
   σ·√[(AᵀA)⁻¹]_pp (A flattened to (3N, P), regressors from ``effects.design``). Reported:
   median and max over the parameters of each group (K = scale + misalignment, 9 values;
   H = g-sensitivity, 9 values).
3. **Allan N** — :func:`gyrocore.noise.allan.allan_analysis` on white noise: (a) the MC spread of
   N̂ over the spread implied by its reported 95 % interval, which comes from the
   chi-square (Greenhall EDF) weights of the fit: σ_c = (hi² − lo²)/(2·1.96) on the variance
   coefficient c = N², so σ_N = σ_c/(2N); ratio ≈ 1 = an honest interval. (b) the MC spread
   over the CRB of a white-noise density from n samples: the sample variance has
   var = 2σ⁴/n, so std(N̂)/N ≥ 1/√(2n) (delta method) — Allan-based N is not efficient; this
   says by how much.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.noise.allan import allan_analysis
from gyrocore.calib.lsq import build_design
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import Recording

G_M_S2 = 9.80665
Z95 = 1.959963984540054  # two-sided 95 % normal quantile

#: The six mounts: which sensor axis points up (+1) or down (−1).
MOUNTS = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0), (2, -1.0))


def _rngs(seed: int, n: int) -> list[np.random.Generator]:
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]


def _ratio_ci(n: int) -> float:
    """Relative standard error of a sample standard deviation from n draws, ≈ 1/√(2(n−1))."""
    return 1.0 / math.sqrt(2.0 * (n - 1))


# ---------------------------------------------------------------------------- 1. static bias
def static_bias(instances: int, seed: int, *, rate_hz=200.0, duration_s=10.0, n_rad_per_sqrt_s=1e-3, rule="mean"):
    from gyrocore.calib.bias import StaticBiasCalibrator

    n = int(round(rate_hz * duration_s))
    # Three windows of T = n / rate: the estimate is the first window the motion gate accepts
    # (a still window is refused with probability false_reject_rate = 1e-3).
    n_rec = 3 * n
    t = np.arange(n_rec) / rate_hz
    sigma = n_rad_per_sqrt_s * math.sqrt(rate_hz)  # DESIGN.md noise convention
    errs, reported = [], []
    cal = StaticBiasCalibrator(window_samples=n, rule=rule)
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=np.zeros((n_rec, 3)))
    for rng in _rngs(seed, instances):
        b = rng.normal(0.0, 0.01, 3)
        gyro = E.deterministic({"bias": {"b_rad_s": b}}, inp) + rng.normal(0.0, sigma, (n_rec, 3))
        res = cal.fit(Recording(t_s=t, gyro_rad_s=gyro, meta={"scenario": "static"}))
        if res.window_samples != n:
            raise RuntimeError(f"bias window {res.window_samples} != {n} samples")
        errs.append(np.asarray(res.bias_rad_s) - b)
        reported.append(np.asarray(res.bias_se_rad_s, float))
    errs = np.asarray(errs)
    crb = n_rad_per_sqrt_s / math.sqrt(n / rate_hz)  # N/√T = σ/√n (per axis, rad/s)
    std = float(np.std(errs, ddof=1))  # pooled over axes: 3·instances draws
    return {
        "estimator": f"gyrocore.calib.bias.StaticBiasCalibrator(rule={rule!r})",
        "rate_hz": rate_hz,
        "duration_s": n / rate_hz,
        "n_rad_per_sqrt_s": n_rad_per_sqrt_s,
        "mc_std_rad_s": std,
        "crb_rad_s": crb,
        "ratio": std / crb,
        "ratio_mc_rel_se": _ratio_ci(errs.size),
        "mean_error_over_crb": float(np.mean(errs)) / crb,
        "reported_stderr_over_crb": float(np.median(np.asarray(reported))) / crb,
        "goal": "<= 1.1" if rule == "mean" else "sqrt(pi/2) = 1.2533 expected for a median",
    }


# ---------------------------------------------------------------------------- 2. rate table
RATE_TABLE_EFFECTS = ("bias", "scale", "misalignment", "g_sensitivity")


def rate_table_inputs(*, rate_hz=200.0, segment_s=5.0, table_rate_rad_s=1.0) -> E.ModelInputs:
    """Six mounts × (still, +rate, −rate): reference rate and specific force in S."""
    n_seg = int(round(rate_hz * segment_s))
    omega, force = [], []
    for axis, sign in MOUNTS:
        up = np.zeros(3)
        up[axis] = sign
        for r in (0.0, table_rate_rad_s, -table_rate_rad_s):
            omega.append(np.tile(r * up, (n_seg, 1)))
            force.append(np.tile(G_M_S2 * up, (n_seg, 1)))  # +g on the up axis at rest
    omega = np.concatenate(omega)
    n = omega.shape[0]
    return E.ModelInputs(t_s=np.arange(n) / rate_hz, omega_S_rad_s=omega, f_S_m_s2=np.concatenate(force))


def rate_table(instances: int, seed: int, *, rate_hz=100.0, segment_s=5.0, n_rad_per_sqrt_s=1e-3):
    inp = rate_table_inputs(rate_hz=rate_hz, segment_s=segment_s)
    n = inp.n
    sigma = n_rad_per_sqrt_s * math.sqrt(rate_hz)
    A, names, slices = build_design(RATE_TABLE_EFFECTS, inp)
    Af = A.reshape(3 * n, -1)
    crb = sigma * np.sqrt(np.diag(np.linalg.inv(Af.T @ Af)))  # σ·√[(AᵀA)⁻¹]_pp
    thetas_err, reported = [], []
    for rng in _rngs(seed, instances):
        params = {
            "bias": {"b_rad_s": rng.normal(0, 0.01, 3)},
            "scale": {"s": rng.normal(0, 0.01, 3)},
            "misalignment": {"m_rad": rng.normal(0, 0.005, 6)},
            "g_sensitivity": {"h_rad_s_per_m_s2": rng.normal(0, 1e-4, (3, 3))},
        }
        y = E.deterministic(params, inp) + rng.normal(0.0, sigma, (n, 3))
        rec = Recording(
            t_s=inp.t_s,
            gyro_rad_s=y,
            accel_m_s2=inp.f_S_m_s2,
            ref_rate_rad_s=inp.omega_S_rad_s,
            meta={"sensor": "white", "scenario": "rate_table"},
        )
        res = Calibrator(effects=RATE_TABLE_EFFECTS).fit(rec)
        if res.unobservable:
            raise RuntimeError(f"rate-table design left {res.unobservable} unobservable")
        flat = lambda d: np.concatenate([np.ravel(d[e][k]) for e in RATE_TABLE_EFFECTS for k in E.PARAM_SCHEMA[e]])  # noqa: E731
        thetas_err.append(flat(res.params) - flat(params))
        reported.append(flat(res.stderr))
    err = np.asarray(thetas_err)
    std = np.std(err, axis=0, ddof=1)
    ratio = std / crb
    rep = np.median(np.asarray(reported), axis=0) / crb
    groups = {
        "bias": slices["bias"],
        "K (scale+misalignment)": np.r_[slices["scale"], slices["misalignment"]],
        "H (g-sensitivity)": slices["g_sensitivity"],
    }
    out = {
        "estimator": "gyrocore.calibrator.Calibrator(effects=bias,scale,misalignment,g_sensitivity)",
        "design": f"6 mounts x (still, +1, -1 rad/s) x {segment_s:g} s at {rate_hz:g} Hz",
        "n_rad_per_sqrt_s": n_rad_per_sqrt_s,
        "ratio_mc_rel_se": _ratio_ci(instances),
        "groups": {},
    }
    for g, sl in groups.items():
        idx = np.arange(len(names))[sl]
        out["groups"][g] = {
            "n_params": int(idx.size),
            "crb_median": float(np.median(crb[idx])),
            "ratio_median": float(np.median(ratio[idx])),
            "ratio_max": float(np.max(ratio[idx])),
            "reported_stderr_over_crb_median": float(np.median(rep[idx])),
        }
    return out


# ---------------------------------------------------------------------------- 3. Allan N
def allan_n(instances: int, seed: int, *, rate_hz=100.0, duration_s=1000.0, n_rad_per_sqrt_s=1e-3):
    n = int(round(rate_hz * duration_s))
    t = np.arange(n) / rate_hz
    sigma = n_rad_per_sqrt_s * math.sqrt(rate_hz)
    est, implied, unresolved = [], [], 0
    for rng in _rngs(seed, instances):
        rec = Recording(t_s=t, gyro_rad_s=rng.normal(0.0, sigma, (n, 3)))
        res = allan_analysis(rec)
        for ax in res.axes.values():
            nhat = ax.all_terms()["arw_rad_per_sqrt_s"]
            if nhat is None:
                unresolved += 1
                continue
            lo, hi = ax.interval("arw_rad_per_sqrt_s")
            sigma_c = (hi**2 - lo**2) / (2 * Z95)  # on c = N²
            est.append(nhat)
            implied.append(sigma_c / (2 * nhat))  # delta method: σ_N = σ_c/(2N)
    est = np.asarray(est)
    std = float(np.std(est, ddof=1))
    crb = n_rad_per_sqrt_s / math.sqrt(2 * n)
    return {
        "estimator": "gyrocore.noise.allan.allan_analysis (joint IEEE 952 fit)",
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "n_rad_per_sqrt_s": n_rad_per_sqrt_s,
        "n_estimates": int(est.size),
        "n_unresolved": unresolved,
        "mean_over_true": float(np.mean(est)) / n_rad_per_sqrt_s,
        "mc_std_rad_per_sqrt_s": std,
        "ci_implied_std_median": float(np.median(implied)),
        "ratio_to_chi2_interval": std / float(np.median(implied)),
        "crb_rad_per_sqrt_s": crb,
        "ratio_to_crb": std / crb,
        "ratio_mc_rel_se": _ratio_ci(est.size),
    }


# ---------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instances", type=int, default=200, help="Monte Carlo instances per estimator")
    ap.add_argument("--allan-instances", type=int, default=None, help="instances for Allan N (default: --instances/2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="bias,table,allan", help="comma list of bias,table,allan")
    ap.add_argument("--json", action="store_true", help="print only JSON")
    a = ap.parse_args(argv)
    only = {s.strip() for s in a.only.split(",")}
    res: dict = {"instances": a.instances, "seed": a.seed}
    t0 = time.perf_counter()
    if "bias" in only:
        res["static_bias"] = static_bias(a.instances, a.seed)
        res["static_bias_median"] = static_bias(a.instances, a.seed, rule="median")
    if "table" in only:
        res["rate_table"] = rate_table(a.instances, a.seed + 1)
    if "allan" in only:
        res["allan_n"] = allan_n(a.allan_instances or max(2, a.instances // 2), a.seed + 2)
    res["wall_s"] = time.perf_counter() - t0
    if a.json:
        print(json.dumps(res, indent=1))
        return 0
    print(
        f"estimator efficiency: MC std / bound, {a.instances} instances, seed {a.seed} "
        f"(MC rel. s.e. of a ratio ≈ 1/sqrt(2(n-1)))"
    )
    for key in ("static_bias", "static_bias_median"):
        if key in res:
            r = res[key]
            print(
                f"  {r['estimator']} ({r['duration_s']:g} s at {r['rate_hz']:g} Hz) vs N/sqrt(T): "
                f"{r['ratio']:.3f} ± {r['ratio'] * r['ratio_mc_rel_se']:.3f} ({r['goal']}); "
                f"reported s.e./CRB {r['reported_stderr_over_crb']:.3f}"
            )
    if "rate_table" in res:
        r = res["rate_table"]
        for g, v in r["groups"].items():
            print(
                f"  rate table {g:<24s} vs LS CRB: median {v['ratio_median']:.3f}, max {v['ratio_max']:.3f} "
                f"(±{r['ratio_mc_rel_se']:.3f} each); reported s.e./CRB {v['reported_stderr_over_crb_median']:.3f}"
            )
    if "allan_n" in res:
        r = res["allan_n"]
        print(
            f"  Allan N ({r['duration_s']:g} s at {r['rate_hz']:g} Hz, {r['n_estimates']} estimates): "
            f"vs its chi-square interval {r['ratio_to_chi2_interval']:.3f} ± {r['ratio_to_chi2_interval'] * r['ratio_mc_rel_se']:.3f}; "
            f"vs CRB 1/sqrt(2n) {r['ratio_to_crb']:.2f}; mean N/true {r['mean_over_true']:.4f}"
        )
    print(f"  wall {res['wall_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
