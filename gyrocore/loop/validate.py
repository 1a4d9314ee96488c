"""The loop's model outside its loop: as a parameter file, as a correction of another recording, and
scored on a recording not used to fit it (:func:`validate_model`, the honest "after")."""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.attitude import rate_error_vs_attitude
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from . import lines as LN
from .residual import Residual, build_residual
from .result import LoopResult
from .model import advance
from .evidence import rms
from .scoring import attitude_error_deg

__all__ = [
    "loop_parameters",
    "loop_calibration",
    "model_correction",
    "validate_model",
    "split_halves",
    "check_compatible",
]


def _schema_shape(effect: str, pname: str, order: int) -> tuple:
    base = effect.split("[")[0]
    if base in ("regressor", "step"):
        return (3,)
    if base == "periodic":
        return (3,)
    shape = E.PARAM_SCHEMA[effect][pname]
    return tuple(order if d == "p" else d for d in shape)


def loop_parameters(result: LoopResult, rec: Recording, *, thermal_order: int = 1) -> tuple[dict, dict]:
    """The loop's final model as parameter-file parameters and standard errors.

    Returns ``(params, stderr)``, each ``{effect: {param: ndarray}}`` in the
    :data:`gyrocore.effects.registry.PARAM_SCHEMA` form (SI); family terms (``regressor[..]``,
    ``periodic[..]``, ``step[..]``) carry their coefficients on every axis (0 where the loop
    did not fit one). Thermal polynomials are referenced to the recording's mean temperature
    (``t0_c``) with its range; ``earth_rate`` is converted from the fitted vector Ω_W to
    latitude and heading (W = the reference's world frame, z up).
    """
    params: dict = {}
    stderr: dict = {}
    for eff, table in result.params.items():
        order = thermal_order if eff in ("bias_thermal", "scale_thermal") else 1
        if eff == "earth_rate":
            om = np.array([table[f"omega_W_rad_s[{k}]"][0] for k in range(3)])
            lat = float(np.arctan2(om[2], np.hypot(om[0], om[1])))
            head = float(np.arctan2(om[0], om[1]))
            params[eff] = {"latitude_rad": np.asarray(lat), "heading_rad": np.asarray(head)}
            stderr[eff] = {"latitude_rad": np.asarray(np.nan), "heading_rad": np.asarray(np.nan)}
            continue
        by_param: dict[str, dict] = {}
        for key, (v, se) in table.items():
            pname, _, idx = key.partition("[")
            by_param.setdefault(pname, {})[idx.rstrip("]")] = (v, se)
        params[eff], stderr[eff] = {}, {}
        for pname, vals in by_param.items():
            shape = _schema_shape(eff, pname, order)
            val = np.zeros(shape)
            err = np.full(shape, np.nan)
            for idx, (v, se) in vals.items():
                ix = tuple(int(x) for x in idx.split(",")) if idx else ()
                val[ix] = v
                err[ix] = se
            params[eff][pname] = val
            stderr[eff][pname] = err
        if eff.startswith("periodic["):  # both halves of the line on every axis
            for pname in ("a_cos_rad_s", "a_sin_rad_s"):
                params[eff].setdefault(pname, np.zeros(3))
                stderr[eff].setdefault(pname, np.full(3, np.nan))
        if eff in ("bias_thermal", "scale_thermal"):
            T = np.asarray(rec.temp_c, float)
            params[eff].update(
                t0_c=np.asarray(result.t0_c if result.t0_c is not None else float(np.mean(T))),
                temp_min_c=np.asarray(float(np.nanmin(T))),
                temp_max_c=np.asarray(float(np.nanmax(T))),
            )
            stderr[eff].update(t0_c=np.asarray(np.nan), temp_min_c=np.asarray(np.nan), temp_max_c=np.asarray(np.nan))
    return params, stderr


