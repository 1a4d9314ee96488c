"""One door for every calibrator: the protocol, its registered entries and the command form.

DESIGN.md "Scoring a user's calibration". A calibration routine has two steps:

``fit(recordings) -> params``
    ``recordings``: the unit's calibration recordings, in order the rate-table run, then the
    thermal run (:class:`gyrocore.data.recording.Recording`, truth metadata stripped; they keep the
    references a real calibration rig gives: the table's rate and attitude, the chamber's
    temperature). ``params`` is the routine's own object (opaque to the harness).
``apply(recording, params) -> gyro``
    ``recording``: a scored recording with *no* truth (no ``ref_*`` columns, no
    ``params_true`` or seed metadata; it keeps the gyro, the accelerometer, the temperature
    and the ``power_up_index`` column, as a flight log does). Returns the corrected gyro,
    rad/s, sensor frame, shape (N, 3), same rows.

Python form: ``module:factory`` (``factory()`` returns an object with ``fit`` and ``apply``),
or one of the registered names in :data:`REGISTRY`:

``core``       gyroharness's own calibration core, exactly as the ablation uses it
               (:class:`CoreCalibrator`);
``article``    the source article's method: power-up bias = mean of the first 200 still
               samples (its Σ|Δ| < 500 counts gate), M = C·B⁻¹ from rate-table integrals;
``px4``        PX4-like: a 3rd-order thermal bias polynomial (TC_G*) fitted on the still parts
               of the thermal run plus the stored calibration offset (CAL_GYRO*_OFF); no
               power-up re-estimate;
``ardupilot``  ArduPilot-like: the start-up gyro calibration (INS_GYR_CAL=1) at every power-up:
               consecutive 0.5-s means until two agree within 0.1 °/s, bias = their average.

Command form (any language): :class:`CommandCalibrator` writes the recordings as data files
into a fresh temporary folder, runs the user's fit and apply command templates there (never
through a shell; placeholders ``{params}``, ``{inputs}``, ``{input}``, ``{output}``; a
timeout), reads the corrected file back and checks it (:func:`check_output`). The truth never
enters the folder; it stays in the harness's memory.

A user's Python routine (``module:factory`` not in :data:`REGISTRY`) runs in its own process
with the same per-step timeout (:class:`IsolatedCalibrator`).

A routine that fails (raises, crashes, hangs, writes nothing, NaN, wrong rows, deg/s where
rad/s belong) raises :class:`RoutineFailure` with a one-line reason; the harness records the
unit as failed and goes on.
"""

from __future__ import annotations

import importlib
import math
import os
import shlex
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording

from . import stages as S
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import read_csv, write_csv
from sim.presets import load_preset

__all__ = [
    "CalibrationRoutine",
    "RoutineFailure",
    "REGISTRY",
    "load_calibrator",
    "strip_truth",
    "TRUTH_FREE_META",
    "calibration_recordings",
    "CoreParams",
    "CoreCalibrator",
    "ArticleCalibrator",
    "PX4Calibrator",
    "ArduPilotCalibrator",
    "CommandCalibrator",
    "IsolatedCalibrator",
    "split_template",
    "check_output",
    "run_routine",
    "datasheet_noise_params",
]

DEG = math.pi / 180.0


# ------------------------------------------------------------------------------ protocol
@runtime_checkable
class CalibrationRoutine(Protocol):
    """What every calibrator offers (see the module docstring)."""

    def fit(self, recordings: Sequence[Recording]) -> Any: ...

    def apply(self, recording: Recording, params: Any) -> np.ndarray: ...


class RoutineFailure(Exception):
    """A user's routine failed on one unit; ``str(exc)`` is the one-line reason."""


#: Registered calibrators: name -> "module:factory".
REGISTRY: dict[str, str] = {
    "core": "experiments.calibrators:CoreCalibrator",
    "article": "experiments.calibrators:ArticleCalibrator",
    "px4": "experiments.calibrators:PX4Calibrator",
    "ardupilot": "experiments.calibrators:ArduPilotCalibrator",
}


def load_calibrator(spec: str, **options) -> CalibrationRoutine:
    """A calibrator from a registered name or ``module:factory`` (``factory(**options)``).

    The module is imported from ``sys.path`` plus the current directory (a ``my_cal.py`` beside
    the user is ``my_cal:factory``).

    Raises :class:`~gyrocore.errors.GyroInputError` (one line) for an unknown name, a module
    that does not import, a missing factory, or an object without ``fit``/``apply``.
    """
    target = REGISTRY.get(spec, spec)
    mod_name, sep, attr = target.partition(":")
    if not sep or not mod_name or not attr:
        raise GyroInputError(
            f"calibrator {spec!r}: expected a registered name ({', '.join(REGISTRY)}) or module:factory"
        )
    if os.getcwd() not in sys.path and "" not in sys.path:  # a module beside the user, as `python -m` does
        sys.path.insert(0, os.getcwd())
    try:
        mod = importlib.import_module(mod_name)
    except Exception as exc:  # noqa: BLE001 - the user's module: any import error becomes one line
        raise GyroInputError(f"calibrator {spec!r}: cannot import {mod_name}: {type(exc).__name__}: {exc}") from None
    factory = getattr(mod, attr, None)
    if factory is None or not callable(factory):
        raise GyroInputError(f"calibrator {spec!r}: {mod_name} has no callable {attr}")
    obj = factory(**options)
    if not (callable(getattr(obj, "fit", None)) and callable(getattr(obj, "apply", None))):
        raise GyroInputError(f"calibrator {spec!r}: {attr}() returned an object without fit() and apply()")
    return obj


