"""Experiment ``protocol``: the shortest calibration protocol that reaches a drift target.

"How long must I calibrate for X°?" — answered with the error budget
(:mod:`gyrocore.budget`) on the scored manoeuvre (a 10-min hover), then confirmed by
simulation.

Protocol knobs and how each enters the budget
---------------------------------------------
* power-up still window T_w (paid at every power-up): exact — the window's samples enter
  the noise quadratic form (white N²/T_w plus the slow-noise correlation);
* rate-table run, fraction f of the reference six-mount profile's time per mount (rates and
  mounts kept: all six mounts are needed to observe misalignment and g-sensitivity): least
  squares with white residuals, SE ∝ 1/√(samples) ⇒ SE(f) = SE_ref/√f for scale,
  misalignment, g-sensitivity, nonlinearity;
* thermal run, fraction d of the reference duration with the same temperature span (ramp
  rate ∝ 1/d): SE(d) = SE_ref/√d for the thermal polynomials and the re-referenced scale.
  (A smaller span would also raise the polynomial SEs ∝ span^(−k) and leave the flight's
  temperatures outside the fitted range; not offered.)

SE_ref are the standard errors of an actual calibration of one unit with the reference
protocol (:func:`experiments.ablation.calibrate_instance`); the noise is the unit's
(simulation truth; a user passes the identified noise). The cost of a protocol is its total
calibration time T_w + f·T_table + d·T_thermal; the answer is the cheapest grid point whose
predicted *final* error (or RMS / floor) meets the target. The window dimension is then
confirmed by simulation: units flown with a ground phase of T_w, scored like the ablation.
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

__all__ = ["Target", "TARGETS", "hover_trajectory", "evaluate_grid", "choose", "run"]

SENSOR = "icm42688p"
#: Reference protocol times (the ablation's calibration runs), s.
TABLE_REF_S = 387.0
THERMAL_REF_S = 900.0
WINDOWS_S = (0.5, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0)
TABLE_FRACTIONS = (0.125, 0.25, 0.5, 1.0)
THERMAL_FRACTIONS = (0.125, 0.25, 0.5, 1.0)
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


def evaluate_grid(res, ground_s: float, groups, *, windows=WINDOWS_S, table=TABLE_FRACTIONS,
                  thermal=THERMAL_FRACTIONS) -> list[dict]:
    """Predicted hover error for every protocol of the grid.

    One budget per window length (its trajectory); the table/thermal fractions scale each
    parameter group's variance by 1/f (SE ∝ 1/√f), exactly, without recomputing."""
    from gyrocore.budget import NoiseModel, predict_error

    noise = NoiseModel.from_params(res.params_true)
    rows = []
    for tw in windows:
        inp, segs, start = _prefixed_inputs(res, ground_s, tw)
        pr = predict_error(inp, start=start, segments=segs, noise=noise, groups=groups, max_blocks=400)
        base = np.zeros_like(pr.t_s)
        tab = np.zeros_like(pr.t_s)
        th = np.zeros_like(pr.t_s)
        for k in pr.predicted:
            v = pr.var_rad2[k]
            if k.startswith("param:"):
                if k[len("param:"):] in TABLE_GROUPS:
                    tab = tab + v
                else:
                    th = th + v
            else:
                base = base + v
        for f in table:
            for d in thermal:
                v = base + tab / f + th / d
                p = _Pred(final_predicted_deg=math.degrees(math.sqrt(max(v[-1], 0.0))),
                          rms_predicted_deg=math.degrees(math.sqrt(max(pr._mean(v), 0.0))),
                          rms_floor_deg=pr.rms_floor_deg, final_floor_deg=pr.final_floor_deg)
                rows.append({"window_s": tw, "table_fraction": f, "thermal_fraction": d,
                             "cost_s": tw + f * TABLE_REF_S + d * THERMAL_REF_S,
                             "final_deg": p.final_predicted_deg, "rms_deg": p.rms_predicted_deg,
                             "floor_rms_deg": p.rms_floor_deg, "floor_final_deg": p.final_floor_deg,
                             "pred": p})
    return rows