def loop_calibration(
    result: LoopResult, rec: Recording, *, source_path=None, sensor: str | None = None, thermal_order: int = 1
):
    """The loop's final model as a :class:`gyrocore.calib.params.CalibrationResult` (the parameter
    file ``loop -o`` and ``calibrate`` with a reference attitude write)."""
    from pathlib import Path

    from gyrocore.calib.params import CalibrationResult
    from gyrocore.data.recording import file_sha256

    params, stderr = loop_parameters(result, rec, thermal_order=thermal_order)
    src_name = src_sha = None
    if source_path is not None and Path(source_path).is_file():
        src_name, src_sha = Path(source_path).name, file_sha256(source_path)
    elif source_path is not None:
        src_name = Path(source_path).name
    rms = np.full(3, result.residual_rms_after_rad_s)
    notes = [
        f"fitted by the residual loop against the {result.reference} reference ({result.description}); "
        f"residual_rms_rad_s is the RMS of the window residual over all axes"
    ]
    notes += [f"found: {s.effect}" for s in result.found]
    notes += [f"unexplained ({u.kind}, axis {u.axis}): {u.effect}" for u in result.unexplained]
    thermal = {e: thermal_order for e in params if e in ("bias_thermal", "scale_thermal")}
    return CalibrationResult(
        effects=tuple(params),
        params=params,
        stderr=stderr,
        residual_rms_rad_s=rms,
        method=f"loop_{result.reference}",
        covariance="hac",
        sensor=sensor or str(rec.meta.get("sensor", "unknown")),
        source_file=src_name,
        source_sha256=src_sha,
        n_samples=int(rec.n),
        thermal_order=thermal,
        notes=tuple(notes),
    )


def _param_theta(res: Residual, effect: str, pd: Mapping[str, np.ndarray]) -> np.ndarray:
    """Flatten one effect's parameters in the column order of its regressors."""
    names, _ = res.regressors(
        effect,
        order=int(np.shape(pd.get("poly_rad_s", pd.get("poly_per_c", np.zeros((3, 1)))))[1])
        if effect in ("bias_thermal", "scale_thermal")
        else 1,
    )
    th = np.zeros(len(names))
    for p, n in enumerate(names):
        pname, _, idx = n.partition("[")
        ix = tuple(int(x) for x in idx.rstrip("]").split(",")) if idx else ()
        th[p] = float(np.asarray(pd[pname], float)[ix])
    return th


def model_correction(res: Residual, params: Mapping[str, Mapping[str, np.ndarray]]) -> np.ndarray:
    """Per-sample correction Σ A_e·θ_e (rad/s, (N, 3)) of a parameter set on a residual's
    inputs — the loop's linearised measurement model (``time_offset`` excluded: it is applied
    exactly by advancing the gyro; ``earth_rate`` through latitude/heading and the attitude).

    Thermal polynomials use the parameters' own ``t0_c`` (not the new record's mean).
    """
    n = res.inputs.n
    c = np.zeros((n, 3))
    for eff, pd in params.items():
        if eff in ("time_offset",):
            continue
        if eff == "earth_rate":
            if res.R_WS is not None:
                w_W = E.earth_rate_W(float(pd["latitude_rad"]), float(pd["heading_rad"]))
                c += np.einsum("nji,j->ni", res.R_WS, w_W)
            continue
        if eff in ("bias_thermal", "scale_thermal"):
            coef = np.asarray(pd["poly_rad_s" if eff == "bias_thermal" else "poly_per_c"], float)
            _, A = E.design(eff, res.inputs, order=coef.shape[1], t0_c=float(pd["t0_c"]))
            c += np.einsum("nip,p->ni", A, coef.reshape(-1))
            continue
        th = _param_theta(res, eff, pd)
        c += res.sample_correction(eff, th)
    return c


def validate_model(
    rec: Recording,
    *,
    params_after: Mapping,
    params_before: Mapping,
    reference: str = "auto",
    segments=None,
    window_s: float | None = None,
    refit_bias: bool = True,
) -> dict:
    """Score two parameter sets on a recording not used to fit them (the honest "after").

    ``time_offset`` is applied exactly (the gyro advanced by τ), every other effect through
    the linearised model on this recording's inputs (:func:`model_correction`). The constant
    bias is redrawn at every power-up (turn-on repeatability), so with ``refit_bias`` it is
    re-estimated on this recording for both sets (the window residual's mean): everything
    else is transferred.

    Returns the DESIGN.md ``validation`` keys (``file`` is added by the caller).
    """
    out = {}
    sample = {}
    lines = sorted({k for k in params_after if k.startswith("periodic[")})
    for tag, params in (("before", params_before), ("after", params_after)):
        r = rec
        # narrow-band lines are terms of the measurement's own time (the loop removes them from
        # the raw gyro, before the time-offset advance): removed here the same way — applied
        # after the advance they would be off in phase by 2πf·τ
        per = {k: v for k, v in params.items() if k.startswith("periodic[")}
        if per:
            from dataclasses import replace

            r = replace(rec, gyro_rad_s=rec.gyro_rad_s - _periodic_raw(rec.t_s, per))
            params = {k: v for k, v in params.items() if k not in per}
        tau = float(params.get("time_offset", {}).get("tau_s", 0.0)) if "time_offset" in params else 0.0
        if tau != 0.0:
            r = advance(r, tau)
        res = build_residual(r, reference=reference, segments=segments, window_s=window_s)
        corr = model_correction(res, params)
        y = res.y_rad_s - res.window_mean(corr)
        if refit_bias:
            _, Xb = res.regressors("bias")
            th, *_ = np.linalg.lstsq(Xb.reshape(-1, 3), y.reshape(-1), rcond=None)
            y = y - np.einsum("mip,p->mi", Xb, th)
            corr = corr + th[None, :]
        out[f"residual_rms_{tag}_rad_s"] = rms(y)
        out[f"attitude_error_{tag}_deg"] = attitude_error_deg(res, r, corr)
        out["reference"] = res.kind
        out["n_windows"] = res.m
        if lines and res.kind in ("rate", "attitude"):
            sample[tag] = _sample_residual(res.kind, r, corr)
    out["bias"] = "re-estimated on this recording (turn-on bias)" if refit_bias else "transferred"
    if len(sample) == 2:
        out["periodic"] = _line_validation(sample, lines)
    return out