# ------------------------------------------------------------------------------ what a routine sees
#: Metadata a routine may see (what a real log or rig file states). Everything else — the
#: true parameters, seeds, the list of simulated effects, notes — is truth and is dropped.
TRUTH_FREE_META = (
    "sensor",
    "sensor_part",
    "scenario",
    "scenario_description",
    "rate_hz",
    "duration_s",
    "accel",
    "power_up_t_s",
    "model",
    "runner",
    "physics_rate_hz",
    "gyro_rate_hz",
)
#: Extra metadata kept in *calibration* recordings: the table program is the rig's reference.
CALIBRATION_META = ("table_phases",)


def strip_truth(rec: Recording, *, references: bool) -> Recording:
    """The recording as a routine may see it.

    ``references=True`` (calibration runs) keeps the rig's references (``ref_*`` columns: the
    table's rate and attitude; the temperature column) and the table program;
    ``references=False`` (scored recordings) drops every ``ref_*`` column. Both keep only
    :data:`TRUTH_FREE_META` metadata and the ``power_up_index`` extra column.
    """
    keep = TRUTH_FREE_META + (CALIBRATION_META if references else ())
    meta = {k: v for k, v in rec.meta.items() if k in keep}
    extra = {k: v for k, v in rec.extra.items() if k == "power_up_index"}
    return Recording(
        t_s=rec.t_s,
        gyro_rad_s=rec.gyro_rad_s,
        accel_m_s2=rec.accel_m_s2,
        temp_c=rec.temp_c,
        ref_rate_rad_s=rec.ref_rate_rad_s if references else None,
        ref_quat_wxyz=rec.ref_quat_wxyz if references else None,
        meta=meta,
        extra=extra,
    )


#: Durations of the quick calibration runs (``quick=True``), s: table, thermal.
QUICK_CALIBRATION_S = (120.0, 300.0)


