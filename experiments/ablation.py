"""Experiment ``ablation``: how much attitude drift each correction removes, per scenario.

For each scenario and each simulated sensor instance (a unit drawn from a preset: its own
biases, scale factors, … and its own noise), the scored recording's gyro is integrated from
the true initial attitude after applying a subset of corrections, and the attitude error
angle against the truth is scored (final, RMS, deg/min; :mod:`gyrocore.attitude`).

Rows
----
``none``            the raw gyro.
``all``             every correction whose effect is present in the instance.
``all but X``       every present correction except X.
``only X``          X alone.
``true params``     all present effects removed with the instance's *true* parameters
                    (reference: what a perfect calibration would give).
``floor``           truth + the recording's own stochastic noise only (every deterministic
                    error removed exactly) — DESIGN.md "The score".

Which effects are *present* comes from the instance's true parameters. The corrections are
what a user would really get: parameters estimated by the calibration core
(:class:`gyrocore.model.Calibrator`) from calibration recordings of the same instance (a
rate-table run and a thermal run, separate power-ups with fresh noise), plus the power-up
bias taken at the start of the scored recording, still, *after* the other corrections
(turn-on bias changes at every power-up). ``bias`` in a row means that power-up bias.

The Monte Carlo over instances runs through :mod:`experiments.montecarlo`
(:func:`ablation_task` is its task function); tables give the median and 90th percentile.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyrocore import effects as E
from gyrocore.attitude import AttitudeScore, error_angle_rad, integrate_gyro, score_attitude

from .report import ExperimentResult, md_table, new_figure, save_figure

__all__ = [
    "SCENARIOS",
    "CORRECTABLE",
    "present_effects",
    "row_names",
    "corrected_gyro",
    "score_variants",
    "InstanceAblation",
    "ablate_instance",
    "ablation_task",
    "run",
    "CURVE_FRACTIONS",
]

#: Scenarios scored by the ablation (sim.scenarios names).
SCENARIOS = ("static", "static_bumped", "turntable", "thermal", "hover", "power_cycles")

#: Deterministic effects that :func:`gyrocore.effects.correct` can remove.
CORRECTABLE = (
    "bias",
    "bias_thermal",
    "bias_temp_rate",
    "bias_ramp",
    "scale",
    "scale_thermal",
    "scale_asymmetry",
    "scale_nonlinearity",
    "misalignment",
    "g_sensitivity",
    "g2_sensitivity",
    "time_offset",
    "earth_rate",
)

#: Fractions of the scored duration at which error curves are kept (for median curves).
CURVE_FRACTIONS = tuple(np.round(np.linspace(0.0, 1.0, 21), 3))
#: Sensor instances per scenario in the default run, and the --quick duration, s.
DEFAULT_INSTANCES = 12
QUICK_DURATION_S = 20.0


def present_effects(params_true: Mapping[str, Mapping[str, np.ndarray]]) -> list[str]:
    """Correctable effects with a non-zero parameter in the instance's true parameters."""
    out = []
    for e in CORRECTABLE:
        if e not in params_true:
            continue
        pd = params_true[e]
        if e == "bias":
            vals = [np.asarray(pd["b_rad_s"]), np.asarray(pd.get("turn_on_sigma_rad_s", 0.0))]
        elif e in ("bias_thermal", "scale_thermal"):
            vals = [np.asarray(pd[k]) for k in E.PARAM_SCHEMA[e] if k.startswith("poly")]
        elif e == "earth_rate":
            vals = [np.ones(1)]
        else:
            vals = [np.asarray(pd[k]) for k in E.PARAM_SCHEMA[e]]
        if any(np.any(v != 0) for v in vals):
            out.append(e)
    return out


def row_names(present: Sequence[str]) -> list[str]:
    """Row labels in table order."""
    rows = ["none", "all"]
    if len(present) > 1:
        rows += [f"all but {e}" for e in present]
        rows += [f"only {e}" for e in present]
    rows += ["true params", "floor"]
    return rows