def choose(rows: Sequence[dict], target: Target) -> dict | None:
    """The cheapest protocol meeting ``target`` (ties: the smaller predicted error)."""
    ok = [r for r in rows if target.met(r["pred"])]
    if not ok:
        return None
    return min(ok, key=lambda r: (r["cost_s"], r["final_deg"]))


def confirm(window_s: float, seeds: Sequence[int], *, airborne_s: float, cache_dir: str | None = None) -> list[dict]:
    """Fly ``seeds`` units with a ground phase of ``window_s`` + 1 s, power-up bias from a
    ``window_s`` still window, reference calibration; measured vs predicted error."""
    import warnings

    from sim import scenarios as S

    from . import ablation as A

    spec = S.load_scenario("hover")
    ground = window_s + 1.0
    spec = dataclasses.replace(spec, hover={**dict(spec.hover), "ground_s": ground})
    out = []
    for sd in seeds:
        with warnings.catch_warnings(), single_thread_blas():
            warnings.simplefilter("ignore")
            ab = A.ablate_instance(spec, sensor=SENSOR, seed=int(sd), duration_s=ground + 3.0 + airborne_s,
                                   powerup_window_s=window_s, mahony_kp_per_s=None, cache_dir=cache_dir)
        out.append({"seed": int(sd), "final_deg": ab.scores["all"].final_error_deg,
                    "rms_deg": ab.scores["all"].rms_error_deg, "floor_rms_deg": ab.scores["floor"].rms_error_deg,
                    "pred_final_deg": ab.prediction.final_predicted_deg, "pred_rms_deg": ab.prediction.rms_predicted_deg,
                    "pred_floor_rms_deg": ab.prediction.rms_floor_deg})
    return out