def calibration_recordings(
    sensor: str, seed: int, *, quick: bool = False, durations_s: tuple[float | None, float | None] | None = None
) -> tuple[Recording, Recording]:
    """The unit's calibration recordings, as simulated (truth still in them; needs :mod:`sim`).

    1. ``turntable`` run ``run=1`` (same unit, another power-up, fresh noise);
    2. ``thermal`` run ``run=2``.

    ``durations_s`` overrides (table, thermal) durations; ``quick`` uses
    :data:`QUICK_CALIBRATION_S`; else the scenarios' defaults.
    """
    import warnings

    from sim import scenarios as S

    if durations_s is None:
        durations_s = QUICK_CALIBRATION_S if quick else (None, None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r1 = S.simulate("turntable", sensor=sensor, seed=seed, run=1, duration_s=durations_s[0]).recording
        r2 = S.simulate("thermal", sensor=sensor, seed=seed, run=2, duration_s=durations_s[1]).recording
    return r1, r2


def datasheet_noise_params(sensor: str | None) -> dict | None:
    """The datasheet's white noise and LSB of a preset, as params (for the power-up gate).

    Noise levels and the output stage are the same for every unit of a preset
    (sim/presets.py), so this is what a user reads off the datasheet. None if unknown.
    """
    if not sensor:
        return None
    try:
        p = load_preset(sensor)
    except Exception:  # noqa: BLE001 - an unknown part: the gate estimates σ from the data
        return None
    out: dict = {}
    arw = p.distribution("arw")
    if arw and "n_rad_per_sqrt_s" in arw and "arw" in p.effects:
        out["arw"] = {"n_rad_per_sqrt_s": np.full(3, float(arw["n_rad_per_sqrt_s"]))}
        if "quantization" in p.effects:
            out["quantization"] = {"lsb_rad_s": np.asarray(float(p.lsb_rad_s))}
    return out or None


def _since_power_up(rec: Recording) -> np.ndarray | None:
    """Time since the first sample of each power-up (``power_up_index``), s; None without it."""
    pu = rec.extra.get("power_up_index")
    if pu is None:
        return None
    pu = np.asarray(pu)
    edges = np.concatenate([[0], np.flatnonzero(np.diff(pu) != 0) + 1])
    start = np.repeat(rec.t_s[edges], np.diff(np.concatenate([edges, [rec.n]])))
    return rec.t_s - start


def _power_up_segments(rec: Recording) -> list[slice]:
    pu = rec.extra.get("power_up_index")
    if pu is None:
        return [slice(0, rec.n)]
    edges = np.flatnonzero(np.diff(np.asarray(pu)) != 0) + 1
    a = np.concatenate([[0], edges]).astype(int)
    b = np.concatenate([edges, [rec.n]]).astype(int)
    return [slice(int(i), int(j)) for i, j in zip(a, b)]


# ------------------------------------------------------------------------------ the core
@dataclass(frozen=True)
class CoreParams:
    """What :class:`CoreCalibrator` fitted.

    Attributes
    ----------
    effects : tuple of str
        The corrections :meth:`CoreCalibrator.apply` makes (``bias`` = power-up bias).
    stages : tuple of dict
        Calibration stages for :func:`experiments.ablation.corrected_gyro`.
    results : tuple
        The :class:`gyrocore.calib.params.CalibrationResult` of each stage (None where not fitted).
    """

    effects: tuple[str, ...]
    stages: tuple[dict, ...]
    results: tuple = ()
    format_version: int = 1


class CoreCalibrator:
    """gyroharness's calibration core behind the door (what the ablation scores).

    Parameters
    ----------
    effects : sequence of str, optional
        Corrections to fit and apply. Default: the correctable effects the sensor's datasheet
        model has (the preset named by the recordings' ``# sensor:`` metadata) — in the
        ablation, the effects present in the unit (the same list for every preset unit).
    cal_kw : mapping, optional
        :class:`gyrocore.calibrator.Calibrator` options (default the ablation's).

    ``fit``: the rate-table run → the table effects (:data:`experiments.ablation.TABLE_EFFECTS`)
    present; the thermal run, first corrected with that, → ``bias`` + the thermal effects
    (+ ``scale`` re-referenced with ``scale_thermal``). ``apply``: those corrections, then the
    power-up bias from the first still window of each power-up
    (:func:`experiments.ablation.powerup_windows`, gate σ from the datasheet).
    """

    name = "core"

    def __init__(
        self,
        *,
        effects: Sequence[str] | None = None,
        cal_kw: Mapping | None = None,
        powerup_window_s: float | None = None,
    ) -> None:
        self.effects = None if effects is None else tuple(effects)
        self.cal_kw = dict(cal_kw) if cal_kw is not None else None
        # still-window length of the power-up bias in apply(), s (None: ablation.POWERUP_WINDOW_S)
        self.powerup_window_s = powerup_window_s

    def _effects_for(self, rec: Recording) -> tuple[str, ...]:
        if self.effects is not None:
            return self.effects
        sensor = rec.meta.get("sensor")
        try:
            on = load_preset(sensor).effects
        except Exception as exc:  # noqa: BLE001
            raise GyroInputError(
                f"core calibrator: no effects given and no known sensor preset ({sensor!r}): {exc}"
            ) from None
        return tuple(e for e in E.CORRECTABLE if e in on)

    def fit(self, recordings: Sequence[Recording]) -> CoreParams:
        import warnings

        recs = list(recordings)
        if not recs:
            raise GyroInputError("core calibrator: no calibration recordings")
        present = self._effects_for(recs[0])
        kw = self.cal_kw if self.cal_kw is not None else S._CAL_KW
        tt = [e for e in S.TABLE_EFFECTS if e in present]
        th = [e for e in S.THERMAL_EFFECTS if e in present]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r1 = Calibrator(effects=["bias"] + [e for e in tt if e != "bias"], **kw).fit(recs[0]) if tt else None
            s1 = S._stage_from(r1, 1)
            r2 = None
            if th:
                if len(recs) < 2:
                    raise GyroInputError("core calibrator: thermal effects need the thermal run (second recording)")
                rec2 = recs[1]
                if s1:
                    inp2 = E.ModelInputs(t_s=rec2.t_s, f_S_m_s2=rec2.accel_m_s2, temp_c=rec2.temp_c)
                    p1 = {eff: pd for key_, (eff, pd, _) in S._as_stages(s1)[0].items() if eff != "bias"}
                    rec2 = rec2.with_gyro(E.correct(p1, rec2.gyro_rad_s, inp2) if p1 else rec2.gyro_rad_s)
                eff2 = ["bias"] + (["scale"] if "scale_thermal" in th else []) + th
                eff2 += [e for e in S.THERMAL_NUISANCE if e not in eff2]  # fitted, not applied (ablation._stage_from)
                r2 = Calibrator(effects=eff2, **kw).fit(rec2)
        return CoreParams(effects=tuple(present), stages=(s1, S._stage_from(r2, 2)), results=(r1, r2))

    def apply(self, recording: Recording, params: CoreParams) -> np.ndarray:
        rec = recording
        inp = E.ModelInputs(
            t_s=rec.t_s, f_S_m_s2=rec.accel_m_s2, temp_c=rec.temp_c, t_since_power_up_s=_since_power_up(rec)
        )
        sensor = rec.meta.get("sensor")
        still = S.powerup_windows(
            rec,
            datasheet_noise_params(sensor),
            bias_bound_rad_s=S.bias_bound_rad_s(sensor) if sensor else None,
            window_s=self.powerup_window_s,
        )
        return S.corrected_gyro(rec.gyro_rad_s, inp, list(params.stages), list(params.effects), still)


# ------------------------------------------------------------------------------ the article
#: The article's window (samples) and motion threshold (raw counts, Σ|Δ| per axis).
ARTICLE_WINDOW = 200
ARTICLE_THRESHOLD_COUNTS = 500.0
#: How far into a power-up the still window is searched, s.
SEARCH_S = 30.0


def _lsb_rad_s(rec: Recording, default_lsb_per_dps: float = 131.0) -> float:
    """Count size of the sensor (datasheet), rad/s; the article's MPU-6050 ±250 °/s if unknown."""
    try:
        return float(load_preset(rec.meta.get("sensor")).lsb_rad_s)
    except Exception:  # noqa: BLE001 - no preset: the article's own sensor
        return DEG / default_lsb_per_dps


def article_powerup_bias(
    gyro_rad_s: np.ndarray,
    lsb_rad_s: float,
    rate_hz: float,
    *,
    window: int = ARTICLE_WINDOW,
    threshold_counts: float = ARTICLE_THRESHOLD_COUNTS,
) -> np.ndarray:
    """The article's power-up bias: mean of the first ``window`` samples whose motion sum passes.

    Non-overlapping windows in the first :data:`SEARCH_S`; a window passes when
    Σ|g[k] − g[k−1]| (raw counts) ≤ ``threshold_counts`` on every axis. If none passes (the
    article would wait for ever), the first window is used.
    """
    g = np.asarray(gyro_rad_s, float)
    n_search = int(min(g.shape[0], max(window, SEARCH_S * rate_hz)))
    counts = g[:n_search] / lsb_rad_s
    for a in range(0, n_search - window + 1, window):
        s = np.abs(np.diff(counts[a : a + window], axis=0)).sum(axis=0)
        if np.all(s <= threshold_counts):
            return g[a : a + window].mean(axis=0)
    return g[:window].mean(axis=0)


def motion_segments(ref_rate_rad_s: np.ndarray, *, still_rad_s: float = 1e-6) -> list[slice]:
    """Maximal runs of samples where the reference rate is non-zero."""
    moving = np.linalg.norm(np.asarray(ref_rate_rad_s, float), axis=1) > still_rad_s
    d = np.diff(np.concatenate([[0], moving.astype(np.int8), [0]]))
    return [slice(int(a), int(b)) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]


def integral_m(
    t_s: np.ndarray, gyro_rad_s: np.ndarray, ref_rad_s: np.ndarray, bias_rad_s: np.ndarray, *, pad: int = 50
) -> np.ndarray:
    """The article's integral method generalised to any number of rotations.

    Per motion segment k (padded by ``pad`` still samples each side): B_k = ∫(ω̂ − b) dt and
    C_k = ∫ω_ref dt (rad, trapezoid). M minimises Σ_k |C_k − M·B_k|², M = (Σ C Bᵀ)(Σ B Bᵀ)⁻¹;
    with exactly three rotations about x, y, z that is the article's M = C·B⁻¹.
    """
    t = np.asarray(t_s, float)
    g = np.asarray(gyro_rad_s, float) - np.asarray(bias_rad_s, float)
    r = np.asarray(ref_rad_s, float)
    CB = np.zeros((3, 3))
    BB = np.zeros((3, 3))
    for s in motion_segments(r):
        a, b = max(0, s.start - pad), min(t.size, s.stop + pad)
        if b - a < 3:
            continue
        B = np.trapezoid(g[a:b], t[a:b], axis=0)
        C = np.trapezoid(r[a:b], t[a:b], axis=0)
        CB += np.outer(C, B)
        BB += np.outer(B, B)
    if np.linalg.matrix_rank(BB) < 3:
        raise GyroInputError("article method: the table run does not turn about three independent axes")
    return np.linalg.solve(BB.T, CB.T).T


class ArticleCalibrator:
    """The source article's method (ARTICLE.md §1, §5): ω = M·(ω̂ − b).

    ``fit``: bias of the table run from its first still 200 samples, M from the table's
    rotations (:func:`integral_m`); the thermal run is not used (the article has no thermal
    model). ``apply``: b = the article's power-up bias per power-up
    (:func:`article_powerup_bias`), then M.
    """

    name = "article"

    def fit(self, recordings: Sequence[Recording]) -> dict:
        rec = recordings[0]
        if rec.ref_rate_rad_s is None:
            raise GyroInputError("article method: the table run has no reference rate")
        lsb = _lsb_rad_s(rec)
        still = np.linalg.norm(rec.ref_rate_rad_s, axis=1) <= 1e-6
        b = article_powerup_bias(rec.gyro_rad_s[still], lsb, rec.rate_hz)
        return {"M": integral_m(rec.t_s, rec.gyro_rad_s, rec.ref_rate_rad_s, b), "lsb_rad_s": lsb}

    def apply(self, recording: Recording, params: Mapping) -> np.ndarray:
        w = np.asarray(recording.gyro_rad_s, float).copy()
        for seg in _power_up_segments(recording):
            w[seg] -= article_powerup_bias(w[seg], float(params["lsb_rad_s"]), recording.rate_hz)
        return w @ np.asarray(params["M"], float).T


# ------------------------------------------------------------------------------ PX4-like
class PX4Calibrator:
    """PX4-like bias rule: thermal compensation polynomial + stored offset, no power-up step.

    PX4's thermal calibration fits, per axis, the gyro offset as a 3rd-order polynomial of
    temperature about a reference temperature (parameters ``TC_G0_X3_*`` … ``TC_G0_X0_*``,
    ``TC_G0_TREF``; outside the calibrated range the temperature is clamped to it), and the
    gyro calibration stores one offset per axis (``CAL_GYRO0_*OFF``) measured still.
    ``fit``: the polynomial from the still samples of the thermal run, the offset = mean of the
    table run's still samples after the polynomial. ``apply``: ω = ω̂ − poly(clamp(T)) − offset.
    Scale errors are not modelled (PX4 has no gyro scale calibration).
    """

    name = "px4"

    def fit(self, recordings: Sequence[Recording]) -> dict:
        table = recordings[0]
        thermal = recordings[1] if len(recordings) > 1 else None
        out = {"tref_c": 25.0, "tmin_c": 25.0, "tmax_c": 25.0, "poly": np.zeros((3, 4))}
        if thermal is not None and thermal.temp_c is not None:
            still = (
                np.ones(thermal.n, bool)
                if thermal.ref_rate_rad_s is None
                else np.linalg.norm(thermal.ref_rate_rad_s, axis=1) <= 1e-6
            )
            T = thermal.temp_c[still]
            tref = float(0.5 * (T.min() + T.max()))
            X = np.vander(T - tref, 4)  # x^3, x^2, x, 1
            coef, *_ = np.linalg.lstsq(X, thermal.gyro_rad_s[still], rcond=None)
            out.update(tref_c=tref, tmin_c=float(T.min()), tmax_c=float(T.max()), poly=coef.T.copy())
        still = (
            np.ones(table.n, bool)
            if table.ref_rate_rad_s is None
            else np.linalg.norm(table.ref_rate_rad_s, axis=1) <= 1e-6
        )
        out["offset_rad_s"] = (table.gyro_rad_s[still] - self._poly(out, table.temp_c, int(still.sum()), still)).mean(
            axis=0
        )
        return out

    @staticmethod
    def _poly(p: Mapping, temp_c: np.ndarray | None, n: int, rows=slice(None)) -> np.ndarray:
        if temp_c is None:
            return np.zeros((n, 3))
        T = np.clip(np.asarray(temp_c, float)[rows], p["tmin_c"], p["tmax_c"]) - p["tref_c"]
        return np.vander(T, 4) @ np.asarray(p["poly"], float).T

    def apply(self, recording: Recording, params: Mapping) -> np.ndarray:
        w = np.asarray(recording.gyro_rad_s, float)
        return w - self._poly(params, recording.temp_c, recording.n) - np.asarray(params["offset_rad_s"], float)


# ------------------------------------------------------------------------------ ArduPilot-like
class ArduPilotCalibrator:
    """ArduPilot-like bias rule: the start-up gyro calibration at every power-up.

    ``AP_InertialSensor::_init_gyro`` (INS_GYR_CAL = 1): average the gyro over short windows;
    when two consecutive averages differ by less than 0.1 °/s (norm), the offset is their mean;
    after 30 tries the closest pair is used. Here the windows are 0.5 s. No table or thermal
    calibration is used (ArduPilot has no gyro scale calibration); ``fit`` returns nothing.
    """

    name = "ardupilot"
    window_s = 0.5
    converge_rad_s = 0.1 * DEG
    tries = 30

    def fit(self, recordings: Sequence[Recording]) -> dict:
        return {}

    def startup_offset(self, gyro_rad_s: np.ndarray, rate_hz: float) -> np.ndarray:
        n = max(1, int(round(self.window_s * rate_hz)))
        g = np.asarray(gyro_rad_s, float)
        means = [g[a : a + n].mean(axis=0) for a in range(0, min(g.shape[0] - n + 1, (self.tries + 1) * n), n)]
        if len(means) < 2:
            return g.mean(axis=0)
        best, best_d = None, np.inf
        for m0, m1 in zip(means[:-1], means[1:]):
            d = float(np.linalg.norm(m1 - m0))
            if d < best_d:
                best, best_d = 0.5 * (m0 + m1), d
            if d < self.converge_rad_s:
                return 0.5 * (m0 + m1)
        return best

    def apply(self, recording: Recording, params: Mapping) -> np.ndarray:
        w = np.asarray(recording.gyro_rad_s, float).copy()
        for seg in _power_up_segments(recording):
            w[seg] -= self.startup_offset(w[seg], recording.rate_hz)
        return w


# ------------------------------------------------------------------------------ command form
PLACEHOLDERS = ("{params}", "{inputs}", "{input}", "{output}")


def split_template(template: str, *, allowed: Sequence[str]) -> list[str]:
    """Split a command template once (POSIX shell-like quoting, :func:`shlex.split`).

    Raises a one-line :class:`GyroInputError` for an empty or unbalanced template, a
    placeholder the step does not offer, or ``{inputs}`` inside a larger word (it expands to
    several arguments).
    """
    try:
        argv = shlex.split(template)
    except ValueError as exc:
        raise GyroInputError(f"command template {template!r}: {exc}") from None
    if not argv:
        raise GyroInputError("command template is empty")
    for a in argv:
        for ph in PLACEHOLDERS:
            if ph in a and ph not in allowed:
                raise GyroInputError(
                    f"command template {template!r}: {ph} is not available here (this step offers {', '.join(allowed)})"
                )
        if "{inputs}" in a and a != "{inputs}":
            raise GyroInputError(
                f"command template {template!r}: {{inputs}} must be a word of its own "
                "(it becomes one argument per calibration recording)"
            )
    return argv


def expand(argv: Sequence[str], values: Mapping[str, str | Sequence[str]]) -> list[str]:
    """Substitute placeholders in an already split template: each becomes whole argument(s).

    ``values["{inputs}"]`` is a list (one argument each); other values are strings substituted
    inside their word. Nothing is re-split or interpreted, so spaces, ``;`` or ``$(...)`` in a
    path stay literal characters of one argument.
    """
    out: list[str] = []
    for a in argv:
        if a == "{inputs}":
            out.extend(str(x) for x in values["{inputs}"])
            continue
        for ph in ("{params}", "{input}", "{output}"):
            if ph in a and ph in values:
                a = a.replace(ph, str(values[ph]))
        out.append(a)
    return out


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1][:300] if lines else ""


