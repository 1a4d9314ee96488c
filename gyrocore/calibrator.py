"""The correction model: fit any subset of catalogue effects.

``Calibrator(effects=[...]).fit(recording)`` returns a frozen
:class:`~gyrocore.calib.params.CalibrationResult`
(parameters in :data:`gyrocore.effects.registry.PARAM_SCHEMA` form, SI, with standard errors);
``result.apply(recording)`` removes the effects with :func:`gyrocore.effects.registry.correct`.
The references are taken from the file, in this order:

1. a segments file of known rotation angles (``segments=``) → the article's integral method
   (:func:`gyrocore.calib.rotations.integral_calibration`): bias from the still parts, K and M from
   the integrated outputs; effects ``bias``, ``scale``, ``misalignment`` and
   ``g_sensitivity`` (fitted on the still poses first, as in imucal's Ferraris method);
2. reference rates (``ref_*_rad_s`` columns, rate table or simulation) → joint least squares
   of all effects against y − ω_ref (:mod:`gyrocore.calib.lsq`);
3. neither → still parts (:data:`gyrocore.calib.rotations.STILL_GATE`) with reference rate 0:
   bias-type effects (bias, thermal bias, ramp, g-sensitivity over several poses); the
   rate-dependent ones are then reported unobservable by name.

The result and its parameter file are :mod:`gyrocore.calib.params`.

Article form (ARTICLE.md §5): ω = M·diag(1/s)·(ω̂′ − b), ω̂′ = ω̂ − H·a, which is this
model with K⁻¹ = M·diag(1/s) (:func:`gyrocore.effects.registry.article_from_k`), b = ``bias`` and
H = ``g_sensitivity``.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace as _replace
from pathlib import Path
from typing import Sequence

import numpy as np

from gyrocore.calib.params import CalibrationResult, needs_accel, needs_temp, noise_model_dict
from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError
from gyrocore.calib.rows import ReferenceRows
from gyrocore.data.columns import columns_of
from gyrocore.data.recording import ACCEL_COLS, REF_RATE_COLS, TEMP_COL, Recording, file_sha256
from gyrocore.data.still import moving_throughout, still_samples
from gyrocore.noise.model import NoiseModel

__all__ = [
    "FITTABLE",
    "Calibrator",
    "IntegralMethod",
    "PosesMethod",
    "AttitudeMethod",
    "LeastSquaresMethod",
    "near_rate_changes",
    "has_reference_attitude",
]

#: Catalogue effects that ``calibrate`` can fit (those with least-squares regressors); every
#: family term (``periodic[...]``, ``step[...]``, ``regressor[...]``) is fittable too.
FITTABLE: tuple[str, ...] = tuple(e.name for e in E.REGISTRY.values() if e.fittable)
_INTEGRAL_EFFECTS = ("bias", "scale", "misalignment", "g_sensitivity")
_THERMAL_META = E.THERMAL_META


def _not_fittable_message(eff: str) -> str:
    if eff in E.STOCHASTIC:
        return f"effect {eff} is a noise term, identified by 'gyroharness allan', not by calibrate"
    return f"effect {eff} is not fitted by calibrate (fittable: {', '.join(FITTABLE)})"


# ============================================================================ estimator
def _unflatten(effect: str, vec: np.ndarray, order: int) -> dict[str, np.ndarray]:
    """Flat LsqFit slice -> {param: array} in PARAM_SCHEMA shapes."""
    return E.resolve(effect).unflatten(vec, order)


def near_rate_changes(
    t_s: np.ndarray, w_ref_rad_s, margin_s: float, *, threshold_rad_s2: float = 1e-2, chunk_rows: int = 1 << 20
) -> np.ndarray:
    """Boolean (N,): samples within ``margin_s`` of a change of the reference rate
    (|Δω_ref|/Δt > ``threshold_rad_s2`` on any axis) — rate ramps and their filter transients.

    ``w_ref_rad_s``: the (N, 3) reference rate, or a callable ``(a, b) -> rows a:b`` (a spilled
    record read a window at a time, :meth:`gyrocore.calib.rows.ReferenceRows.ref_rows`); windows of
    ``chunk_rows`` rows, each read with one row either side. Sample i is a ramp sample when the
    rate changes faster than the threshold between i−1 and i or between i and i+1; every sample
    within k = round(margin_s / median Δt) samples of a ramp sample is near (the dilation
    marks each run of ramp samples ± k: the same mask as a convolution with a box of 2k + 1).
    Memory: the mask (1 B/sample) and one window."""
    t = np.asarray(t_s, float)
    n = t.size
    if n < 3:
        return np.zeros(n, bool)
    read = w_ref_rad_s if callable(w_ref_rad_s) else (lambda a, b, _w=np.asarray(w_ref_rad_s, float): _w[a:b])
    ramp = np.zeros(n, bool)
    step = max(int(chunk_rows), 2)
    for a in range(0, n, step):
        b = min(a + step, n)
        lo, hi = max(a - 1, 0), min(b + 1, n)
        w = np.asarray(read(lo, hi), float)
        fast = np.max(np.abs(np.diff(w, axis=0)), axis=1) / np.diff(t[lo:hi]) > threshold_rad_s2  # pairs lo..hi-1
        # sample i (a ≤ i < b) is a ramp sample if pair (i−1, i) or pair (i, i+1) is fast
        i = np.arange(a, b)
        left = np.zeros(b - a, bool)
        has_left = i - 1 >= lo
        left[has_left] = fast[(i - 1 - lo)[has_left]]
        right = np.zeros(b - a, bool)
        has_right = i + 1 < hi
        right[has_right] = fast[(i - lo)[has_right]]
        ramp[a:b] = left | right
    if not ramp.any():
        return ramp
    k = int(round(margin_s / float(np.median(np.diff(t)))))
    near = np.zeros(n, bool)
    for a in range(0, n, step):  # runs of ramp samples, window by window (a run may span two)
        idx = np.flatnonzero(ramp[a : a + step])
        if idx.size == 0:
            continue
        cut = np.flatnonzero(np.diff(idx) > 1)
        starts = idx[np.r_[0, cut + 1]] + a
        ends = idx[np.r_[cut, idx.size - 1]] + a
        for s0, e0 in zip(starts, ends):
            near[max(s0 - k, 0) : min(e0 + k + 1, n)] = True
    return near


def _outliers(axis_residual, used: np.ndarray, n: int) -> np.ndarray:
    """Rows whose residual lies more than 6 robust σ (1.4826·MAD) from the median on any axis,
    among the ``used`` rows; ``axis_residual(i)`` returns a fresh (N,) copy of axis i, worked
    on in place (the median and the MAD do not depend on the order the partition leaves: the
    same values as ``np.median(e[used], axis=0)``, one (N,) array at a time)."""
    med, s_rob = np.zeros(3), np.zeros(3)
    all_used = bool(used.all())
    for i in range(3):
        ei = axis_residual(i)
        ei = ei if all_used else ei[used]
        med[i] = np.median(ei, overwrite_input=True)
        np.subtract(ei, med[i], out=ei)
        np.abs(ei, out=ei)
        s_rob[i] = 1.4826 * np.median(ei, overwrite_input=True)
        del ei
    thr = 6.0 * np.where(s_rob > 0, s_rob, np.inf)
    bad = np.zeros(n, bool)  # |e − med| > thr on any axis, one axis at a time
    for i in range(3):
        ei = axis_residual(i)
        np.subtract(ei, med[i], out=ei)
        np.abs(ei, out=ei)
        bad |= ei > thr[i]
        del ei
    return bad & used


def _settle_time_offset(refit):
    """Gauss–Newton on the time offset τ (the regressor −dω/dt is a linearisation): fit at τ = 0,
    then refit at the accumulated τ until its step is below 1e-3 standard errors (at most 8
    steps). Returns the last fit and τ, s. Only one fit is held at a time (each holds a
    full-resolution residual)."""
    fit = refit(0.0)
    tau_total = 0.0
    for _ in range(8):
        d = float(fit.effect_theta("time_offset")[0])
        if not np.isfinite(fit.effect_stderr("time_offset")[0]) or d == 0.0:
            break
        tau_total += d
        fit = None  # free the previous full-resolution residual first
        fit = refit(tau_total)
        if abs(float(fit.effect_theta("time_offset")[0])) < 1e-3 * float(fit.effect_stderr("time_offset")[0]):
            break
    return fit, tau_total


def _external_bias_dict(ext) -> dict:
    """``bias_rad_s``, ``bias_stderr_rad_s``, ``noise_lr_rad2_s`` from a StaticBiasResult or a mapping."""
    if hasattr(ext, "bias_rad_s") and hasattr(ext, "noise_sigma_rad_s"):
        # StaticBiasResult: long-run variance σ²·VIF per sample → (rad/s)²·s with the window's rate
        rate = ext.window_samples / ext.window_s
        lr = np.asarray(ext.noise_sigma_rad_s, float) ** 2 * np.asarray(ext.vif, float) / rate
        return {
            "bias_rad_s": np.asarray(ext.bias_rad_s, float),
            "bias_stderr_rad_s": np.asarray(ext.bias_se_rad_s, float),
            "noise_lr_rad2_s": lr,
        }
    try:
        d = {k: np.asarray(ext[k], float) for k in ("bias_rad_s", "bias_stderr_rad_s", "noise_lr_rad2_s")}
    except (KeyError, TypeError):
        raise GyroInputError("external bias needs bias_rad_s, bias_stderr_rad_s and noise_lr_rad2_s") from None
    return d


def has_reference_attitude(rec: Recording) -> bool:
    """True when the recording carries a reference attitude (``ref_q*``) valid at two or more
    samples."""
    q = rec.ref_quat_wxyz
    return q is not None and int(np.isfinite(q).all(axis=1).sum()) >= 2


class Calibrator:
    """Fit catalogue effects against the references in a recording.

    Parameters
    ----------
    effects : sequence of str
        Effects to fit: catalogue (see :data:`FITTABLE`) or registry family terms
        (``periodic[37.5]``, ``step[12.25]``, ``regressor[omega_y*omega_z]``;
        :func:`gyrocore.effects.registry.resolve`), e.g. ``["bias", "scale", "misalignment"]``. Order matters only for observability: an earlier effect keeps a
        column that a later one duplicates.
    thermal_order : "auto" or int
        Polynomial order of ``bias_thermal``/``scale_thermal``; "auto" chooses it from the
        data (:func:`gyrocore.calib.thermal.select_thermal_orders`, up to ``max_thermal_order``).
    max_thermal_order : int
    thermal_alpha : float
        Significance level of the order tests.
    segments : path or sequence, optional
        Known-rotation segments → the integral method.
    covariance : str
        ``"auto"`` (Ljung–Box switch), ``"ols"``, ``"hac"``, ``"newey_west"``, ``"block"``, or
        ``"noise_model"``: the sandwich with the row covariance implied by the gyro's noise
        model (white + flicker + rate random walk + Gauss–Markov, started at the power-up =
        the first sample; :func:`gyrocore.calib.covariance.noise_model_meat`). The model is ``noise`` if
        given, else identified (:func:`gyrocore.noise.allan.identify_noise`, GMWM) on the residual
        of the first fit (outliers of the robust pass set to 0). Least-squares method only.
    noise : gyrocore.noise.model.NoiseModel or gyrocore.noise.allan.AllanAnalysis, optional
        The noise model for ``covariance="noise_model"`` (e.g. identified on a still
        recording of the same session); default: identified from the fit's residual.
    ramp_margin_s : float
        Reference-rate method: leave out the samples within this time of a change of the
        reference rate (|Δω_ref|/dt > 1e-2 rad/s²). At rate ramps the gyro's own output
        filter leaves a transient no catalogue effect describes (on the icm42688p table run
        10× the noise); fitted, it biased the g-sensitivity by up to 4 standard errors
        0 (default): use every sample.
    on_unobservable : {"drop", "raise"}
        Report unobservable parameters (fit the rest) or raise
        :class:`~gyrocore.errors.UnobservableError`.
    robust : bool
        After a first fit, exclude samples whose residual exceeds 6 robust σ (rate-table
        transients the model does not describe) and refit; the count is a note.
    max_rows : int
        Fit block means of consecutive samples when the data have more rows than this
        (exact for the linear model; see ``lsq.solve(average=)``).
    still_window_s, still_false_reject_rate : float
        Still detection (no reference rate / integral method).
    sensor : str, optional
        Sensor name; default the file's ``# sensor:`` metadata.
    external_bias : StaticBiasResult or mapping, optional
        Integral method only: take the bias from elsewhere (e.g. a static recording of the
        same session) instead of the still parts of the data — for hand turns without a
        still part. A :class:`gyrocore.calib.bias.StaticBiasResult`, or a mapping with
        ``bias_rad_s``, ``bias_stderr_rad_s`` and ``noise_lr_rad2_s`` ((rad/s)²·s, the
        long-run noise variance, N² for white noise). Its standard error and the noise are
        propagated into the standard errors of K and M.
    """

    def __init__(
        self,
        *,
        effects: Sequence[str],
        thermal_order: str | int = "auto",
        max_thermal_order: int = 3,
        thermal_alpha: float = 0.01,
        segments=None,
        covariance: str = "auto",
        on_unobservable: str = "drop",
        robust: bool = True,
        max_rows: int = 30000,
        still_window_s: float = 1.0,
        still_false_reject_rate: float = 1e-3,
        sensor: str | None = None,
        external_bias=None,
        noise=None,
        ramp_margin_s: float = 0.0,
        angle_sigma_deg: float = 0.0,
        axis_sigma_deg: float = 0.0,
        poses: bool = False,
        pose_std_factor: float = 5.0,
    ) -> None:
        effs = E.check_effect_names(effects)
        if not effs:
            raise GyroInputError("no effects given to calibrate (e.g. --effects bias,scale,misalignment)")
        if len(set(effs)) != len(effs):
            raise GyroInputError("an effect is listed twice")
        for e in effs:
            if not E.resolve(e).fittable:
                raise GyroInputError(_not_fittable_message(e))
        if thermal_order != "auto":
            try:
                thermal_order = int(thermal_order)
            except (TypeError, ValueError):
                raise GyroInputError(f"thermal order must be 'auto' or 1..3, got {thermal_order!r}") from None
            if not 1 <= thermal_order <= 3:
                raise GyroInputError(f"thermal order must be 'auto' or 1..3, got {thermal_order}")
        if not 1 <= int(max_thermal_order) <= 3:
            raise GyroInputError(f"max thermal order must be 1..3, got {max_thermal_order}")
        if segments is not None:
            bad = [e for e in effs if e not in _INTEGRAL_EFFECTS]
            if bad:
                raise GyroInputError(
                    f"with a segments file (integral method) only {', '.join(_INTEGRAL_EFFECTS)} can be fitted, not {', '.join(bad)}"
                )
        if external_bias is not None:
            if segments is None:
                raise GyroInputError("an external bias is used by the integral method only (give a segments file)")
            if "g_sensitivity" in effs:
                raise GyroInputError(
                    "g_sensitivity with an external bias is not supported (it is fitted on the still poses with the bias)"
                )
            external_bias = _external_bias_dict(external_bias)
        if noise is not None and not isinstance(noise, NoiseModel):
            noise = noise.noise_model(("x", "y", "z"))  # an identification (identify_noise)
        self.noise = noise
        if not (np.isfinite(ramp_margin_s) and ramp_margin_s >= 0):
            raise GyroInputError(f"ramp margin must be >= 0 s, got {ramp_margin_s}")
        self.ramp_margin_s = float(ramp_margin_s)
        for nm, v in (("angle", angle_sigma_deg), ("axis", axis_sigma_deg)):
            if not (np.isfinite(v) and v >= 0):
                raise GyroInputError(f"{nm} uncertainty must be >= 0 deg, got {v}")
        #: known rotations' angle / axis uncertainty (integral method), deg
        self.angle_sigma_deg = float(angle_sigma_deg)
        self.axis_sigma_deg = float(axis_sigma_deg)
        self.external_bias = external_bias
        self.effects = tuple(effs)
        self.thermal_order = thermal_order
        self.max_thermal_order = int(max_thermal_order)
        self.thermal_alpha = float(thermal_alpha)
        self.segments = segments
        self.covariance = covariance
        self.on_unobservable = on_unobservable
        self.robust = bool(robust)
        self.max_rows = int(max_rows)
        self.still_window_s = float(still_window_s)
        self.still_false_reject_rate = float(still_false_reject_rate)
        self.sensor = sensor
        if poses:
            bad = [e for e in effs if e not in ("bias", "scale", "misalignment")]
            if bad or segments is not None or external_bias is not None:
                raise GyroInputError(
                    "the multi-pose method (poses) fits bias, scale and misalignment only, without segments or an "
                    "external bias" + (f", not {', '.join(bad)}" if bad else "")
                )
        #: multi-pose method (gravity directions of still poses as the reference; Tedaldi et al. 2014)
        self.poses = bool(poses)
        if not (np.isfinite(pose_std_factor) and pose_std_factor >= 1):
            raise GyroInputError(f"pose std factor must be >= 1, got {pose_std_factor}")
        self.pose_std_factor = float(pose_std_factor)

    def _common(self, meta, source_path, *, has_accel: bool, has_temp: bool) -> dict:
        """The result fields every fit path shares (sensor, data file name and SHA-256), after
        checking that the data carry the columns the effects need (one ``error:`` line)."""
        for eff in self.effects:
            if needs_accel(eff) and not has_accel:
                raise GyroInputError(f"effect {eff} needs the accel_*_m_s2 columns, which the data lack")
            if needs_temp(eff) and not has_temp:
                raise GyroInputError(f"effect {eff} needs the temp_c column, which the data lack")
        src_name = src_sha = None
        if source_path is not None:
            src_name = Path(source_path).name
            src_sha = file_sha256(source_path)
        sensor = self.sensor or str(meta.get("sensor", "unknown"))
        return dict(sensor=sensor, source_file=src_name, source_sha256=src_sha)

    # ------------------------------------------------------------------ public
    def fit(self, recording, *, source_path: str | os.PathLike | None = None) -> CalibrationResult:
        """Fit the effects; ``source_path`` (the data file) is recorded by name and SHA-256.

        ``recording``: a :class:`~gyrocore.data.recording.Recording`, or the columns of one held on
        disk (a :class:`gyrocore.data.spill.ColumnSpill`, e.g. ``spill_columns(path, folder,
        accel=True, groups=("temp", "ref_rate"))``: a long file fitted a window at a time by the
        least-squares method, with the numbers of the same fit in memory). The method is
        :meth:`strategy`'s."""
        cols = columns_of(recording)
        common = self._common(
            cols.meta,
            source_path,
            has_accel=all(c in cols.names for c in ACCEL_COLS),
            has_temp=TEMP_COL in cols.names,
        )
        return self.strategy(cols).fit(cols, common, source_path)

    def strategy(self, cols):
        """The method for the references in the data (the module docstring's order): known
        rotations (:class:`IntegralMethod`), gravity poses (:class:`PosesMethod`), a reference
        attitude without reference rates (:class:`AttitudeMethod`), else reference rates or the
        still parts (:class:`LeastSquaresMethod`)."""
        if self.segments is not None:
            return IntegralMethod(self)
        if self.poses:
            return PosesMethod(self)
        rec = getattr(cols, "recording", None)
        if not all(c in cols.names for c in REF_RATE_COLS) and rec is not None and has_reference_attitude(rec):
            return AttitudeMethod(self)
        return LeastSquaresMethod(self)