def corrected_gyro(
    gyro_rad_s: np.ndarray,
    inp: E.ModelInputs,
    params_est: Mapping[str, Mapping[str, np.ndarray]],
    subset: Sequence[str],
    still: slice | None,
) -> np.ndarray:
    """The gyro after the corrections in ``subset`` (rad/s, (N, 3)).

    Non-bias effects are removed with ``params_est`` (:func:`gyrocore.effects.correct`). If
    ``"bias"`` is in ``subset`` the power-up bias is the mean of the corrected rate over the
    ``still`` samples at the start of the recording (true rate 0 there), subtracted after the
    other corrections, as a user does after applying a calibration file. Without a still
    window the calibration's own ``bias`` (a stale turn-on draw) is used if it has one.
    """
    others = {e: params_est[e] for e in subset if e != "bias" and e in params_est}
    g = np.asarray(gyro_rad_s, float)
    w = E.correct(others, g, inp) if others else g.copy()
    if "bias" in subset:
        if still is not None and (still.stop or 0) > (still.start or 0):
            w = w - w[still].mean(axis=0)
        elif "bias" in params_est:
            w = w - np.asarray(params_est["bias"]["b_rad_s"], float)
    return w


def score_variants(
    t_s: np.ndarray,
    q_true_wxyz: np.ndarray,
    variants: Mapping[str, np.ndarray],
    *,
    start: int = 0,
) -> dict[str, tuple[AttitudeScore, np.ndarray]]:
    """Integrate each gyro variant from the true attitude at sample ``start`` and score it.

    Returns ``{name: (AttitudeScore, error_rad (N − start,))}``.
    """
    t = np.asarray(t_s, float)[start:]
    q_true = np.asarray(q_true_wxyz, float)[start:]
    out = {}
    for name, w in variants.items():
        q = integrate_gyro(t, np.asarray(w, float)[start:], q0_wxyz=q_true[0])
        e = error_angle_rad(q, q_true)
        out[name] = (score_attitude(t, e), e)
    return out


# ------------------------------------------------------------------ one instance (needs sim)
@dataclass(frozen=True)
class InstanceAblation:
    """Ablation of one sensor instance in one scenario.

    Attributes
    ----------
    scenario, sensor : str
    seed : int
    present : tuple of str
        Correctable effects present in the instance.
    estimated : tuple of str
        Effects the calibration core estimated (others fall back to no correction).
    scores : dict
        ``{row: AttitudeScore}``.
    t_s : ndarray, shape (M,)
        Time since the start of scoring (decimated), s.
    errors_deg : dict
        ``{row: ndarray (M,)}`` error angle curves (decimated), degrees.
    notes : tuple of str
    """

    scenario: str
    sensor: str
    seed: int
    present: tuple[str, ...]
    estimated: tuple[str, ...]
    scores: Mapping[str, AttitudeScore]
    t_s: np.ndarray
    errors_deg: Mapping[str, np.ndarray]
    notes: tuple[str, ...] = ()


def _fittable_from(rec_kind: str, present: Sequence[str]) -> list[str]:
    """Which present effects each calibration recording is used to fit."""
    table = {
        "turntable": ("bias", "scale", "misalignment", "g_sensitivity", "scale_asymmetry",
                      "scale_nonlinearity", "g2_sensitivity", "time_offset"),
        "thermal": ("bias", "bias_thermal", "scale_thermal", "bias_temp_rate", "bias_ramp"),
    }[rec_kind]
    return [e for e in table if e in present]


def _still_window(rec, *, max_s: float = 10.0) -> slice | None:
    """Still samples at the start of ``rec`` (motion-gated static calibration, gyrocore.bias)."""
    from gyrocore import bias as B

    return B.startup_still_slice(rec, max_duration_s=max_s)