def _periodic_raw(t: np.ndarray, per: Mapping) -> np.ndarray:
    """Σ a_cos·cos(2πft) + a_sin·sin(2πft) of ``periodic[f]`` parameter sets, (N, 3) rad/s."""
    c = np.zeros((t.shape[0], 3))
    for name, pd in per.items():
        f = E.resolve(name).arg
        ph = 2 * np.pi * f * np.asarray(t, float)
        c += np.outer(np.cos(ph), np.asarray(pd["a_cos_rad_s"], float)) + np.outer(
            np.sin(ph), np.asarray(pd["a_sin_rad_s"], float)
        )
    return c


def _sample_residual(kind: str, rec: Recording, corr: np.ndarray):
    """Sample-level residual (t, e (n, 3), valid (n,)) of a corrected gyro against the rate
    reference or the differentiated attitude reference."""
    g = rec.gyro_rad_s - corr
    if kind == "rate":
        e = g - rec.ref_rate_rad_s
        return rec.t_s, e, np.all(np.isfinite(e), axis=1)
    e, _, ok = rate_error_vs_attitude(rec.t_s, rec.ref_quat_wxyz, g)
    return rec.t_s, e, ok


def _line_validation(sample: dict, lines: Sequence[str]) -> list[dict]:
    """Each periodic term on the validation recording: the line's amplitude in the
    sample-level residual before its removal (the model without the loop's additions) and
    after (the final model), each with its least-squares standard error (white-noise OLS at
    that frequency: the local PSD is what the F-test already judged smooth)."""
    out = []
    for name in lines:
        f = E.resolve(name).arg
        row = {"effect": name, "frequency_hz": f}
        for tag in ("before", "after"):
            t, e, ok = sample[tag]
            coef, se = LN.fit_sinusoid(e[ok], t[ok], f)
            row[f"amplitude_{tag}_rad_s"] = [float(np.hypot(coef[0, i], coef[1, i])) for i in range(3)]
            row[f"amplitude_std_error_{tag}_rad_s"] = [
                float(np.hypot(se[0, i], se[1, i]) / np.sqrt(2)) for i in range(3)
            ]
        out.append(row)
    return out


def split_halves(rec: Recording) -> tuple[Recording, Recording]:
    """The first and second halves of a recording (by time)."""
    t = rec.t_s
    k = int(np.searchsorted(t, 0.5 * (t[0] + t[-1])))
    if k < 10 or rec.n - k < 10:
        raise GyroInputError("the recording is too short to split into halves")
    return rec.slice(0, k), rec.slice(k, rec.n)


def check_compatible(rec_fit: Recording, rec_val: Recording, *, fit_name: str, val_name: str) -> None:
    """One ``error:`` line when a validation recording does not match the fitted one: another
    sensor, sample rate (> 2 % apart) or units."""
    s1, s2 = rec_fit.meta.get("sensor"), rec_val.meta.get("sensor")
    if s1 and s2 and str(s1).strip().lower() != str(s2).strip().lower() and "unknown" not in (s1, s2):
        raise GyroInputError(
            f"--validate {val_name}: sensor '{s2}' differs from the fitted file's '{s1}' "
            "(a model of one sensor does not transfer to another)"
        )
    r1, r2 = rec_fit.rate_hz, rec_val.rate_hz
    if not (abs(r1 - r2) <= 0.02 * max(r1, r2)):
        raise GyroInputError(
            f"--validate {val_name}: sample rate {r2:.6g} Hz differs from the fitted file's {r1:.6g} Hz"
        )
    u1, u2 = rec_fit.meta.get("units"), rec_val.meta.get("units")
    if u1 and u2 and u1 != u2:
        raise GyroInputError(f"--validate {val_name}: units '{u2}' differ from the fitted file's '{u1}'")