def _in_memory(cols, what: str) -> Recording:
    """The recording in memory behind a chunk source, or one error line for a recording on disk."""
    rec = getattr(cols, "recording", None)
    if rec is None:
        raise GyroInputError(
            f"{what} needs the recording in memory (a long file on disk is fitted against its reference rates only)"
        )
    return rec


# ============================================================================ the four methods
class IntegralMethod:
    """Known rotations (a segments file): the article's integral method."""

    def __init__(self, options: "Calibrator") -> None:
        self.o = options

    def fit(self, cols, common: dict, source_path=None) -> CalibrationResult:
        from gyrocore.calib import lsq  # (lazy: scipy.stats is ~40 MiB that applying a calibration does not need)
        from gyrocore.calib.rotations import integral_calibration

        from gyrocore.calib.rotations import STILL_GATE, segments_from_any

        rec = _in_memory(cols, "the integral method (segments)")
        segs = segments_from_any(self.o.segments)
        if self.o.external_bias is not None:
            still = None  # no still part needed: the bias comes from elsewhere
        else:
            still = still_samples(
                rec,
                _replace(STILL_GATE, window_s=self.o.still_window_s, false_reject_rate=self.o.still_false_reject_rate),
                exclude_s=[(s_.t_start_s, s_.t_end_s) for s_ in segs],
                margin_s=0.5,
            )
        params: dict = {}
        stderr: dict = {}
        notes = []
        H = None
        unobs: tuple = ()
        reasons: dict = {}
        if "g_sensitivity" in self.o.effects:
            # H from the still poses (rate 0, gravity in different directions), jointly with
            # the bias; then removed before integrating (imucal's Ferraris does the same)
            inp = E.ModelInputs(t_s=rec.t_s, omega_S_rad_s=np.zeros((rec.n, 3)), f_S_m_s2=rec.accel_m_s2)
            fit = lsq.fit_effects(
                rec.gyro_rad_s,
                ["bias", "g_sensitivity"],
                inp,
                weights=still.astype(float),
                covariance=self.o.covariance,
                on_unobservable=self.o.on_unobservable,
            )
            H = fit.effect_theta("g_sensitivity").reshape(3, 3)
            params["g_sensitivity"] = {"h_rad_s_per_m_s2": H}
            stderr["g_sensitivity"] = {"h_rad_s_per_m_s2": fit.effect_stderr("g_sensitivity").reshape(3, 3)}
            unobs, reasons = fit.unobservable, dict(fit.unobservable_reason)
            notes.append(
                f"g_sensitivity fitted on {int(still.sum())} still samples (poses), standard errors: {fit.cov_kind}"
            )
        res = integral_calibration(
            rec,
            segs,
            still=still,
            h_rad_s_per_m_s2=H,
            **(self.o.external_bias or {}),
            angle_sigma_rad=np.radians(self.o.angle_sigma_deg),
            axis_sigma_rad=np.radians(self.o.axis_sigma_deg),
        )
        if self.o.angle_sigma_deg or self.o.axis_sigma_deg:
            notes.append(
                f"standard errors include the known angles' uncertainty: angle {self.o.angle_sigma_deg:g} deg, "
                f"axis {self.o.axis_sigma_deg:g} deg per segment"
            )
        if self.o.external_bias is not None:
            notes.append(
                "bias taken from outside the data (external bias; its standard error is propagated into K and M)"
            )
        if "bias" in self.o.effects:
            params["bias"] = {"b_rad_s": res.bias_rad_s}
            stderr["bias"] = {"b_rad_s": res.bias_stderr_rad_s}
        if "scale" in self.o.effects:
            params["scale"] = {"s": res.scale}
            stderr["scale"] = {"s": res.scale_stderr}
        if "misalignment" in self.o.effects:
            params["misalignment"] = {"m_rad": res.misalignment_rad}
            stderr["misalignment"] = {"m_rad": res.misalignment_stderr_rad}
        elif "scale" in self.o.effects:
            notes.append("misalignment not requested: K's off-diagonal terms are left in the data")
        if "bias" not in self.o.effects:
            notes.append("bias not requested but still removed before integrating (the integral method needs it)")
        integral = {
            "M": res.M,
            "M_stderr": res.M_stderr,
            "K": res.K,
            "K_stderr": res.K_stderr,
            "B_rad": res.B_rad,
            "C_rad": res.C_rad,
            "angle_residual_rad": res.angle_residual_rad,
            "noise_lr_rad2_s": res.noise_lr_rad2_s,
            "n_still": res.n_still,
            "segment_duration_s": res.segment_duration_s,
        }
        rms = res.still_rms_rad_s
        params = {e: params[e] for e in self.o.effects if e in params}
        stderr = {e: stderr[e] for e in self.o.effects if e in stderr}
        return CalibrationResult(
            effects=self.o.effects,
            params=params,
            stderr=stderr,
            residual_rms_rad_s=rms,
            unobservable=unobs,
            unobservable_reason=reasons,
            method="integral",
            covariance="integral",
            n_samples=int(res.n_still),
            notes=tuple(notes),
            integral=integral,
            **common,
        )