def ablate_instance(
    scenario: str,
    *,
    sensor: str = "icm42688p",
    seed: int = 0,
    duration_s: float | None = None,
    quick: bool = False,
    calibration: Mapping[str, Mapping[str, np.ndarray]] | None = None,
) -> InstanceAblation:
    """Run the whole ablation for one instance of ``sensor`` in ``scenario`` (needs :mod:`sim`)."""
    from sim import scenarios as S

    from gyrocore.model import Calibrator

    res = S.simulate(scenario, sensor=sensor, duration_s=duration_s, seed=seed)
    rec, truth, p_true = res.recording, res.truth, res.params_true
    present = present_effects(p_true)
    notes: list[str] = []
    # --- calibration recordings of the same instance (other power-ups, fresh noise)
    params_est: dict[str, dict[str, np.ndarray]] = {} if calibration is None else {k: dict(v) for k, v in calibration.items()}
    if calibration is None:
        for kind in ("turntable", "thermal"):
            fit = [e for e in _fittable_from(kind, present) if e not in params_est or e == "bias"]
            if not fit:
                continue
            cal = S.simulate(kind, sensor=sensor, seed=seed, run=1 + ("turntable", "thermal").index(kind),
                             duration_s=60.0 if quick else None)
            result = Calibrator(effects=fit).fit(cal.recording)
            for e, pd in result.params.items():
                if e == "bias" and "bias" in params_est:
                    continue
                params_est[e] = pd
    estimated = tuple(e for e in present if e in params_est or e == "bias")
    missing = [e for e in present if e not in estimated]
    if missing:
        notes.append(f"not estimated by the calibration runs: {', '.join(missing)}")
    inp = E.ModelInputs(t_s=rec.t_s, omega_S_rad_s=None, f_S_m_s2=rec.accel_m_s2, temp_c=rec.temp_c,
                        q_SW_wxyz=truth.q_SW_wxyz, t_since_power_up_s=truth.t_since_power_up_s)
    still = _still_window(rec)
    if still is None and "bias" in present:
        notes.append("no still window at the start: bias from the calibration run")
    variants: dict[str, np.ndarray] = {}
    for row in row_names(present):
        if row == "none":
            variants[row] = rec.gyro_rad_s
        elif row == "all":
            variants[row] = corrected_gyro(rec.gyro_rad_s, inp, params_est, present, still)
        elif row.startswith("all but "):
            x = row[len("all but "):]
            variants[row] = corrected_gyro(rec.gyro_rad_s, inp, params_est, [e for e in present if e != x], still)
        elif row.startswith("only "):
            variants[row] = corrected_gyro(rec.gyro_rad_s, inp, params_est, [row[len("only "):]], still)
        elif row == "true params":
            ptrue = {e: p_true[e] for e in present if e != "bias"}
            w = E.correct(ptrue, rec.gyro_rad_s, inp) if ptrue else rec.gyro_rad_s.copy()
            if "bias" in present:
                w = w - S.true_bias_rad_s(res)  # the per-power-up true bias (N, 3)
            variants[row] = w
        elif row == "floor":
            variants[row] = S.floor_gyro(res)
    start = 0 if still is None else int(still.stop)
    sc = score_variants(rec.t_s, truth.q_SW_wxyz, variants, start=start)
    t = rec.t_s[start:] - rec.t_s[start]
    idx = np.unique(np.clip(np.round(np.asarray(CURVE_FRACTIONS) * (t.size - 1)).astype(int), 0, t.size - 1))
    return InstanceAblation(
        scenario=scenario, sensor=sensor, seed=seed, present=tuple(present), estimated=estimated,
        scores={k: v[0] for k, v in sc.items()}, t_s=t[idx],
        errors_deg={k: np.degrees(v[1][idx]) for k, v in sc.items()}, notes=tuple(notes),
    )


# ------------------------------------------------------------------ Monte Carlo task
def _key(row: str) -> str:
    return row.replace(" ", "_")


#: Rows whose error curves are kept per instance (for median curves).
CURVE_ROWS = ("none", "all", "true params", "floor")


