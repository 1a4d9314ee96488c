"""A calibration as stages, and the gyro a user gets from it.

A calibration is applied stage by stage (the rate-table run's effects, then the thermal run's);
the power-up bias is re-estimated from the first still window of each power-up, as a flight
controller does. Shared by the ablation experiment (:mod:`experiments.ablation`) and the core
calibrator entry (:mod:`experiments.calibrators`).
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.calib.bias import StaticBiasCalibrator
from gyrocore.errors import GyroInputError
from sim.presets import load_preset

__all__ = [
    "TABLE_EFFECTS",
    "THERMAL_EFFECTS",
    "THERMAL_NUISANCE",
    "POWERUP_WINDOW_S",
    "POWERUP_SEARCH_S",
    "SE_SUFFIX",
    "corrected_gyro",
    "powerup_window",
    "powerup_windows",
    "bias_bound_rad_s",
]


#: Effects fitted on the rate-table run (constant temperature) and on the thermal run.
TABLE_EFFECTS = (
    "bias",
    "scale",
    "misalignment",
    "g_sensitivity",
    "scale_asymmetry",
    "scale_nonlinearity",
    "g2_sensitivity",
    "time_offset",
)
THERMAL_EFFECTS = ("bias_thermal", "scale_thermal", "bias_temp_rate", "bias_ramp")
#: Power-up still window (s) and how far into the recording it may be searched (s).
POWERUP_WINDOW_S = 2.0
POWERUP_SEARCH_S = 30.0
#: Calibrator settings for the ablation: block means of ≤ 15000 rows (exact for the linear
#: model) and the "noise_model" covariance: the sandwich with the row covariance implied by the
#: noise model identified (GMWM) on the fit's own residual (white + flicker + RRW + GM). The
#: standard errors feed the drift prediction (:func:`predict_instance`), and the identified
#: noise model is the prediction's noise. Why not the others: with "ols" the rate-table
#: g-sensitivity errors were 5–9 standard errors (bias instability drifts between the mounts);
#: the "auto" HAC (exponential-tail autocovariance) gave |error|/SE RMS 0.82.
#: Rate ramps (± 0.25 s) are left out of both fits: the on-chip low-pass leaves a transient
#: there (RMS 3.3e-3 rad/s on the table run, 10× the noise) that biased the g-sensitivity by up
#: to 4 standard errors and that the noise identification took for a Gauss–Markov term.
_CAL_KW = {"covariance": "noise_model", "max_rows": 15000, "ramp_margin_s": 0.25}
#: Nuisance effects fitted with the thermal run but not applied elsewhere: the thermal run's
#: output filter (25 Hz at 100 Hz) delays the rate by ≈ 7 ms, and its unmodelled residual bursts
#: at every rate ramp (RMS 4.3e-3 rad/s against 5.8e-4 of noise) made the thermal standard errors
#: 3× too large; a fitted time offset (7.07 ms) brings the residual to the noise. Its value
#: belongs to that run's filter setting, not to the 1-kHz flights, so it is dropped from the stage.
THERMAL_NUISANCE = ("time_offset",)


def _as_stages(calibration) -> list[dict]:
    """Normalise a calibration to a list of stages ``{effect: (params, toggle_effect)}``.

    A plain ``{effect: params}`` mapping is one stage whose entries toggle with their own
    name. A list of such mappings is applied in order. An entry key ``"scale@scale_thermal"``
    is effect ``scale`` toggled by ``scale_thermal`` (the thermal run's re-referenced scale).
    """
    if isinstance(calibration, Mapping):
        calibration = [calibration]
    out = []
    for st in calibration:
        d = {}
        for key, pd in st.items():
            eff, _, toggle = key.partition("@")
            d[key] = (eff, dict(pd), toggle or eff)
        out.append(d)
    return out


def corrected_gyro(
    gyro_rad_s: np.ndarray,
    inp: E.ModelInputs,
    calibration,
    subset: Sequence[str],
    still: slice | None,
) -> np.ndarray:
    """The gyro after the corrections in ``subset`` (rad/s, (N, 3)).

    Non-bias effects are removed with the calibration's estimates
    (:func:`gyrocore.effects.registry.correct`, stage by stage; see :func:`_as_stages`). If ``"bias"``
    is in ``subset`` the power-up bias is the mean of the corrected rate over the ``still``
    samples at the start of the recording (true rate 0 there), subtracted after the other
    corrections, as a user does after applying a calibration file. Without a still window
    the calibration's own last ``bias`` (a stale turn-on draw) is used if it has one.
    ``still`` may also be a list of ``(power-up segment slice, still window slice or None)``:
    one power-up calibration per power-up.
    """
    stages = _as_stages(calibration)
    w = np.asarray(gyro_rad_s, float).copy()
    stale_bias = None
    for st in stages:
        active = {eff: pd for key, (eff, pd, tog) in st.items() if tog in subset and eff != "bias"}
        if active:
            w = E.correct(active, w, inp)
        for key, (eff, pd, tog) in st.items():
            if eff == "bias":
                stale_bias = np.asarray(pd["b_rad_s"], float)
    if "bias" in subset:
        segs = still if isinstance(still, list) else [(slice(0, w.shape[0]), still)]
        for seg, win in segs:
            if win is not None and (win.stop or 0) > (win.start or 0):
                w[seg] = w[seg] - w[win].mean(axis=0)
            elif stale_bias is not None:
                w[seg] = w[seg] - stale_bias
    return w


def _stage_from(result, stage: int) -> dict:
    if result is None:
        return {}
    out = {}
    for eff, pd in result.params.items():
        if stage == 2 and eff in THERMAL_NUISANCE:
            continue
        key = "scale@scale_thermal" if (stage == 2 and eff == "scale") else eff
        out[key] = {k: np.asarray(v, float) for k, v in pd.items()}
        # standard errors ride along as extra "<param>__se" entries (ignored by correct();
        # read by the drift prediction, :func:`predict_instance`)
        for k, v in (result.stderr.get(eff) or {}).items():
            if k in E.PARAM_SCHEMA.get(eff, {}) and k not in ("t0_c", "temp_min_c", "temp_max_c"):
                out[key][f"{k}{SE_SUFFIX}"] = np.asarray(v, float)
    return out


#: Suffix of the standard-error entries carried in a calibration stage (see :func:`_stage_from`).
SE_SUFFIX = "__se"


def powerup_window(
    rec, params_true: Mapping | None = None, *, bias_bound_rad_s: float | None = None, window_s: float | None = None
) -> slice | None:
    """The first still :data:`POWERUP_WINDOW_S` window in the first :data:`POWERUP_SEARCH_S`.

    Motion-gated static calibration (:class:`gyrocore.calib.bias.StaticBiasCalibrator`, variance
    gate, false-reject rate 1e-3), refusing while moving and retrying on the next window, as
    a flight controller does at power-up. The gate uses the sensor's white-noise σ (datasheet
    noise density and LSB: σ² = N²·rate + LSB²/12) when known, so rotor vibration cannot
    inflate it. A variance (or Σ|Δ|) gate cannot see a *steady* rotation, so a window whose
    mean exceeds ``bias_bound_rad_s`` (a plausible bias: 5× the datasheet bias spread) is
    refused too and the search goes on after it. None if the start never goes still.
    """
    rate = rec.rate_hz
    n_search = int(min(rec.n, POWERUP_SEARCH_S * rate))
    sigma = None
    if params_true is not None and "arw" in params_true:
        # per-sample white σ² = N²·rate + LSB²/12 (rounding noise); the datasheet knows both
        var = np.asarray(params_true["arw"]["n_rad_per_sqrt_s"], float) ** 2 * rate
        if "quantization" in params_true:
            var = var + float(params_true["quantization"]["lsb_rad_s"]) ** 2 / 12.0
        sigma = np.sqrt(var)
    win_s = POWERUP_WINDOW_S if window_s is None else float(window_s)
    n_search = max(n_search, int(min(rec.n, 2 * win_s * rate)))
    cal = StaticBiasCalibrator(window_s=win_s, rule="mean", statistic="variance", noise_sigma_rad_s=sigma)
    start = 0
    while n_search - start >= win_s * rate:
        try:
            r = cal.fit(rec.slice(start, n_search))
        except GyroInputError:
            return None
        a = start + int(r.window_start_index)
        b = a + int(r.window_samples)
        if bias_bound_rad_s is None or np.all(np.abs(r.bias_rad_s) <= bias_bound_rad_s):
            return slice(a, b)
        start = b  # a steady rotation passed the gate: not a bias
    return None


def bias_bound_rad_s(sensor: str) -> float | None:
    """5× the datasheet bias spread √(σ_b² + σ_turn-on²) of a preset, rad/s (None if unknown)."""
    try:
        d = load_preset(sensor).distribution("bias") or {}
    except Exception:  # noqa: BLE001 - a sensor file without a bias level: no bound
        return None
    sb = float(d.get("b_sigma_rad_s", 0.0))
    st = float(d.get("turn_on_sigma_rad_s", 0.0))
    v = math.hypot(sb, st)
    return 5.0 * v if v > 0 else None


def powerup_windows(
    rec, params_true: Mapping | None = None, *, bias_bound_rad_s: float | None = None, window_s: float | None = None
) -> list[tuple[slice, slice | None]]:
    """One (segment, still window) per power-up (extra column ``power_up_index``; else one).

    ``window_s``: still-window length, s (default :data:`POWERUP_WINDOW_S`)."""
    kw = {"bias_bound_rad_s": bias_bound_rad_s, "window_s": window_s}
    pu = rec.extra.get("power_up_index")
    if pu is None:
        return [(slice(0, rec.n), powerup_window(rec, params_true, **kw))]
    pu = np.asarray(pu)
    edges = np.flatnonzero(np.diff(pu) != 0) + 1
    starts = np.concatenate([[0], edges]).astype(int)
    stops = np.concatenate([edges, [rec.n]]).astype(int)
    out = []
    for a, b in zip(starts, stops):
        win = powerup_window(rec.slice(int(a), int(b)), params_true, **kw) if b - a > 8 else None
        out.append((slice(int(a), int(b)), None if win is None else slice(int(a) + win.start, int(a) + win.stop)))
    return out