class PosesMethod:
    """Still poses joined by turns, gravity as the reference (IMU-TK)."""

    def __init__(self, options: "Calibrator") -> None:
        self.o = options

    def fit(self, cols, common: dict, source_path=None) -> CalibrationResult:
        """The multi-pose method (:func:`gyrocore.calib.rotations.gravity_pose_calibration`, Tedaldi
        et al. 2014, IMU-TK): K from the turns between still poses, each pose's measured
        gravity direction carried through the corrected, integrated gyro onto the next pose's;
        bias from the first pose. scale s_i = K_ii − 1, misalignment = K's off-diagonal entries
        (:data:`gyrocore.effects.registry.MISALIGNMENT_ORDER`), standard errors from the fit's Jacobian
        scaled by its residual (the hand-held poses' tremble included)."""
        from gyrocore.calib.rotations import gravity_pose_calibration

        rec = _in_memory(cols, "the multi-pose method (poses)")
        if rec.accel_m_s2 is None:
            raise GyroInputError("the multi-pose method needs the accel_*_m_s2 columns (gravity is the reference)")
        r = gravity_pose_calibration(rec, pose_std_factor=self.o.pose_std_factor)
        K, Kse = np.asarray(r.K, float), np.asarray(r.K_stderr, float)
        params: dict = {
            "bias": {"b_rad_s": r.bias_rad_s},
            "scale": {"s": np.diag(K) - 1.0},
            "misalignment": {"m_rad": np.array([K[i, j] for i, j in E.MIS_IDX])},
        }
        stderr: dict = {
            "bias": {"b_rad_s": r.bias_stderr_rad_s},
            "scale": {"s": np.diag(Kse).copy()},
            "misalignment": {"m_rad": np.array([Kse[i, j] for i, j in E.MIS_IDX])},
        }
        n_used = int(r.residual_rad.shape[0])
        notes = [
            f"multi-pose method (Tedaldi et al. 2014): {len(r.intervals)} still poses, {n_used} motions between "
            f"them used"
            + (f" ({r.n_motions_saturated} through clipped samples dropped)" if r.n_motions_saturated else "")
            + f"; gravity-direction misfit after calibration {np.degrees(r.rms_residual_rad):.2f} deg RMS; "
            f"Jacobian condition {r.condition:.3g}; bias from the first pose",
            "residual_rms_rad_s: the still poses' scatter is not a rate residual here (the reference is the "
            "gravity direction); see the misfit above",
        ]
        if "scale" in self.o.effects and "misalignment" not in self.o.effects:
            notes.append("misalignment not requested: K's off-diagonal terms are left in the data")
        if "bias" not in self.o.effects:
            notes.append("bias not requested but still removed before integrating (the method needs it)")
        params = {e: params[e] for e in self.o.effects}
        stderr = {e: stderr[e] for e in self.o.effects}
        return CalibrationResult(
            effects=self.o.effects,
            params=params,
            stderr=stderr,
            residual_rms_rad_s=np.full(3, np.nan),
            method="gravity_poses",
            covariance="jacobian",
            n_samples=int(sum(b - a for a, b in r.intervals)),
            notes=tuple(notes),
            **common,
        )