def run(*, out_dir, quick: bool = False, seeds: int | None = None, workers: int | None = None,
        seed: int = 0, **_ignored) -> ExperimentResult:
    """Protocol design for :data:`TARGETS`; table, figure and simulation check into ``out_dir``."""
    from experiments.montecarlo import instance_seeds

    from . import ablation as A

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    airborne = 60.0 if quick else HOVER_S
    unit = instance_seeds(seed, 1)[0]
    res, ground = hover_trajectory(seed=unit, airborne_s=airborne)
    present = A.present_effects(res.params_true)
    with single_thread_blas():
        stages = A.calibrate_instance(SENSOR, unit, present, quick=quick)
    groups = A.calibration_groups(stages, present)
    windows = (0.5, 2.0, 8.0) if quick else WINDOWS_S
    fr = (0.25, 1.0) if quick else TABLE_FRACTIONS
    rows = evaluate_grid(res, ground, groups, windows=windows, table=fr, thermal=fr)
    chosen = {t.name: choose(rows, t) for t in TARGETS}
    # simulation check of the window dimension (reference table and thermal runs)
    n_units = seeds or (1 if quick else 3)
    check_windows = sorted({2.0} | {c["window_s"] for c in chosen.values() if c is not None})
    import shutil
    import tempfile

    cache = tempfile.mkdtemp(prefix="gyroharness-protocol-")
    try:
        conf = {tw: confirm(tw, instance_seeds(seed + 1, n_units), airborne_s=airborne, cache_dir=cache)
                for tw in check_windows}
    finally:
        shutil.rmtree(cache, ignore_errors=True)

    ref = [r for r in rows if r["table_fraction"] == 1.0 and r["thermal_fraction"] == 1.0]
    tab = md_table(["still window, s", "predicted final °", "predicted RMS °", "floor RMS °", "RMS / floor"],
                   [(r["window_s"], r["final_deg"], r["rms_deg"], r["floor_rms_deg"], r["rms_deg"] / r["floor_rms_deg"])
                    for r in ref])
    ch_rows = []
    for t in TARGETS:
        c = chosen[t.name]
        if c is None:
            ch_rows.append((t.name, "not reachable on the grid", "", "", "", "", ""))
        else:
            ch_rows.append((t.name, c["window_s"], c["table_fraction"] * TABLE_REF_S, c["thermal_fraction"] * THERMAL_REF_S,
                            c["cost_s"], c["final_deg"], c["rms_deg"] / c["floor_rms_deg"]))
    ch = md_table(["target", "still window, s", "table run, s", "thermal run, s", "total, s", "predicted final °",
                   "predicted RMS/floor"], ch_rows)
    cf_rows = []
    summary_conf = {}
    for tw, lst in conf.items():
        mf = np.array([x["final_deg"] for x in lst])
        pf = np.array([x["pred_final_deg"] for x in lst])
        mr = np.array([x["rms_deg"] for x in lst])
        prr = np.array([x["pred_rms_deg"] for x in lst])
        fl = np.array([x["floor_rms_deg"] for x in lst])
        cf_rows.append((tw, len(lst), float(np.median(mf)), float(np.median(pf)), float(np.median(mr)),
                        float(np.median(prr)), float(np.mean((mr / prr) ** 2)), float(np.median(mr / fl))))
        summary_conf[str(tw)] = lst
    cf = md_table(["still window, s", "units", "measured final ° (median)", "predicted final °", "measured RMS °",
                   "predicted RMS °", "mean (meas/pred RMS)²", "measured RMS/floor"], cf_rows)
    fig = new_figure(figsize=(6.5, 3.8))
    ax = fig.add_subplot(111)
    for f in sorted({r["table_fraction"] for r in rows}):
        for d in sorted({r["thermal_fraction"] for r in rows}):
            if f != d and not (f == 1.0 or d == 1.0):
                continue
            rr = [r for r in rows if r["table_fraction"] == f and r["thermal_fraction"] == d]
            ax.plot([r["window_s"] for r in rr], [r["final_deg"] for r in rr], marker=".",
                    label=f"table ×{f:g}, thermal ×{d:g}")
    ax.plot([r["window_s"] for r in ref], [r["floor_final_deg"] for r in ref], "k--", label="floor (final)")
    for tw, lst in conf.items():
        ax.plot([tw] * len(lst), [x["final_deg"] for x in lst], "kx", ms=6)
    ax.axhline(1.0, color="r", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("power-up still window, s")
    ax.set_ylabel(f"final attitude error after {airborne:g} s of hover, deg")
    ax.set_title("Predicted drift vs calibration protocol (x: simulated units)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=6)
    figp = save_figure(fig, out_dir, "protocol_hover")
    md = [
        f"Predicted attitude error after {airborne:g} s of hover (sensor {SENSOR}, unit seed {unit}) for a grid of "
        "calibration protocols: power-up still window, rate-table run (fraction of the reference six-mount profile, "
        f"{TABLE_REF_S:g} s) and thermal run (fraction of the reference {THERMAL_REF_S:g} s, same 15→45 °C span). "
        "Budget: gyrocore.budget with the reference calibration's standard errors scaled by 1/√fraction (least "
        "squares, white residuals) and the unit's noise. The power-up window is exact in the budget.\n",
        "#### Still window, reference table and thermal runs\n", tab,
        "\n#### Shortest protocol per target\n", ch,
        "\n#### Simulation check (window dimension; reference table and thermal calibration)\n", cf,
        f"\n![protocol]({figp})",
    ]
    summary = {
        "targets": {t.name: (None if chosen[t.name] is None else
                             {k: v for k, v in chosen[t.name].items() if k != "pred"}) for t in TARGETS},
        "grid": [{k: v for k, v in r.items() if k != "pred"} for r in rows],
        "confirmation": summary_conf,
        "airborne_s": airborne,
    }
    return ExperimentResult(name="protocol", title="Protocol design: how long to calibrate for a drift target",
                            markdown="\n".join(md), figures=(figp,), summary=summary,
                            wall_s=time.perf_counter() - t0)