def instance_metrics(ab: InstanceAblation) -> dict[str, float]:
    """Flatten an :class:`InstanceAblation` into named scalars (Monte Carlo metrics)."""
    m: dict[str, float] = {"duration_s": float(ab.t_s[-1]) if ab.t_s.size else float("nan")}
    for e in CORRECTABLE:
        m[f"present__{e}"] = float(e in ab.present)
    for row, s in ab.scores.items():
        k = _key(row)
        m[f"{k}__final_deg"] = s.final_error_deg
        m[f"{k}__rms_deg"] = s.rms_error_deg
        m[f"{k}__drift_deg_per_min"] = s.drift_deg_per_min
    fl = ab.scores.get("floor")
    if fl is not None:
        for row, s in ab.scores.items():
            m[f"{_key(row)}__over_floor"] = s.rms_error_deg / fl.rms_error_deg if fl.rms_error_deg > 0 else float("nan")
    for row in CURVE_ROWS:
        if row in ab.errors_deg:
            for i, v in enumerate(ab.errors_deg[row]):
                m[f"{_key(row)}__e{i:02d}_deg"] = float(v)
    return m


def ablation_task(task) -> "Any":
    """Monte Carlo task function (:mod:`experiments.montecarlo`): one instance through the ablation.

    Options (``task.options``): ``quick`` (bool).
    """
    import warnings

    from experiments.montecarlo import TaskResult

    opts = dict(task.options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ab = ablate_instance(task.scenario, sensor=task.sensor, seed=task.seed, duration_s=task.duration_s,
                             quick=bool(opts.get("quick", False)))
    return TaskResult.from_task(task, instance_metrics(ab))


# ------------------------------------------------------------------ report
DEFAULT_SENSORS = ("icm42688p",)


def _rows_in(campaign, scenario: str, sensor: str) -> list[str]:
    """Row keys present in the campaign for (scenario, sensor), table order."""
    keys = []
    for s in campaign.summary:
        if s.scenario == scenario and s.sensor == sensor and s.metric.endswith("__final_deg"):
            keys.append(s.metric[: -len("__final_deg")])
    order = {"none": 0, "all": 1, "true_params": 98, "floor": 99}
    return sorted(keys, key=lambda k: (order.get(k, 2 if k.startswith("all_but") else 3), keys.index(k)))


def campaign_tables(campaign) -> tuple[str, dict]:
    """Markdown tables (median and p90 per row) and a JSON-able summary of an ablation campaign."""
    md, summary = [], {}
    for sc in campaign.scenarios:
        for se in campaign.sensors:
            tab = {s.metric: s for s in campaign.summary if s.scenario == sc and s.sensor == se}
            if not tab:
                continue
            keys = _rows_in(campaign, sc, se)
            present = [e for e in CORRECTABLE if tab.get(f"present__{e}") is not None and tab[f"present__{e}"].median > 0]
            dur = tab["duration_s"].median if "duration_s" in tab else float("nan")
            n = tab[f"{keys[0]}__final_deg"].n if keys else 0
            md.append(f"### {sc} — {se}\n")
            md.append(f"{n} sensor instances, {dur:.0f} s scored; effects present: {', '.join(present) or 'none'}.\n")
            rows = []
            for k in keys:
                f, r, d = tab[f"{k}__final_deg"], tab[f"{k}__rms_deg"], tab[f"{k}__drift_deg_per_min"]
                of = tab.get(f"{k}__over_floor")
                rows.append((k.replace("_", " ").replace("all but", "all but").replace("true params", "true params"),
                             f.median, f.p90, r.median, r.p90, d.median, d.p90,
                             of.median if of else float("nan"), of.p90 if of else float("nan")))
            md.append(md_table(["correction", "final °, median", "final °, p90", "RMS °, median", "RMS °, p90",
                                "°/min, median", "°/min, p90", "RMS/floor, median", "RMS/floor, p90"], rows))
            md.append("")
            summary[f"{sc}/{se}"] = {
                k: {"final_deg_median": tab[f"{k}__final_deg"].median, "final_deg_p90": tab[f"{k}__final_deg"].p90,
                    "rms_deg_median": tab[f"{k}__rms_deg"].median, "rms_deg_p90": tab[f"{k}__rms_deg"].p90}
                for k in keys if k in ("none", "all", "true_params", "floor")
            }
            summary[f"{sc}/{se}"]["present"] = present
            summary[f"{sc}/{se}"]["instances"] = n
    return "\n".join(md), summary


def curve_figure(campaign, scenario: str, sensor: str, out_dir) -> str | None:
    """Median (line) and 90th percentile (band edge) error curves of none/all/true/floor."""
    by_row: dict[str, np.ndarray] = {}
    tasks = [t for t in campaign.tasks if t.scenario == scenario and t.sensor == sensor]
    if not tasks:
        return None
    dur = float(np.nanmedian([t.metrics_dict.get("duration_s", np.nan) for t in tasks]))
    for row in CURVE_ROWS:
        k = _key(row)
        curves = []
        for t in tasks:
            md = t.metrics_dict
            c = [md.get(f"{k}__e{i:02d}_deg", np.nan) for i in range(len(CURVE_FRACTIONS))]
            curves.append(c)
        arr = np.asarray(curves, float)
        if np.all(np.isnan(arr)):
            continue
        by_row[row] = arr
    fig = new_figure(figsize=(6.5, 3.6))
    ax = fig.add_subplot(111)
    tt = np.asarray(CURVE_FRACTIONS) * dur
    for row, arr in by_row.items():
        med = np.nanmedian(arr, axis=0)
        p90 = np.nanpercentile(arr, 90, axis=0)
        (ln,) = ax.plot(tt, med, label=f"{row} (median)")
        ax.fill_between(tt, med, p90, color=ln.get_color(), alpha=0.15)
    ax.set_yscale("log")
    ax.set_xlabel("time since the end of the power-up still window, s")
    ax.set_ylabel("attitude error, deg")
    ax.set_title(f"{scenario} — {sensor}: error vs time (band: median..p90)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return save_figure(fig, out_dir, f"ablation_{scenario}_{sensor}")


def run(*, out_dir, quick: bool = False, seeds: int | None = None, workers: int | None = None,
        scenarios: Sequence[str] | None = None, sensors: Sequence[str] | None = None,
        duration_s: float | None = None, seed: int = 0, **_ignored) -> ExperimentResult:
    """Monte Carlo ablation over scenarios × sensor instances; tables and curves into ``out_dir``."""
    from experiments.montecarlo import run_campaign, write_campaign

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    scenarios = tuple(scenarios or SCENARIOS)
    sensors = tuple(sensors or DEFAULT_SENSORS)
    instances = seeds or (2 if quick else DEFAULT_INSTANCES)
    if duration_s is None and quick:
        duration_s = QUICK_DURATION_S
    camp = run_campaign(scenarios=scenarios, sensors=sensors, instances=instances, seed=seed,
                        duration_s=duration_s, workers=workers, task_function=ablation_task,
                        options={"quick": bool(quick)})
    write_campaign(camp, out_dir / "ablation_montecarlo")
    tables, summary = campaign_tables(camp)
    figs = []
    fig_md = []
    for sc in scenarios:
        for se in sensors:
            f = curve_figure(camp, sc, se, out_dir)
            if f:
                figs.append(f)
                fig_md.append(f"![{sc} {se}]({f})")
    md = [
        f"Attitude error of the integrated gyro against the truth, per scenario, over {instances} sensor instances "
        f"of {', '.join(sensors)} (median and 90th percentile). Rows: no correction; all corrections; all but one; one "
        "alone; all with the instance's true parameters; the floor (truth + the recording's own stochastic noise). "
        "Corrections are estimated by the calibration core from separate calibration recordings of the same unit "
        "(rate table, thermal), plus the power-up bias from the still start of the scored recording. Scoring starts "
        "at the end of that still window, from the true attitude. RMS/floor = RMS error over the floor's RMS error "
        "(same instance).\n",
        tables,
        "\n".join(fig_md),
        f"\nPer-instance results: `ablation_montecarlo/` (JSON, CSV). Campaign wall time {camp.wall_s:.1f} s on "
        f"{camp.workers} worker(s) ({camp.backend}).",
    ]
    return ExperimentResult(name="ablation", title="Ablation: attitude drift with and without each correction",
                            markdown="\n".join(md), figures=tuple(figs), summary=summary,
                            wall_s=time.perf_counter() - t0)