class AttitudeMethod:
    """A reference attitude without reference rates: the residual loop's fit of the named effects."""

    def __init__(self, options: "Calibrator") -> None:
        self.o = options

    def fit(self, cols, common: dict, source_path=None) -> CalibrationResult:
        """A reference attitude (e.g. optical motion capture) and no reference rate: the
        residual loop's machinery — attitude increments over 1-s windows, the optical attitude
        never differentiated (:func:`gyrocore.loop.residual.build_residual`, reference
        ``"attitude"``) — fits exactly the named effects (no search); its joint fit (HAC
        standard errors) is the calibration. Without this path the still parts alone would be
        fitted against rate 0 and every rate-dependent effect reported unobservable."""
        from dataclasses import replace

        from gyrocore.loop.loop import run_loop
        from gyrocore.loop.model import FITTABLE as LOOP_FITTABLE
        from gyrocore.loop.validate import loop_calibration

        rec = cols.recording  # chosen only for a recording in memory (Calibrator._strategy)
        bad = [e for e in self.o.effects if e not in LOOP_FITTABLE]
        if bad:
            raise GyroInputError(
                f"against a reference attitude {', '.join(bad)} cannot be fitted (fittable: {', '.join(LOOP_FITTABLE)})"
            )
        order = 1 if self.o.thermal_order == "auto" else int(self.o.thermal_order)
        r = run_loop(
            rec,
            declared=list(self.o.effects),
            candidates=[],
            reference="attitude",
            thermal_order=order,
            open_search=False,
        )
        res = loop_calibration(r, rec, source_path=source_path, sensor=common["sensor"], thermal_order=order)
        notes = (
            list(res.notes)
            + [f"calibrated against the reference attitude (ref_q*): {r.description}, {r.n_windows} windows"]
            + list(r.notes)
        )
        if self.o.thermal_order == "auto" and any(e in self.o.effects for e in ("bias_thermal", "scale_thermal")):
            notes.append("thermal order 1 (order selection is not done against an attitude reference)")
        return replace(res, notes=tuple(notes), method="attitude_reference")