def run_command(argv: Sequence[str], *, cwd: str, timeout_s: float, step: str) -> None:
    """Run one step (no shell), in ``cwd``, killing its whole process group on timeout."""
    try:
        proc = subprocess.Popen(
            list(argv),
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
    except OSError as exc:
        raise RoutineFailure(f"{step} command {argv[0]!r} cannot be started: {exc.strerror or exc}") from None
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.communicate()
        raise RoutineFailure(f"{step} command timed out after {timeout_s:g} s (killed)") from None
    if proc.returncode != 0:
        why = _last_line(err.decode("utf-8", "replace")) or _last_line(out.decode("utf-8", "replace"))
        code = proc.returncode
        what = f"was killed by signal {-code}" if code < 0 else f"exited with status {code}"
        raise RoutineFailure(f"{step} command {what}" + (f": {why}" if why else ""))


#: A corrected rate whose regression slope on the raw rate lies within this factor of
#: 180/π is deg/s written where rad/s belong (a calibration changes the slope by percent,
#: not by 57×).
DEG_SLOPE_FACTOR = 1.5


def check_output(
    raw_rad_s: np.ndarray, corrected: np.ndarray, *, t_in: np.ndarray | None = None, t_out: np.ndarray | None = None
) -> np.ndarray:
    """Validate a routine's corrected gyro against the raw one; one-line :class:`RoutineFailure`.

    Checks: shape (N, 3) with N = the input's rows; every value finite; the ``t_s`` column (if
    written) equal to the input's (1 µs); no units mix-up: the least-squares slope of the
    corrected rate on the raw rate (all axes, means removed) is ≈ 1 for any calibration (scale
    errors are percent), ≈ 57.3 for deg/s and ≈ 0.0175 for rad/s read as deg/s; a slope within
    a factor :data:`DEG_SLOPE_FACTOR` of those is refused.
    """
    raw = np.asarray(raw_rad_s, float)
    try:
        w = np.asarray(corrected, float)
    except (TypeError, ValueError) as exc:
        raise RoutineFailure(f"corrected gyro is not numeric: {exc}") from None
    if w.ndim != 2 or w.shape[1] != 3:
        raise RoutineFailure(f"corrected gyro has shape {w.shape}, expected ({raw.shape[0]}, 3)")
    if w.shape[0] != raw.shape[0]:
        raise RoutineFailure(f"corrected gyro has {w.shape[0]} rows, the input has {raw.shape[0]}")
    bad = ~np.isfinite(w)
    if bad.any():
        rows = np.flatnonzero(bad.any(axis=1))
        raise RoutineFailure(f"corrected gyro has {int(bad.sum())} non-finite values (NaN/inf), first at row {rows[0]}")
    if t_in is not None and t_out is not None:
        if t_out.shape != t_in.shape or float(np.max(np.abs(t_out - t_in))) > 1e-6:
            raise RoutineFailure("corrected file's t_s differs from the input's (rows reordered, dropped or retimed)")
    x = raw - raw.mean(axis=0)
    y = w - w.mean(axis=0)
    sxx = float(np.sum(x * x))
    if sxx > 0:
        k = float(np.sum(x * y)) / sxx
        for unit_k, msg in (
            (180.0 / math.pi, "deg/s written where rad/s belong"),
            (math.pi / 180.0, "rad/s divided by 57.3 (read as deg/s?)"),
        ):
            if unit_k / DEG_SLOPE_FACTOR < abs(k) < unit_k * DEG_SLOPE_FACTOR:
                raise RoutineFailure(f"corrected rate = {k:.4g} × the raw rate: {msg}")
    return w


@dataclass
class CommandCalibrator:
    """The command protocol: any program, two command templates.

    Parameters
    ----------
    fit_cmd : str
        e.g. ``"./cal fit {params} {inputs}"``; runs once per unit.
    apply_cmd : str
        e.g. ``"./cal apply {params} {input} {output}"``; runs once per scored recording.
    timeout_s : float
        Per step.
    workdir : str, optional
        Parent of the temporary folders (default the system's).

    ``fit`` creates the unit's temporary folder and writes ``cal_1_turntable.csv``,
    ``cal_2_thermal.csv`` there; ``apply`` writes ``input.csv`` and reads ``output.csv``;
    :meth:`close` (or the harness, via :func:`run_routine`) removes the folder. Relative
    program paths are resolved against the harness's working directory before the run (the
    steps run inside the temporary folder).
    """

    fit_cmd: str
    apply_cmd: str
    timeout_s: float = 120.0
    workdir: str | None = None
    name: str = "command"
    _tmp: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self._fit_argv = _resolve_program(split_template(self.fit_cmd, allowed=("{params}", "{inputs}")))
        self._apply_argv = _resolve_program(split_template(self.apply_cmd, allowed=("{params}", "{input}", "{output}")))

    def fit(self, recordings: Sequence[Recording]) -> str:
        self.close()
        self._tmp = tempfile.TemporaryDirectory(prefix="gyroharness-routine-", dir=self.workdir)
        d = Path(self._tmp.name)
        names = ("cal_1_turntable.csv", "cal_2_thermal.csv")
        paths = []
        for i, rec in enumerate(recordings):
            p = d / (names[i] if i < len(names) else f"cal_{i + 1}.csv")
            write_csv(rec, p)
            paths.append(str(p))
        params = str(d / "params")
        run_command(
            expand(self._fit_argv, {"{params}": params, "{inputs}": paths}),
            cwd=str(d),
            timeout_s=self.timeout_s,
            step="fit",
        )
        return params

    def apply(self, recording: Recording, params: str) -> np.ndarray:
        import warnings

        if self._tmp is None:
            raise RoutineFailure("apply before fit")
        d = Path(self._tmp.name)
        inp, out = d / "input.csv", d / "output.csv"
        for p in (inp, out):
            if p.exists():
                p.unlink()
        write_csv(recording, inp)
        run_command(
            expand(self._apply_argv, {"{params}": params, "{input}": str(inp), "{output}": str(out)}),
            cwd=str(d),
            timeout_s=self.timeout_s,
            step="apply",
        )
        if not out.exists():
            raise RoutineFailure("apply command wrote no output file")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = read_csv(out, repair=False, checks=False)
        except GyroInputError as exc:
            raise RoutineFailure(f"output file rejected: {str(exc).replace(str(d) + os.sep, '')}") from None
        return check_output(recording.gyro_rad_s, got.gyro_rad_s, t_in=recording.t_s, t_out=got.t_s)

    def close(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


# ------------------------------------------------------------------------------ a user's Python routine, isolated
def _isolated_worker(conn, spec: str) -> None:  # pragma: no cover - runs in the child process
    """The child's loop: load the routine once, then answer ``("fit", recs)`` / ``("apply", rec)``.

    The routine's params stay in the child (they need not pickle); replies are
    ``("ok", value)`` or ``("error", one_line_reason)``.
    """
    import warnings

    warnings.simplefilter("ignore")
    try:
        routine = load_calibrator(spec)
    except GyroInputError as exc:
        conn.send(("error", str(exc).splitlines()[0]))
        return
    params = None
    while True:
        try:
            step, payload = conn.recv()
        except EOFError:
            return
        if step == "close":
            return
        try:
            if step == "fit":
                params = routine.fit(payload)
                conn.send(("ok", None))
            else:
                conn.send(("ok", np.asarray(routine.apply(payload, params))))
        except RoutineFailure as exc:
            conn.send(("error", str(exc)))
        except Exception as exc:  # noqa: BLE001 - the user's code: any error becomes the unit's reason
            conn.send(("error", f"{step} raised {type(exc).__name__}: {_one_line(exc)}"))


@dataclass
class IsolatedCalibrator:
    """A user's Python routine (``module:factory``) run in its own process, with a timeout.

    The Python form runs the user's code; code that hangs (a loop that never ends, a lock)
    must not hang the harness. The routine is created in a child process started with the
    ``spawn`` method (no inherited threads or locks; the parent's ``sys.path`` and working
    directory carry over, so a ``my_cal.py`` beside the user still imports), stays there for
    the unit, and answers ``fit`` / ``apply`` through a pipe; each step has ``timeout_s``
    seconds, after which the child is killed and the unit fails with one line. The
    registered calibrators (:data:`REGISTRY`) are the harness's own code and run in-process.

    Parameters
    ----------
    spec : str
        ``module:factory``.
    timeout_s : float
        Per step (fit, each apply), s.
    """

    spec: str
    timeout_s: float = 120.0
    _proc: Any = field(default=None, repr=False)
    _conn: Any = field(default=None, repr=False)

    def _start(self) -> None:
        import multiprocessing as mp

        self.close()
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_isolated_worker, args=(child, self.spec), daemon=True, name="gyroharness-routine"
        )
        self._proc.start()
        child.close()
        self._conn = parent

    def _call(self, step: str, payload) -> Any:
        if self._conn is None:
            raise RoutineFailure("apply before fit")
        try:
            self._conn.send((step, payload))
            ready = self._conn.poll(self.timeout_s)
        except (BrokenPipeError, EOFError, OSError):
            ready = True  # the child is gone: recv below says how
        if not ready:
            self.close()
            raise RoutineFailure(f"{step} timed out after {self.timeout_s:g} s (killed)")
        try:
            status, value = self._conn.recv()
        except (EOFError, OSError):
            code = None
            if self._proc is not None:
                self._proc.join(timeout=5.0)
                code = self._proc.exitcode
            self.close()
            raise RoutineFailure(f"{step}: the routine's process died (exit code {code})") from None
        if status != "ok":
            raise RoutineFailure(str(value))
        return value

    def fit(self, recordings: Sequence[Recording]) -> None:
        self._start()
        return self._call("fit", list(recordings))

    def apply(self, recording: Recording, params: Any) -> np.ndarray:
        return self._call("apply", recording)

    def close(self) -> None:
        if self._conn is not None:
            try:
                self._conn.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            self._proc.join(timeout=1.0)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
            self._proc = None


def _resolve_program(argv: list[str]) -> list[str]:
    """Make a relative program path (``./cal``, ``bin/cal``) absolute: steps run elsewhere."""
    prog = argv[0]
    if os.sep in prog and not os.path.isabs(prog):
        argv = [os.path.abspath(prog)] + argv[1:]
    # relative file arguments (a script: "python my_cal.py ...") likewise
    return [argv[0]] + [
        os.path.abspath(a)
        if (not a.startswith("-") and "{" not in a and os.path.isfile(a) and not os.path.isabs(a))
        else a
        for a in argv[1:]
    ]


def run_routine(
    routine: CalibrationRoutine, calibration: Sequence[Recording], scored: Sequence[Recording]
) -> list[np.ndarray]:
    """Fit on the calibration recordings and apply to each scored recording (all truth-free).

    Returns the checked corrected gyros. Raises :class:`RoutineFailure` with a one-line reason
    when the routine fails in any way (its exception, its command, or its output).
    """
    try:
        try:
            params = routine.fit(list(calibration))
        except RoutineFailure:
            raise
        except Exception as exc:  # noqa: BLE001 - the user's code: any error becomes the unit's reason
            raise RoutineFailure(f"fit raised {type(exc).__name__}: {_one_line(exc)}") from None
        out = []
        for rec in scored:
            try:
                w = routine.apply(rec, params)
            except RoutineFailure:
                raise
            except Exception as exc:  # noqa: BLE001
                raise RoutineFailure(f"apply raised {type(exc).__name__}: {_one_line(exc)}") from None
            out.append(check_output(rec.gyro_rad_s, w))
        return out
    finally:
        close = getattr(routine, "close", None)
        if callable(close):
            close()


def _one_line(exc: BaseException) -> str:
    s = " ".join(str(exc).split())
    return s[:300]
