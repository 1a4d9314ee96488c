"""Experiment ``protocol``: the shortest calibration protocol that reaches a drift target.

"How long must I calibrate for X°?" — answered with the error budget
(:mod:`gyrocore.budget`) on the scored manoeuvre (a 10-min hover), then confirmed by
simulation.

Protocol knobs and how each enters the budget
---------------------------------------------
* power-up still window T_w (paid at every power-up): exact — the window's samples enter
  the noise quadratic form (white N²/T_w plus the slow-noise correlation);
* rate-table run (:data:`TABLE_PROTOCOLS`: mounts, rates, revolutions) and thermal run
  (:data:`THERMAL_PROTOCOLS`: ambient span and duration, i.e. ramp rate): their parameters'
  standard errors are *predicted from the design*, before any data: the candidate run's
  reference trajectory (rate, specific force, temperature; simulated), the calibration's
  own rows (ramps left out, block means) and the noise-model covariance
  (:func:`gyrocore.lsq.noise_model_meat`, the same sandwich the calibration reports; its
  honesty is checked by Monte Carlo in docs/accuracy.md) — :func:`design_stderr`. A
  parameter the candidate cannot observe (three mounts: g-sensitivity not separable from the
  bias) makes the candidate ineligible.

The noise model is the one the reference calibration identified (GMWM on its residual). The
cost of a protocol is its total calibration time T_w + T_table + T_thermal; the answer is the
cheapest grid point whose predicted *final* error (or RMS / floor) meets the target. The
choice is then confirmed by simulation (:func:`confirm`): units flown with a ground phase of
T_w, scored like the ablation, measured against predicted.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from gyrocore import effects as E

from .report import ExperimentResult, md_table, new_figure, save_figure, single_thread_blas

__all__ = ["Target", "TARGETS", "TableProtocol", "ThermalProtocol", "TABLE_PROTOCOLS", "THERMAL_PROTOCOLS",
           "hover_trajectory", "design_stderr", "candidate_stderr", "evaluate_grid", "choose", "confirm", "run"]

SENSOR = "icm42688p"
#: Reference protocol times (the ablation's calibration runs), s.
TABLE_REF_S = 387.0
THERMAL_REF_S = 900.0
WINDOWS_S = (0.5, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0)
_SIX = ("+x", "-x", "+y", "-y", "+z", "-z")
_THREE = ("+x", "+y", "+z")


@dataclass(frozen=True)
class TableProtocol:
    """A rate-table calibration run: mounts, rates (deg/s, each turned both ways), revolutions."""

    label: str
    mounts: tuple[str, ...]
    rates_dps: tuple[float, ...]
    revolutions: float


@dataclass(frozen=True)
class ThermalProtocol:
    """A thermal calibration run: ambient start → peak → start (°C) over ``duration_s`` (the
    scenario's ramp shape: the ramps take 35 % of the duration each way)."""

    label: str
    start_c: float
    peak_c: float
    duration_s: float


#: Candidate rate-table runs (the first is the reference, the ablation's).
TABLE_PROTOCOLS = (
    TableProtocol("6 mounts, 90+360 °/s, 5 rev", _SIX, (90.0, 360.0), 5.0),
    TableProtocol("6 mounts, 90+360 °/s, 2 rev", _SIX, (90.0, 360.0), 2.0),
    TableProtocol("6 mounts, 360 °/s, 2 rev", _SIX, (360.0,), 2.0),
    TableProtocol("6 mounts, 90 °/s, 1 rev", _SIX, (90.0,), 1.0),
    TableProtocol("3 mounts, 90+360 °/s, 5 rev", _THREE, (90.0, 360.0), 5.0),
    TableProtocol("3 mounts, 360 °/s, 1 rev", _THREE, (360.0,), 1.0),
)
#: Candidate thermal runs (the first is the reference): span and ramp rate.
THERMAL_PROTOCOLS = (
    ThermalProtocol("15→45 °C, 900 s", 15.0, 45.0, 900.0),
    ThermalProtocol("15→45 °C, 450 s", 15.0, 45.0, 450.0),
    ThermalProtocol("15→45 °C, 225 s", 15.0, 45.0, 225.0),
    ThermalProtocol("20→40 °C, 900 s", 20.0, 40.0, 900.0),
    ThermalProtocol("20→40 °C, 450 s", 20.0, 40.0, 450.0),
    ThermalProtocol("25→35 °C, 450 s", 25.0, 35.0, 450.0),
)
#: Airborne time scored, s (the target's "after 10 min of hover").
HOVER_S = 600.0
TABLE_GROUPS = ("scale", "misalignment", "g_sensitivity", "scale_nonlinearity", "scale_asymmetry", "g2_sensitivity")


@dataclass(frozen=True)
class Target:
    """A drift target: final error ≤ ``final_deg`` or RMS ≤ ``floor_ratio`` × the floor's RMS."""

    name: str
    final_deg: float | None = None
    floor_ratio: float | None = None

    def met(self, pred) -> bool:
        if self.final_deg is not None:
            return pred.final_predicted_deg <= self.final_deg
        return pred.rms_predicted_deg <= self.floor_ratio * pred.rms_floor_deg


TARGETS = (Target("final error ≤ 1° after 10 min of hover", final_deg=1.0),
           Target("RMS error ≤ 1.3 × floor over 10 min of hover", floor_ratio=1.3))


def hover_trajectory(*, seed: int, airborne_s: float):
    """One simulated hover (ground phase, take-off, hover): the true inputs after the ground
    phase, the unit's true parameters and the ground-phase attitude/force/temperature."""
    import warnings

    from sim import scenarios as S

    spec = S.load_scenario("hover")
    ground = float(spec.hover.get("ground_s", 5.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = S.simulate("hover", sensor=SENSOR, seed=seed, duration_s=ground + 3.0 + airborne_s)
    return res, ground


def _prefixed_inputs(res, ground_s: float, window_s: float):
    """Trajectory = ``window_s`` still (the ground attitude) + the flight from take-off.

    Returns (ModelInputs, segments, start)."""
    tr = res.truth
    rate = res.recording.rate_hz
    i_to = int(round(ground_s * rate))
    nw = max(1, int(round(window_s * rate)))
    w = np.asarray(tr.omega_S_rad_s, float)[i_to:]
    n = nw + w.shape[0]

    def pre(x):
        x = np.asarray(x, float)
        return np.concatenate([np.repeat(x[i_to - 1:i_to], nw, axis=0), x[i_to:]], axis=0)

    t = np.arange(n) / rate
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=np.concatenate([np.zeros((nw, 3)), w]), f_S_m_s2=pre(tr.f_S_m_s2),
                        temp_c=pre(tr.temp_c), q_SW_wxyz=pre(tr.q_SW_wxyz), t_since_power_up_s=t)
    return inp, [(slice(0, n), slice(0, nw))], nw


@dataclass(frozen=True)
class _Pred:
    final_predicted_deg: float
    rms_predicted_deg: float
    rms_floor_deg: float
    final_floor_deg: float


def design_stderr(spec, *, seed: int, effects: Sequence[str], noise, orders=None, run: int = 1,
                  duration_s: float | None = None) -> dict:
    """Standard errors a calibration run *would* report, predicted from its design alone.

    Simulates the candidate run's reference trajectory (rate, specific force, temperature of
    ``spec``; the gyro samples are not used), builds the calibration's rows as
    :class:`gyrocore.model.Calibrator` does with the ablation's settings (ramps ± the
    ramp margin left out, block means of ≤ ``max_rows`` rows) and evaluates the noise-model
    sandwich (AᵀWA)⁻¹·(Σ U_iᵀ C_i U_i)·(AᵀWA)⁻¹ of ``noise`` (:func:`gyrocore.lsq.solve`
    with r = 0: the covariance does not depend on the data).

    Returns
    -------
    dict with ``se`` ({effect: flat ndarray}, SI), ``unobservable`` (names), ``t0_c`` (mean
    temperature, the thermal polynomials' centre), ``duration_s``.
    """
    import warnings

    from gyrocore import lsq
    from gyrocore.model import near_rate_changes
    from sim import scenarios as S

    from . import ablation as A

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = S.simulate(spec, sensor=SENSOR, seed=int(seed), run=run, duration_s=duration_s).recording
    t = np.asarray(rec.t_s, float)
    w = np.asarray(rec.ref_rate_rad_s, float)
    wts = (~near_rate_changes(t, w, float(A._CAL_KW.get("ramp_margin_s", 0.0)))).astype(float)
    avg = max(1, int(math.ceil(float(np.count_nonzero(wts)) / float(A._CAL_KW.get("max_rows", 30000)))))
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=rec.accel_m_s2, temp_c=rec.temp_c)
    fit = lsq.fit_effects(np.zeros((t.size, 3)), list(effects), inp, orders=orders, weights=wts, average=avg,
                          covariance="noise_model", noise_model=noise, t_s=t - t[0], axis_weighting=False,
                          keep_residual=False)
    t0 = float(np.mean(rec.temp_c)) if rec.temp_c is not None else float("nan")
    return {"se": {e: fit.effect_stderr(e).copy() for e in effects}, "unobservable": tuple(fit.unobservable),
            "t0_c": t0, "duration_s": float(rec.duration_s)}


def table_spec(p: TableProtocol):
    """The turntable scenario with the protocol's mounts, rates and revolutions."""
    from sim import scenarios as S

    spec = S.load_scenario("turntable")
    return dataclasses.replace(spec, table={**dict(spec.table), "mounts": list(p.mounts),
                                            "rates_dps": list(p.rates_dps), "revolutions": float(p.revolutions)})


def thermal_spec(p: ThermalProtocol):
    """The thermal scenario with the protocol's ambient span and duration."""
    from sim import scenarios as S

    spec = S.load_scenario("thermal")
    th = dict(spec.thermal)
    th["ramps"] = {**dict(th.get("ramps", {})), "start_c": float(p.start_c), "peak_c": float(p.peak_c)}
    return dataclasses.replace(spec, thermal=th, duration_s=float(p.duration_s))


def _is_table(name: str, groups) -> bool:
    """Which calibration run a parameter group comes from (scale: the thermal run's
    re-referenced scale when scale_thermal is calibrated)."""
    if name == "scale":
        return not any(g.name == "scale_thermal" for g in groups)
    return name in TABLE_GROUPS


def candidate_stderr(groups, *, seed: int, noise_table, noise_thermal, table=TABLE_PROTOCOLS,
                     thermal=THERMAL_PROTOCOLS, thermal_orders=None) -> tuple[list[dict], list[dict]]:
    """Predicted standard errors of every table and thermal candidate (:func:`design_stderr`).

    Returns (table candidates, thermal candidates): dicts with ``label``, ``cost_s``,
    ``se`` ({group: flat ndarray}), ``t0_c``, ``unobservable`` (a candidate with any is
    ineligible)."""
    names = [g.name for g in groups]
    tab_eff = ["bias"] + [n for n in names if _is_table(n, groups)]
    th_eff = ["bias"] + [n for n in names if not _is_table(n, groups)]
    out_t, out_h = [], []
    for p in table:
        d = design_stderr(table_spec(p), seed=seed, effects=tab_eff, noise=noise_table)
        out_t.append({"label": p.label, "cost_s": d["duration_s"], "se": d["se"], "t0_c": d["t0_c"],
                      "unobservable": d["unobservable"], "protocol": dataclasses.asdict(p)})
    for p in thermal:
        d = design_stderr(thermal_spec(p), seed=seed, effects=th_eff, noise=noise_thermal, run=2,
                          orders=thermal_orders)
        out_h.append({"label": p.label, "cost_s": d["duration_s"], "se": d["se"], "t0_c": d["t0_c"],
                      "unobservable": d["unobservable"], "protocol": dataclasses.asdict(p)})
    return out_t, out_h


def _recentred(g, t0_c: float):
    """Group ``g`` with its thermal polynomials centred on ``t0_c`` (the candidate run's mean)."""
    from gyrocore.budget import ParameterGroup

    if not np.isfinite(t0_c):
        return g
    params = {e: ({**dict(pd), "t0_c": np.asarray(t0_c)} if "t0_c" in pd else pd) for e, pd in g.params.items()}
    return ParameterGroup(name=g.name, params=params, stderr=g.stderr)


def evaluate_grid(res, ground_s: float, groups, *, windows=WINDOWS_S, table=None, thermal=None,
                  noise=None) -> list[dict]:
    """Predicted hover error for every protocol of the grid (window × table × thermal).

    One budget per window length (its trajectory) for the noise and the window
    (:func:`gyrocore.budget.predict_error`); each parameter group's variance
    Σ_p |S_p(t)|²·SE_p² from its sensitivity S (:func:`gyrocore.budget.sensitivity`) and the
    candidate's standard errors. ``table``/``thermal``: candidates of
    :func:`candidate_stderr` (None: one "reference" candidate with the groups' own standard
    errors). ``noise``: the noise model (None: the unit's true noise)."""
    from gyrocore.budget import NoiseModel, make_blocks, predict_error, rotation_matrices, sensitivity

    if noise is None:
        noise = NoiseModel.from_params(res.params_true)
    table = table or [{"label": "reference", "cost_s": TABLE_REF_S, "se": None, "t0_c": float("nan"), "unobservable": ()}]
    thermal = thermal or [{"label": "reference", "cost_s": THERMAL_REF_S, "se": None, "t0_c": float("nan"),
                           "unobservable": ()}]
    rows = []
    for tw in windows:
        inp, segs, start = _prefixed_inputs(res, ground_s, tw)
        pr = predict_error(inp, start=start, segments=segs, noise=noise, groups=(), max_blocks=400)
        base = pr.total_var_rad2()
        blocks = make_blocks(np.asarray(inp.t_s, float), start=start, segments=segs, max_blocks=400)
        R = rotation_matrices(inp.q_SW_wxyz)
        sc = blocks.scored
        cache: dict = {}

        def s2(g, t0):
            key = (g.name, round(float(t0), 6) if np.isfinite(t0) else None)
            if key not in cache:
                _, S, se = sensitivity(inp, R, blocks, segs, _recentred(g, t0))
                cache[key] = (np.sum(S ** 2, axis=1)[sc], np.where(np.isfinite(se), se, 0.0))
            return cache[key]

        def var(cand, tab: bool):
            v = np.zeros_like(base)
            for g in groups:
                if _is_table(g.name, groups) != tab:
                    continue
                S2, se_ref = s2(g, cand.get("t0_c", float("nan")) if not tab else float("nan"))
                se = se_ref if cand["se"] is None else np.asarray(cand["se"].get(g.name, se_ref), float)
                v = v + S2 @ np.where(np.isfinite(se), se, 0.0) ** 2
            return v

        vt = [var(c, True) for c in table]
        vh = [var(c, False) for c in thermal]
        for c1, a in zip(table, vt):
            for c2, b in zip(thermal, vh):
                v = base + a + b
                p = _Pred(final_predicted_deg=math.degrees(math.sqrt(max(v[-1], 0.0))),
                          rms_predicted_deg=math.degrees(math.sqrt(max(pr._mean(v), 0.0))),
                          rms_floor_deg=pr.rms_floor_deg, final_floor_deg=pr.final_floor_deg)
                rows.append({"window_s": tw, "table": c1["label"], "thermal": c2["label"],
                             "table_s": c1["cost_s"], "thermal_s": c2["cost_s"],
                             "eligible": not (c1["unobservable"] or c2["unobservable"]),
                             "cost_s": tw + c1["cost_s"] + c2["cost_s"],
                             "final_deg": p.final_predicted_deg, "rms_deg": p.rms_predicted_deg,
                             "floor_rms_deg": p.rms_floor_deg, "floor_final_deg": p.final_floor_deg,
                             "table_deg": math.degrees(math.sqrt(max(pr._mean(a), 0.0))),
                             "thermal_deg": math.degrees(math.sqrt(max(pr._mean(b), 0.0))),
                             "pred": p})
    return rows


def choose(rows: Sequence[dict], target: Target) -> dict | None:
    """The cheapest eligible protocol meeting ``target`` (ties: the smaller predicted error)."""
    ok = [r for r in rows if r.get("eligible", True) and target.met(r["pred"])]
    if not ok:
        return None
    return min(ok, key=lambda r: (r["cost_s"], r["final_deg"]))


def true_calibration(sensor: str, seed: int) -> list[dict]:
    """Calibration stages holding the unit's *true* parameters (every present effect but the
    bias, no standard errors): the power-up window and the noise are then all that is left —
    what the window dimension of the protocol is about."""
    import warnings

    from sim import scenarios as S

    from . import ablation as A

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pt = S.simulate("static", sensor=sensor, seed=int(seed), duration_s=2.0).params_true
    return [{e: {k: np.asarray(v, float) for k, v in pt[e].items()} for e in A.present_effects(pt) if e != "bias"}]


def confirm(window_s: float, seeds: Sequence[int], *, airborne_s: float, cache_dir: str | None = None,
            calibration: str = "true") -> list[dict]:
    """Fly ``seeds`` units with a ground phase of ``window_s`` + 1 s, power-up bias from a
    ``window_s`` still window; measured vs predicted error. ``calibration``: ``"true"``
    (:func:`true_calibration`, isolates the window) or ``"reference"`` (the unit's own
    reference calibration runs)."""
    import warnings

    from sim import scenarios as S

    from . import ablation as A

    spec = S.load_scenario("hover")
    ground = window_s + 1.0
    spec = dataclasses.replace(spec, hover={**dict(spec.hover), "ground_s": ground})
    out = []
    for sd in seeds:
        cal = true_calibration(SENSOR, int(sd)) if calibration == "true" else None
        with warnings.catch_warnings(), single_thread_blas():
            warnings.simplefilter("ignore")
            ab = A.ablate_instance(spec, sensor=SENSOR, seed=int(sd), duration_s=ground + 3.0 + airborne_s,
                                   powerup_window_s=window_s, mahony_kp_per_s=None, cache_dir=cache_dir,
                                   calibration=cal)
        out.append({"seed": int(sd), "final_deg": ab.scores["all"].final_error_deg,
                    "rms_deg": ab.scores["all"].rms_error_deg, "floor_rms_deg": ab.scores["floor"].rms_error_deg,
                    "pred_final_deg": ab.prediction.final_predicted_deg, "pred_rms_deg": ab.prediction.rms_predicted_deg,
                    "pred_floor_rms_deg": ab.prediction.rms_floor_deg})
    return out


def _interval(x: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean of log x and its Student-t interval, back-transformed: (geometric mean, lo, hi)."""
    from scipy import stats

    lx = np.log(np.asarray(x, float))
    m = float(lx.mean())
    if lx.size < 2:
        return math.exp(m), float("nan"), float("nan")
    h = float(stats.t.ppf(0.5 + level / 2, lx.size - 1)) * float(lx.std(ddof=1)) / math.sqrt(lx.size)
    return math.exp(m), math.exp(m - h), math.exp(m + h)


def run(*, out_dir, quick: bool = False, seeds: int | None = None, workers: int | None = None,
        seed: int = 0, **_ignored) -> ExperimentResult:
    """Protocol design for :data:`TARGETS`; tables, figure and simulation check into ``out_dir``."""
    import shutil
    import tempfile

    from experiments.montecarlo import instance_seeds

    from . import ablation as A

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    airborne = 60.0 if quick else HOVER_S
    unit = instance_seeds(seed, 1)[0]
    res, ground = hover_trajectory(seed=unit, airborne_s=airborne)
    present = A.present_effects(res.params_true)
    with single_thread_blas():
        core = A.calibrate_core(SENSOR, unit, present, quick=quick)
    stages = list(core.stages)
    groups = A.calibration_groups(stages, present)
    nm = A.identified_noise(core, float(res.recording.rate_hz))
    r1, r2 = (tuple(core.results) + (None, None))[:2]
    n_tab = r1.noise() if r1 is not None and r1.noise_model else nm
    n_th = r2.noise() if r2 is not None and r2.noise_model else nm
    orders = dict(r2.thermal_order) if r2 is not None else None
    windows = (0.5, 2.0, 8.0, 30.0) if quick else WINDOWS_S
    tabs = TABLE_PROTOCOLS[:2] if quick else TABLE_PROTOCOLS
    ths = THERMAL_PROTOCOLS[:2] if quick else THERMAL_PROTOCOLS
    with single_thread_blas():
        cand_t, cand_h = candidate_stderr(groups, seed=unit, noise_table=n_tab, noise_thermal=n_th, table=tabs,
                                          thermal=ths, thermal_orders=orders)
    rows = evaluate_grid(res, ground, groups, windows=windows, table=cand_t, thermal=cand_h, noise=nm)
    chosen = {t.name: choose(rows, t) for t in TARGETS}
    # simulation check: the chosen window against the 2-s reference, true-parameter calibration
    n_units = seeds or (1 if quick else 12)
    check_windows = sorted({2.0} | {c["window_s"] for c in chosen.values() if c is not None})
    cache = tempfile.mkdtemp(prefix="gyroharness-protocol-")
    try:
        conf = {tw: confirm(tw, instance_seeds(seed + 1, n_units), airborne_s=airborne, cache_dir=cache)
                for tw in check_windows}
    finally:
        shutil.rmtree(cache, ignore_errors=True)

    ref_t, ref_h = cand_t[0]["label"], cand_h[0]["label"]
    ref = [r for r in rows if r["table"] == ref_t and r["thermal"] == ref_h]
    tab = md_table(["still window, s", "predicted final °", "predicted RMS °", "floor RMS °", "RMS / floor"],
                   [(r["window_s"], r["final_deg"], r["rms_deg"], r["floor_rms_deg"], r["rms_deg"] / r["floor_rms_deg"])
                    for r in ref])
    w_show = 2.0 if 2.0 in windows else windows[0]

    def se_med(c, g):
        v = np.asarray(c["se"].get(g, [np.nan]), float)
        v = v[np.isfinite(v)]
        return float(np.median(v)) if v.size else float("inf")

    def at(label_t=None, label_h=None):
        return next(r for r in rows if r["window_s"] == w_show and r["table"] == (label_t or ref_t)
                    and r["thermal"] == (label_h or ref_h))

    tt_rows = [(c["label"], c["cost_s"], se_med(c, "g_sensitivity") if "g_sensitivity" in c["se"] else "",
                se_med(c, "misalignment") if "misalignment" in c["se"] else "",
                ", ".join(c["unobservable"][:3]) + (" …" if len(c["unobservable"]) > 3 else "") or "—",
                at(label_t=c["label"])["table_deg"], at(label_t=c["label"])["final_deg"]) for c in cand_t]
    t_tab = md_table(["table run", "duration, s", "g-sens SE (median), rad/s/(m/s²)", "misalignment SE, rad",
                      "unobservable", f"table params' hover RMS ° ({w_show:g}-s window)", "predicted final °"], tt_rows)
    th_rows = [(c["label"], c["cost_s"], se_med(c, "bias_thermal") if "bias_thermal" in c["se"] else "",
                ", ".join(c["unobservable"][:3]) or "—", at(label_h=c["label"])["thermal_deg"],
                at(label_h=c["label"])["final_deg"]) for c in cand_h]
    h_tab = md_table(["thermal run", "duration, s", "bias_thermal SE (median), SI", "unobservable",
                      f"thermal params' hover RMS ° ({w_show:g}-s window)", "predicted final °"], th_rows)
    ch_rows = []
    for t in TARGETS:
        c = chosen[t.name]
        if c is None:
            ch_rows.append((t.name, "not reachable on the grid", "", "", "", "", ""))
        else:
            ch_rows.append((t.name, c["window_s"], c["table"], c["thermal"], c["cost_s"], c["final_deg"],
                            c["rms_deg"] / c["floor_rms_deg"]))
    ch = md_table(["target", "still window, s", "table run", "thermal run", "total, s", "predicted final °",
                   "predicted RMS/floor"], ch_rows)
    cf_rows = []
    summary_conf = {}
    for tw, lst in conf.items():
        mr = np.array([x["rms_deg"] for x in lst])
        prr = np.array([x["pred_rms_deg"] for x in lst])
        fl = np.array([x["floor_rms_deg"] for x in lst])
        r2v = (mr / prr) ** 2
        se2 = float(np.std(r2v, ddof=1) / math.sqrt(r2v.size)) if r2v.size > 1 else float("nan")
        g, lo, hi = _interval(mr / fl)
        cf_rows.append((tw, len(lst), float(np.median(mr)), float(np.median(prr)), f"{np.mean(r2v):.2f} ± {se2:.2f}",
                        float(np.median(prr / np.array([x["pred_floor_rms_deg"] for x in lst]))),
                        f"{g:.2f} [{lo:.2f}, {hi:.2f}]"))
        summary_conf[str(tw)] = {"units": lst, "measured_over_floor_geomean": g, "ci95": [lo, hi],
                                 "mean_r2": float(np.mean(r2v)), "mean_r2_se": se2}
    cf = md_table(["still window, s", "units", "measured RMS ° (median)", "predicted RMS ° (median)",
                   "mean (meas/pred RMS)² ± se", "predicted RMS/floor", "measured RMS/floor: geo-mean [95 % CI]"], cf_rows)
    fig = new_figure(figsize=(10.0, 3.8))
    ax = fig.add_subplot(121)
    for c in cand_t:
        rr = [r for r in rows if r["table"] == c["label"] and r["thermal"] == ref_h]
        ax.plot([r["window_s"] for r in rr], [r["final_deg"] for r in rr], marker=".",
                ls="-" if not c["unobservable"] else ":", label=c["label"])
    ax.plot([r["window_s"] for r in ref], [r["floor_final_deg"] for r in ref], "k--", label="floor (final)")
    for tw, lst in conf.items():
        ax.plot([tw] * len(lst), [x["final_deg"] for x in lst], "kx", ms=5)
    ax.axhline(1.0, color="r", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("power-up still window, s")
    ax.set_ylabel(f"final error after {airborne:g} s of hover, deg")
    ax.set_title("table runs (reference thermal run); x: simulated units", fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=6)
    ax2 = fig.add_subplot(122)
    for c in cand_h:
        rr = [r for r in rows if r["thermal"] == c["label"] and r["table"] == ref_t]
        ax2.plot([r["window_s"] for r in rr], [r["rms_deg"] / r["floor_rms_deg"] for r in rr], marker=".",
                 label=c["label"])
    ax2.axhline(1.3, color="r", lw=0.8)
    ax2.set_xscale("log")
    ax2.set_xlabel("power-up still window, s")
    ax2.set_ylabel("predicted RMS / floor RMS")
    ax2.set_title("thermal runs (reference table run)", fontsize=8)
    ax2.grid(alpha=0.3, which="both")
    ax2.legend(fontsize=6)
    figp = save_figure(fig, out_dir, "protocol_hover")
    md = [
        f"Predicted attitude error after {airborne:g} s of hover (sensor {SENSOR}, unit seed {unit}) for a grid of "
        "calibration protocols: power-up still window × rate-table run (mounts, rates, revolutions) × thermal run "
        "(ambient span, duration = ramp rate). The table and thermal runs' standard errors are predicted from each "
        "candidate's design with the noise-model covariance (experiments.protocol.design_stderr), the noise is the "
        "model the reference calibration identified; the power-up window is exact in the budget.\n",
        "#### Still window (reference table and thermal runs)\n", tab,
        "\n#### Rate-table run candidates (reference thermal run)\n", t_tab,
        "\n#### Thermal run candidates (reference table run)\n", h_tab,
        "\n#### Shortest protocol per target\n", ch,
        "\n#### Simulation check (units flown with each window; calibration = the unit's true parameters, so only "
        "the window and the noise differ)\n", cf,
        f"\n![protocol]({figp})",
    ]
    summary = {
        "targets": {t.name: (None if chosen[t.name] is None else
                             {k: v for k, v in chosen[t.name].items() if k != "pred"}) for t in TARGETS},
        "grid": [{k: v for k, v in r.items() if k != "pred"} for r in rows],
        "table_candidates": [{k: v for k, v in c.items() if k != "se"} for c in cand_t],
        "thermal_candidates": [{k: v for k, v in c.items() if k != "se"} for c in cand_h],
        "confirmation": summary_conf,
        "airborne_s": airborne,
    }
    return ExperimentResult(name="protocol", title="Protocol design: how long to calibrate for a drift target",
                            markdown="\n".join(md), figures=(figp,), summary=summary,
                            wall_s=time.perf_counter() - t0)