class LeastSquaresMethod:
    """Reference rates (or the still parts against rate 0): joint least squares, window by window."""

    def __init__(self, options: "Calibrator") -> None:
        self.o = options

    #: Noise identification for ``covariance="noise_model"`` uses only samples farther than
    #: this from a change of the reference rate (|Δω_ref|/dt > :data:`RAMP_RATE_RAD_S2`): at rate
    #: ramps the residual holds the on-chip low-pass's transient (deterministic, ≈ 10× the
    #: noise on the icm42688p table run: RMS 3.3e-3 vs 3.1e-4 rad/s on the plateaus), which a
    #: noise model must not absorb (GMWM took it for a Gauss–Markov term σ 5e-4 rad/s, τc 0.15 s,
    #: in every unit, and the scale/misalignment standard errors came out 2–5× too large).
    QUIET_MARGIN_S = 0.25
    RAMP_RATE_RAD_S2 = 1e-2

    @classmethod
    def _identified_noise(
        cls, axis, bad: np.ndarray, rate_hz: float, notes: list, w_ref=None, t_s: np.ndarray | None = None
    ) -> dict:
        """solve() options of the noise-model covariance, the model identified (GMWM, per axis)
        on the residual — ``axis(i)`` returns axis i as a fresh (N,) array — without the
        ``bad`` samples and, with a reference rate ``w_ref`` ((N, 3), or a window reader
        ``(a, b) -> rows`` for a spilled record), without the samples within
        :data:`QUIET_MARGIN_S` of a rate change; the kept stretches are joined (the slow
        noise barely moves across a sub-second gap)."""
        import warnings

        from gyrocore.noise.allan import identify_noise

        keep = ~np.asarray(bad, bool)
        n = keep.size
        if w_ref is not None and n > 2:
            tt = np.arange(n) / rate_hz if t_s is None else t_s
            near = near_rate_changes(tt, w_ref, cls.QUIET_MARGIN_S)
            if np.count_nonzero(keep & ~near) >= 0.25 * n:
                keep &= ~near
        if not keep.all():
            notes.append(
                f"noise identified on {100.0 * keep.mean():.0f} % of the samples (rate ramps and outliers left out)"
            )
        models = []
        for i in range(3):
            x = axis(i)
            x = x[keep] if not keep.all() else x
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the short-record note of identify_noise
                models.append(identify_noise(x, rate_hz=rate_hz, check_static=False).axes["x"].model)
            del x
        # the residual's N, B, K and Gauss-Markov pair, one identification per axis (Q and R are
        # no terms of the sandwich, :func:`gyrocore.calib.lsq.noise_model_meat`)
        nm = NoiseModel(
            **{
                k: np.array([float(getattr(m_, k)[0]) for m_ in models])
                for k in (
                    "arw_rad_per_sqrt_s",
                    "bias_instability_rad_s",
                    "rrw_rad_per_s_sqrt_s",
                    "correlated_sigma_rad_s",
                    "correlated_tau_c_s",
                )
            },
            source="GMWM on the fit residual",
        )

        def fmt(a):
            return "/".join(f"{v:.3g}" for v in np.asarray(a, float))

        notes.append(
            "standard errors: noise-model sandwich, noise identified on the fit residual (GMWM): "
            f"N {fmt(nm.arw_rad_per_sqrt_s)} rad/sqrt(s), B {fmt(nm.bias_instability_rad_s)} rad/s, "
            f"K {fmt(nm.rrw_rad_per_s_sqrt_s)} rad/s/sqrt(s), GM sigma {fmt(nm.correlated_sigma_rad_s)} rad/s "
            f"tau {fmt(nm.correlated_tau_c_s)} s"
        )
        return dict(covariance="noise_model", noise_model=nm)

    def _ramp_weights(self, t_s: np.ndarray, w_ref, notes: list) -> np.ndarray:
        """Fit weights (N,): 0 within ``ramp_margin_s`` of a reference-rate change (when that
        leaves ≥ 25 % of the samples), else a read-only broadcast 1 (no (N,) array for a long
        record). ``w_ref``: (N, 3) or a window reader ``(a, b) -> rows`` (a spilled record:
        :func:`near_rate_changes` reads it a window at a time, the same mask)."""
        n = int(np.asarray(t_s).size)
        if self.o.ramp_margin_s > 0:
            near = near_rate_changes(t_s, w_ref, self.o.ramp_margin_s)
            if near.any() and np.count_nonzero(~near) >= 0.25 * n:
                notes.append(
                    f"left out {int(near.sum())} samples within {self.o.ramp_margin_s:g} s of a reference-rate "
                    "change (rate ramps: the gyro's own filter transient)"
                )
                return (~near).astype(float)
        return np.broadcast_to(1.0, (n,))

    def fit(self, cols, common: dict, source_path=None) -> CalibrationResult:
        """Reference rates, or the still parts against rate 0: the joint least squares of
        :func:`gyrocore.calib.lsq.fit_effects`, read a window at a time from ``cols`` (a recording
        in memory or its columns on disk: the same path, the same numbers)."""
        lhs, weights, method, notes = self._references(cols)
        fit, tau_total, opts, orders, tests = self._fits(cols, lhs, weights, notes)
        return self._result(cols, fit, tau_total, opts, orders, tests, method, notes, common)

    def _references(self, cols):
        """(lhs(τ) → the fit's rows r = y − ω_ref(t − τ) and inputs, weights (N,), method,
        notes): the reference rates with their ramps left out, or the still parts against rate 0."""
        notes: list[str] = []
        if all(c in cols.names for c in REF_RATE_COLS):
            weights = self._ramp_weights(cols.t_s, ReferenceRows(cols).ref_rows, notes)
            return (lambda tau: ReferenceRows(cols, tau_s=tau)), weights, "rate_reference", notes
        rec = _in_memory(cols, "a fit without reference rates (the still parts)")
        from gyrocore.calib.rotations import STILL_GATE

        gate = _replace(STILL_GATE, window_s=self.o.still_window_s, false_reject_rate=self.o.still_false_reject_rate)
        m = still_samples(rec, gate)
        if m.sum() < 10:
            raise GyroInputError(
                "no reference rates (ref_*_rad_s) and no still part in the data: nothing to calibrate against"
            )
        moving = moving_throughout(rec, gate)
        if moving:
            raise GyroInputError(
                f"no reference rates (ref_*_rad_s) and no still part: the record moves throughout ({moving}), so its "
                "quietest windows are motion, not a bias; give a reference (known rotations --segments, ref_* "
                "columns) or a still recording"
            )
        notes.append(
            f"no reference rates: fitted against rate 0 on {int(m.sum())} still samples "
            f"({100.0 * m.mean():.0f} % of the file); Earth rate is absorbed in the bias"
        )
        rate_effects = [e for e in self.o.effects if {"omega", "alpha"} & set(E.resolve(e).inputs)]
        if rate_effects:
            # against rate 0 their regressors are zero: say what would excite them (a multi-pose
            # session such as IMU-TK's turns between poses without a rate reference)
            notes.append(
                f"{', '.join(rate_effects)} need a reference for the motion: reference rates (ref_*_rad_s), a "
                "reference attitude (ref_q*), known rotations (--segments), or, for a multi-pose session (still "
                "poses joined by turns, IMU-TK), the poses' gravity directions (--poses)"
            )
        return (lambda tau: ReferenceRows(cols, tau_s=tau)), m.astype(float), "still", notes

    def _fits(self, cols, lhs, weights, notes: list):
        """The fits: at the highest thermal order (time offset settled by Gauss–Newton, the
        robust pass, the noise model identified), the thermal orders from the data, the final
        fit. Returns (final fit, τ, solver options, orders, order tests)."""
        from gyrocore.calib import lsq  # (lazy: scipy.stats is ~40 MiB that applying a calibration does not need)

        o = self.o
        n_all = cols.n
        has_ref = all(c in cols.names for c in REF_RATE_COLS)

        def ref_at(tau):  # ω_ref(t − τ) as a window reader (the noise identification's ramp mask)
            return ReferenceRows(cols, tau_s=tau).ref_rows if has_ref else None

        # the first fits' full-resolution residual, a scratch column of the source's kind (in
        # memory, or a file per axis beside a spill), read back one axis at a time
        residual = cols.scratch("residual", 3)
        n_used = int(np.sum(weights > 0))
        average = max(1, int(math.ceil(n_used / o.max_rows)))
        if average > 1:
            notes.append(f"fitted block means of {average} samples ({n_used} samples)")
        model_cov = o.covariance == "noise_model"
        t_all = np.asarray(cols.t_s, float)
        rate_hz = float((n_all - 1) / max(float(t_all[-1] - t_all[0]), 1e-300)) if n_all > 1 else float("nan")
        # sample times since the first sample (flicker and random walk start there)
        t_since = t_all - float(t_all[0])
        # with the noise-model covariance the first fits (time offset, robust pass) use OLS
        # standard errors; the model is identified on their residual, then used from the
        # thermal order tests on
        opts = dict(
            weights=weights,
            average=average,
            covariance="ols" if model_cov else o.covariance,
            on_unobservable=o.on_unobservable,
        )
        effects = list(o.effects)
        thermal = [e for e in effects if e in E.POLYNOMIAL]
        # 1) fit at the highest thermal order (or the fixed one) to settle τ and transients
        orders: dict[str, int] = {
            e: (o.max_thermal_order if o.thermal_order == "auto" else int(o.thermal_order)) for e in thermal
        }
        tests = []

        def first_fit(tau):
            return lsq.fit_effects(
                lhs(tau), effects, None, orders=orders, residual_sink=residual.write, keep_residual=False, **opts
            )

        # time_offset: Gauss–Newton on τ (the regressor −dω/dt is a linearisation)
        fit, tau_total = _settle_time_offset(first_fit) if "time_offset" in effects else (first_fit(0.0), 0.0)
        # robust pass: drop transients the model does not describe
        if o.robust and fit.rank:
            used = weights > 0
            bad = _outliers(residual.axis, used, n_all)
            if model_cov and o.noise is None:
                opts.update(self._identified_noise(residual.axis, bad | ~used, rate_hz, notes, ref_at(tau_total)))
            nb = int(bad.sum())
            # only when outliers are rare (< 5 %): otherwise the model is wrong, not the samples
            if 0 < nb < 0.05 * used.sum():
                weights = np.where(bad, 0.0, weights)
                opts["weights"] = weights
                notes.append(f"excluded {nb} samples with residual > 6 robust sigma (transients)")
        if model_cov and "noise_model" not in opts:
            if o.noise is not None:
                opts.update(covariance="noise_model", noise_model=o.noise, t_s=t_since)
                notes.append("standard errors: noise-model sandwich (noise model given)")
            else:
                opts.update(self._identified_noise(residual.axis, ~(weights > 0), rate_hz, notes, ref_at(tau_total)))
        if model_cov:
            opts["t_s"] = t_since
        opts["rate_hz"] = rate_hz
        # 2) thermal order from the data, then the final fit (the scratch residual is no
        #    longer needed: free it before the next fits)
        residual.close()
        fit = None
        solve_opts = {k: v for k, v in opts.items() if k != "rate_hz"}
        if thermal and o.thermal_order == "auto":
            from gyrocore.calib.thermal import select_thermal_orders

            orders, tests = select_thermal_orders(
                lhs(tau_total),
                None,
                effects,
                max_order=o.max_thermal_order,
                alpha=o.thermal_alpha,
                **dict(solve_opts, on_unobservable="drop", keep_residual=False),
            )
        # only θ, its standard errors and the residual RMS are kept from the final fit
        fit = lsq.fit_effects(lhs(tau_total), effects, None, orders=orders, keep_residual=False, **solve_opts)
        if "time_offset" in effects and np.isfinite(fit.effect_stderr("time_offset")[0]):
            tau_total += float(fit.effect_theta("time_offset")[0])
        return fit, tau_total, opts, orders, tests

    def _result(self, cols, fit, tau_total, opts, orders, tests, method, notes, common) -> CalibrationResult:
        """The :class:`CalibrationResult` of the final fit (thermal polynomials with their
        centre and the temperature range of the rows used)."""
        effects = list(self.o.effects)
        params: dict = {}
        stderr: dict = {}
        for eff in effects:
            sl = fit.slices[eff]
            order = orders.get(eff, 1)
            params[eff] = _unflatten(eff, fit.theta[sl], order)
            stderr[eff] = _unflatten(eff, fit.stderr[sl], order)
            if eff in E.POLYNOMIAL:
                T = cols.column(TEMP_COL)
                used_rows = opts["weights"] > 0
                # design() centres the polynomial on the mean temperature of all rows it gets;
                # the range over the rows used, without a copy of them (min/max are exact)
                params[eff].update(
                    t0_c=np.asarray(float(np.mean(T))),
                    temp_min_c=np.asarray(float(np.min(T, where=used_rows, initial=np.inf))),
                    temp_max_c=np.asarray(float(np.max(T, where=used_rows, initial=-np.inf))),
                )
                del T, used_rows
                stderr[eff].update({k: np.asarray(np.nan) for k in _THERMAL_META})
        if "time_offset" in effects:
            params["time_offset"]["tau_s"] = np.asarray(
                tau_total if np.isfinite(fit.effect_stderr("time_offset")[0]) else 0.0
            )
        return CalibrationResult(
            effects=tuple(effects),
            params=params,
            stderr=stderr,
            residual_rms_rad_s=np.asarray(fit.residual_rms_rad_s, float),
            unobservable=fit.unobservable,
            unobservable_reason=dict(fit.unobservable_reason),
            method=method,
            covariance=fit.cov_kind,
            n_samples=int(np.sum(opts["weights"] > 0)),
            thermal_order=orders,
            thermal_tests=tuple(t_.__dict__ for t_ in tests),
            notes=tuple(notes),
            noise_model=noise_model_dict(opts.get("noise_model"), opts["rate_hz"]),
            **common,
        )
