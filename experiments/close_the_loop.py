"""Experiment ``close_the_loop``: the residual loop on simulated data with undeclared effects.

Two parts:

* :func:`synthetic_recording` — a fast, rich synthetic reference (multi-axis tumbling at
  0.02–1.3 Hz with both signs of rate, a warm-up plus oscillating temperature so that T, dT/dt
  and t are distinguishable, gravity plus linear acceleration) through the shared measurement
  model :func:`gyrocore.effects.registry.deterministic` and the noise generators of :mod:`sim.noise`
  (ARW + flicker bias instability). Used by the tests and the Monte Carlo.
* :func:`run` — the whole cycle on the hover and turntable scenarios of :mod:`sim.scenarios`
  with one undeclared effect, plots of the residual against its regressor before and after,
  and the Monte Carlo identification / false-alarm table (:func:`identification_rates`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.attitude import integrate_gyro
from gyrocore.data.recording import atomic_write_text, Recording
from experiments.report import ExperimentResult, md_table
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.loop.loop import run_loop
from gyrocore.loop.model import CANDIDATES, COMPANION
from gyrocore.loop.plots import plot_found
from gyrocore.loop.validate import loop_parameters, split_halves, validate_model
from gyrocore.readers.convert import load_with_segments
from sim import noise
from sim.presets import load_preset, PRESETS
from sim.scenarios import simulate

__all__ = [
    "DEFAULT_EFFECT_PARAMS",
    "effect_params",
    "synthetic_recording",
    "identification_rates",
    "run",
]

DEG = np.pi / 180.0

#: Magnitude per effect (the "1×" size in :func:`effect_params`), SI, a typical consumer-MEMS
#: value (datasheet order of magnitude, ICM-42688-P / BMI088 class).
DEFAULT_MAGNITUDE: dict[str, float] = {
    "bias": 0.5 * DEG,  # rad/s
    "bias_thermal": 0.01 * DEG,  # rad/s/°C
    "bias_temp_rate": 0.1 * DEG,  # rad/s per °C/s
    "bias_ramp": 2e-4 * DEG,  # rad/s² (0.72 °/s/h)
    "scale": 0.005,  # 0.5 %
    "scale_thermal": 1e-4,  # 0.01 %/°C
    "scale_asymmetry": 0.002,
    "scale_nonlinearity": 0.002,  # s/rad
    "misalignment": 0.002,  # rad
    "g_sensitivity": 0.05 * DEG / 9.80665,  # rad/s per m/s² (0.05 °/s/g)
    "g2_sensitivity": 0.01 * DEG / 9.80665**2,  # rad/s per (m/s²)²
    "time_offset": 0.002,  # s
    "earth_rate": 1.0,  # (fixed by physics; scale factor on nothing)
}


def effect_params(effect: str, scale: float = 1.0) -> dict[str, np.ndarray]:
    """Parameters of one effect at ``scale`` × :data:`DEFAULT_MAGNITUDE` (signs/axes varied)."""
    m = DEFAULT_MAGNITUDE[effect] * scale
    v3 = np.array([1.0, -0.7, 0.5]) * m
    if effect == "bias":
        return {"b_rad_s": v3}
    if effect == "bias_thermal":
        return {
            "poly_rad_s": v3[:, None],
            "t0_c": np.array(25.0),
            "temp_min_c": np.array(-40.0),
            "temp_max_c": np.array(85.0),
        }
    if effect == "bias_temp_rate":
        return {"k_rad_s_per_c_per_s": v3}
    if effect == "bias_ramp":
        return {"ramp_rad_s2": v3}
    if effect == "scale":
        return {"s": v3}
    if effect == "scale_thermal":
        return {
            "poly_per_c": v3[:, None],
            "t0_c": np.array(25.0),
            "temp_min_c": np.array(-40.0),
            "temp_max_c": np.array(85.0),
        }
    if effect == "scale_asymmetry":
        return {"a": v3}
    if effect == "scale_nonlinearity":
        return {"s2_s_per_rad": v3}
    if effect == "misalignment":
        return {"m_rad": np.array([1.0, -0.5, 0.8, 0.3, -0.9, 0.6]) * m}
    if effect == "g_sensitivity":
        return {"h_rad_s_per_m_s2": np.array([[1.0, 0.2, -0.3], [0.1, -0.8, 0.2], [-0.2, 0.3, 0.6]]) * m}
    if effect == "g2_sensitivity":
        g = np.zeros((3, 6))
        g[0, 0], g[1, 1], g[2, 2], g[0, 4], g[2, 3] = 1.0, -0.8, 0.6, 0.5, -0.4
        return {"g_rad_s_per_m2_s4": g * m}
    if effect == "time_offset":
        return {"tau_s": np.array(m)}
    if effect == "earth_rate":
        return {"latitude_rad": np.array(48.0 * DEG), "heading_rad": np.array(30.0 * DEG)}
    raise KeyError(effect)


DEFAULT_EFFECT_PARAMS = {e: effect_params(e) for e in DEFAULT_MAGNITUDE}


def synthetic_recording(
    params: Mapping[str, Mapping[str, np.ndarray]],
    *,
    seed: int,
    duration_s: float = 60.0,
    rate_hz: float = 200.0,
    arw_rad_per_sqrt_s: float = 0.005 * DEG,
    bias_instability_rad_s: float = 3.0 / 3600 * DEG,
    with_quat: bool = False,
    temp_profile: str = "warmup",
    rrw_rad_s_per_sqrt_s: float = 0.0,
    gm_sigma_rad_s: float = 0.0,
    gm_tau_s: float = 100.0,
) -> Recording:
    """A rich synthetic recording through the shared measurement model.

    Parameters
    ----------
    params : mapping
        Deterministic effects of the sensor (``{effect: {param: array}}``, SI).
    seed : int
        Seed of the trajectory phases and the noise (np.random.default_rng).
    duration_s, rate_hz : float
        Length, s, and sample rate, Hz.
    arw_rad_per_sqrt_s : float
        White rate noise density N (rad/√s); per-sample σ = N·√rate_hz.
    bias_instability_rad_s : float
        Flicker bias instability B (rad/s).
    with_quat : bool
        Also write the true attitude in ``ref_q*``.
    rrw_rad_s_per_sqrt_s : float
        Rate random walk K (rad/s/√s), 0 = none.
    gm_sigma_rad_s, gm_tau_s : float
        First-order Gauss–Markov bias σ (rad/s, 0 = none) and correlation time (s).
    temp_profile : {"warmup", "linear"}
        ``"warmup"``: 25 °C + 12 °C·(1 − e^(−3t/T)) + 2 °C·sin(8πt/T), so T, dT/dt and t are
        distinguishable; ``"linear"``: 25 → 37 °C linearly in time (then ``bias_thermal`` of
        order 1 and ``bias_ramp`` are the same regressor: the ambiguous case).

    Returns
    -------
    Recording
        gyro (measured), accel (true specific force + 0.02 m/s² noise), temp_c, the true
        world-relative rate in ``ref_*_rad_s`` (and attitude when asked).
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * rate_hz)) + 1
    t = np.arange(n) / rate_hz
    # rate: per axis, three sinusoids (0.02–1.3 Hz) with random phases, amplitude ≈ 1.2 rad/s
    freqs = np.array([[0.05, 0.31, 1.1], [0.07, 0.43, 0.9], [0.03, 0.23, 1.3]])
    amps = np.array([0.8, 0.5, 0.3])
    phases = rng.uniform(0, 2 * np.pi, (3, 3))

    def omega_at(tt: np.ndarray) -> np.ndarray:
        w = np.zeros((tt.shape[0], 3))
        for i in range(3):
            for k in range(3):
                w[:, i] += amps[k] * np.sin(2 * np.pi * freqs[i, k] * tt + phases[i, k])
        return w

    omega = omega_at(t)
    q = integrate_gyro(t, omega)
    up_S = np.stack(
        [
            2 * (q[:, 1] * q[:, 3] - q[:, 0] * q[:, 2]),
            2 * (q[:, 2] * q[:, 3] + q[:, 0] * q[:, 1]),
            1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2),
        ],
        axis=1,
    )
    f = 9.80665 * up_S + 1.0 * np.sin(
        2 * np.pi * np.array([0.37, 0.53, 0.29]) * t[:, None] + rng.uniform(0, 2 * np.pi, 3)
    )
    if temp_profile == "warmup":
        temp = 25.0 + 12.0 * (1 - np.exp(-t / (duration_s / 3))) + 2.0 * np.sin(2 * np.pi * t / (duration_s / 4))
    elif temp_profile == "linear":
        temp = 25.0 + 12.0 * t / duration_s
    else:
        raise ValueError(f"unknown temp_profile {temp_profile!r}")
    params = dict(params)
    omega_sensed = omega
    if "time_offset" in params:
        # the delay is applied exactly to the analytic trajectory (effects.deterministic
        # delays by linear interpolation, which at 200 Hz also attenuates the 1 Hz motion by
        # ~1e-4 — a scale-like artefact the loop would rightly report)
        omega_sensed = omega_at(t - float(params.pop("time_offset")["tau_s"]))
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=omega_sensed, f_S_m_s2=f, temp_c=temp, q_SW_wxyz=q)
    y = E.deterministic(params, inp)
    y = y + noise.white_rate_noise(rng, n, rate_hz=rate_hz, n_rad_per_sqrt_s=arw_rad_per_sqrt_s)
    if bias_instability_rad_s > 0:
        y = y + noise.flicker_noise(rng, n, rate_hz=rate_hz, b_rad_s=bias_instability_rad_s)
    if rrw_rad_s_per_sqrt_s > 0:
        y = y + noise.rate_random_walk(rng, n, rate_hz=rate_hz, k_rad_s_per_sqrt_s=rrw_rad_s_per_sqrt_s)
    if gm_sigma_rad_s > 0:
        y = y + noise.gauss_markov(rng, n, rate_hz=rate_hz, sigma_rad_s=gm_sigma_rad_s, tau_c_s=gm_tau_s)
    acc = f + rng.standard_normal((n, 3)) * 0.02
    return Recording(
        t_s=t,
        gyro_rad_s=y,
        accel_m_s2=acc,
        temp_c=np.round(temp, 3),
        ref_rate_rad_s=omega,
        ref_quat_wxyz=q if with_quat else None,
        meta={"source": "experiments.close_the_loop.synthetic_recording", "seed": str(seed)},
    )


