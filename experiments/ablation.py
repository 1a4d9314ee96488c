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
(:class:`gyrocore.calibrator.Calibrator`) from calibration recordings of the same instance (a
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
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.attitude import AttitudeScore, error_angle_rad, integrate_gyro, score_attitude

from .stages import (  # noqa: F401  (the stage helpers, reached as ablation.X by its callers)
    _CAL_KW,
    POWERUP_SEARCH_S,
    POWERUP_WINDOW_S,
    SE_SUFFIX,
    TABLE_EFFECTS,
    THERMAL_EFFECTS,
    THERMAL_NUISANCE,
    _as_stages,
    _stage_from,
    bias_bound_rad_s,
    corrected_gyro,
    powerup_window,
    powerup_windows,
)
from .report import ExperimentResult, md_table, new_figure, save_figure, single_thread_blas
from .calibrators import calibration_recordings, CoreCalibrator, CoreParams, strip_truth
from .montecarlo import run_campaign, TaskResult, write_campaign
from gyrocore.attitude import mahony, tilt_error_rad
from gyrocore.calib.budget import ParameterGroup, predict_error
from gyrocore.noise.model import NoiseModel
from gyrocore.calib.params import load_params, save_params
from gyrocore.data.recording import atomic_write_text
from sim import scenarios as S

__all__ = [
    "SCENARIOS",
    "CORRECTABLE",
    "present_effects",
    "row_names",
    "corrected_gyro",
    "score_variants",
    "InstanceAblation",
    "ablate_instance",
    "calibrate_core",
    "calibrate_instance",
    "ablation_task",
    "run",
    "CURVE_FRACTIONS",
]

#: Scenarios scored by the ablation (sim.scenarios names).
SCENARIOS = ("static", "static_bumped", "turntable", "thermal", "hover", "power_cycles")

#: Deterministic effects that :func:`gyrocore.effects.registry.correct` can remove.
CORRECTABLE = E.CORRECTABLE

#: Fractions of the scored duration at which error curves are kept (for median curves).
CURVE_FRACTIONS = tuple(np.round(np.linspace(0.0, 1.0, 21), 3))
#: Sensor instances per scenario in the default run, and the --quick duration, s.
DEFAULT_INSTANCES = 12
QUICK_DURATION_S = 20.0
#: ``gyroharness run`` (standard size): units per scenario and scored durations, s (the accuracy
#: contract's short runs, the rate-table run cut to 120 s), with the quick calibration runs
#: (:data:`experiments.calibrators.QUICK_CALIBRATION_S`). With n units the interval [min, max]
#: holds the median with probability 1 − 2·0.5ⁿ (n = 5: 93.8 %).
STANDARD_INSTANCES = 5
STANDARD_DURATIONS_S = {
    "static": 60.0,
    "static_bumped": 30.0,
    "turntable": 120.0,
    "thermal": 300.0,
    "hover": 15.0,
    "power_cycles": 60.0,
}


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
    prediction : gyrocore.calib.budget.ErrorPrediction or None
        Predicted error of the ``all`` row from the calibration's standard errors and the
        noise model the calibration identified (:func:`predict_instance`).
    prediction_true_noise : gyrocore.calib.budget.ErrorPrediction or None
        The same with the unit's *true* noise (simulation only): the contract's quality
        statistic (predicted/floor), which should move with the protocol and the estimator,
        not with the noise identification's own scatter.
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
    prediction: Any = None
    prediction_true_noise: Any = None


def calibrate_core(
    sensor: str,
    seed: int,
    present: Sequence[str],
    *,
    quick: bool = False,
    cache_dir: str | None = None,
    durations_s: tuple[float, float] | None = None,
):
    """The core's calibration of this unit, through the calibrator door.

    The unit's calibration recordings (:func:`experiments.calibrators.calibration_recordings`:
    a ``turntable`` run ``run=1`` and a ``thermal`` run ``run=2``, stripped of their truth by
    :func:`experiments.calibrators.strip_truth`) go to
    ``CoreCalibrator(effects=present).fit`` (:class:`experiments.calibrators.CoreCalibrator`):
    the table effects of :data:`TABLE_EFFECTS` present, then ``bias`` + the present
    :data:`THERMAL_EFFECTS` (+ ``scale`` re-referenced with ``scale_thermal``) on the thermal run
    corrected with stage 1. Returns its :class:`~experiments.calibrators.CoreParams`, cached as
    parameter files in ``cache_dir``.
    """
    import json

    tt = [e for e in TABLE_EFFECTS if e in present]
    th = [e for e in THERMAL_EFFECTS if e in present]
    # a sensor may be a TOML path: keep the key a plain file name inside cache_dir (a path with
    # "/" made Path(cache_dir) / key point outside cache_dir, shared between caches)
    safe = "".join(c if (c.isalnum() or c in "._-") else "_" for c in str(sensor))
    runs = "quick" if quick else "full"
    if durations_s is not None:  # other calibration-run durations (table, thermal), s
        runs = f"{durations_s[0]:g}-{durations_s[1]:g}"
    key = (
        f"{safe}_{seed}_{runs}_{'-'.join(tt)}_{'-'.join(th)}_{_CAL_KW['covariance']}"
        f"_r{_CAL_KW.get('ramp_margin_s', 0):g}"
    )
    paths = None
    if cache_dir:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        paths = [Path(cache_dir) / f"{key}_stage{i}.json" for i in (1, 2)]
        done = Path(cache_dir) / f"{key}.done"
        if done.exists():
            have = json.loads(done.read_text())
            res = tuple(load_params(p) if have[i] else None for i, p in enumerate(paths))
            return CoreParams(
                effects=tuple(present), stages=tuple(_stage_from(r, i + 1) for i, r in enumerate(res)), results=res
            )
    recs = [
        strip_truth(r, references=True)
        for r in calibration_recordings(sensor, seed, quick=quick, durations_s=durations_s)
    ]
    params = CoreCalibrator(effects=present).fit(recs)
    if paths:
        for p, r in zip(paths, params.results):
            if r is not None:
                save_params(r, p)
        atomic_write_text(done, json.dumps([r is not None for r in params.results]))
    return params


def calibrate_instance(
    sensor: str, seed: int, present: Sequence[str], *, quick: bool = False, cache_dir: str | None = None
) -> list[dict]:
    """What a user would get for this unit: the stages of :func:`calibrate_core` (for :func:`corrected_gyro`)."""
    return list(calibrate_core(sensor, seed, present, quick=quick, cache_dir=cache_dir).stages)


#: Mahony proportional gain for the tilt rows, 1/s (tilt time constant ≈ 1 s), and its gate:
#: the accelerometer is used only while | |f| − g | < 1 m/s².
MAHONY_KP_PER_S = 1.0


def _tilt_rows(rec, truth, w_all: np.ndarray, start: int, kp: float) -> dict:
    t = rec.t_s[start:]
    q_true = truth.q_SW_wxyz[start:]
    q_int = integrate_gyro(t, w_all[start:], q0_wxyz=q_true[0])
    q_mah, _ = mahony(t, w_all[start:], rec.accel_m_s2[start:], q0_wxyz=q_true[0], kp_per_s=kp, accel_gate_m_s2=1.0)
    out = {}
    for name, q in (("all (tilt)", q_int), ("all + Mahony (tilt)", q_mah)):
        e = tilt_error_rad(q, q_true)
        out[name] = (score_attitude(t, e), e)
    return out


def ablate_instance(
    scenario: str,
    *,
    sensor: str = "icm42688p",
    seed: int = 0,
    duration_s: float | None = None,
    quick: bool = False,
    calibration=None,
    cache_dir: str | None = None,
    mahony_kp_per_s: float | None = MAHONY_KP_PER_S,
    predict: bool = True,
    powerup_window_s: float | None = None,
) -> InstanceAblation:
    """Run the whole ablation for one instance of ``sensor`` in ``scenario`` (needs :mod:`sim`).

    ``calibration`` (stages, see :func:`corrected_gyro`) skips the calibration runs. With
    ``mahony_kp_per_s`` two extra rows score the *tilt* error (roll/pitch only) of the
    all-corrections gyro: integrated alone (``all (tilt)``) and fused with the accelerometer's
    view of gravity by :func:`gyrocore.attitude.mahony` (``all + Mahony (tilt)``).
    """
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = S.simulate(scenario, sensor=sensor, duration_s=duration_s, seed=seed, run=0)
    rec, truth, p_true = res.recording, res.truth, res.params_true
    present = present_effects(p_true)
    notes: list[str] = list(res.notes)

    if calibration is None:
        core_params = calibrate_core(sensor, seed, present, quick=quick, cache_dir=cache_dir)
        calibration = list(core_params.stages)
    else:
        core_params = CoreParams(
            effects=tuple(present), stages=(calibration,) if isinstance(calibration, Mapping) else tuple(calibration)
        )
    stages = _as_stages(calibration)
    have = {tog for st in stages for (_, _, tog) in st.values()}
    estimated = tuple(e for e in present if e in have or e == "bias")
    missing = [e for e in present if e not in estimated]
    if missing:
        notes.append(f"not estimated by the calibration runs: {', '.join(missing)}")
    inp = E.ModelInputs(
        t_s=rec.t_s,
        omega_S_rad_s=None,
        f_S_m_s2=rec.accel_m_s2,
        temp_c=rec.temp_c,
        q_SW_wxyz=truth.q_SW_wxyz,
        t_since_power_up_s=truth.t_since_power_up_s,
    )
    still = powerup_windows(rec, p_true, bias_bound_rad_s=bias_bound_rad_s(sensor), window_s=powerup_window_s)
    n_missing = sum(w is None for _, w in still)
    if n_missing and "bias" in present:
        notes.append(
            f"no still window at {n_missing} of {len(still)} power-up(s): bias there from the calibration "
            "run (a stale turn-on draw)"
        )
    variants: dict[str, np.ndarray] = {}
    for row in row_names(present):
        if row == "none":
            variants[row] = rec.gyro_rad_s
        elif row == "all":  # through the calibrator door, on the recording stripped of its truth
            # the power-up window of the prediction's length (a protocol with another window
            # must be scored with it: before, the all row always took a 2-s window)
            variants[row] = CoreCalibrator(effects=present, powerup_window_s=powerup_window_s).apply(
                strip_truth(rec, references=False), core_params
            )
        elif row.startswith("all but "):
            x = row[len("all but ") :]
            variants[row] = corrected_gyro(rec.gyro_rad_s, inp, calibration, [e for e in present if e != x], still)
        elif row.startswith("only "):
            variants[row] = corrected_gyro(rec.gyro_rad_s, inp, calibration, [row[len("only ") :]], still)
        elif row == "true params":
            ptrue = {e: p_true[e] for e in present if e != "bias"}
            w = E.correct(ptrue, rec.gyro_rad_s, inp) if ptrue else rec.gyro_rad_s.copy()
            if "bias" in present:  # the true per-power-up bias, removed in sensor units before K⁻¹
                w = w - S.true_bias_rad_s(res) @ np.linalg.inv(E.k_matrix(p_true)).T
            variants[row] = w
        elif row == "floor":
            variants[row] = S.floor_gyro(res)
    start = 0 if still[0][1] is None else int(still[0][1].stop)
    sc = score_variants(rec.t_s, truth.q_SW_wxyz, variants, start=start)
    if mahony_kp_per_s and rec.accel_m_s2 is not None:
        sc.update(_tilt_rows(rec, truth, variants["all"], start, mahony_kp_per_s))
    t = rec.t_s[start:] - rec.t_s[start]
    idx = np.clip(np.round(np.asarray(CURVE_FRACTIONS) * (t.size - 1)).astype(int), 0, t.size - 1)
    prediction = prediction_true = None
    if predict:
        nm = identified_noise(core_params, float(rec.rate_hz))
        if nm is None:
            notes.append("prediction: no identified noise model in the calibration; the unit's true noise is used")
        prediction = predict_instance(res, calibration, present, still, start, noise=nm)
        prediction_true = predict_instance(res, calibration, present, still, start) if nm is not None else prediction
    return InstanceAblation(
        scenario=scenario,
        sensor=sensor,
        seed=seed,
        present=tuple(present),
        estimated=estimated,
        scores={k: v[0] for k, v in sc.items()},
        t_s=t[idx],
        errors_deg={k: np.degrees(v[1][idx]) for k, v in sc.items()},
        notes=tuple(notes),
        prediction=prediction,
        prediction_true_noise=prediction_true,
    )


# ------------------------------------------------------------------ predicted drift
#: Effects the calibration never corrects but that are part of every gyro's achievable error
#: (the on-chip low-pass is not invertible): predicted, not counted against the calibration.
IRREDUCIBLE = ("lowpass",)


def calibration_groups(calibration, present: Sequence[str]) -> list:
    """One :class:`gyrocore.calib.budget.ParameterGroup` per estimated effect of the ``all`` row.

    The power-up bias replaces every stage's ``bias`` (its own error is the window's noise,
    predicted from the noise model). An effect fitted again by a later stage (``scale``
    re-referenced by the thermal run) is superseded: the later fit estimates the residual left
    by the earlier one, so only its error remains (to first order).
    """
    last: dict[str, tuple[dict, dict]] = {}
    for st in _as_stages(calibration):
        for key, (eff, pd, tog) in st.items():
            if eff == "bias" or tog not in present:
                continue
            schema = E.PARAM_SCHEMA[eff]
            params = {k: np.asarray(v, float) for k, v in pd.items() if k in schema}
            se = {k[: -len(SE_SUFFIX)]: np.asarray(v, float) for k, v in pd.items() if k.endswith(SE_SUFFIX)}
            last[eff] = (params, se)
    return [ParameterGroup(name=eff, params={eff: p}, stderr={eff: se}) for eff, (p, se) in last.items()]


def uncorrected_rate_errors(res, present: Sequence[str], estimated: Sequence[str]) -> dict[str, np.ndarray]:
    """Deterministic rate errors left in the ``all`` gyro, rad/s (N, 3), from the true parameters:
    present effects the calibration did not estimate, and (key ``lowpass``) the on-chip
    low-pass, D(ω) − ω per power-up (the filter restarts from steady state)."""
    from scipy import signal

    truth, p_true, rec = res.truth, res.params_true, res.recording
    w = np.asarray(truth.omega_S_rad_s, float)
    inp = E.ModelInputs(
        t_s=rec.t_s,
        omega_S_rad_s=w,
        f_S_m_s2=np.asarray(truth.f_S_m_s2, float),
        temp_c=np.asarray(truth.temp_c, float),
        q_SW_wxyz=truth.q_SW_wxyz,
        t_since_power_up_s=truth.t_since_power_up_s,
    )
    out = {}
    for e in present:
        if e in estimated or e == "bias":
            continue
        out[e] = E.deterministic({e: p_true[e]}, inp) - w
    if "lowpass" in p_true:
        fc = float(np.asarray(p_true["lowpass"]["bandwidth_hz"]))
        b, a = signal.butter(2, fc, fs=rec.rate_hz)
        z0 = signal.lfilter_zi(b, a)
        d = np.empty_like(w)
        pu = np.asarray(truth.power_up_index)
        edges = np.concatenate([[0], np.flatnonzero(np.diff(pu) != 0) + 1, [w.shape[0]]])
        for lo, hi in zip(edges[:-1], edges[1:]):
            for i in range(3):
                x = w[lo:hi, i]
                d[lo:hi, i] = signal.lfilter(b, a, x, zi=z0 * x[0])[0] - x
        out["lowpass"] = d
    return out


def identified_noise(core_params, rate_hz: float, *, slow_from_longest: bool = True):
    """The noise model identified by the calibration (:class:`gyrocore.noise.model.NoiseModel`), None
    when the calibration carries none.

    White level: that of the calibration run whose sample rate is ``rate_hz`` (it includes that
    rate's quantization noise; the table run is 1 kHz, the thermal run 100 Hz), else the first
    one with a model. Slow terms (flicker B, rate random walk K, Gauss–Markov σ, τc) — the same
    sensor property at any rate — with ``slow_from_longest`` from the calibration run with the
    longest record (n_samples / rate; the 900-s thermal run against the 387-s table run).

    Why: the table fit's residual is a regression residual, r = (I − H)·noise, and
    its regressors are piecewise constant over the six ≈ 65-s mounts (bias, and the
    g-sensitivity columns: gravity is fixed in the sensor frame while the table turns about the
    vertical), so the fit absorbs most of the mount-to-mount wander of the slow noise — exactly
    the octaves (τ ≈ 30–130 s) that carry B in a 387-s record. GMWM on it found B² low
    (B/B_true 0.86 on average over fresh unit-axes, one in 16 with no flicker at all) and the
    static prediction E[r²] 1.06–1.10. The thermal run's regressors are smooth over 900 s
    (a low-order temperature polynomial, scale × rate): its B/B_true averages ≈ 1 and its
    interval is narrower (χ² pivot dof ≈ 50–90 against 15–45); docs/accuracy.md.
    """
    results = [r for r in (getattr(core_params, "results", None) or ()) if r is not None and r.noise_model]
    if not results:
        return None
    at_rate = [r for r in results if abs(float(r.noise_model.get("rate_hz", np.nan)) - rate_hz) <= 1e-3 * rate_hz]
    src = at_rate[0] if at_rate else results[0]
    nm = src.noise()
    if slow_from_longest and len(results) > 1:

        def record_s(r):
            rate = float(r.noise_model.get("rate_hz", np.nan))
            return float(getattr(r, "n_samples", 0) or 0) / rate if rate > 0 else 0.0

        longest = max(results, key=record_s)
        if longest is not src and record_s(longest) > record_s(src):
            from dataclasses import replace

            slow = longest.noise()
            nm = replace(
                nm,
                bias_instability_rad_s=slow.bias_instability_rad_s,
                rrw_rad_per_s_sqrt_s=slow.rrw_rad_per_s_sqrt_s,
                correlated_sigma_rad_s=slow.correlated_sigma_rad_s,
                correlated_tau_c_s=slow.correlated_tau_c_s,
            )
    return nm


def predict_instance(res, calibration, present: Sequence[str], still, start: int, *, noise=None):
    """Predicted attitude error of the ``all`` row (:func:`gyrocore.calib.budget.predict_error`).

    Noise: ``noise`` (a :class:`gyrocore.noise.model.NoiseModel`: the model the calibration
    identified on its own residual, :func:`identified_noise`); None: the unit's true noise
    terms (simulation only).
    Parameter errors: the calibration's standard errors (diagonal). Power-up bias: the still
    windows actually used. Uncorrected: present effects the calibration did not estimate
    (reported, not predicted) and the low-pass (predicted: no correction removes it).
    """
    rec, truth, p_true = res.recording, res.truth, res.params_true
    groups = calibration_groups(calibration, present)
    estimated = [g.name for g in groups]
    inp = E.ModelInputs(
        t_s=rec.t_s,
        omega_S_rad_s=np.asarray(truth.omega_S_rad_s, float),
        f_S_m_s2=np.asarray(truth.f_S_m_s2, float),
        temp_c=np.asarray(truth.temp_c, float),
        q_SW_wxyz=truth.q_SW_wxyz,
        t_since_power_up_s=truth.t_since_power_up_s,
    )
    stale = None
    if "bias" in p_true:
        stale = np.asarray(p_true["bias"].get("turn_on_sigma_rad_s", np.zeros(3)), float) * math.sqrt(2.0)
    unc = uncorrected_rate_errors(res, present, estimated)
    # Irreducible and exact: the scorer's integrator on the true rate (the floor's own error;
    # not zero when the truth is sampled at the output rate, e.g. 100 Hz) and on the true rate
    # plus the low-pass error (minus its window mean, as the power-up bias removes it).
    w_true = np.asarray(truth.omega_S_rad_s, float)
    d = np.zeros_like(w_true)
    for key in IRREDUCIBLE:
        if key in unc:
            d = d + unc.pop(key)
    for seg, win in still:
        if win is not None:
            d[seg] = d[seg] - d[win].mean(axis=0)
    t_sc, q_sc = rec.t_s[start:], truth.q_SW_wxyz[start:]
    e_int = error_angle_rad(integrate_gyro(t_sc, w_true[start:], q0_wxyz=q_sc[0]), q_sc)
    e_irr = error_angle_rad(integrate_gyro(t_sc, (w_true + d)[start:], q0_wxyz=q_sc[0]), q_sc)
    if noise is None:
        noise = NoiseModel.from_params(p_true)
    return predict_error(
        inp,
        start=start,
        segments=still,
        noise=noise,
        groups=groups,
        uncorrected=unc,
        stale_bias_sigma_rad_s=stale,
        exact_error_rad={"irreducible (low-pass, integration)": e_irr},
        floor_exact_error_rad={"integration": e_int},
    )


# ------------------------------------------------------------------ Monte Carlo task
def _key(row: str) -> str:
    """Metric-name form of a row label (spaces -> '-'; effect names have no '-')."""
    return row.replace(" ", "-")


def _label(key: str) -> str:
    return key.replace("-", " ")


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
            if "(tilt)" in row:  # tilt-only errors are not comparable with the full-angle floor
                continue
            m[f"{_key(row)}__over_floor"] = s.rms_error_deg / fl.rms_error_deg if fl.rms_error_deg > 0 else float("nan")
    pr = ab.prediction
    if pr is not None:
        all_rms = ab.scores["all"].rms_error_deg
        m["pred__rms_deg"] = pr.rms_predicted_deg
        m["pred__final_deg"] = pr.final_predicted_deg
        m["pred__final_sd_deg2"] = math.degrees(math.degrees(pr.final_sd_rad2))
        m["pred__rms_with_uncorrected_deg"] = pr.rms_with_uncorrected_deg
        m["pred-floor__rms_deg"] = pr.rms_floor_deg
        m["pred-floor__final_deg"] = pr.final_floor_deg
        m["all__over_pred"] = all_rms / pr.rms_predicted_deg if pr.rms_predicted_deg > 0 else float("nan")
        if fl is not None and pr.rms_floor_deg > 0:
            m["floor__over_pred-floor"] = fl.rms_error_deg / pr.rms_floor_deg
        for comp, deg in pr.budget_deg().items():
            m[f"budget__{_key(comp)}__deg"] = deg
        pt = getattr(ab, "prediction_true_noise", None)
        if pt is not None:
            m["pred-true-noise__rms_deg"] = pt.rms_predicted_deg
            m["pred-true-noise-floor__rms_deg"] = pt.rms_floor_deg
    for row in CURVE_ROWS:
        if row in ab.errors_deg:
            for i, v in enumerate(ab.errors_deg[row]):
                m[f"{_key(row)}__e{i:02d}_deg"] = float(v)
    return m


def ablation_task(task) -> "Any":
    """Monte Carlo task function (:mod:`experiments.montecarlo`): one instance through the ablation.

    Options (``task.options``): ``quick`` (bool), ``cache_dir`` (calibration cache),
    ``durations`` (tuple of (scenario, seconds), used when the task has no duration).
    """
    import warnings

    opts = dict(task.options)
    dur = task.duration_s if task.duration_s is not None else dict(opts.get("durations", ())).get(task.scenario)
    with warnings.catch_warnings(), single_thread_blas():
        warnings.simplefilter("ignore")
        ab = ablate_instance(
            task.scenario,
            sensor=task.sensor,
            seed=task.seed,
            duration_s=dur,
            quick=bool(opts.get("quick", False)),
            cache_dir=opts.get("cache_dir"),
        )
    return TaskResult.from_task(task, instance_metrics(ab))


# ------------------------------------------------------------------ report
DEFAULT_SENSORS = ("icm42688p",)


def _rows_in(campaign, scenario: str, sensor: str) -> list[str]:
    """Row keys present in the campaign for (scenario, sensor), table order."""
    keys = []
    for s in campaign.summary:
        if (
            s.scenario == scenario
            and s.sensor == sensor
            and s.metric.endswith("__final_deg")
            and not s.metric.startswith("pred")
        ):  # predictions are not correction rows
            keys.append(s.metric[: -len("__final_deg")])
    order = {"none": 0, "all": 1, "true-params": 96, "floor": 97, "all-(tilt)": 98, "all-+-Mahony-(tilt)": 99}
    return sorted(keys, key=lambda k: (order.get(k, 2 if k.startswith("all-but") else 3), keys.index(k)))


def campaign_tables(campaign) -> tuple[str, dict]:
    """Markdown tables (median and p90 per row) and a JSON-able summary of an ablation campaign."""
    md, summary = [], {}
    for sc in campaign.scenarios:
        for se in campaign.sensors:
            tab = {s.metric: s for s in campaign.summary if s.scenario == sc and s.sensor == se}
            if not tab:
                continue
            keys = _rows_in(campaign, sc, se)
            present = [
                e for e in CORRECTABLE if tab.get(f"present__{e}") is not None and tab[f"present__{e}"].median > 0
            ]
            dur = tab["duration_s"].median if "duration_s" in tab else float("nan")
            n = tab[f"{keys[0]}__final_deg"].n if keys else 0
            md.append(f"### {sc} — {se}\n")
            md.append(f"{n} sensor instances, {dur:.0f} s scored; effects present: {', '.join(present) or 'none'}.\n")
            rows = []
            for k in keys:
                f, r, d = tab[f"{k}__final_deg"], tab[f"{k}__rms_deg"], tab[f"{k}__drift_deg_per_min"]
                of = tab.get(f"{k}__over_floor")
                rows.append(
                    (
                        _label(k),
                        f.median,
                        f.p90,
                        r.median,
                        r.p90,
                        d.median,
                        d.p90,
                        of.median if of else float("nan"),
                        of.p90 if of else float("nan"),
                    )
                )
            md.append(
                md_table(
                    [
                        "correction",
                        "final °, median",
                        "final °, p90",
                        "RMS °, median",
                        "RMS °, p90",
                        "°/min, median",
                        "°/min, p90",
                        "RMS/floor, median",
                        "RMS/floor, p90",
                    ],
                    rows,
                )
            )
            md.append("")
            summary[f"{sc}/{se}"] = {
                k: {
                    "final_deg_median": tab[f"{k}__final_deg"].median,
                    "final_deg_p90": tab[f"{k}__final_deg"].p90,
                    "rms_deg_median": tab[f"{k}__rms_deg"].median,
                    "rms_deg_p90": tab[f"{k}__rms_deg"].p90,
                }
                for k in keys
                if k in ("none", "all", "true-params", "floor")
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
        med = np.nanmedian(arr, axis=0)[1:]  # t = 0 is 0 by construction (log axis)
        p90 = np.nanpercentile(arr, 90, axis=0)[1:]
        (ln,) = ax.plot(tt[1:], med, marker=".", label=f"{row} (median)")
        ax.fill_between(tt[1:], med, p90, color=ln.get_color(), alpha=0.15)
    ax.set_yscale("log")
    ax.set_xlabel("time since the end of the power-up still window, s")
    ax.set_ylabel("attitude error, deg")
    ax.set_title(f"{scenario} — {sensor}: error vs time (band: median..p90)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return save_figure(fig, out_dir, f"ablation_{scenario}_{sensor}")


def prediction_summary(campaign) -> dict:
    """``{scenario: {"rms_all_deg", "rms_predicted_deg", "rms_floor_deg", "budget": {component: deg}, …}}``:
    medians over the instances (first sensor of each scenario), plus the calibration check
    mean of (measured/predicted)² with its standard error and the median ratio."""
    out = {}
    for sc in campaign.scenarios:
        ms = [t.metrics_dict for t in campaign.tasks if t.scenario == sc]
        ms = [m for m in ms if "pred__rms_deg" in m]
        if not ms:
            continue

        def med(k):
            x = np.array([m.get(k, np.nan) for m in ms], float)
            return float(np.nanmedian(x)) if np.any(np.isfinite(x)) else float("nan")

        r = np.array([m["all__over_pred"] for m in ms], float)
        r = r[np.isfinite(r)]
        comps = [k for k in ms[0] if k.startswith("budget__")]
        out[sc] = {
            "instances": len(ms),
            "rms_all_deg": med("all__rms_deg"),
            "rms_predicted_deg": med("pred__rms_deg"),
            "rms_floor_deg": med("floor__rms_deg"),
            "rms_floor_predicted_deg": med("pred-floor__rms_deg"),
            "final_all_deg": med("all__final_deg"),
            "final_predicted_deg": med("pred__final_deg"),
            "measured_over_predicted_median": float(np.median(r)) if r.size else float("nan"),
            "measured2_over_predicted2_mean": float(np.mean(r**2)) if r.size else float("nan"),
            "measured2_over_predicted2_se": float(np.std(r**2, ddof=1) / np.sqrt(r.size))
            if r.size > 1
            else float("nan"),
            # simulation only: E[r² | unit] = (prediction with the unit's true noise / with the
            # identified noise)², the expectation of r² given the calibration, free of the χ²
            # scatter of one run's error (docs/accuracy.md, "Is the prediction calibrated?")
            "expected_r2_given_unit_mean": _expected_r2(ms),
            "budget": {_label(k[len("budget__") : -len("__deg")]): med(k) for k in comps},
        }
    return out


def _expected_r2(ms: Sequence[Mapping[str, float]]) -> float:
    x = np.array(
        [
            (m["pred-true-noise__rms_deg"] / m["pred__rms_deg"]) ** 2
            for m in ms
            if m.get("pred__rms_deg", 0) > 0 and m.get("pred-true-noise__rms_deg", 0) > 0
        ],
        float,
    )
    return float(x.mean()) if x.size else float("nan")


def budget_markdown(pred: Mapping[str, Mapping]) -> str:
    """Budget table: one row per scenario, the median RMS-equivalent share of each component."""
    comps: list[str] = []
    for v in pred.values():
        for c in v["budget"]:
            if c not in comps:
                comps.append(c)
    comps = [c for c in comps if any(abs(v["budget"].get(c, 0.0)) >= 5e-4 for v in pred.values())]
    head = ["scenario", "measured RMS °", "predicted RMS °", "floor RMS °", "mean (meas/pred)² ± se"] + comps
    rows = []
    for sc, v in pred.items():
        rows.append(
            [
                sc,
                v["rms_all_deg"],
                v["rms_predicted_deg"],
                v["rms_floor_deg"],
                f"{v['measured2_over_predicted2_mean']:.2f} ± {v['measured2_over_predicted2_se']:.2f}",
            ]
            + [_budget_cell(v["budget"].get(c, 0.0)) for c in comps]
        )
    return md_table(head, rows)


def _budget_cell(share_deg: float) -> float | str:
    """A budget share for the table: shares below 1e-6 ° are rounding of an exactly-zero
    sensitivity (a parameter the scenario's motion does not excite: 1e-14 ° is float64 noise on
    a ~1° total), printed ``0`` instead of ``2.07e-14``."""
    return 0.0 if abs(share_deg) < 1e-6 else share_deg


def budget_figure(pred: Mapping[str, Mapping], out_dir, name: str = "ablation_budget") -> str | None:
    """Stacked bars per scenario: each component's share of the predicted mean squared error
    (% of the predicted total; a negative share below zero), with the measured median RMS² as a
    star on the same scale (100 % = measured as predicted)."""
    if not pred:
        return None
    comps: list[str] = []
    for v in pred.values():
        for c in v["budget"]:
            if c not in comps:
                comps.append(c)
    fig = new_figure(figsize=(10.0, 4.4))
    ax = fig.add_subplot(111)
    names = list(pred)
    x = np.arange(len(names))
    tot = np.array([pred[n]["rms_predicted_deg"] ** 2 for n in names])
    pos = np.zeros(len(names))
    neg = np.zeros(len(names))
    for c in comps:
        v = np.array([np.sign(pred[n]["budget"].get(c, 0.0)) * pred[n]["budget"].get(c, 0.0) ** 2 for n in names])
        v = 100.0 * v / np.where(tot > 0, tot, np.nan)
        if np.all(np.abs(np.nan_to_num(v)) < 0.5):
            continue
        base = np.where(v >= 0, pos, neg)
        ax.bar(x, v, bottom=base, label=c, width=0.6)
        pos = pos + np.where(v >= 0, v, 0)
        neg = neg + np.where(v < 0, v, 0)
    ax.plot(
        x,
        [100.0 * pred[n]["rms_all_deg"] ** 2 / pred[n]["rms_predicted_deg"] ** 2 for n in names],
        "k*",
        ms=10,
        label="measured RMS² (median) / predicted",
    )
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(x)
    ax.set_xticklabels([f"{n}\n{pred[n]['rms_predicted_deg']:.3g}°" for n in names], fontsize=8)
    ax.set_ylabel("share of the predicted mean squared error, %")
    ax.set_title("Predicted error budget per scenario (medians over units; under the name: predicted RMS)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=6, ncol=2, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    return save_figure(fig, out_dir, name)


def run(
    *,
    out_dir,
    quick: bool = False,
    seeds: int | None = None,
    workers: int | None = None,
    scenarios: Sequence[str] | None = None,
    sensors: Sequence[str] | None = None,
    duration_s: float | None = None,
    seed: int = 0,
    size: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    **_ignored,
) -> ExperimentResult:
    """Monte Carlo ablation over scenarios × sensor instances; tables and curves into ``out_dir``.

    ``size`` (``gyroharness run``): ``"quick"`` (= ``quick``), ``"standard"`` (:data:`STANDARD_INSTANCES`
    units, the quick calibration runs, :data:`STANDARD_DURATIONS_S`) or ``"full"`` (default: the
    scenarios' own durations, full calibration runs, :data:`DEFAULT_INSTANCES` units).
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    size = size or ("quick" if quick else "full")
    quick = size == "quick"
    scenarios = tuple(scenarios or SCENARIOS)
    sensors = tuple(sensors or DEFAULT_SENSORS)
    instances = seeds or {"quick": 2, "standard": STANDARD_INSTANCES}.get(size, DEFAULT_INSTANCES)
    if duration_s is None and quick:
        duration_s = QUICK_DURATION_S
    durations = tuple(STANDARD_DURATIONS_S.items()) if size == "standard" and duration_s is None else ()
    import shutil
    import tempfile

    cache = tempfile.mkdtemp(prefix="gyroharness-calcache-")
    try:
        opts = {"quick": bool(quick or size == "standard"), "cache_dir": cache}
        if durations:
            opts["durations"] = durations
        camp = run_campaign(
            scenarios=scenarios,
            sensors=sensors,
            instances=instances,
            seed=seed,
            duration_s=duration_s,
            workers=workers,
            task_function=ablation_task,
            options=opts,
            progress=progress or False,
        )
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    write_campaign(camp, out_dir / "ablation_montecarlo")
    tables, summary = campaign_tables(camp)
    pred = prediction_summary(camp)
    summary["scenarios"] = pred
    figs = []
    fig_md = []
    bf = budget_figure(pred, out_dir)
    if bf:
        figs.append(bf)
    for sc in scenarios:
        for se in sensors:
            f = curve_figure(camp, sc, se, out_dir)
            if f:
                figs.append(f)
                fig_md.append(f"![{sc} {se}]({f})")
    md = [
        _units_sentence(instances),
        f"Attitude error of the integrated gyro against the truth, per scenario, over {instances} sensor instances "
        f"of {', '.join(sensors)} (median and 90th percentile). Rows: no correction; all corrections; all but one; one "
        "alone; all with the instance's true parameters; the floor (truth + the recording's own stochastic noise). "
        "Corrections are estimated by the calibration core from separate calibration recordings of the same unit "
        "(rate table, thermal), plus the power-up bias from the still start of the scored recording. Scoring starts "
        "at the end of that still window, from the true attitude. RMS/floor = RMS error over the floor's RMS error "
        "(same instance). The last two rows score only the *tilt* (roll/pitch) error of the all-corrections gyro: "
        f"integrated alone, and fused with the accelerometer's view of gravity by a Mahony filter (kp = "
        f"{MAHONY_KP_PER_S:g}/s, accelerometer used while | |f| − g | < 1 m/s²) — the heading it cannot help.\n",
        tables,
        "\n".join(fig_md),
        "\n### Predicted drift and error budget\n\nPredicted RMS error of the all-corrections row from the "
        "calibration's own standard errors, the noise (floor terms; the power-up window's noise, signed: negative "
        "where the window mean removes more slow noise than it adds) and the uncorrected terms "
        "(gyrocore.calib.budget; docs/accuracy.md). Medians over units, degrees (RMS-equivalent shares: their squares "
        "add up).\n",
        budget_markdown(pred),
        f"\n![budget]({bf})" if bf else "",
        f"\nPer-instance results: `ablation_montecarlo/` (JSON, CSV). Campaign wall time {camp.wall_s:.1f} s on "
        f"{camp.workers} worker(s) ({camp.backend}).",
    ]
    return ExperimentResult(
        name="ablation",
        title="Ablation: attitude drift with and without each correction",
        markdown="\n".join(md),
        figures=tuple(figs),
        summary=summary,
        wall_s=time.perf_counter() - t0,
    )


def _units_sentence(n: int) -> str:
    """What n units support: the distribution-free interval of a median and the sign test of a row pair."""
    cover = 1.0 - 2.0 * 0.5**n
    return (
        f"**Units and intervals.** {n} sensor units per scenario (each its own calibration runs and power-up). "
        f"A median over {n} units lies between the smallest and the largest unit's value with probability "
        f"{100 * cover:.1f} % (order statistics, no distribution assumed), so a correction whose median is "
        f"outside the other row's [min, max] differs at that confidence; a row better than another in all "
        f"{n} units is so at one-sided p = {0.5**n:.3g} (sign test). The p90 of {n} units is their "
        + ("largest value. " if n < 10 else "second largest value. ")
        + "`gyroharness run --full` runs 12 units at the scenarios' full durations.\n"
    )


# ------------------------------------------------------------------ accuracy contract
#: Short scored runs of the CI accuracy contract (tests/experiments/test_accuracy_contract.py),
#: with the quick calibration runs. s.
CONTRACT_DURATIONS_S = {
    "static": 60.0,
    "static_bumped": 30.0,
    "turntable": 387.0,
    "thermal": 300.0,
    "hover": 15.0,
    "power_cycles": 60.0,
}
#: The contract uses the full calibration runs (a quick 300-s thermal run makes scale_thermal
#: worse than nothing: the contract would then pin a bad calibration).
CONTRACT_QUICK_CALIBRATION = False
CONTRACT_SENSOR = "icm42688p"
#: An effect "pays off" in a scenario if omitting it raised the RMS error by this factor in
#: every Monte Carlo instance.
PAYS_OFF_MIN_RATIO = 1.05


def contract_campaign(*, instances: int, seed: int = 1, workers: int | None = None, progress: bool = False):
    """The Monte Carlo behind the accuracy contract: every scenario, short runs, quick calibration."""
    import shutil
    import tempfile

    cache = tempfile.mkdtemp(prefix="gyroharness-calcache-")
    try:
        return run_campaign(
            scenarios=SCENARIOS,
            sensors=(CONTRACT_SENSOR,),
            instances=instances,
            seed=seed,
            duration_s=None,
            workers=workers,
            task_function=ablation_task,
            progress=progress,
            options={
                "quick": CONTRACT_QUICK_CALIBRATION,
                "cache_dir": cache,
                "durations": tuple(sorted(CONTRACT_DURATIONS_S.items())),
            },
        )
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def contract_thresholds(campaign, *, n_sigma: float = 4.0) -> dict:
    """Thresholds from a contract campaign, per scenario.

    For a metric x > 0 that varies over sensor instances, log x is close to normal (products of
    independent error sources); the bound exp(mean(log x) + n_sigma·sd(log x)) is exceeded by
    a new instance with probability ≈ Φ(−n_sigma) (3e-5 for 4σ) — a CI failure then means the
    correction stopped paying off, not bad luck. Returned per scenario:

    * ``k_all_over_floor``: bound on RMS(all) / RMS(floor);
    * ``all_final_deg``: bound on the final error with all corrections, degrees;
    * ``pays_off``: effects whose omission raised the RMS error by ≥ 5 % in *every* instance
      (r = RMS(all but X) / RMS(all) ≥ :data:`PAYS_OFF_MIN_RATIO`; r is bounded below near 1
      and skewed, so no parametric tail is claimed). The contract requires r > 1 for them —
      the 5 % margin keeps a working correction from failing it. Effects present but below
      that are in ``negligible`` with their median r.
    """
    out = {}
    for sc in campaign.scenarios:
        tasks = [t.metrics_dict for t in campaign.tasks if t.scenario == sc]
        if not tasks:
            continue

        def col(k):
            return np.array([m.get(k, np.nan) for m in tasks], float)

        def bound(x):
            lx = np.log(x[np.isfinite(x) & (x > 0)])
            return float(np.exp(lx.mean() + n_sigma * lx.std(ddof=1))) if lx.size > 2 else float("nan")

        ratio = col("all__rms_deg") / col("floor__rms_deg")
        pays, negl = [], {}
        for e in CORRECTABLE:
            k = f"all-but-{e}__rms_deg"
            if k not in tasks[0]:
                continue
            r = col(k) / col("all__rms_deg")
            r = r[np.isfinite(r)]
            if r.size > 2 and r.min() >= PAYS_OFF_MIN_RATIO:
                pays.append(e)
            else:
                negl[e] = float(np.median(r)) if r.size else float("nan")
        out[sc] = {
            "instances": len(tasks),
            "k_all_over_floor": bound(ratio),
            "ratio_median": float(np.nanmedian(ratio)),
            "ratio_max": float(np.nanmax(ratio)),
            "all_final_deg": bound(col("all__final_deg")),
            "all_final_median_deg": float(np.nanmedian(col("all__final_deg"))),
            "all_final_max_deg": float(np.nanmax(col("all__final_deg"))),
            "pays_off": pays,
            "negligible": negl,
        }
    return out


# ------------------------------------------------------------------ drift contract
#: One-sided tail probability of each band of the drift contract (6 scenarios × 3 tails + the
#: pooled honesty's 2 tails: 20 tails; a fresh, correct calibration fails CI with probability
#: ≤ 20·α).
DRIFT_TAIL_ALPHA = 1e-4
#: Smallest margin of the quality bound (log): where the Monte Carlo spread of predicted/floor
#: is ~0 (it does not depend on the noise draw), the bound would otherwise pin the
#: implementation (block grid, window search) instead of the calibration: 5 %.
DRIFT_QUALITY_MIN_MARGIN = math.log(1.05)
#: Completeness: the budget's uncorrected terms (present effects the calibration did not
#: estimate, from the true parameters) may add at most 5 % to the predicted RMS error.
DRIFT_COMPLETENESS_MAX = 1.05
#: Confidence with which the Gamma shape of r² behind the honesty band is *not* over-estimated
#: from the Monte Carlo's units (the band uses the lower limit: a wider band; see
#: :func:`r2_shape`).
DRIFT_SHAPE_CONFIDENCE = 0.9


def _quality(m: Mapping[str, float]) -> float:
    """log(predicted / floor RMS) of one unit, both with the unit's true noise when the metrics
    have them (simulation: the statistic then moves only with the protocol and the
    estimator's standard errors; with the identified noise its spread over units was 0.05–0.13
    in log from the identification's own scatter, which hid a halved still window)."""
    if m.get("pred-true-noise-floor__rms_deg", 0) > 0:
        return math.log(m["pred-true-noise__rms_deg"] / m["pred-true-noise-floor__rms_deg"])
    return math.log(m["pred__rms_deg"] / m["pred-floor__rms_deg"])


def _r2(metrics: Sequence[Mapping[str, float]]) -> np.ndarray:
    """r² = (measured / predicted RMS error of the all row)² of each unit (finite ones)."""
    r = np.array([m.get("all__over_pred", np.nan) for m in metrics], float)
    return r[np.isfinite(r)] ** 2


def drift_statistics(metrics: Sequence[Mapping[str, float]]) -> dict:
    """The statistics of the drift contract over a set of units (one scenario's metrics).

    * ``honesty_r2``: mean over units of r² = (measured RMS / predicted RMS)² of the all row.
      The prediction is the *expected* mean-square error, so a calibrated prediction has
      E[r²] = 1 exactly, whatever the spread (a mean of log r or a median of r is not centred
      on 0 or 1: r² ~ χ²_ν/ν has E log r = ½(ψ(ν/2) − log(ν/2)) < 0 and median < 1). Up when the
      estimator is worse than it claims (an effect dropped, a wrong model), down when it
      claims too much uncertainty (an inflated standard error). ``honesty``: the mean of
      log r (reported, not tested);
    * ``quality``: mean over units of log(predicted RMS / predicted floor RMS) (with the true
      noise in simulation, :func:`_quality`) — how far the calibration protocol and estimator
      leave the attitude above the noise floor; nearly deterministic per scenario (it moves
      with the standard errors and the still window, not with the noise draw), so its band is
      tight;
    * ``completeness``: the largest ratio over units of the predicted RMS with the uncorrected
      terms to the predicted RMS.
    """
    r2 = _r2(metrics)
    q = np.array([_quality(m) for m in metrics if m.get("pred-floor__rms_deg", 0) > 0])
    c = np.array(
        [m["pred__rms_with_uncorrected_deg"] / m["pred__rms_deg"] for m in metrics if m.get("pred__rms_deg", 0) > 0]
    )
    return {
        "n": int(r2.size),
        "honesty_r2": float(r2.mean()) if r2.size else float("nan"),
        "honesty": float(np.mean(0.5 * np.log(r2))) if r2.size else float("nan"),
        "quality": float(q.mean()) if q.size else float("nan"),
        "completeness": float(c.max()) if c.size else float("nan"),
    }


def r2_shape(
    r2: np.ndarray, *, confidence: float = DRIFT_SHAPE_CONFIDENCE, seed: int = 0, replicates: int = 4000
) -> tuple[float, float]:
    """Gamma shape k of one unit's r² (maximum likelihood, location 0) and its lower limit at
    ``confidence`` (parametric bootstrap: ``replicates`` samples of the same size from
    Gamma(k̂), refitted; the limit is k̂ divided by the ``confidence`` quantile of k̂*/k̂).

    Why a Gamma: r² is a time-mean of |ε|² over the expected value, a positive quadratic form
    in Gaussian errors; Box (1954) — a scaled χ²_ν (a Gamma with shape ν/2) with the first two
    moments — describes it, and the unit-to-unit spread of the prediction's own error widens
    it (a smaller k). The lower limit makes the band wider when 12–32 units leave k uncertain.
    """
    from scipy import stats

    r2 = np.asarray(r2, float)
    r2 = r2[np.isfinite(r2) & (r2 > 0)]
    if r2.size < 3:
        return float("nan"), float("nan")
    k, _loc, _scale = stats.gamma.fit(r2, floc=0.0)
    rng = np.random.default_rng(seed)
    sim = rng.gamma(k, 1.0, size=(replicates, r2.size))
    # MLE of the shape from the sufficient statistic s = log(mean) − mean(log) (Minka 2002):
    # solve log k − ψ(k) = s by Newton from the closed-form start
    s = np.log(sim.mean(axis=1)) - np.log(sim).mean(axis=1)
    kk = (3.0 - s + np.sqrt((s - 3.0) ** 2 + 24.0 * s)) / (12.0 * s)
    from scipy import special

    for _ in range(6):
        kk = kk - (np.log(kk) - special.digamma(kk) - s) / (1.0 / kk - special.polygamma(1, kk))
    ratio = np.quantile(kk / k, confidence)
    return float(k), float(k / ratio)


def drift_thresholds(campaign, *, alpha: float = DRIFT_TAIL_ALPHA) -> dict:
    """The Monte Carlo statistics behind the drift contract, per scenario.

    ``campaign``: a Monte Carlo campaign (tasks with ``metrics_dict``) or a mapping
    ``{scenario: [metrics, …]}``. Per scenario, over its M units:

    * honesty: r² = (measured/predicted RMS)²; its mean (must be ≈ 1: the prediction is
      calibrated) with its standard error, and the Gamma shape of one unit's r² with its lower
      limit (:func:`r2_shape`) — the band of the mean over n fresh units is the Gamma(n·k)
      interval around 1 (:func:`drift_bands`);
    * quality: y = log(predicted/floor RMS), mean and sd; the mean over n fresh units is a
      prediction from a normal sample, (ȳ_n − ȳ)/(s_y·√(1/n + 1/M)) ~ Student t with M − 1 dof,
      bound ȳ + t_{1−α}·s_y·√(1/n + 1/M) (at least :data:`DRIFT_QUALITY_MIN_MARGIN`).
    """
    if isinstance(campaign, Mapping):
        by = {sc: list(ms) for sc, ms in campaign.items()}
    else:
        by = {sc: [t.metrics_dict for t in campaign.tasks if t.scenario == sc] for sc in campaign.scenarios}
    out: dict = {"alpha": float(alpha), "scenarios": {}}
    for i, (sc, ms) in enumerate(by.items()):
        r2 = _r2(ms)
        y = np.array([_quality(m) for m in ms])
        k_mle, k_lo = r2_shape(r2, seed=i)
        out["scenarios"][sc] = {
            "mc_units": int(r2.size),
            "r2_mean": float(r2.mean()),
            "r2_mean_se": float(r2.std(ddof=1) / math.sqrt(r2.size)),
            "r2_shape_mle": k_mle,
            "r2_shape": k_lo,
            "quality_mean": float(y.mean()),
            "quality_sd": float(y.std(ddof=1)),
            "median_measured_over_predicted": float(np.sqrt(np.median(r2))),
        }
    return out


def drift_bands(thresholds: Mapping, scenario: str, n: int) -> dict:
    """Bands of the mean over ``n`` units: honesty (lo, hi) on the mean r², the Gamma(n·k, 1/(n·k))
    quantiles α and 1 − α (mean 1: a calibrated prediction); quality bound (hi) in log units."""
    from scipy import stats

    th = thresholds["scenarios"][scenario]
    a = thresholds["alpha"]
    M = th["mc_units"]
    t = float(stats.t.ppf(1.0 - a, M - 1))
    nk = n * th["r2_shape"]
    return {
        "honesty_r2_lo": float(stats.gamma.ppf(a, nk, scale=1.0 / nk)),
        "honesty_r2_hi": float(stats.gamma.isf(a, nk, scale=1.0 / nk)),
        "quality_hi": th["quality_mean"]
        + max(t * th["quality_sd"] * math.sqrt(1.0 / n + 1.0 / M), DRIFT_QUALITY_MIN_MARGIN),
    }


def pooled_band(thresholds: Mapping, n_by_scenario: Mapping[str, int]) -> tuple[float, float]:
    """(lo, hi) of the mean over scenarios of their mean r² (each Gamma(n_s·k_s), mean 1): the
    Gamma with the same mean (1) and variance Σ 1/(n_s·k_s) / S² (Satterthwaite), quantiles α and 1 − α."""
    from scipy import stats

    S = len(n_by_scenario)
    var = sum(1.0 / (n * thresholds["scenarios"][sc]["r2_shape"]) for sc, n in n_by_scenario.items()) / S**2
    a = thresholds["alpha"]
    return float(stats.gamma.ppf(a, 1.0 / var, scale=var)), float(stats.gamma.isf(a, 1.0 / var, scale=var))


def drift_contract_failures(stats_by_scenario: Mapping[str, Mapping], thresholds: Mapping) -> list[str]:
    """Messages of every failed band (empty: the contract holds). ``stats_by_scenario`` from
    :func:`drift_statistics`; the bands are evaluated for each scenario's number of units."""
    fails = []
    for sc, st in stats_by_scenario.items():
        b = drift_bands(thresholds, sc, st["n"])
        h, q = st["honesty_r2"], st["quality"]
        if not b["honesty_r2_lo"] <= h <= b["honesty_r2_hi"]:
            fails.append(
                f"{sc}: mean (measured/predicted RMS)² {h:.3g} outside [{b['honesty_r2_lo']:.3g}, "
                f"{b['honesty_r2_hi']:.3g}] (mean over {st['n']} units; 1 if the prediction is calibrated)"
            )
        if not q <= b["quality_hi"]:
            fails.append(
                f"{sc}: predicted/floor RMS {math.exp(q):.3g} > {math.exp(b['quality_hi']):.3g} "
                "(calibration protocol or standard errors worse)"
            )
        if st.get("completeness", 1.0) > DRIFT_COMPLETENESS_MAX:
            fails.append(
                f"{sc}: uncorrected effects add ×{st['completeness']:.3g} to the predicted error "
                f"(> {DRIFT_COMPLETENESS_MAX:g}: a present effect was not calibrated)"
            )
    if len(stats_by_scenario) == len(thresholds["scenarios"]) and len(stats_by_scenario) > 1:
        d = float(np.mean([st["honesty_r2"] for st in stats_by_scenario.values()]))
        lo, hi = pooled_band(thresholds, {sc: st["n"] for sc, st in stats_by_scenario.items()})
        if not lo <= d <= hi:
            fails.append(f"all scenarios: mean (measured/predicted RMS)² {d:.3g} outside [{lo:.3g}, {hi:.3g}]")
    return fails
