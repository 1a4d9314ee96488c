"""Experiment ``protocol``: the shortest calibration protocol that reaches a drift target.

"How long must I calibrate for X°?" — answered with the error budget
(:mod:`gyrocore.calib.budget`) on the scored manoeuvre (a 10-min hover), then confirmed by
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
  (:func:`gyrocore.calib.covariance.noise_model_meat`, the same sandwich the calibration reports; its
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
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from experiments.montecarlo import instance_seeds
from gyrocore.calib.budget import predict_error
from gyrocore.noise.model import NoiseModel, model_value
from gyrocore.effects import registry as E

from . import ablation as A
from .report import ExperimentResult, md_table, new_figure, save_figure, single_thread_blas

__all__ = [
    "Target",
    "TARGETS",
    "TableProtocol",
    "ThermalProtocol",
    "TABLE_PROTOCOLS",
    "THERMAL_PROTOCOLS",
    "NoiseSource",
    "load_noise",
    "simulated_still_noise",
    "record_support",
    "hover_trajectory",
    "design_stderr",
    "candidate_stderr",
    "evaluate_grid",
    "choose",
    "confirm",
    "confirm_all",
    "run",
]

SENSOR = "icm42688p"
#: Reference protocol times (the ablation's calibration runs), s.
TABLE_REF_S = 387.0
THERMAL_REF_S = 900.0
WINDOWS_S = (0.5, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0, 120.0)
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


#: Default targets: "how long must I calibrate for X°" (expected final error after the hover,
#: √E|ε(T)|², for X = 1, 1.5, 2, 3°) and "within 1.3 × the floor" (RMS over the hover).
TARGETS = (
    Target("final error ≤ 1° after the hover", final_deg=1.0),
    Target("final error ≤ 1.5° after the hover", final_deg=1.5),
    Target("final error ≤ 2° after the hover", final_deg=2.0),
    Target("final error ≤ 3° after the hover", final_deg=3.0),
    Target("RMS error ≤ 1.3 × floor over the hover", floor_ratio=1.3),
)


# ----------------------------------------------------------------------------- noise model
#: Length of the simulated still recording the default run identifies the flight's noise on,
#: as a multiple of the flight (and at least :data:`NOISE_RECORD_MIN_S`).
#: held-out units of the check in the standard size of ``gyroharness run`` (full: 8): the
#: Student-t 95 % interval of the mean log error then has 3 degrees of freedom
STANDARD_HELD_OUT = 4
NOISE_RECORD_FACTOR = 4.0
NOISE_RECORD_MIN_S = 1200.0
#: A noise term "matters" for a flight when it raises the flight's floor RMS by this fraction.
SUPPORT_RISE = 0.10
#: Longest still recording the support search considers, s (24 h).
SUPPORT_MAX_RECORD_S = 86400.0
_SLOW_TERMS = ("bias_instability_rad_s", "rrw_rad_per_s_sqrt_s", "correlated_sigma_rad_s")
_TERM_LABEL = {
    "bias_instability_rad_s": "flicker (bias instability) B",
    "rrw_rad_per_s_sqrt_s": "rate random walk K",
    "correlated_sigma_rad_s": "Gauss–Markov σ",
}


@dataclass(frozen=True)
class NoiseSource:
    """The noise model the protocol's flight budget uses and where it comes from.

    Attributes
    ----------
    model : gyrocore.noise.model.NoiseModel
        The noise model of axes x, y, z.
    label : str
        Where it comes from (said in the report and the JSON).
    record_s : float or None
        Length of the still record the model was identified on, s (None: unknown).
    rate_hz : float or None
        That record's sample rate, Hz.
    kind : str
        ``"noise-json"`` (``gyroharness allan/noise --json``), ``"recording"`` (a still data
        file identified here), ``"parameter-file"`` (a calibration's ``noise_model``: its
        residual), ``"simulated-still"``, ``"calibration"`` (the reference calibration's
        residual).
    """

    model: NoiseModel
    label: str
    record_s: float | None
    rate_hz: float | None
    kind: str

    @property
    def n_samples(self) -> int | None:
        if self.record_s is None or self.rate_hz is None:
            return None
        return int(round(self.record_s * self.rate_hz)) + 1


def _noise_from_allan_json(doc: dict, where: str):
    """NoiseModel of axes x, y, z from the JSON of ``gyroharness allan/noise --json`` (per-axis
    terms, null = not resolved, ``ambiguous`` and ``estimate``: each term's model value as the
    identification gives it, :func:`gyrocore.noise.model.model_value`; a missing axis takes the
    mean of the others)."""
    from gyrocore.errors import GyroInputError

    axes = doc.get("axes")
    if not isinstance(axes, dict) or not axes:
        raise GyroInputError(
            f"{where}: no 'axes' in the noise JSON (expected the output of `gyroharness noise --json`)"
        )
    keys = (
        "arw_rad_per_sqrt_s",
        "bias_instability_rad_s",
        "rrw_rad_per_s_sqrt_s",
        "correlated_sigma_rad_s",
        "correlated_tau_c_s",
    )
    models = []
    for a, d in axes.items():
        if a not in ("x", "y", "z") or not isinstance(d, dict):
            continue
        try:
            vals = {k: (None if d.get(k) is None else float(d[k])) for k in keys}
        except (TypeError, ValueError):
            raise GyroInputError(f"{where}: axis {a}: a noise term is not a number") from None
        if vals["arw_rad_per_sqrt_s"] is None or not (vals["arw_rad_per_sqrt_s"] > 0):
            raise GyroInputError(f"{where}: axis {a} has no white rate noise (arw_rad_per_sqrt_s)")
        amb, est = dict(d.get("ambiguous") or {}), dict(d.get("estimate") or {})
        models.append(NoiseModel(**{k: model_value(k, vals[k], amb, est) for k in keys}, axes=(a,), source=where))
    if not models:
        raise GyroInputError(f"{where}: no gyro axis x, y or z in the noise JSON")
    return NoiseModel.stack(models).complete(("x", "y", "z"))


def load_noise(path) -> NoiseSource:
    """The flight's noise model from ``path`` (``experiment protocol --noise FILE``).

    ``path`` is either a JSON file — the output of ``gyroharness allan --json`` /
    ``gyroharness noise --json`` (the record's ``duration_s`` and ``rate_hz`` are used by
    :func:`record_support`), or a parameter file of ``gyroharness calibrate --covariance
    noise_model`` (its ``noise_model``: identified on the calibration residual, record length
    = its fitted samples / rate) — or a still data file (CSV/Parquet, as every command reads
    it), whose noise is identified here as ``gyroharness noise`` does (GMWM, motion gate on;
    long files one axis at a time).
    """
    import json
    import os
    import warnings

    from gyrocore.errors import GyroInputError

    path = str(path)
    if not os.path.isfile(path):
        raise GyroInputError(f"{path}: no such noise file")
    doc = None
    with open(path, "rb") as fh:
        head = fh.read(64).lstrip()
    if head.startswith(b"{"):
        try:
            with open(path, encoding="utf-8") as fh:
                doc = json.load(fh)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise GyroInputError(f"{path}: not a noise JSON ({type(exc).__name__})") from None
        if not isinstance(doc, dict):
            raise GyroInputError(f"{path}: not a noise JSON (top level is not an object)")
    if doc is not None and "axes" in doc:
        model = _noise_from_allan_json(doc, path)
        dur = doc.get("duration_s")
        rate = doc.get("rate_hz")
        dur = float(dur) if isinstance(dur, (int, float)) and dur > 0 else None
        rate = float(rate) if isinstance(rate, (int, float)) and rate > 0 else None
        what = f"{dur:.0f}-s" if dur else "a"
        return NoiseSource(
            model=model,
            label=f"{os.path.basename(path)} (noise JSON: GMWM on {what} still record"
            f"{f' at {rate:g} Hz' if rate else ''})",
            record_s=dur,
            rate_hz=rate,
            kind="noise-json",
        )
    if doc is not None and "noise_model" in doc:
        from gyrocore.calib.params import result_from_dict

        res = result_from_dict(doc, where=path)
        if not res.noise_model:
            raise GyroInputError(
                f"{path}: the parameter file has no noise_model (calibrate with --covariance noise_model)"
            )
        rate = float(res.noise_model.get("rate_hz", float("nan")))
        rate = rate if np.isfinite(rate) and rate > 0 else None
        dur = float(res.n_samples) / rate if rate and res.n_samples else None
        return NoiseSource(
            model=res.noise(),
            label=f"{os.path.basename(path)} (calibration residual, "
            f"{res.n_samples} samples{f' at {rate:g} Hz' if rate else ''})",
            record_s=dur,
            rate_hz=rate,
            kind="parameter-file",
        )
    if doc is not None:
        raise GyroInputError(f"{path}: JSON is neither a noise JSON (`gyroharness noise --json`) nor a parameter file")
    # a still data file: identify as `gyroharness noise FILE` does
    from gyrocore.noise.allan import allan_analysis
    from gyrocore.readers.large import is_large
    from gyrocore.noise.spilled import allan_by_axis
    from gyrocore.data.recording import read_recording

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="no long-tau term resolved")
        if is_large(path, "allan"):
            an = allan_by_axis(path, axes=["x", "y", "z"], max_tau_s=None, kalibr=False, engine="fast")
        else:
            an = allan_analysis(read_recording(path), axes=["x", "y", "z"], check_static=True)
    return NoiseSource(
        model=an.noise_model(("x", "y", "z")),
        label=f"{os.path.basename(path)} (GMWM on its {an.duration_s:.0f}-s still record at {an.rate_hz:g} Hz)",
        record_s=float(an.duration_s),
        rate_hz=float(an.rate_hz),
        kind="recording",
    )


def simulated_still_noise(*, seed: int, duration_s: float) -> NoiseSource:
    """The design unit's noise identified (GMWM) on a simulated still recording of
    ``duration_s`` (scenario ``static``, a separate power-up: run 3) — what a user gets from
    ``gyroharness noise`` on a long still log of the same sensor."""
    import warnings

    from gyrocore.noise.allan import allan_analysis
    from sim import scenarios as S

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = S.simulate("static", sensor=SENSOR, seed=int(seed), run=3, duration_s=float(duration_s)).recording
        an = allan_analysis(rec, axes=["x", "y", "z"])
    del rec
    return NoiseSource(
        model=an.noise_model(("x", "y", "z")),
        label=f"GMWM on a simulated {an.duration_s:.0f}-s still recording of the unit (static, run 3)",
        record_s=float(an.duration_s),
        rate_hz=float(an.rate_hz),
        kind="simulated-still",
    )


def record_support(
    terms: dict,
    *,
    n_samples: int | None,
    rate_hz: float | None,
    unit_var: dict,
    rise: float = SUPPORT_RISE,
    max_record_s: float = SUPPORT_MAX_RECORD_S,
) -> list[dict]:
    """Does the noise record support the flight? The resolvability rule, term by term.

    A flight's floor is set by the slow terms (flicker B, rate random walk K, a Gauss–Markov
    bias) at time scales up to the flight's length; a model identified on a shorter record
    may have missed them or mistaken one for another (a 387-s calibration residual gave a
    10-min floor of 0.54° for a unit whose true floor is 0.81°). For each slow term X:

    * its level: the model's value if the model has it, else (B and K only) the *smallest
      level that matters*, the one that raises the flight's floor RMS by ``rise``:
      x² = ((1 + rise)² − 1)·V_rest / v_X, with V_rest the floor variance of the other terms
      and v_X that of X at unit level (``unit_var``; the floor is linear in each term's
      variance coefficient);
    * a term present but adding less than ``rise`` to the floor RMS does not matter;
    * otherwise it must be resolvable from the record: :func:`gyrocore.noise.gmwm.expected_z`
      (the model with X at its level, the record's sample count and rate) ≥
      :data:`gyrocore.noise.gmwm.Z_POWER` (GMWM claims it with ≥ 90 % probability). If not, the
      record length that would resolve it is searched by doubling (up to ``max_record_s``).

    Parameters
    ----------
    terms : dict
        Axis-mean terms, keys of :func:`gyrocore.noise.gmwm.expected_z` (rad/√s, rad/s, rad/s/√s).
    n_samples, rate_hz : int, float or None
        The noise record (None: unknown → every term that matters is unsupported).
    unit_var : dict
        {term: the flight floor's variance (rad², time mean over the flight) for the term at
        unit level (1 in its unit), the others 0}; ``correlated_sigma_rad_s`` at the model's τc.

    Returns
    -------
    list of dict, one per slow term: ``term``, ``level``, ``present`` (in the model),
    ``floor_rise`` (fractional RMS rise of the floor it causes), ``matters``, ``margin`` (at the
    record), ``resolvable``, ``needed_record_s`` (None: resolvable now; inf: beyond
    ``max_record_s``), ``warn`` (True: a present term or the flicker term the record cannot
    support; an absent random walk or Gauss–Markov term is stated as an assumption instead).
    """
    from gyrocore.noise import gmwm

    lev = {k: float(terms.get(k) or 0.0) for k in ("arw_rad_per_sqrt_s",) + _SLOW_TERMS}
    tau = terms.get("correlated_tau_c_s")
    v_of = {k: float(unit_var.get(k, 0.0)) for k in lev}
    rows = []
    q = (1.0 + rise) ** 2 - 1.0
    for x in _SLOW_TERMS:
        present = lev[x] > 0
        if x == "correlated_sigma_rad_s" and not present:
            continue  # no τc to test an absent Gauss–Markov term at
        v_rest = sum(lev[k] ** 2 * v_of[k] for k in lev if k != x)
        if v_of[x] <= 0 or v_rest <= 0:
            continue
        level = lev[x] if present else math.sqrt(q * v_rest / v_of[x])
        rise_x = math.sqrt(1.0 + level**2 * v_of[x] / v_rest) - 1.0
        row = {
            "term": x,
            "label": _TERM_LABEL[x],
            "level": level,
            "present": present,
            "floor_rise": rise_x,
            "matters": rise_x >= rise * (1 - 1e-9),
            "margin": None,
            "resolvable": True,
            "needed_record_s": None,
            "warn": False,
        }
        if row["matters"]:
            tt = {**{k: (lev[k] or None) for k in lev}, x: level, "correlated_tau_c_s": tau}

            def margin(n):
                return float(gmwm.expected_z(tt, n_samples=int(n), rate_hz=float(rate_hz)).get(x, -math.inf))

            if n_samples is None or rate_hz is None:
                row.update(resolvable=False, needed_record_s=float("nan"))
            else:
                m0 = margin(n_samples)
                row["margin"] = m0
                if m0 < gmwm.Z_POWER:
                    row["resolvable"] = False
                    n, need = int(n_samples), math.inf
                    while n / rate_hz < max_record_s:
                        n *= 2
                        if margin(n) >= gmwm.Z_POWER:
                            need = n / rate_hz
                            break
                    row["needed_record_s"] = need
            row["warn"] = (not row["resolvable"]) and (present or x == "bias_instability_rad_s")
        rows.append(row)
    return rows


def _support_message(rows: list[dict], src: NoiseSource, flight_s: float) -> str | None:
    """The one ``warning:`` line when the noise record does not support the flight."""
    bad = [r for r in rows if r["warn"]]
    if not bad:
        return None
    rec = "of unknown length" if src.record_s is None else f"of {src.record_s:.0f} s"

    def need(r):
        n = r["needed_record_s"]
        if n is None or not np.isfinite(n):
            return "a record of unknown length" if n is not None and np.isnan(n) else f"> {SUPPORT_MAX_RECORD_S:.0f} s"
        return f"≥ {n:.0f} s"

    parts = [
        f"{r['label']} {r['level']:.2g} ({'identified' if r['present'] else 'smallest that matters'}, "
        f"+{100 * r['floor_rise']:.0f} % on the floor) needs {need(r)}"
        for r in bad
    ]
    return (
        f"the noise record {rec} does not support a {flight_s:g}-s flight (resolvability rule, "
        f"gyrocore.noise.gmwm.expected_z, 90 % power): "
        + "; ".join(parts)
        + " — the floor may be under-predicted; give --noise a longer still recording"
    )


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
        return np.concatenate([np.repeat(x[i_to - 1 : i_to], nw, axis=0), x[i_to:]], axis=0)

    t = np.arange(n) / rate
    inp = E.ModelInputs(
        t_s=t,
        omega_S_rad_s=np.concatenate([np.zeros((nw, 3)), w]),
        f_S_m_s2=pre(tr.f_S_m_s2),
        temp_c=pre(tr.temp_c),
        q_SW_wxyz=pre(tr.q_SW_wxyz),
        t_since_power_up_s=t,
    )
    return inp, [(slice(0, n), slice(0, nw))], nw


@dataclass(frozen=True)
class _Pred:
    final_predicted_deg: float
    rms_predicted_deg: float
    rms_floor_deg: float
    final_floor_deg: float


def design_stderr(
    spec, *, seed: int, effects: Sequence[str], noise, orders=None, run: int = 1, duration_s: float | None = None
) -> dict:
    """Standard errors a calibration run *would* report, predicted from its design alone.

    Simulates the candidate run's reference trajectory (rate, specific force, temperature of
    ``spec``; the gyro samples are not used), builds the calibration's rows as
    :class:`gyrocore.calibrator.Calibrator` does with the ablation's settings (ramps ± the
    ramp margin left out, block means of ≤ ``max_rows`` rows) and evaluates the noise-model
    sandwich (AᵀWA)⁻¹·(Σ U_iᵀ C_i U_i)·(AᵀWA)⁻¹ of ``noise`` (:func:`gyrocore.calib.lsq.solve`
    with r = 0: the covariance does not depend on the data).

    Returns
    -------
    dict with ``se`` ({effect: flat ndarray}, SI), ``unobservable`` (names), ``t0_c`` (mean
    temperature, the thermal polynomials' centre), ``duration_s``.
    """
    import warnings

    from gyrocore.calib import lsq
    from gyrocore.calibrator import near_rate_changes
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
    fit = lsq.fit_effects(
        np.zeros((t.size, 3)),
        list(effects),
        inp,
        orders=orders,
        weights=wts,
        average=avg,
        covariance="noise_model",
        noise_model=noise,
        t_s=t - t[0],
        axis_weighting=False,
        keep_residual=False,
    )
    t0 = float(np.mean(rec.temp_c)) if rec.temp_c is not None else float("nan")
    return {
        "se": {e: fit.effect_stderr(e).copy() for e in effects},
        "unobservable": tuple(fit.unobservable),
        "t0_c": t0,
        "duration_s": float(rec.duration_s),
    }


def table_spec(p: TableProtocol):
    """The turntable scenario with the protocol's mounts, rates and revolutions."""
    from sim import scenarios as S

    spec = S.load_scenario("turntable")
    return dataclasses.replace(
        spec,
        table={
            **dict(spec.table),
            "mounts": list(p.mounts),
            "rates_dps": list(p.rates_dps),
            "revolutions": float(p.revolutions),
        },
    )


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


def candidate_stderr(
    groups,
    *,
    seed: int,
    noise_table,
    noise_thermal,
    table=TABLE_PROTOCOLS,
    thermal=THERMAL_PROTOCOLS,
    thermal_orders=None,
) -> tuple[list[dict], list[dict]]:
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
        out_t.append(
            {
                "label": p.label,
                "cost_s": d["duration_s"],
                "se": d["se"],
                "t0_c": d["t0_c"],
                "unobservable": d["unobservable"],
                "protocol": dataclasses.asdict(p),
            }
        )
    for p in thermal:
        d = design_stderr(thermal_spec(p), seed=seed, effects=th_eff, noise=noise_thermal, run=2, orders=thermal_orders)
        out_h.append(
            {
                "label": p.label,
                "cost_s": d["duration_s"],
                "se": d["se"],
                "t0_c": d["t0_c"],
                "unobservable": d["unobservable"],
                "protocol": dataclasses.asdict(p),
            }
        )
    return out_t, out_h


def _recentred(g, t0_c: float):
    """Group ``g`` with its thermal polynomials centred on ``t0_c`` (the candidate run's mean)."""
    from gyrocore.calib.budget import ParameterGroup

    if not np.isfinite(t0_c):
        return g
    params = {e: ({**dict(pd), "t0_c": np.asarray(t0_c)} if "t0_c" in pd else pd) for e, pd in g.params.items()}
    return ParameterGroup(name=g.name, params=params, stderr=g.stderr)


def evaluate_grid(
    res, ground_s: float, groups, *, windows=WINDOWS_S, table=None, thermal=None, noise=None
) -> list[dict]:
    """Predicted hover error for every protocol of the grid (window × table × thermal).

    One budget per window length (its trajectory) for the noise and the window
    (:func:`gyrocore.calib.budget.predict_error`); each parameter group's variance
    Σ_p |S_p(t)|²·SE_p² from its sensitivity S (:func:`gyrocore.calib.budget.sensitivity`) and the
    candidate's standard errors. ``table``/``thermal``: candidates of
    :func:`candidate_stderr` (None: one "reference" candidate with the groups' own standard
    errors). ``noise``: the noise model (None: the unit's true noise)."""
    from gyrocore.calib.budget import make_blocks, predict_error, rotation_matrices, sensitivity

    if noise is None:
        noise = NoiseModel.from_params(res.params_true)
    table = table or [
        {"label": "reference", "cost_s": TABLE_REF_S, "se": None, "t0_c": float("nan"), "unobservable": ()}
    ]
    thermal = thermal or [
        {"label": "reference", "cost_s": THERMAL_REF_S, "se": None, "t0_c": float("nan"), "unobservable": ()}
    ]
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
                cache[key] = (np.sum(S**2, axis=1)[sc], np.where(np.isfinite(se), se, 0.0))
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
                p = _Pred(
                    final_predicted_deg=math.degrees(math.sqrt(max(v[-1], 0.0))),
                    rms_predicted_deg=math.degrees(math.sqrt(max(pr._mean(v), 0.0))),
                    rms_floor_deg=pr.rms_floor_deg,
                    final_floor_deg=pr.final_floor_deg,
                )
                rows.append(
                    {
                        "window_s": tw,
                        "table": c1["label"],
                        "thermal": c2["label"],
                        "table_s": c1["cost_s"],
                        "thermal_s": c2["cost_s"],
                        "eligible": not (c1["unobservable"] or c2["unobservable"]),
                        "cost_s": tw + c1["cost_s"] + c2["cost_s"],
                        "final_deg": p.final_predicted_deg,
                        "rms_deg": p.rms_predicted_deg,
                        "floor_rms_deg": p.rms_floor_deg,
                        "floor_final_deg": p.final_floor_deg,
                        "table_deg": math.degrees(math.sqrt(max(pr._mean(a), 0.0))),
                        "thermal_deg": math.degrees(math.sqrt(max(pr._mean(b), 0.0))),
                        # the noise + window part alone (what a true-parameter flight measures)
                        "noise_final_deg": math.degrees(math.sqrt(max(base[-1], 0.0))),
                        "noise_rms_deg": math.degrees(math.sqrt(max(pr._mean(base), 0.0))),
                        "pred": p,
                    }
                )
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


def confirm(
    window_s: float, seeds: Sequence[int], *, airborne_s: float, cache_dir: str | None = None, calibration: str = "true"
) -> list[dict]:
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
            ab = A.ablate_instance(
                spec,
                sensor=SENSOR,
                seed=int(sd),
                duration_s=ground + 3.0 + airborne_s,
                powerup_window_s=window_s,
                mahony_kp_per_s=None,
                cache_dir=cache_dir,
                calibration=cal,
            )
        out.append(
            {
                "seed": int(sd),
                "final_deg": ab.scores["all"].final_error_deg,
                "rms_deg": ab.scores["all"].rms_error_deg,
                "floor_rms_deg": ab.scores["floor"].rms_error_deg,
                "pred_final_deg": ab.prediction.final_predicted_deg,
                "pred_rms_deg": ab.prediction.rms_predicted_deg,
                "pred_floor_rms_deg": ab.prediction.rms_floor_deg,
            }
        )
    return out


def _confirm_one(args) -> dict:
    window_s, sd, airborne_s, cache_dir = args
    return confirm(window_s, [sd], airborne_s=airborne_s, cache_dir=cache_dir)[0]


def confirm_all(
    windows: Sequence[float],
    seeds: Sequence[int],
    *,
    airborne_s: float,
    cache_dir: str | None = None,
    workers: int | None = None,
) -> dict:
    """:func:`confirm` for every window × unit, on ``workers`` processes (None: the cores of
    this machine; spawned, as :mod:`experiments.montecarlo`). Each flight is seeded by its unit
    alone, so the results do not depend on ``workers``. Returns {window: [unit dicts]}."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from experiments.montecarlo import default_workers
    from gyrocore.fleet import worker_environment

    jobs = [(float(tw), int(sd), float(airborne_s), cache_dir) for tw in windows for sd in seeds]
    n_workers = min(default_workers() if workers is None else int(workers), len(jobs))
    if n_workers <= 1:
        res = [_confirm_one(j) for j in jobs]
    else:
        with ProcessPoolExecutor(max_workers=n_workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            with worker_environment():
                futures = [pool.submit(_confirm_one, j) for j in jobs]
            try:
                res = [f.result() for f in futures]
            except BaseException:
                from experiments.montecarlo import stop_pool

                stop_pool(pool, futures)
                raise
    out: dict = {float(tw): [] for tw in windows}
    for j, r in zip(jobs, res):
        out[j[0]].append(r)
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


def _mean_square_interval(x: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean of x (final error², one value per unit) and its Student-t interval (lower end
    clipped at 0): the n units are independent draws, the mean is ≈ normal for n ≳ 8 (x is
    χ²-like with ~3 dof: skewed, so the interval is approximate on the low side)."""
    from scipy import stats

    x = np.asarray(x, float)
    m = float(x.mean())
    if x.size < 2:
        return m, float("nan"), float("nan")
    h = float(stats.t.ppf(0.5 + level / 2, x.size - 1)) * float(x.std(ddof=1)) / math.sqrt(x.size)
    return m, max(m - h, 0.0), m + h


def _floor_ms(inp, start: int, segs, model) -> float:
    """Time mean of the floor's E|ε|² (rad²) of a flight for a noise model."""
    from gyrocore.calib.budget import predict_error

    pr = predict_error(inp, start=start, segments=segs, noise=model, groups=(), max_blocks=400)
    return float(pr._mean(np.asarray(sum(pr.floor_var_rad2.values()), float))) if pr.floor_var_rad2 else 0.0


def _unit_floor_var(inp, start: int, segs, tau_c_s: float | None) -> dict:
    """{term: the flight floor's mean variance at unit level of that term alone} (linear in
    each term's variance coefficient: :func:`record_support`)."""

    z, one = np.zeros(3), np.ones(3)
    out = {
        "arw_rad_per_sqrt_s": _floor_ms(inp, start, segs, NoiseModel(arw_rad_per_sqrt_s=one)),
        "bias_instability_rad_s": _floor_ms(
            inp, start, segs, NoiseModel(arw_rad_per_sqrt_s=z, bias_instability_rad_s=one)
        ),
        "rrw_rad_per_s_sqrt_s": _floor_ms(inp, start, segs, NoiseModel(arw_rad_per_sqrt_s=z, rrw_rad_per_s_sqrt_s=one)),
    }
    if tau_c_s is not None and np.isfinite(tau_c_s):
        out["correlated_sigma_rad_s"] = _floor_ms(
            inp,
            start,
            segs,
            NoiseModel(arw_rad_per_sqrt_s=z, correlated_sigma_rad_s=one, correlated_tau_c_s=np.full(3, float(tau_c_s))),
        )
    return out


def run(
    *,
    out_dir,
    quick: bool = False,
    seeds: int | None = None,
    workers: int | None = None,
    seed: int = 0,
    noise=None,
    size: str | None = None,
    progress=None,
    **_ignored,
) -> ExperimentResult:
    """Protocol design for :data:`TARGETS`; tables, figures and the held-out simulation check
    into ``out_dir``.

    ``noise``: the flight's noise model — None (default): identified (GMWM) on a simulated
    still recording of the design unit, :data:`NOISE_RECORD_FACTOR` × the flight long;
    ``"calibration"``: the reference calibration's residual model (the previous behaviour);
    a path (:func:`load_noise`) or a :class:`NoiseSource`. One ``warning:`` line when the
    record does not support the flight (:func:`record_support`).
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    # size (gyroharness run): "standard" = the quick design (a 1-min hover, 4 windows, 2 table
    # and 2 thermal protocols, the quick calibration runs) checked on STANDARD_HELD_OUT fresh
    # units; the 10-min hover with the whole grid (--full) costs ~10x the CPU
    size = size or ("quick" if quick else "full")
    quick = size == "quick"

    def tick(k, n=4):
        if progress is not None:
            progress(k, n)

    tick(0)
    airborne = 60.0 if size in ("quick", "standard") else HOVER_S
    d = _design_unit(seed, airborne_s=airborne, quick=quick or size == "standard")
    tick(1)
    src = _flight_noise(noise, d, airborne_s=airborne)
    fn = _flight_noise_support(src, d, airborne_s=airborne)
    g = _design_grid(d, size=size, noise=src.model, tick=tick)
    tick(3)
    # --- held-out check: fresh units (not the design unit) flown with each chosen window;
    # calibration = each unit's true parameters, so the flight measures the window + noise part
    n_units = seeds or {"quick": 1, "standard": STANDARD_HELD_OUT}.get(size, 8)
    check_windows = sorted({c["window_s"] for c in g.chosen.values() if c is not None})
    fresh = instance_seeds(seed + 1, n_units)
    cache = tempfile.mkdtemp(prefix="gyroharness-protocol-")
    try:
        conf = confirm_all(check_windows, fresh, airborne_s=airborne, cache_dir=cache, workers=workers)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    how_rows, how_json = _how_long(g, conf)
    summary_conf, cf = _confirmation_table(g, conf)
    fig0p = _how_long_figure(g, how_json, n_units=n_units, airborne_s=airborne, noise_kind=src.kind, out_dir=out_dir)
    figp = _grid_figure(g, conf, airborne_s=airborne, out_dir=out_dir)
    t_tab, h_tab = _candidate_tables(g)
    md = [
        f"**Size:** a {airborne:g}-s hover, {len(g.windows)} still windows × {len(g.tabs)} rate-table × {len(g.ths)} thermal "
        f"protocols, {n_units} held-out units (95 % intervals: Student-t on their log errors, {n_units - 1} degrees "
        "of freedom)"
        + (
            "; `gyroharness run --full`: the 10-min hover, the whole grid and 8 held-out units.\n"
            if airborne < HOVER_S
            else ".\n"
        ),
        f"**Noise model of the flight:** {src.label}"
        + (
            f" — **warning:** {fn.warning}" if fn.warning else " — the record supports the flight (resolvability rule)."
        ),
        "\n#### How long must I calibrate for X°? (held-out figures first)\n",
        f"Shortest protocol per target by the budget on the design unit (seed {d.unit}); held out: {n_units} fresh "
        f"units (campaign seed {seed + 1}, not the design unit) flown with that protocol's still window and their "
        "true parameters (so the flight measures the window + noise part), plus the budget's parameter share "
        "(the table/thermal runs' standard errors, whose honesty the z-score Monte Carlo of docs/accuracy.md "
        "checks). The target is on the expected error √E|ε(T)|² over units; a single unit's final error "
        "scatters around it (χ²-like).\n",
        _how_long_table(how_rows, n_units),
        f"\n![how long]({fig0p})\n",
        "#### Held-out simulation, per window\n",
        cf,
        "\n#### The flight's noise model and its record\n",
        _floors_table(fn.floors),
        "\nDoes the record support the flight? (`experiments.protocol.record_support`: each slow term that raises "
        f"the flight's floor RMS by ≥ {100 * SUPPORT_RISE:.0f} % must be resolvable from the record, "
        "`gyrocore.noise.gmwm.expected_z` ≥ 1.28, i.e. claimed by GMWM with ≥ 90 % probability)\n",
        _support_table(fn.support),
        f"\n#### Predicted error after {airborne:g} s of hover (sensor {SENSOR}, unit seed {d.unit})\n",
        "Grid: power-up still window × rate-table run (mounts, rates, revolutions) × thermal run (ambient span, "
        "duration = ramp rate). The table and thermal runs' standard errors are predicted from each candidate's "
        "design with the noise-model covariance (experiments.protocol.design_stderr; noise: the model each "
        "reference calibration identified on its own residual, a record as long as the run); the window and the "
        "floor use the flight's noise model above.\n",
        "#### Still window (reference table and thermal runs)\n",
        _window_table(g),
        "\n#### Rate-table run candidates (reference thermal run)\n",
        t_tab,
        "\n#### Thermal run candidates (reference table run)\n",
        h_tab,
        f"\n![protocol]({figp})",
    ]
    summary = _summary(src, fn, g, how_json=how_json, confirmation=summary_conf, fresh=fresh, d=d, airborne_s=airborne)
    return ExperimentResult(
        name="protocol",
        title="Protocol design: how long to calibrate for a drift target",
        markdown="\n".join(md),
        figures=(fig0p, figp),
        summary=summary,
        wall_s=time.perf_counter() - t0,
    )


def _summary(
    src: NoiseSource,
    fn: _FlightNoise,
    g: _Grid,
    *,
    how_json: dict,
    confirmation: dict,
    fresh,
    d: _Design,
    airborne_s: float,
) -> dict:
    """The experiment's JSON summary."""
    return {
        "noise_source": {
            "label": src.label,
            "kind": src.kind,
            "record_s": src.record_s,
            "rate_hz": src.rate_hz,
            "terms": fn.terms,
            "supported": fn.warning is None,
            "warning": fn.warning,
            "support": fn.support,
        },
        "floors": [
            {
                "noise": f[0],
                "floor_rms_deg": f[1],
                "floor_final_deg": f[2],
                "pred_rms_deg_2s": f[3],
                "pred_final_deg_2s": f[4],
            }
            for f in fn.floors
        ],
        "how_long": how_json,
        "targets": {
            t.name: (None if g.chosen[t.name] is None else {k: v for k, v in g.chosen[t.name].items() if k != "pred"})
            for t in TARGETS
        },
        "grid": [{k: v for k, v in r.items() if k != "pred"} for r in g.rows],
        "table_candidates": [{k: v for k, v in c.items() if k != "se"} for c in g.cand_t],
        "thermal_candidates": [{k: v for k, v in c.items() if k != "se"} for c in g.cand_h],
        "confirmation": confirmation,
        "fresh_seeds": [int(s) for s in fresh],
        "design_unit_seed": int(d.unit),
        "airborne_s": airborne_s,
    }


# ------------------------------------------------------------------ the steps of run
@dataclass(frozen=True)
class _Design:
    """The design unit: its hover, its reference calibration and the noise models it identified."""

    unit: int  # the design unit's seed
    res: object  # the hover (simulated)
    ground: float  # ground phase before take-off, s
    groups: dict  # calibration groups (experiments.ablation.calibration_groups)
    nm_cal: object  # the reference calibration's residual noise model
    n_tab: object  # noise model of the rate-table run
    n_th: object  # noise model of the thermal run
    orders: dict | None  # the thermal run's polynomial orders
    cal_src: NoiseSource  # nm_cal as a noise source (``--noise calibration``)


def _design_unit(seed: int, *, airborne_s: float, quick: bool) -> _Design:
    """The design unit's hover and reference calibration (table and thermal runs)."""
    unit = instance_seeds(seed, 1)[0]
    res, ground = hover_trajectory(seed=unit, airborne_s=airborne_s)
    rate = float(res.recording.rate_hz)
    present = A.present_effects(res.params_true)
    with single_thread_blas():
        core = A.calibrate_core(SENSOR, unit, present, quick=quick)
    stages = list(core.stages)
    groups = A.calibration_groups(stages, present)
    nm_cal = A.identified_noise(core, rate)
    r1, r2 = (tuple(core.results) + (None, None))[:2]
    n_tab = r1.noise() if r1 is not None and r1.noise_model else nm_cal
    n_th = r2.noise() if r2 is not None and r2.noise_model else nm_cal
    orders = dict(r2.thermal_order) if r2 is not None else None
    # the calibration runs' residual records (the longest bounds what the model can have seen)
    cal_recs = [
        (float(r.n_samples) / float(r.noise_model["rate_hz"]), float(r.noise_model["rate_hz"]))
        for r in (r1, r2)
        if r is not None and r.noise_model and r.n_samples and np.isfinite(float(r.noise_model.get("rate_hz", np.nan)))
    ]
    cal_rec_s, cal_rate = max(cal_recs) if cal_recs else (None, None)
    cal_src = NoiseSource(
        model=nm_cal,
        label="the reference calibration's residual model (experiments.ablation.identified_noise)",
        record_s=cal_rec_s,
        rate_hz=cal_rate,
        kind="calibration",
    )
    return _Design(unit, res, ground, groups, nm_cal, n_tab, n_th, orders, cal_src)


def _flight_noise(noise, d: _Design, *, airborne_s: float) -> NoiseSource:
    """The flight's noise model (see :func:`run`'s ``noise``)."""
    if isinstance(noise, NoiseSource):
        return noise
    if noise is None:
        return simulated_still_noise(seed=d.unit, duration_s=max(NOISE_RECORD_FACTOR * airborne_s, NOISE_RECORD_MIN_S))
    if str(noise) == "calibration":
        return d.cal_src
    return load_noise(noise)


@dataclass(frozen=True)
class _FlightNoise:
    """What the flight's noise model says about the flight and whether its record supports it."""

    terms: dict  # axis means of its terms (NoiseModel.mean_terms)
    support: list  # record_support's rows
    warning: str | None  # the one warning line when the record does not support the flight
    floors: list  # (noise model, floor RMS °, floor final °, predicted RMS °, predicted final °) on a 2-s window


def _flight_noise_support(src: NoiseSource, d: _Design, *, airborne_s: float) -> _FlightNoise:
    """Whether the record supports the flight (one ``warning:``), and the flight's floor under
    the flight's model, the reference calibration's and the unit's true noise."""
    inp2, segs2, start2 = _prefixed_inputs(d.res, d.ground, 2.0)
    terms = src.model.mean_terms()
    unit_var = _unit_floor_var(inp2, start2, segs2, terms.get("correlated_tau_c_s"))
    support = record_support(terms, n_samples=src.n_samples, rate_hz=src.rate_hz, unit_var=unit_var)
    warn_msg = _support_message(support, src, airborne_s)
    if warn_msg:
        warnings.warn(warn_msg, UserWarning, stacklevel=3)
    floors = []
    for name, model in (
        ("flight noise model used: " + src.label, src.model),
        ("reference calibration's residual model", d.nm_cal),
        ("the unit's true noise (simulation only)", NoiseModel.from_params(d.res.params_true)),
    ):
        if model is None:
            continue
        pr = predict_error(inp2, start=start2, segments=segs2, noise=model, groups=(), max_blocks=400)
        floors.append((name, pr.rms_floor_deg, pr.final_floor_deg, pr.rms_predicted_deg, pr.final_predicted_deg))
    return _FlightNoise(terms, support, warn_msg, floors)


@dataclass(frozen=True)
class _Grid:
    """The protocol grid evaluated on the design unit and the protocol chosen per target."""

    windows: tuple  # still windows, s
    tabs: tuple  # rate-table protocols
    ths: tuple  # thermal protocols
    cand_t: list  # table candidates (candidate_stderr)
    cand_h: list  # thermal candidates
    rows: list  # evaluate_grid's rows
    chosen: dict  # {target name: row or None}

    @property
    def ref_t(self) -> str:
        return self.cand_t[0]["label"]

    @property
    def ref_h(self) -> str:
        return self.cand_h[0]["label"]

    @property
    def ref(self) -> list:
        """The rows of the reference table and thermal runs (one per still window)."""
        return [r for r in self.rows if r["table"] == self.ref_t and r["thermal"] == self.ref_h]


def _design_grid(d: _Design, *, size: str, noise, tick) -> _Grid:
    """The candidates' standard errors, the grid's predicted errors and the choice per target."""
    small = size in ("quick", "standard")  # the standard report: the quick grid, the full hover
    windows = (0.5, 2.0, 8.0, 30.0) if small else WINDOWS_S
    tabs = TABLE_PROTOCOLS[:2] if small else TABLE_PROTOCOLS
    ths = THERMAL_PROTOCOLS[:2] if small else THERMAL_PROTOCOLS
    with single_thread_blas():
        cand_t, cand_h = candidate_stderr(
            d.groups,
            seed=d.unit,
            noise_table=d.n_tab,
            noise_thermal=d.n_th,
            table=tabs,
            thermal=ths,
            thermal_orders=d.orders,
        )
    tick(2)
    rows = evaluate_grid(d.res, d.ground, d.groups, windows=windows, table=cand_t, thermal=cand_h, noise=noise)
    chosen = {t.name: choose(rows, t) for t in TARGETS}
    return _Grid(windows, tabs, ths, cand_t, cand_h, rows, chosen)


def _how_long(g: _Grid, conf: dict) -> tuple[list, dict]:
    """How long must I calibrate for X°? Per target, the chosen protocol's held-out figures
    first (table rows and JSON)."""
    how_rows, how_json = [], {}
    for t in TARGETS:
        c = g.chosen[t.name]
        if c is None:
            best = min(
                (r for r in g.rows if r["eligible"]),
                key=lambda r: r["final_deg"] if t.final_deg is not None else r["rms_deg"] / r["floor_rms_deg"],
            )
            how_rows.append(
                (
                    t.name,
                    "not reachable on the grid",
                    "",
                    "",
                    "",
                    "",
                    "",
                    f"best: {best['final_deg']:.2f}° final, RMS/floor {best['rms_deg'] / best['floor_rms_deg']:.2f} "
                    f"({best['window_s']:g}-s window); floor final {best['floor_final_deg']:.2f}°",
                )
            )
            how_json[t.name] = None
            continue
        lst = conf[c["window_s"]]
        fin2 = np.array([x["final_deg"] for x in lst]) ** 2
        par2 = max(c["final_deg"] ** 2 - c["noise_final_deg"] ** 2, 0.0)  # parameter shares (budget, final)
        m2, lo2, hi2 = _mean_square_interval(fin2)
        est = math.sqrt(m2 + par2)
        ci = (math.sqrt(lo2 + par2), math.sqrt(hi2 + par2)) if np.isfinite(hi2) else (float("nan"), float("nan"))
        mr = np.array([x["rms_deg"] for x in lst])
        fl = np.array([x["floor_rms_deg"] for x in lst])
        gm, glo, ghi = _interval(mr / fl)
        if t.final_deg is not None:
            held = f"{est:.2f} [{ci[0]:.2f}, {ci[1]:.2f}]"
            within = f"{int(np.sum(np.sqrt(fin2 + par2) <= t.final_deg))}/{len(lst)}"
            verdict = "yes" if est <= t.final_deg else "no"
        else:
            held = f"RMS/floor {gm:.2f} [{glo:.2f}, {ghi:.2f}]"
            within = f"{int(np.sum(mr / fl <= t.floor_ratio))}/{len(lst)}"
            verdict = "yes" if gm <= t.floor_ratio else "no"
        how_rows.append(
            (
                t.name,
                c["cost_s"],
                f"{c['window_s']:g} s window; {c['table']}; {c['thermal']}",
                held,
                within,
                verdict,
                c["final_deg"] if t.final_deg is not None else c["rms_deg"] / c["floor_rms_deg"],
                f"window + noise part: predicted {c['noise_final_deg']:.2f}° final, measured "
                f"√mean {math.sqrt(m2):.2f}° [{math.sqrt(lo2):.2f}, {math.sqrt(hi2):.2f}]",
            )
        )
        how_json[t.name] = {
            "window_s": c["window_s"],
            "table": c["table"],
            "thermal": c["thermal"],
            "cost_s": c["cost_s"],
            "predicted_final_deg": c["final_deg"],
            "predicted_rms_over_floor": c["rms_deg"] / c["floor_rms_deg"],
            "predicted_noise_final_deg": c["noise_final_deg"],
            "parameter_final_deg": math.sqrt(par2),
            "heldout_final_deg": est,
            "heldout_final_ci95_deg": list(ci),
            "heldout_noise_final_deg": math.sqrt(m2),
            "heldout_noise_final_ci95_deg": [math.sqrt(lo2), math.sqrt(hi2)],
            "heldout_rms_over_floor": gm,
            "heldout_rms_over_floor_ci95": [glo, ghi],
            "units_within": within,
            "met": verdict == "yes",
        }
    return how_rows, how_json


def _how_long_table(how_rows: list, n_units: int) -> str:
    return md_table(
        [
            "target",
            "total calibration time, s",
            "shortest protocol (budget)",
            f"held-out: {n_units} fresh units, final ° √mean [95 % CI] (or RMS/floor)",
            "units within target",
            "met on fresh units",
            "predicted (budget)",
            "detail",
        ],
        how_rows,
    )


def _window_table(g: _Grid) -> str:
    return md_table(
        ["still window, s", "predicted final °", "predicted RMS °", "floor RMS °", "RMS / floor"],
        [
            (r["window_s"], r["final_deg"], r["rms_deg"], r["floor_rms_deg"], r["rms_deg"] / r["floor_rms_deg"])
            for r in g.ref
        ],
    )


def _candidate_tables(g: _Grid) -> tuple[str, str]:
    """The rate-table and thermal candidates: their cost, standard errors, what they cannot
    observe and their share of the hover error at the 2-s window (reference other run)."""
    w_show = 2.0 if 2.0 in g.windows else g.windows[0]

    def se_med(c, grp):
        v = np.asarray(c["se"].get(grp, [np.nan]), float)
        v = v[np.isfinite(v)]
        return float(np.median(v)) if v.size else float("inf")

    def at(label_t=None, label_h=None):
        return next(
            r
            for r in g.rows
            if r["window_s"] == w_show and r["table"] == (label_t or g.ref_t) and r["thermal"] == (label_h or g.ref_h)
        )

    tt_rows = [
        (
            c["label"],
            c["cost_s"],
            se_med(c, "g_sensitivity") if "g_sensitivity" in c["se"] else "",
            se_med(c, "misalignment") if "misalignment" in c["se"] else "",
            ", ".join(c["unobservable"][:3]) + (" …" if len(c["unobservable"]) > 3 else "") or "—",
            at(label_t=c["label"])["table_deg"],
            at(label_t=c["label"])["final_deg"],
        )
        for c in g.cand_t
    ]
    t_tab = md_table(
        [
            "table run",
            "duration, s",
            "g-sens SE (median), rad/s/(m/s²)",
            "misalignment SE, rad",
            "unobservable",
            f"table params' hover RMS ° ({w_show:g}-s window)",
            "predicted final °",
        ],
        tt_rows,
    )
    th_rows = [
        (
            c["label"],
            c["cost_s"],
            se_med(c, "bias_thermal") if "bias_thermal" in c["se"] else "",
            ", ".join(c["unobservable"][:3]) or "—",
            at(label_h=c["label"])["thermal_deg"],
            at(label_h=c["label"])["final_deg"],
        )
        for c in g.cand_h
    ]
    h_tab = md_table(
        [
            "thermal run",
            "duration, s",
            "bias_thermal SE (median), SI",
            "unobservable",
            f"thermal params' hover RMS ° ({w_show:g}-s window)",
            "predicted final °",
        ],
        th_rows,
    )
    return t_tab, h_tab


def _floors_table(floors: list) -> str:
    return md_table(
        [
            "noise model",
            "floor RMS °",
            "floor final °",
            "predicted RMS ° (2-s window)",
            "predicted final ° (2-s window)",
        ],
        floors,
    )


def _support_table(support: list) -> str:
    def _need(r):
        n = r["needed_record_s"]
        if n is None:
            return "resolvable"
        if np.isnan(n):
            return "record length unknown"
        return f"≥ {n:.0f} s" if np.isfinite(n) else f"> {SUPPORT_MAX_RECORD_S:.0f} s"

    return md_table(
        [
            "term",
            "level (axis mean)",
            "in the model",
            "raises the flight floor RMS by",
            "margin at the record (resolvable ≥ 1.28)",
            "record needed",
            "warning",
        ],
        [
            (
                r["label"],
                f"{r['level']:.3g}",
                "yes" if r["present"] else "no (smallest level that matters)",
                f"{100 * r['floor_rise']:.0f} %",
                "" if r["margin"] is None else f"{r['margin']:.2f}",
                _need(r),
                "yes" if r["warn"] else ("assumed absent" if not r["resolvable"] else ""),
            )
            for r in support
        ],
    )


def _confirmation_table(g: _Grid, conf: dict) -> tuple[dict, str]:
    """Per still window: the fresh units measured against the budget (JSON and table)."""
    cf_rows = []
    summary_conf = {}
    for tw, lst in conf.items():
        mr = np.array([x["rms_deg"] for x in lst])
        prr = np.array([x["pred_rms_deg"] for x in lst])
        fl = np.array([x["floor_rms_deg"] for x in lst])
        r2v = (mr / prr) ** 2
        se2 = float(np.std(r2v, ddof=1) / math.sqrt(r2v.size)) if r2v.size > 1 else float("nan")
        gm, lo, hi = _interval(mr / fl)
        budget_row = next(r for r in g.ref if r["window_s"] == tw)
        cf_rows.append(
            (
                tw,
                len(lst),
                float(np.sqrt(np.mean(np.array([x["final_deg"] for x in lst]) ** 2))),
                budget_row["noise_final_deg"],
                float(np.median(mr)),
                float(np.median(prr)),
                f"{np.mean(r2v):.2f} ± {se2:.2f}",
                f"{gm:.2f} [{lo:.2f}, {hi:.2f}]",
            )
        )
        summary_conf[str(tw)] = {
            "units": lst,
            "measured_over_floor_geomean": gm,
            "ci95": [lo, hi],
            "mean_r2": float(np.mean(r2v)),
            "mean_r2_se": se2,
            "budget_noise_final_deg": budget_row["noise_final_deg"],
        }
    cf = md_table(
        [
            "still window, s",
            "fresh units",
            "measured final ° (√mean of squares)",
            "budget final ° (window + noise, flight noise model)",
            "measured RMS ° (median)",
            "predicted RMS ° (median, unit's true noise)",
            "mean (meas/pred RMS)² ± se",
            "measured RMS/floor: geo-mean [95 % CI]",
        ],
        cf_rows,
    )
    return summary_conf, cf


def _how_long_figure(g: _Grid, how_json: dict, *, n_units: int, airborne_s: float, noise_kind: str, out_dir) -> str:
    """Cost against predicted final error of the grid, the shortest protocol per target and the held-out points."""
    fig0 = new_figure(figsize=(6.4, 4.2))
    ax0 = fig0.add_subplot(111)
    elig = [r for r in g.rows if r["eligible"]]
    ax0.scatter([r["cost_s"] for r in elig], [r["final_deg"] for r in elig], s=6, c="0.7", label="grid protocols")
    order = sorted(elig, key=lambda r: (r["cost_s"], r["final_deg"]))
    front, best = [], math.inf
    for r in order:
        if r["final_deg"] < best:
            best = r["final_deg"]
            front.append(r)
    ax0.step(
        [r["cost_s"] for r in front],
        [r["final_deg"] for r in front],
        where="post",
        color="C0",
        label="shortest protocol for a target (budget)",
    )
    for t in TARGETS:
        if t.final_deg is None:
            continue
        ax0.axhline(t.final_deg, color="r", lw=0.6, ls=":")
        j = how_json.get(t.name)
        if j:
            lo_, hi_ = j["heldout_final_ci95_deg"]
            ax0.errorbar(
                [j["cost_s"]],
                [j["heldout_final_deg"]],
                yerr=[[j["heldout_final_deg"] - lo_], [hi_ - j["heldout_final_deg"]]],
                fmt="kx",
                ms=6,
                capsize=3,
            )
    ax0.plot([], [], "kx", label=f"held out: {n_units} fresh units (95 % CI)")
    ax0.axhline(g.ref[0]["floor_final_deg"], color="k", lw=0.8, ls="--", label="floor (final)")
    ax0.set_xscale("log")
    ax0.set_xlabel("total calibration time (still window + table + thermal run), s")
    ax0.set_ylabel(f"final attitude error after {airborne_s:g} s of hover, deg")
    ax0.set_title(f"How long must I calibrate? (noise: {noise_kind})", fontsize=8)
    ax0.grid(alpha=0.3, which="both")
    ax0.legend(fontsize=6)
    return save_figure(fig0, out_dir, "protocol_how_long")


def _grid_figure(g: _Grid, conf: dict, *, airborne_s: float, out_dir) -> str:
    """The grid by knob: final error per table run against the still window (fresh units as
    crosses), RMS / floor per thermal run."""
    fig = new_figure(figsize=(10.0, 3.8))
    ax = fig.add_subplot(121)
    for c in g.cand_t:
        rr = [r for r in g.rows if r["table"] == c["label"] and r["thermal"] == g.ref_h]
        ax.plot(
            [r["window_s"] for r in rr],
            [r["final_deg"] for r in rr],
            marker=".",
            ls="-" if not c["unobservable"] else ":",
            label=c["label"],
        )
    ax.plot([r["window_s"] for r in g.ref], [r["floor_final_deg"] for r in g.ref], "k--", label="floor (final)")
    for tw, lst in conf.items():
        ax.plot([tw] * len(lst), [x["final_deg"] for x in lst], "kx", ms=5)
    ax.axhline(1.0, color="r", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("power-up still window, s")
    ax.set_ylabel(f"final error after {airborne_s:g} s of hover, deg")
    ax.set_title("table runs (reference thermal run); x: fresh simulated units", fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=6)
    ax2 = fig.add_subplot(122)
    for c in g.cand_h:
        rr = [r for r in g.rows if r["thermal"] == c["label"] and r["table"] == g.ref_t]
        ax2.plot(
            [r["window_s"] for r in rr], [r["rms_deg"] / r["floor_rms_deg"] for r in rr], marker=".", label=c["label"]
        )
    ax2.axhline(1.3, color="r", lw=0.8)
    ax2.set_xscale("log")
    ax2.set_xlabel("power-up still window, s")
    ax2.set_ylabel("predicted RMS / floor RMS")
    ax2.set_title("thermal runs (reference table run)", fontsize=8)
    ax2.grid(alpha=0.3, which="both")
    ax2.legend(fontsize=6)
    return save_figure(fig, out_dir, "protocol_hover")