# ---------------------------------------------------------------------------- Monte Carlo
def _one_trial(effect: str, scale: float, seed: int, duration_s: float, rate_hz: float, alpha: float) -> dict:
    params = {"bias": effect_params("bias")}
    if effect != "none":
        params[effect] = effect_params(effect, scale)
    rec = synthetic_recording(params, seed=seed, duration_s=duration_s, rate_hz=rate_hz)
    r = run_loop(rec, declared=["bias"], alpha=alpha)
    found = r.found_effects
    return {
        "found": found,
        "identified": effect in found,
        "exact": found == ([] if effect == "none" else [effect]),
        # the constant companion of a thermal polynomial (its value at the mean temperature) is
        # part of the same physical effect, not a false alarm
        "false_alarm": any(f not in (effect, COMPANION.get(effect)) for f in found),
        "att_before_deg": r.attitude_error_before_deg,
        "att_after_deg": r.attitude_error_after_deg,
    }


def identification_rates(
    *,
    seeds: Sequence[int] = range(20),
    scales: Sequence[float] = (1.0,),
    effects: Sequence[str] | None = None,
    duration_s: float = 40.0,
    rate_hz: float = 200.0,
    alpha: float = 0.01,
    progress: bool = False,
) -> list[dict]:
    """Identification and false-alarm rates of the loop over seeds, per effect and magnitude.

    For each effect (and ``"none"``, the null case), each magnitude ``scale`` × the 1× size of
    :data:`DEFAULT_MAGNITUDE` and each seed, a :func:`synthetic_recording` with that one
    undeclared effect (and a declared bias) goes through :func:`gyrocore.loop.loop.run_loop`.

    Returns
    -------
    list of dict
        One row per (effect, scale): ``identification_rate`` (effect among the found),
        ``exact_rate`` (found == [effect]), ``false_alarm_rate`` (any other effect found),
        ``n``, ``magnitude_si``, and the median attitude error before/after, deg. The
        constant companion of a thermal effect (``scale`` for ``scale_thermal``) is not
        counted as a false alarm.
    """
    effects = list(effects) if effects is not None else ["none"] + [c for c in CANDIDATES if c != "bias"]
    rows = []
    for eff in effects:
        for sc in scales if eff not in ("none", "earth_rate") else (1.0,):
            trials = []
            for s in seeds:
                trials.append(_one_trial(eff, sc, int(s), duration_s, rate_hz, alpha))
                if progress:
                    print(f"{eff} x{sc} seed {s}: {trials[-1]['found']}", flush=True)
            n = len(trials)
            rows.append(
                {
                    "effect": eff,
                    "scale": sc,
                    "magnitude_si": None if eff == "none" else DEFAULT_MAGNITUDE[eff] * sc,
                    "n": n,
                    "identification_rate": float(np.mean([t["identified"] for t in trials])) if eff != "none" else None,
                    "exact_rate": float(np.mean([t["exact"] for t in trials])),
                    "false_alarm_rate": float(np.mean([t["false_alarm"] for t in trials])),
                    "att_before_deg_median": float(np.median([t["att_before_deg"] for t in trials])),
                    "att_after_deg_median": float(np.median([t["att_after_deg"] for t in trials])),
                }
            )
    return rows


def rates_markdown(rows: Sequence[dict]) -> str:
    """Markdown table of :func:`identification_rates` rows plus the smallest magnitude found."""
    out = [
        "| effect | magnitude (×1 size) | magnitude, SI | n | identified | exactly it | false alarm | attitude err. before → after (median, deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ident = "—" if r["identification_rate"] is None else f"{100 * r['identification_rate']:.0f} %"
        mag = "—" if r["magnitude_si"] is None else f"{r['magnitude_si']:.3g}"
        out.append(
            f"| {r['effect']} | {r['scale']:g} | {mag} | {r['n']} | {ident} | {100 * r['exact_rate']:.0f} % | "
            f"{100 * r['false_alarm_rate']:.0f} % | {r['att_before_deg_median']:.3g} → {r['att_after_deg_median']:.3g} |"
        )
    # smallest magnitude with identification ≥ 90 %
    out += ["", "| effect | smallest magnitude found in ≥ 90 % of seeds (SI) | × 1 size |", "|---|---|---|"]
    for eff in dict.fromkeys(r["effect"] for r in rows):
        if eff == "none":
            continue
        ok = [r for r in rows if r["effect"] == eff and (r["identification_rate"] or 0) >= 0.9]
        if ok:
            best = min(ok, key=lambda r: r["scale"])
            out.append(f"| {eff} | {best['magnitude_si']:.3g} | {best['scale']:g} |")
        else:
            out.append(f"| {eff} | not found at the tested sizes | — |")
    return "\n".join(out)


# ---------------------------------------------------------------------------- open search Monte Carlo
#: Coloured noise of the open-search Monte Carlo on the synthetic generator (white + flicker +
#: RRW + Gauss–Markov), SI: ARW 0.005 °/s/√Hz, B 3 °/h, K 10 °/h/√h, GM 0.002 °/s with τ 20 s.
OPEN_NOISE = {
    "arw_rad_per_sqrt_s": 0.005 * DEG,
    "bias_instability_rad_s": 3.0 / 3600 * DEG,
    "rrw_rad_s_per_sqrt_s": 10.0 / 3600 / 60 * DEG,
    "gm_sigma_rad_s": 0.002 * DEG,
    "gm_tau_s": 20.0,
}

#: Out-of-catalogue terms injected per kind at size 1 (SI): a product regressor ω_y·ω_z on x
#: (rad/s per (rad/s)²), a 37.3 Hz line on y (amplitude rad/s), a bias step at 0.43·T (rad/s,
#: direction (1, −0.5, 0.75)).
OPEN_UNIT = {"regressor": 1e-3, "periodic": 1e-3, "step": 1e-3}


def inject_open(rec: Recording, kind: str, size: float, *, f_hz: float = 37.3, t_frac: float = 0.43) -> Recording:
    """``rec`` with one out-of-catalogue term of ``size`` added to its gyro (see :data:`OPEN_UNIT`)."""
    from dataclasses import replace

    g = rec.gyro_rad_s.copy()
    if kind == "regressor":
        w = rec.ref_rate_rad_s
        g[:, 0] += size * w[:, 1] * w[:, 2]
    elif kind == "periodic":
        g[:, 1] += size * np.cos(2 * np.pi * f_hz * rec.t_s + 0.4)
    elif kind == "step":
        t0 = rec.t_s[0] + t_frac * (rec.t_s[-1] - rec.t_s[0])
        g += np.where(rec.t_s[:, None] >= t0, size * np.array([1.0, -0.5, 0.75])[None, :], 0.0)
    elif kind != "none":
        raise ValueError(kind)
    return replace(rec, gyro_rad_s=g)


def _open_trial(kind: str, size: float, seed: int, duration_s: float, rate_hz: float, alpha: float) -> dict:
    rec = synthetic_recording(
        {"bias": effect_params("bias")}, seed=seed, duration_s=duration_s, rate_hz=rate_hz, **OPEN_NOISE
    )
    rec = inject_open(rec, kind, size * OPEN_UNIT.get(kind, 0.0))
    r = run_loop(rec, declared=["bias"], alpha=alpha, seed=seed)
    kinds = [u.kind for u in r.unexplained]
    out = {
        "kinds": kinds,
        "found": r.found_effects,
        "described": kind in kinds,
        # an open-search claim of another kind is a false alarm of the open search; catalogue
        # claims (the catalogue's own error rate, docs/loop.md §4) are counted apart
        "false_alarm": any(k != kind for k in kinds),
        "catalogue_claim": bool(r.found_effects),
    }
    for u in r.unexplained:
        if u.kind == kind:
            out["rms_before"], out["rms_after"] = u.residual_rms_before_rad_s, u.residual_rms_after_rad_s
            break
    return out


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial confidence interval of k/n (scipy.stats.binomtest)."""
    from scipy.stats import binomtest

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=level, method="exact")
    return float(ci.low), float(ci.high)


def open_search_rates(
    *,
    kinds: Sequence[str] = ("none", "regressor", "periodic", "step"),
    sizes: Sequence[float] = (0.5, 1.0, 2.0, 4.0),
    seeds: Sequence[int] = range(20),
    duration_s: float = 40.0,
    rate_hz: float = 200.0,
    alpha: float = 0.01,
    progress: bool = False,
) -> list[dict]:
    """Description (detection) and false-alarm rates of the open search per kind and size, on
    the synthetic tumbling generator with coloured noise (:data:`OPEN_NOISE`).

    Returns one row per (kind, size): n, described, false alarms (any other claim), both with
    Clopper–Pearson 95 % intervals, and the median residual RMS before → after the term.
    """
    rows = []
    for kind in kinds:
        for sz in (1.0,) if kind == "none" else sizes:
            trials = []
            for s in seeds:
                trials.append(_open_trial(kind, sz, int(s), duration_s, rate_hz, alpha))
                if progress:
                    print(f"{kind} x{sz} seed {s}: {trials[-1]['found']} {trials[-1]['kinds']}", flush=True)
            n = len(trials)
            kd = sum(t["described"] for t in trials)
            kf = sum(t["false_alarm"] for t in trials)
            rb = [t["rms_before"] for t in trials if "rms_before" in t]
            ra = [t["rms_after"] for t in trials if "rms_after" in t]
            kc = sum(t["catalogue_claim"] for t in trials)
            rows.append(
                {
                    "kind": kind,
                    "size": sz,
                    "size_si": sz * OPEN_UNIT.get(kind, 0.0),
                    "n": n,
                    "catalogue_claims": kc,
                    "catalogue_claims_ci95": clopper_pearson(kc, n),
                    "described": kd / n if kind != "none" else None,
                    "described_ci95": clopper_pearson(kd, n) if kind != "none" else None,
                    "false_alarms": kf,
                    "false_alarm_rate": kf / n,
                    "false_alarm_ci95": clopper_pearson(kf, n),
                    "rms_before_median_rad_s": float(np.median(rb)) if rb else None,
                    "rms_after_median_rad_s": float(np.median(ra)) if ra else None,
                }
            )
    return rows


def simulator_null_false_alarms(
    *,
    presets: Sequence[str] | None = None,
    scenarios: Sequence[tuple[str, float]] = (("turntable", 60.0), ("static", 120.0)),
    seeds: Sequence[int] = range(10),
    alpha: float = 0.01,
    progress: bool = False,
) -> dict:
    """False alarms of the open search on simulator null recordings: every preset, its whole
    deterministic model declared, its noise with RRW and Gauss–Markov switched on (white +
    flicker + RRW + GM). A false alarm is any ``unexplained`` entry (the catalogue's own finds —
    e.g. ``time_offset``, the on-chip filter's group delay — are listed, not counted).
    """
    presets = list(presets) if presets is not None else sorted(PRESETS)
    runs = []
    for p in presets:
        spec = load_preset(p)
        for sc, dur in scenarios:
            for s in seeds:
                inst = spec.draw_instance(int(s), include=("rrw", "correlated"))
                ov = {e: {k: np.asarray(v).tolist() for k, v in inst[e].items()} for e in ("rrw", "correlated")}
                sim = simulate(sc, sensor=p, duration_s=dur, seed=int(s), overrides=ov)
                declared = [e for e in sim.params_true if e in CANDIDATES]
                r = run_loop(sim.recording, declared=declared, alpha=alpha, seed=int(s))
                runs.append(
                    {
                        "preset": p,
                        "scenario": sc,
                        "seed": int(s),
                        "found": r.found_effects,
                        "unexplained": [u.effect for u in r.unexplained],
                        "false_alarm": bool(r.unexplained),
                    }
                )
                if progress:
                    print(p, sc, s, r.found_effects, runs[-1]["unexplained"], flush=True)
    k = sum(r["false_alarm"] for r in runs)
    return {
        "n": len(runs),
        "false_alarms": k,
        "rate": k / max(len(runs), 1),
        "ci95": clopper_pearson(k, len(runs)),
        "alpha": alpha,
        "runs": runs,
    }


def open_rates_markdown(rows: Sequence[dict]) -> str:
    """Markdown table of :func:`open_search_rates` rows."""
    D = 180.0 / np.pi
    out = [
        "| kind | size (× unit) | size | n | described (95 % CI) | open-search false alarms (95 % CI) | catalogue claims | residual RMS before → after, median (°/s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    unit = {"regressor": "rad/s per (rad/s)²", "periodic": "rad/s", "step": "rad/s", "none": ""}
    for r in rows:
        d = (
            "—"
            if r["described"] is None
            else (
                f"{100 * r['described']:.0f} % ({100 * r['described_ci95'][0]:.0f}–"
                f"{100 * r['described_ci95'][1]:.0f} %)"
            )
        )
        fa = f"{r['false_alarms']}/{r['n']} ({100 * r['false_alarm_ci95'][0]:.1f}–{100 * r['false_alarm_ci95'][1]:.1f} %)"
        rms = (
            "—"
            if r["rms_before_median_rad_s"] is None
            else f"{r['rms_before_median_rad_s'] * D:.3g} → {r['rms_after_median_rad_s'] * D:.3g}"
        )
        size = "—" if r["kind"] == "none" else f"{r['size_si']:.3g} {unit[r['kind']]}"
        out.append(
            f"| {r['kind']} | {r['size']:g} | {size} | {r['n']} | {d} | {fa} | {r['catalogue_claims']}/{r['n']} | {rms} |"
        )
    return "\n".join(out)


#: The measured sets of docs/measured.md: (name, path(s) under the data folder, run_loop options).
MEASURED: tuple[tuple[str, tuple[str, ...], dict], ...] = (
    ("BROAD 02 slow rotation", ("broad/02_undisturbed_slow_rotation_B.hdf5",), {}),
    ("BROAD 05 slow rotation, breaks", ("broad/05_undisturbed_slow_rotation_with_breaks_B.hdf5",), {}),
    ("BROAD 07 fast rotation", ("broad/07_undisturbed_fast_rotation_B.hdf5",), {}),
    ("BROAD 09 fast rotation, breaks", ("broad/09_undisturbed_fast_rotation_with_breaks_B.hdf5",), {}),
    ("sunsided set-2 static 10 min", ("sunsided_mpu6050/set-2/unmoved-with-x-pointing-forward-10min",), {}),
    (
        "sunsided set-1 session (static + 2 turns about x, y, z)",
        (
            "sunsided_mpu6050/set-1/unmoved-x-pointing-forward",
            "sunsided_mpu6050/set-1/rotate-360ccw-around-x-pointing-forward",
            "sunsided_mpu6050/set-1/rotate-360ccw-around-y-pointing-left",
            "sunsided_mpu6050/set-1/rotate-360ccw-around-z-pointing-up",
        ),
        {"angle_mode": "axis"},
    ),
    (
        "sunsided set-2 session (static + 2 turns about x, y, z)",
        (
            "sunsided_mpu6050/set-2/unmoved-with-x-pointing-forward",
            "sunsided_mpu6050/set-2/rotate-ccw-around-x-pointing-forward",
            "sunsided_mpu6050/set-2/rotate-ccw-around-y-pointing-left",
            "sunsided_mpu6050/set-2/rotate-ccw-around-z-pointing-up",
        ),
        {"angle_mode": "axis"},
    ),
    ("imucal Ferraris session (6 poses + 3 turns)", ("imucal_ferraris/example_ferraris_session.csv",), {}),
    ("tomisuarez2 static 449 s", ("tomisuarez2_mpu6050/imu_static_test.csv",), {}),
    ("tomisuarez2 +90° about X (hand)", ("tomisuarez2_mpu6050/imu_90_x_rot.csv",), {"angle_mode": "axis"}),
    ("PX4 sample.ulg (stationary part)", ("pyulog_samples/sample.ulg",), {}),
)


def measured_runs(data_dir, *, names: Sequence[str] | None = None) -> list[dict]:
    """Run the loop (declared: bias) on the measured sets of :data:`MEASURED`.

    Returns one row per set: name, reference, found (with key evidence), residual RMS and
    attitude error before/after, notes; or the one-line error when the data cannot do it.
    """
    import warnings

    rows = []
    for name, paths, opts in MEASURED:
        if names is not None and name not in names:
            continue
        full = [Path(data_dir) / p for p in paths]
        if not all(p.exists() for p in full):
            continue
        try:
            if len(full) == 1:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RepairWarning)
                    c = load_with_segments(full[0])
                rec, segs = c.recording, list(c.segments)
            else:
                rec, segs = concat_session(full)
            r = run_loop(rec, declared=["bias"], segments=segs, **opts)
        except GyroInputError as exc:
            rows.append({"name": name, "error": str(exc)})
            continue
        rows.append(
            {
                "name": name,
                "reference": r.reference,
                "n_windows": r.n_windows,
                "found": [
                    {
                        "effect": s.effect,
                        "log10_p": s.evidence.log10_p,
                        "ambiguous_with": list(s.evidence.ambiguous_with),
                        "params": s.evidence.params,
                        "std_errors": s.evidence.std_errors,
                    }
                    for s in r.found
                ],
                "residual_rms_before_dps": r.residual_rms_before_rad_s * 180 / np.pi,
                "residual_rms_after_dps": r.residual_rms_after_rad_s * 180 / np.pi,
                "attitude_error_before_deg": r.attitude_error_before_deg,
                "attitude_error_after_deg": r.attitude_error_after_deg,
                "ljung_box_p": r.remaining.ljung_box_p,
                "notes": list(r.notes),
                "final_params": r.params,
            }
        )
    return rows


#: BROAD trials of the out-of-sample table (fit on one, score on another: 12 ordered pairs).
BROAD_TRIALS = (
    ("02", "broad/02_undisturbed_slow_rotation_B.hdf5"),
    ("05", "broad/05_undisturbed_slow_rotation_with_breaks_B.hdf5"),
    ("07", "broad/07_undisturbed_fast_rotation_B.hdf5"),
    ("09", "broad/09_undisturbed_fast_rotation_with_breaks_B.hdf5"),
)
#: Long static logs of the out-of-sample table (fit on the first half, score on the second).
STATIC_LOGS = (
    ("sunsided set-2 static 10 min", "sunsided_mpu6050/set-2/unmoved-with-x-pointing-forward-10min"),
    ("tomisuarez2 static 449 s", "tomisuarez2_mpu6050/imu_static_test.csv"),
    ("PX4 sample.ulg (stationary part)", "pyulog_samples/sample.ulg"),
)


def _load_quiet(path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        return load_with_segments(path)


def _loop_summary(r) -> dict:
    return {
        "reference": r.reference,
        "n_windows": r.n_windows,
        "found": [{"effect": s.effect, "log10_p": s.evidence.log10_p} for s in r.found],
        "unexplained": [u.to_json() for u in r.unexplained],
        "open_search": r.open_search,
        "residual_rms_before_rad_s": r.residual_rms_before_rad_s,
        "residual_rms_after_rad_s": r.residual_rms_after_rad_s,
        "attitude_error_before_deg": r.attitude_error_before_deg,
        "attitude_error_after_deg": r.attitude_error_after_deg,
        "ljung_box_p": r.remaining.ljung_box_p,
        "params": r.params,
    }


def out_of_sample_runs(data_dir, *, declared: Sequence[str] = ("bias",), progress: bool = False) -> dict:
    """The out-of-sample table of docs/measured.md, one setting for every set (the loop's
    defaults, declared ``bias``, open search on): BROAD fit-on-A / score-on-B for all 12 ordered
    pairs, and the long static logs first half → second half
    (:func:`gyrocore.loop.validate.validate_model`: the turn-on bias re-estimated on the scored part,
    everything else transferred; "before" = the declared model fitted on the same data).

    Same numbers as ``gyroharness loop A --effects bias --validate B --json`` and
    ``gyroharness loop LOG --effects bias --validate-split --json``.
    """
    data = Path(data_dir)
    out: dict = {"broad": {"fits": {}, "pairs": []}, "static": []}
    fits = {}
    for tag, rel in BROAD_TRIALS:
        p = data / rel
        if not p.exists():
            continue
        rec = _load_quiet(p).recording
        r = run_loop(rec, declared=list(declared))
        base = run_loop(rec, declared=list(declared), candidates=[], open_search=False)
        fits[tag] = (rec, loop_parameters(r, rec)[0], loop_parameters(base, rec)[0])
        out["broad"]["fits"][tag] = _loop_summary(r)
        if progress:
            print("fit", tag, [s.effect for s in r.found], [u.effect for u in r.unexplained], flush=True)
    for a, (rec_a, p_after, p_before) in fits.items():
        for b, (rec_b, _, _) in fits.items():
            if a == b:
                continue
            v = validate_model(rec_b, params_after=p_after, params_before=p_before)
            out["broad"]["pairs"].append({"fit": a, "score": b, **v})
            if progress:
                print("pair", a, b, v, flush=True)
    for name, rel in STATIC_LOGS:
        p = data / rel
        if not p.exists():
            continue
        rec = _load_quiet(p).recording
        first, second = split_halves(rec)
        r = run_loop(first, declared=list(declared))
        base = run_loop(first, declared=list(declared), candidates=[], open_search=False)
        v = validate_model(
            second, params_after=loop_parameters(r, first)[0], params_before=loop_parameters(base, first)[0]
        )
        full = run_loop(rec, declared=list(declared))
        out["static"].append(
            {
                "name": name,
                "path": rel,
                "first_half": _loop_summary(r),
                "validation": v,
                "whole": _loop_summary(full),
                "split_t_s": float(second.t_s[0]),
            }
        )
        if progress:
            print("static", name, v, flush=True)
    return out


def out_of_sample_markdown(res: dict) -> str:
    """The tables of docs/measured.md from :func:`out_of_sample_runs` output."""
    D = 180.0 / np.pi
    out = [
        "| fit on → score on | residual RMS, declared model → final model (°/s) | attitude error, declared → final (°) |",
        "|---|---|---|",
    ]
    for p in res["broad"]["pairs"]:
        out.append(
            f"| BROAD {p['fit']} → {p['score']} | {p['residual_rms_before_rad_s'] * D:.3g} → "
            f"{p['residual_rms_after_rad_s'] * D:.3g} | {p['attitude_error_before_deg']:.3g} → "
            f"{p['attitude_error_after_deg']:.3g} |"
        )
    for st in res["static"]:
        v = st["validation"]
        out.append(
            f"| {st['name']}: first half → second half (t ≥ {st['split_t_s']:.4g} s) | "
            f"{v['residual_rms_before_rad_s'] * D:.3g} → {v['residual_rms_after_rad_s'] * D:.3g} | "
            f"{v['attitude_error_before_deg']:.3g} → {v['attitude_error_after_deg']:.3g} |"
        )
    out += [
        "",
        "| fitted on | found (catalogue) | unexplained (open search) | Ljung–Box p after |",
        "|---|---|---|---|",
    ]

    def desc(f):
        return ", ".join(x["effect"] for x in f["found"]) or "nothing"

    def udesc(f):
        return ", ".join(u["effect"] for u in f["unexplained"]) or "nothing"

    for t, f in res["broad"]["fits"].items():
        out.append(f"| BROAD {t} (whole trial) | {desc(f)} | {udesc(f)} | {f['ljung_box_p']:.2g} |")
    for st in res["static"]:
        out.append(
            f"| {st['name']}, first half | {desc(st['first_half'])} | {udesc(st['first_half'])} | "
            f"{st['first_half']['ljung_box_p']:.2g} |"
        )
        out.append(
            f"| {st['name']}, whole | {desc(st['whole'])} | {udesc(st['whole'])} | {st['whole']['ljung_box_p']:.2g} |"
        )
    out += [
        "",
        "| set (whole) | strongest library term: log10 p / threshold | strongest line: Hz, log10 p / threshold | best step: t, p / threshold |",
        "|---|---|---|---|",
    ]

    def os_row(name, f):
        o = f.get("open_search") or {}
        g = o.get("regressor") or {}
        reg = (
            f"{g['term']} on {g['axis']}: {g['log10_p']:.2g} / {np.log10(g['threshold']):.2g}"
            if "term" in g
            else g.get("skipped", "—")
        )
        ls = o.get("periodic") or []
        if ls:
            b = min(ls, key=lambda d: d["log10_p"])
            line = f"{b['frequency_hz']:.4g} Hz on {b['axis']}: {b['log10_p']:.2g} / {np.log10(b['threshold']):.2g}"
        else:
            line = "—"
        sp = o.get("step")
        step = f"{sp['t_s']:.4g} s: {sp['bootstrap_p']:.2g} / {sp['threshold']:.2g}" if sp else "—"
        return f"| {name} | {reg} | {line} | {step} |"

    for t, f in res["broad"]["fits"].items():
        out.append(os_row(f"BROAD {t}", f))
    for st in res["static"]:
        out.append(os_row(st["name"], st["whole"]))
    return "\n".join(out)


# ---------------------------------------------------------------------------- the experiment
#: Undeclared effects injected per scenario (SI; the simulator adds them, the calibration is
#: not told) — and, for hover, an effect of the preset left out of the declared model.
CASES: tuple[dict, ...] = (
    {
        "scenario": "turntable",
        "overrides": {"scale_asymmetry": {"a": [0.004, -0.003, 0.002]}},
        "leave_out": (),
        "undeclared": ("scale_asymmetry",),
    },
    {
        "scenario": "hover",
        "overrides": {"scale_nonlinearity": {"s2_s_per_rad": [0.02, 0.02, 0.01]}},
        "leave_out": ("g_sensitivity",),
        "undeclared": ("g_sensitivity", "scale_nonlinearity"),
    },
)


def run(
    *,
    out_dir,
    quick: bool = False,
    seed: int = 0,
    seeds: int | None = None,
    workers: int | None = None,
    sensor: str = "icm42688p",
    mc_seeds: int = 0,
    **_ignored,
):
    """The whole cycle on the turntable and hover scenarios with undeclared effects.

    For each case: simulate with :func:`sim.scenarios.simulate` (the undeclared effect in
    ``overrides``; the preset's other deterministic effects declared, minus ``leave_out``),
    run :func:`gyrocore.loop.loop.run_loop`, plot the residual against each found effect's
    regressor before and after (:func:`gyrocore.loop.plots.plot_found`), and tabulate the steps.
    ``mc_seeds`` > 0 adds the synthetic identification / false-alarm table
    (:func:`identification_rates`).

    Returns
    -------
    experiments.report.ExperimentResult
    """
    import time as _time

    t_start = _time.time()
    out = Path(out_dir)
    fig_dir = out / "figures"
    D = 180.0 / np.pi
    md = [
        "The residual loop starts from the declared effects, traces what the residual still holds to a "
        "catalogue effect through its physical regressors (HAC Wald tests, Holm-controlled family-wise "
        "error α = 0.01, out-of-sample guard), adds it, refits, and repeats. Here the simulator puts an "
        "effect into the sensor that the calibration is not told about.",
        "",
    ]
    figures: list[str] = []
    summary: dict = {"cases": []}
    for case in CASES:
        dur = {"turntable": 45.0 if quick else 120.0, "hover": 15.0 if quick else 30.0}[case["scenario"]]
        sim = simulate(case["scenario"], sensor=sensor, duration_s=dur, seed=seed, overrides=case["overrides"])
        declared = [
            e for e in sim.params_true if e in CANDIDATES and e not in case["overrides"] and e not in case["leave_out"]
        ]
        res = run_loop(sim.recording, declared=declared)
        paths = plot_found(res, fig_dir, prefix=f"close_the_loop_{case['scenario']}")
        figures += [str(p.relative_to(out)) for p in paths]
        rows = []
        for k, s in enumerate(res.found, 1):
            ev = s.evidence
            rows.append(
                [
                    k,
                    s.effect,
                    f"{ev.statistic:.3g} ({ev.df1}, {ev.df2})",
                    f"{ev.log10_p:.3g}",
                    f"{np.log10(ev.threshold):.3g}",
                    s.residual_rms_before_rad_s * D,
                    s.residual_rms_after_rad_s * D,
                    s.attitude_error_before_deg,
                    s.attitude_error_after_deg,
                    ", ".join(ev.ambiguous_with) or "—",
                ]
            )
        md += [
            f"### {case['scenario']} ({dur:g} s, sensor {sensor}, seed {seed})",
            "",
            f"Undeclared: {', '.join(case['undeclared'])} (injected: {', '.join(case['overrides'])}; "
            f"left out of the model: {', '.join(case['leave_out']) or 'nothing'}). "
            f"Declared: {', '.join(declared)}. Reference: {res.reference}, {res.n_windows} windows.",
            "",
        ]
        if rows:
            md.append(
                md_table(
                    [
                        "step",
                        "effect",
                        "F (df)",
                        "log10 p",
                        "log10 threshold",
                        "RMS before, °/s",
                        "RMS after, °/s",
                        "attitude before, °",
                        "attitude after, °",
                        "ambiguous with",
                    ],
                    rows,
                )
            )
        else:
            md.append("Nothing significant found.")
        missed = [u for u in case["undeclared"] if u not in res.found_effects]
        extra = [f for f in res.found_effects if f not in case["undeclared"]]
        md += [
            "",
            f"Found {', '.join(res.found_effects) or 'nothing'}; missed: {', '.join(missed) or 'none'}; "
            f"not injected but found: {', '.join(extra) or 'none'}"
            + (
                " (time_offset here is the on-chip low-pass filter's group delay — 1/√2 sample for the "
                "preset's digital Butterworth at a quarter of the sample rate — which the linear model does not "
                "carry: a real effect of the simulated sensor)"
                if "time_offset" in extra
                else ""
            )
            + ".",
            "",
            f"Remaining residual: Ljung–Box p = {res.remaining.ljung_box_p:.3g}; Allan slope "
            + ", ".join(f"{x:.2f}" for x in res.remaining.allan_slope)
            + " (−½ white).",
            "",
        ]
        for p in paths:
            md.append(f"![{p.stem}](figures/{p.name})")
        md.append("")
        summary["cases"].append(
            {
                "scenario": case["scenario"],
                "undeclared": list(case["undeclared"]),
                "found": res.found_effects,
                "missed": missed,
                "extra": extra,
                "residual_rms_before_rad_s": res.residual_rms_before_rad_s,
                "residual_rms_after_rad_s": res.residual_rms_after_rad_s,
                "attitude_error_before_deg": res.attitude_error_before_deg,
                "attitude_error_after_deg": res.attitude_error_after_deg,
            }
        )
    if mc_seeds:
        rows = identification_rates(seeds=range(mc_seeds), scales=(0.3, 1.0))
        md += [
            "### Identification and false alarms over seeds (synthetic tumbling reference)",
            "",
            rates_markdown(rows),
            "",
        ]
        summary["rates"] = rows

    text = "\n".join(md)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "close_the_loop.md", "## Closing the loop\n\n" + text + "\n")
    return ExperimentResult(
        name="close_the_loop",
        title="Closing the loop: undeclared effects",
        markdown=text,
        figures=tuple(figures),
        summary=summary,
        wall_s=_time.time() - t_start,
    )


# ---------------------------------------------------------------------------- measured sets
def concat_session(paths: Sequence, *, gap_s: float = 1.0):
    """Concatenate recordings of one session (e.g. sunsided's three ``rotate-*`` runs and a
    static run of the same set) into one recording with their known-rotation segments.

    Time is shifted so that each recording starts ``gap_s`` after the previous one ends (no
    samples in the gap: windows never span it). Columns missing in any recording are dropped.
    This assumes one bias for the whole session (same power-up); say so where it is used.

    Returns
    -------
    (Recording, list of gyrocore.data.segments.Segment)
    """
    import warnings

    recs, segs, t0 = [], [], 0.0
    for p in paths:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RepairWarning)
            c = load_with_segments(p)
        r = c.recording
        shift = t0 - r.t_s[0]
        recs.append((r, shift))
        segs.extend(s.shifted(shift) for s in c.segments)
        t0 = r.t_s[-1] + shift + gap_s
    t = np.concatenate([r.t_s + sh for r, sh in recs])
    gyro = np.concatenate([r.gyro_rad_s for r, _ in recs])
    acc = np.concatenate([r.accel_m_s2 for r, _ in recs]) if all(r.accel_m_s2 is not None for r, _ in recs) else None
    temp = np.concatenate([r.temp_c for r, _ in recs]) if all(r.temp_c is not None for r, _ in recs) else None
    meta = {"source": " + ".join(str(p) for p in paths), "note": f"concatenated session, {gap_s:g} s gaps"}
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=acc, temp_c=temp, meta=meta), segs


if __name__ == "__main__":  # pragma: no cover - the Monte Carlo script
    import argparse
    import json as _json

    ap = argparse.ArgumentParser(description="Loop identification / false-alarm Monte Carlo")
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--seed-start", type=int, default=0, help="first seed (seeds seed-start .. seed-start+seeds-1)")
    ap.add_argument("--scales", default="0.03,0.1,0.3,1")
    ap.add_argument("--effects", default=None)
    ap.add_argument("--out", default=None, help="write rows as JSON here")
    ap.add_argument("--measured", default=None, metavar="DATA_DIR", help="run the measured sets instead")
    ap.add_argument("--open", action="store_true", help="open-search rates (kinds x sizes, synthetic coloured noise)")
    ap.add_argument("--open-kinds", default="none,regressor,periodic,step")
    ap.add_argument("--open-sizes", default="0.5,1,2,4")
    ap.add_argument(
        "--simulator-null",
        action="store_true",
        help="open-search false alarms on simulator null recordings, every preset",
    )
    ap.add_argument(
        "--out-of-sample",
        default=None,
        metavar="DATA_DIR",
        help="the out-of-sample table of docs/measured.md (BROAD pairs, static halves), JSON",
    )
    a = ap.parse_args()
    if a.out_of_sample:
        from gyrocore.data.jsonable import to_jsonable

        res = out_of_sample_runs(a.out_of_sample, progress=True)
        text = _json.dumps(to_jsonable(res), indent=1)
        if a.out:
            from gyrocore.data.recording import atomic_write_text

            atomic_write_text(a.out, text)
        else:
            print(text)
        raise SystemExit(0)
    if a.open or a.simulator_null:
        from gyrocore.data.jsonable import to_jsonable

        if a.open:
            rows = open_search_rates(
                kinds=a.open_kinds.split(","),
                sizes=[float(x) for x in a.open_sizes.split(",")],
                seeds=range(a.seed_start, a.seed_start + a.seeds),
                progress=True,
            )
            print(open_rates_markdown(rows))
        else:
            rows = simulator_null_false_alarms(seeds=range(a.seed_start, a.seed_start + a.seeds), progress=True)
            print(f"simulator null: {rows['false_alarms']}/{rows['n']} false alarms, 95 % CI {rows['ci95']}")
        if a.out:
            from gyrocore.data.recording import atomic_write_text

            atomic_write_text(a.out, _json.dumps(to_jsonable(rows), indent=1))
        raise SystemExit(0)
    if a.measured:
        from gyrocore.data.jsonable import to_jsonable

        rows = measured_runs(a.measured)
        print(_json.dumps(to_jsonable(rows), indent=1))
        raise SystemExit(0)
    rows = identification_rates(
        seeds=range(a.seeds),
        scales=[float(x) for x in a.scales.split(",")],
        effects=a.effects.split(",") if a.effects else None,
        progress=True,
    )
    print(rates_markdown(rows))
    if a.out:
        from gyrocore.data.recording import atomic_write_text

        atomic_write_text(a.out, _json.dumps(rows, indent=1))
